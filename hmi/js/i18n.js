// The screens' language (issue 33, finding 9): French or English, every label and message
// of the front end from one catalogue per language (i18n/en.js, i18n/fr.js: plain objects
// of key -> text, no build step; a page loads the one of its language, the other when it
// is switched to), numbers, dates and times in the language's format.
// The language: the one chosen with the header's switch (remembered by this browser), else
// the browser's (navigator.languages: fr* -> French), else English. Texts that come from the
// supervisor are shown as it sends them unless they carry a stable code (an alarm's
// `code` and `params`, a state's name): docs/adr/0045-screens-in-french-and-english.md.
export const LANGUAGES = ["en", "fr"];
const KEY = "hmi.lang";

/** The language the browser prefers among ours: fr* -> French, anything else English. */
export function browserLanguage(languages = navigator.languages || [navigator.language]) {
  for (const tag of languages || []) {
    if (String(tag).toLowerCase().startsWith("fr")) return "fr";
    if (String(tag).toLowerCase().startsWith("en")) return "en";
  }
  return "en";
}

function stored() {
  try {
    const v = localStorage.getItem(KEY);
    return LANGUAGES.includes(v) ? v : null;
  } catch {
    return null;
  }
}

const loaded = {}; // language -> its catalogue, once imported

async function load(language) {
  if (!loaded[language]) loaded[language] = (await import(`./i18n/${language}.js`)).default;
  return loaded[language];
}

let current = stored() || browserLanguage();
// (top-level await: the app's modules run once the page's language is there, so the
// first paint is in it)
await load(current);

/** Both catalogues (the browser tests compare them). */
export async function catalogues() {
  const out = {};
  for (const language of LANGUAGES) out[language] = await load(language);
  return out;
}

export const lang = () => current;

/**
 * The locale numbers and dates are written in: the browser's own locale when it is of the
 * screens' language (en-US keeps month/day, en-GB day/month), else the language's usual
 * one. Times are 24 h whatever the locale (a lab's clock; the trend and the tables agree).
 */
export function locale() {
  for (const tag of navigator.languages || [navigator.language]) {
    if (String(tag).toLowerCase().split("-")[0] === current) return String(tag);
  }
  return current === "fr" ? "fr-FR" : "en-GB";
}

/** Choose the language (the header's switch): its catalogue loaded, the choice
 * remembered, then the listeners repaint. */
export async function setLang(value) {
  if (!LANGUAGES.includes(value) || value === current) return;
  await load(value);
  current = value;
  try {
    localStorage.setItem(KEY, value);
  } catch {
    // a browser without storage keeps the choice for this page only
  }
  formats.clear();
  document.documentElement.lang = value;
  for (const fn of listeners) fn(value);
}

const listeners = new Set();
export function onLangChange(fn) {
  listeners.add(fn);
  return () => listeners.delete(fn);
}

/** Is there a text for `key` in the current language? */
export const has = (key) => key in loaded[current];

/**
 * The text of `key` with its {name} placeholders filled from `params`. With a numeric
 * `params.count`, the plural form `key_one` / `key_other` by the language's rule (French:
 * 0 and 1 are singular) where the catalogue has them. A key missing from the catalogue is
 * shown as the key itself (the browser tests check both catalogues have the same keys).
 */
export function t(key, params = {}) {
  const cat = loaded[current];
  let k = key;
  if (typeof params.count === "number") {
    const form = plural(params.count);
    if (`${key}_${form}` in cat) k = `${key}_${form}`;
  }
  const text = k in cat ? cat[k] : key;
  return text.replace(/\{(\w+)\}/g, (m, name) => (name in params ? String(params[name]) : m));
}

/** The text of `key` if the catalogue has it, else `fallback` (a server's free text). */
export const tOr = (key, fallback, params) => (has(key) ? t(key, params) : fallback);

/** A state, mode or other name the supervisor sends (a stable code) in the language. */
export const tValue = (kind, value) =>
  value === null || value === undefined || value === "" ? value : tOr(`${kind}.${value}`, String(value));

