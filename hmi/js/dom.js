// Small DOM helpers: escaping, value formatting, and the binding of elements to tags
// (<span data-tag="ch0.voltage" data-fmt="n3">), refreshed on each live delta. Numbers,
// dates and words in the screens' language (i18n.js).
import { fmtDateTime, fmtNumber, fmtSignificant, lang, t, tOr, tValue } from "./i18n.js";

export function esc(s) {
  return String(s ?? "")
    .replaceAll("&", "&amp;")
    .replaceAll("<", "&lt;")
    .replaceAll(">", "&gt;")
    .replaceAll('"', "&quot;")
    .replaceAll("'", "&#39;");
}

export const $ = (sel, root = document) => root.querySelector(sel);
export const $$ = (sel, root = document) => Array.from(root.querySelectorAll(sel));

/** Seconds as h:mm:ss (or d h:mm:ss), "—" when not known. */
export function fmtDuration(s) {
  if (s === null || s === undefined || !Number.isFinite(Number(s))) return "—";
  let t = Math.max(0, Math.round(Number(s)));
  const d = Math.floor(t / 86400);
  t -= d * 86400;
  const h = Math.floor(t / 3600);
  const m = Math.floor((t % 3600) / 60);
  const sec = t % 60;
  const hms = `${h}:${String(m).padStart(2, "0")}:${String(sec).padStart(2, "0")}`;
  return d ? `${t("unit.days", { n: d })} ${hms}` : hms;
}

/** A date and time (unix seconds) in the locale's order, 24 h (i18n.js). */
export function fmtTime(unixS) {
  if (!unixS) return "—";
  return fmtDateTime(unixS);
}

/** An alarm's text in the screens' language: in English the supervisor's own message (it
 * writes them in English); in another by its stable `code` and `params` when the
 * supervisor sends them and the catalogue has the code, else the message as it came. */
export function alarmText(a) {
  if (!a) return "";
  if (!a.code || lang() === "en") return a.message ?? "";
  return tOr(`alarm.${a.code}`, a.message ?? "", alarmParams(a.params));
}

/** An alarm's numeric params in the locale's format, as the supervisor's own text writes
 * them: a measured value in volts or amperes with 3 decimals, in °C with 1, seconds with
 * 2, a limit or a tolerance as given (up to 6 significant digits). */
function alarmParams(params) {
  const out = {};
  for (const [k, v] of Object.entries(params || {})) {
    // (a word of a state — "open", "on" — in the language; names and reasons as they are)
    if (typeof v !== "number") out[k] = typeof v === "string" ? tOr(`alarmWord.${v}`, v) : v ?? "";
    else if (k.endsWith("_s")) out[k] = fmtNumber(v, 2);
    else if (/^(limit|tolerance)/.test(k)) out[k] = fmtSignificant(v, 6);
    else if (k.endsWith("_c")) out[k] = fmtNumber(v, 1);
    else if (/_(v|a)$/.test(k)) out[k] = fmtNumber(v, 3);
    else out[k] = fmtSignificant(v, 6);
  }
  return out;
}

/** A number's text without the sign of a value that rounds to zero: "-0.000" (a current
 * of -0.0001 A, or -0 itself) reads as a small negative figure that is not there; "0.000".
 * Kept apart so that any other formatting (toFixed, Intl.NumberFormat) can run its text
 * through it: it only drops a minus before digits that are all zero. */
export function noNegativeZero(text) {
  return /^[-\u2212](?=[^1-9]*$)(?=.*0)/.test(text) ? text.slice(1) : text;
}

/** A unit as the screens write it; the tags keep their units as they are on the wire
 * (OPC UA and InfluxDB consumers read "degC"), only what an operator reads changes. */
const UNIT_LABELS = { degC: "°C", degF: "°F", K: "K", ohm: "Ω", mohm: "mΩ", pct: "%", percent: "%" };
export function unitLabel(unit) {
  if (unit === null || unit === undefined) return "";
  return UNIT_LABELS[unit] ?? String(unit);
}

