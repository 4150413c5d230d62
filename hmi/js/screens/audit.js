// The audit trail (issue 34, docs/audit.md): who did what to the bench, an engineer's
// (GET /api/audit, /api/audit/verify; the nav shows it to engineers only, and anyone else
// who comes by its address reads the server's refusal in words). The chain's check first
// (whole, or the first broken entry), then the entries newest first with filters, a page
// at a time, and the same selection as a CSV download.
import { get } from "../api.js";
import { esc, fmtTime } from "../dom.js";
import { t } from "../i18n.js";
import { localInput } from "./alarmjournal.js";

const DAY_S = 86400;
const PAGE = 100; // entries a page (the API's default)
// The kinds of docs/audit.md, offered as the filter's suggestions (a family matches its
// kinds: "command" is every command.<verb>).
const KINDS = ["command", "login", "login.failed", "logout", "recipe.save", "user.add", "user.remove", "alarm.silence", "calibration.write", "io_map.load"];

/** An <input type="datetime-local">'s value (local time) as the API's ISO text (UTC). */
function isoOfInput(value) {
  if (!value) return "";
  const d = new Date(value);
  return Number.isFinite(d.getTime()) ? d.toISOString() : "";
}

/** A hash shortened for the eye (the whole one in the tooltip and the export). */
const short = (hash) => (hash && hash.length > 16 ? `${hash.slice(0, 8)}…${hash.slice(-8)}` : hash || "");

/** The log's times are ISO texts (UTC): shown as every table shows a time. */
const timeOf = (iso) => {
  const ms = Date.parse(iso);
  return Number.isFinite(ms) ? fmtTime(ms / 1000) : iso;
};

const MAX_DETAILS = 300; // characters shown (a recipe's diff is in the export, whole)

/** An entry's details for the eye: "name: value" pairs (a value that is no text as
 * JSON), cut past MAX_DETAILS; the export keeps them exact. */
function details(value) {
  if (value === null || value === undefined || value === "") return "";
  const json = (v) => (typeof v === "string" ? v : JSON.stringify(v));
  const isObject = typeof value === "object" && !Array.isArray(value);
  const text = isObject ? Object.entries(value).map(([k, v]) => `${k}: ${json(v)}`).join(" · ") : json(value);
  return text.length > MAX_DETAILS ? `${text.slice(0, MAX_DETAILS)}…` : text;
}

function row(e) {
  return `<tr data-seq="${e.seq}" data-kind="${esc(e.kind)}">
    <td class="num">${e.seq}</td>
    <td class="time">${esc(timeOf(e.time))}</td>
    <td translate="no">${esc(e.actor)}</td>
    <td translate="no">${esc(e.kind)}</td>
    <td class="wrap" translate="no">${esc(e.target)}</td>
    <td class="wrap details" translate="no"><code>${esc(details(e.details))}</code></td></tr>`;
}

function html(app) {
  const tx = (k, p) => esc(t(k, p));
  const channels = (app.bench?.channels || []).map((c) => `<option value="${esc(c.name)}">${esc(c.name)}</option>`).join("");
  const kinds = KINDS.map((k) => `<option value="${k}"></option>`).join("");
  const cols = ["seq", "time", "actor", "kind", "target", "details"].map((c) => `<th scope="col">${tx(`audit.col.${c}`)}</th>`).join("");
  return `<h1>${tx("nav.audit")}</h1>
    <p class="muted">${tx("audit.hint")}</p>
    <p id="audit-refused" class="result refused" role="alert" hidden></p>
    <div id="audit-body">
    <section class="panel" aria-labelledby="audit-verify-title"><h2 id="audit-verify-title">${tx("audit.verifyTitle")}</h2>
      <p id="audit-verify" class="result" role="status" aria-live="polite">…</p>
      <button type="button" id="audit-reverify" class="small">${tx("audit.reverify")}</button></section>
    <section class="panel journal" aria-labelledby="audit-entries-title"><h2 id="audit-entries-title">${tx("audit.entries")}</h2>
      <form id="audit-form" class="filters">
        <label>${tx("journal.since")} <input type="datetime-local" step="1" id="audit-since" name="since"></label>
        <label>${tx("journal.until")} <input type="datetime-local" step="1" id="audit-until" name="until"></label>
        <label>${tx("journal.actor")} <input id="audit-actor" name="actor" autocomplete="off" size="14" placeholder="hmi:…" translate="no"></label>
        <label>${tx("audit.kind")} <input id="audit-kind" name="kind" list="audit-kinds" autocomplete="off" size="14" translate="no"></label>
        <datalist id="audit-kinds">${kinds}</datalist>
        <label>${tx("journal.channel")} <select id="audit-channel" name="channel"><option value="">${tx("journal.anyChannel")}</option>${channels}</select></label>
        <span class="filter-actions"><button type="submit" id="audit-search" class="primary">${tx("journal.search")}</button>
        <a id="audit-export" class="button-link" href="/api/audit?format=csv" download="audit-trail.csv">${tx("journal.export")}</a></span>
      </form>
      <p id="audit-count" class="muted" role="status" aria-live="polite"></p>
      <table class="grid audit" id="audit-table"><caption class="sr-only">${tx("audit.entries")}</caption>
        <thead><tr>${cols}</tr></thead><tbody></tbody></table>
      <p id="audit-none" class="muted" hidden>${tx("audit.none")}</p>
      <button type="button" id="audit-older" class="small" hidden>${tx("audit.older")}</button>
    </section></div>`;
}

