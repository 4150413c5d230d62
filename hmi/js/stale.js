// A page that has lost its supervisor must not look live (ISA-101). Two ways to lose it:
// the live data is down (the WebSocket closed and the polls fail), or it is silent (the
// connection is open but nothing comes: every delta carries scan.count, which changes at
// every scan, so a live supervisor sends one each publish period — at most 10 s). Then a
// banner says since when the values are stale and how long ago, the page's title starts
// with STALE (a panel's tab or window list shows it), and hmi.css marks every value
// (body.stale): hatched and grey, still readable, never in the colour of a live alarm.
import { $ } from "./dom.js";
import { fmtClock, t } from "./i18n.js";

const TICK_MS = 1000;
/** No data for this long on an open connection: stale (over the longest publish period). */
const SILENCE_S = 15;

/** "12 s", "3 min 5 s", "2 h 10 min": how long ago, coarse enough to read at a glance. */
export function ago(seconds) {
  const s = Math.max(0, Math.floor(seconds));
  if (s < 60) return `${s} s`;
  const m = Math.floor(s / 60);
  if (m < 60) return `${m} min ${s % 60} s`;
  const h = Math.floor(m / 60);
  return `${h} h ${m % 60} min`;
}

export class StaleDisplay {
  constructor() {
    this.sinceMs = null; // when the values were last fresh (null: they are fresh)
    this.why = () => ""; // why the values are stale, in the language of the moment
    this.state = "connecting";
    this.lastFreshMs = Date.now();
    this.silenceS = SILENCE_S; // the browser tests shorten it
    this.title = document.title;
    this.onChange = null; // called when the page turns stale or fresh, or silent or not
    setInterval(() => this.evaluate(), TICK_MS);
  }

  /** Follow the live data's state ("down" is stale at once; while "connecting" — the
   * page's first load, a log out — there are no values to mark). */
  follow(state) {
    const open = (x) => x === "live" || x === "polling";
    // Entering a live state means values just came (a snapshot, a poll's answer).
    if (open(state) && !open(this.state)) this.lastFreshMs = Date.now();
    this.state = state;
    this.evaluate();
  }

  /** Values arrived (a snapshot, a delta, a poll's answer). */
  fresh() {
    this.lastFreshMs = Date.now();
    if (this.sinceMs !== null) this.evaluate();
  }

  /** Stale because the open connection is silent (not closed). */
  get silent() {
    return this.sinceMs !== null && this.state !== "down";
  }

  evaluate() {
    const before = `${this.sinceMs === null}${this.silent}`;
    const now = Date.now();
    const open = this.state === "live" || this.state === "polling";
    const silent = open && now - this.lastFreshMs > this.silenceS * 1000;
    if (this.state === "down") {
      // The connection was good until it closed (the WebSocket sends every change): the
      // values were fresh until now — unless they had already gone silent before.
      if (this.sinceMs === null) this.sinceMs = now;
      this.why = () => t("stale.down");
    } else if (silent) {
      this.sinceMs = this.lastFreshMs;
      const silentS = (now - this.lastFreshMs) / 1000;
      this.why = () => t("stale.silent", { ago: ago(silentS) });
    } else {
      this.sinceMs = null;
    }
    this.paint();
    if (this.onChange && before !== `${this.sinceMs === null}${this.silent}`) this.onChange();
  }

  /** The screen's own title (the page sets it at each route): kept, prefixed while stale. */
  setTitle(title) {
    this.title = title;
    this.paint();
  }

  paint() {
    const since = this.sinceMs;
    document.body.classList.toggle("stale", since !== null);
    document.title = since === null ? this.title : `${t("stale.titlePrefix")} — ${this.title}`;
    const el = $("#stale");
    const link = $("#link");
    if (!el || !link) return;
    el.hidden = since === null;
    if (since === null) {
      link.title = t("link.title");
      return;
    }
    const at = fmtClock(new Date(since));
    el.dataset.since = String(since / 1000);
    el.textContent = t("stale.banner", { at, ago: ago((Date.now() - since) / 1000), why: this.why() });
    link.title = t("link.staleSince", { at });
  }
}