/** A tag's value as text by a format: n<digits>, dur, pct, bool, text (default). */
export function fmtValue(value, fmt, el) {
  if (value === null || value === undefined) return "—";
  if (fmt === "dur") return fmtDuration(value);
  if (fmt === "pct") return Number.isFinite(value) ? `${Math.round(value * 100)} %` : "—";
  if (fmt === "bool" || typeof value === "boolean") {
    const on = el?.dataset.true ?? t("value.on");
    const off = el?.dataset.false ?? t("value.off");
    return value ? on : off;
  }
  if (typeof value === "number" && fmt && fmt.startsWith("n")) {
    return fmtNumber(value, Number(fmt.slice(1)) || 0);
  }
  if (typeof value === "number" && !Number.isInteger(value)) return fmtNumber(value, 3);
  if (value === "") return el?.dataset.empty ?? "—";
  // A name the supervisor sends (a state, a mode: data-enum="chain") in the language.
  if (el?.dataset.enum && typeof value === "string") return tValue(el.dataset.enum, value);
  return String(value);
}

/** Is this value abnormal for the element's rule (data-abn: false|true|nonempty|nonzero)? */
function abnormal(rule, value) {
  switch (rule) {
    case "false":
      return value === false;
    case "true":
      return value === true;
    case "nonempty":
      return typeof value === "string" && value !== "";
    case "nonzero":
      return typeof value === "number" && value !== 0;
    default:
      return false;
  }
}

/** The reason of a tag whose sensor the bench does not have (core/quality.py Reason.NOT_FITTED). */
export const NOT_FITTED = "not fitted";

/** Write one tag into one element (text, quality class, abnormal class, source time). */
export function paint(el, tag) {
  if (!tag) {
    delete el.dataset.shown;
    el.textContent = "—";
    el.classList.add("q-bad");
    el.title = t("tag.missing");
    return;
  }
  if (tag.quality === "BAD" && tag.reason === NOT_FITTED) {
    // No sensor on this bench (a Chadèche board has no thermometer): nothing is wrong,
    // so grey "n/a", never the colour of a fault.
    delete el.dataset.shown;
    el.textContent = t("value.na");
    el.classList.remove("q-bad", "q-uncertain", "abn");
    el.classList.add("q-na");
    el.title = t("tag.notFitted");
    el.dataset.version = String(tag.version ?? "");
    return;
  }
  el.classList.remove("q-na");
  const text = fmtValue(tag.value, el.dataset.fmt, el);
  const unit = el.dataset.unit === "none" || !tag.unit || tag.unit === "1" ? "" : unitLabel(tag.unit);
  const withUnit = unit && text !== "—" && el.dataset.fmt !== "dur";
  const shown = withUnit ? `${text} ${unit}` : text;
  if (el.dataset.shown !== shown) {
    el.dataset.shown = shown;
    if (withUnit && el.classList.contains("big")) {
      // Large numerals, the unit small beside them (it does not change, the number does).
      el.textContent = text;
      const u = document.createElement("small");
      u.className = "unit";
      u.textContent = ` ${unit}`;
      el.append(u);
    } else {
      el.textContent = shown;
    }
  }
  el.classList.toggle("q-bad", tag.quality === "BAD");
  el.classList.toggle("q-uncertain", tag.quality === "UNCERTAIN");
  el.classList.toggle("abn", abnormal(el.dataset.abn, tag.value));
  el.title = tag.quality === "GOOD" ? "" : `${tag.quality}: ${tag.reason}`;
  // For the browser test's latency probe: when the value was changed on the server.
  if (tag.source_time) el.dataset.sourceTime = String(tag.source_time);
  el.dataset.version = String(tag.version ?? "");
}

/** Elements of `root` bound to tags; refresh(names|null) repaints those of the names. */
export function bindTags(root, live) {
  const index = new Map();
  for (const el of root.querySelectorAll("[data-tag]")) {
    const name = el.dataset.tag;
    if (!index.has(name)) index.set(name, []);
    index.get(name).push(el);
  }
  const refresh = (names) => {
    const list = names ?? Array.from(index.keys());
    for (const name of list) {
      const els = index.get(name);
      if (!els) continue;
      const tag = live.tags.get(name);
      for (const el of els) paint(el, tag);
    }
  };
  refresh(null);
  return refresh;
}

/** Show a command's outcome in `el` (role=status): the reason of a refusal, in colour. */
export function showResult(el, answer, okText) {
  if (!el) return;
  const d = answer.data || {};
  el.hidden = false;
  el.classList.toggle("refused", !answer.ok);
  el.classList.toggle("accepted", answer.ok);
  let reason = d.reason || d.error || "";
  if (Array.isArray(d.details) && d.details.length) reason += ` — ${d.details.join("; ")}`;
  if (!reason) reason = answer.ok ? okText || t("result.done") : `HTTP ${answer.status}`;
  el.textContent = answer.ok ? reason : t("result.refused", { status: answer.status, reason });
}