function queryOf(form) {
  const q = new URLSearchParams();
  const v = (name) => form.elements[name].value.trim();
  for (const name of ["since", "until"]) if (isoOfInput(v(name))) q.set(name, isoOfInput(v(name)));
  for (const name of ["actor", "kind", "channel"]) if (v(name)) q.set(name, v(name));
  return q;
}

/** The chain's check in words: whole, or where it breaks. */
function verifyText(d) {
  if (d.ok) return t("audit.verifyOk", { n: d.entries, count: d.entries, head: short(d.head) });
  const b = d.first_broken;
  if (!b) return t("audit.verifyAnchor");
  return t("audit.verifyBroken", { seq: b.seq, time: b.time ? timeOf(b.time) : "—", problem: b.problem });
}

/** A refusal in words: the 403 of a viewer or an operator, a missing log, anything else. */
function refusalText(answer) {
  const reason = answer.data?.reason || `HTTP ${answer.status}`;
  if (answer.status === 403) return t("audit.forbidden", { reason });
  if (answer.status === 503) return t("audit.noLog", { reason });
  return t("result.refused", { status: answer.status, reason });
}

export async function render({ root, app }) {
  root.dataset.title = t("nav.audit");
  root.innerHTML = html(app);
  const $ = (sel) => root.querySelector(sel);
  const form = $("#audit-form");
  form.elements.since.value = localInput(Math.floor(Date.now() / 1000) - DAY_S);
  let gen = 0;
  let before = null;
  let brokenSeq = null; // the chain's first broken entry, marked in the table when shown

  // (in words too, not the colour alone)
  const markBroken = () => {
    for (const tr of root.querySelectorAll("#audit-table tbody tr")) {
      const here = brokenSeq !== null && Number(tr.dataset.seq) === brokenSeq;
      tr.classList.toggle("abn", here);
      const mark = tr.querySelector(".broken-mark");
      if (here && !mark) tr.cells[0].insertAdjacentHTML("beforeend", `<div class="broken-mark">${esc(t("audit.brokenHere"))}</div>`);
      if (!here && mark) mark.remove();
    }
  };

  const refuse = (answer) => {
    $("#audit-refused").hidden = false;
    $("#audit-refused").textContent = refusalText(answer);
    // (an operator sees the refusal only, not an empty form they may not use)
    $("#audit-body").hidden = answer.status === 403;
  };

  const verify = async () => {
    const el = $("#audit-verify");
    el.textContent = "…";
    el.classList.remove("accepted", "refused");
    const answer = await get("/api/audit/verify");
    if (!answer.ok) {
      el.textContent = refusalText(answer);
      el.classList.add("refused");
      if (answer.status === 403) refuse(answer);
      return;
    }
    el.dataset.ok = String(answer.data.ok);
    brokenSeq = answer.data.first_broken ? answer.data.first_broken.seq : null;
    markBroken();
    el.textContent = verifyText(answer.data);
    el.classList.add(answer.data.ok ? "accepted" : "refused");
  };

  const load = async (more) => {
    const q = queryOf(form);
    const mine = more ? gen : ++gen;
    const link = new URLSearchParams(q);
    link.set("format", "csv");
    $("#audit-export").href = `/api/audit?${link}`;
    q.set("limit", String(PAGE));
    if (more && before) q.set("before", String(before));
    const answer = await get(`/api/audit?${q}`);
    if (mine !== gen) return;
    const body = $("#audit-table tbody");
    if (!more) body.innerHTML = "";
    if (!answer.ok) {
      refuse(answer);
      return;
    }
    body.insertAdjacentHTML("beforeend", answer.data.entries.map(row).join(""));
    markBroken();
    before = answer.data.next_before;
    const shown = body.children.length;
    $("#audit-none").hidden = shown > 0;
    $("#audit-older").hidden = !before;
    $("#audit-count").textContent = t("audit.count", { n: shown, count: shown });
    root.querySelector("#audit-table").dataset.loaded = String(mine);
  };

  form.addEventListener("submit", (ev) => {
    ev.preventDefault();
    load(false);
  });
  $("#audit-older").addEventListener("click", () => load(true));
  $("#audit-reverify").addEventListener("click", verify);
  await Promise.all([verify(), load(false)]);
  return null;
}