const formats = new Map();
function format(key, make) {
  let f = formats.get(key);
  if (!f) {
    f = make();
    formats.set(key, f);
  }
  return f;
}

function plural(n) {
  return format("plural", () => new Intl.PluralRules(locale())).select(n);
}

/**
 * A number with `digits` decimals in the locale's format ("1,500" in French, "1.500" in
 * English; no thousands separator: a bench's values are read digit by digit). A value that
 * rounds to zero is written unsigned ("0,000", never "-0,000").
 */
export function fmtNumber(value, digits = 3) {
  const v = Number(value);
  if (!Number.isFinite(v)) return "—";
  const d = Math.max(0, Math.min(20, digits));
  const nf = format(`n${d}`, () => new Intl.NumberFormat(locale(), { minimumFractionDigits: d, maximumFractionDigits: d, useGrouping: false }));
  return nf.format(Math.abs(v) < 0.5 * 10 ** -d ? 0 : v);
}

/** A number with up to `significant` significant digits (axis ticks, legends, ratios). */
export function fmtSignificant(value, significant = 6) {
  const v = Number(value);
  if (!Number.isFinite(v)) return "—";
  const nf = format(`s${significant}`, () => new Intl.NumberFormat(locale(), { maximumSignificantDigits: significant, useGrouping: false }));
  const s = nf.format(v);
  // (-0 and a value rounding to zero: unsigned)
  return /^-0([.,]0*)?$/.test(s) ? s.slice(1) : s;
}

const DATE = { year: "numeric", month: "2-digit", day: "2-digit" };
const TIME = { hour: "2-digit", minute: "2-digit", second: "2-digit", hourCycle: "h23" };

/** A date and time (unix seconds) as the tables show it: the locale's order, 24 h. */
export function fmtDateTime(unixS) {
  if (!unixS && unixS !== 0) return "—";
  return format("dt", () => new Intl.DateTimeFormat(locale(), { ...DATE, ...TIME })).format(new Date(unixS * 1000));
}

/** A time of day (unix seconds or a Date), 24 h with seconds. */
export function fmtClock(when) {
  const d = when instanceof Date ? when : new Date(when * 1000);
  return format("clock", () => new Intl.DateTimeFormat(locale(), TIME)).format(d);
}

/**
 * A time axis's tick labels (uPlot's `values` for a time scale, seconds): hours and minutes,
 * with seconds when the ticks are less than a minute apart, the day and month when they are
 * a day or more apart or the day changes — the same locale and 24 h as the tables.
 */
export function timeTicks(u, splits, axisIdx, space, incr) {
  const hm = format("hm", () => new Intl.DateTimeFormat(locale(), { hour: "2-digit", minute: "2-digit", hourCycle: "h23" }));
  const hms = format("clock", () => new Intl.DateTimeFormat(locale(), TIME));
  const dm = format("dm", () => new Intl.DateTimeFormat(locale(), { day: "2-digit", month: "2-digit" }));
  let day = null;
  return splits.map((s) => {
    if (s === null || s === undefined) return "";
    const d = new Date(s * 1000);
    if (incr >= 86400) return dm.format(d);
    const text = (incr < 60 ? hms : hm).format(d);
    const today = d.toDateString();
    const changed = day !== null && today !== day;
    day = today;
    return changed ? `${dm.format(d)}\n${text}` : text;
  });
}

/** Translate the static page (index.html): data-i18n (text), data-i18n-title,
 * data-i18n-aria-label, data-i18n-placeholder hold the keys. */
export function translateStatic(root = document) {
  for (const el of root.querySelectorAll("[data-i18n]")) el.textContent = t(el.dataset.i18n);
  for (const [attr, data] of [
    ["title", "i18nTitle"],
    ["aria-label", "i18nAriaLabel"],
    ["placeholder", "i18nPlaceholder"],
  ]) {
    for (const el of root.querySelectorAll(`[data-i18n-${attr}]`)) el.setAttribute(attr, t(el.dataset[data]));
  }
  document.documentElement.lang = current;
}
