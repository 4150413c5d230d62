// A page that has lost its supervisor must not look live (ISA-101): once the live data is
// down, a banner says since when the values are stale — the moment the connection was
// lost, the last time they were known fresh — and how long ago, and the page's title
// starts with STALE (a panel's tab or window list shows it). The values themselves are
// marked by hmi.css (body.stale): hatched and grey, still readable, never in the colour
// of a live alarm.
import { $ } from "./dom.js";

const TICK_MS = 1000;

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
    this.title = document.title;
    this._timer = null;
  }

  /** Follow the live data's state: "down" is stale; "live" and "polling" are fresh; while
   * "connecting" (the page's first load, a log out) there are no values to mark. */
  follow(state) {
    const stale = state === "down";
    document.body.classList.toggle("stale", stale);
    if (stale && this.sinceMs === null) {
      this.sinceMs = Date.now();
      this._timer = setInterval(() => this.paint(), TICK_MS);
    } else if (!stale && this.sinceMs !== null) {
      this.sinceMs = null;
      clearInterval(this._timer);
      this._timer = null;
    }
    this.paint();
  }

  /** The screen's own title (the page sets it at each route): kept, prefixed while stale. */
  setTitle(title) {
    this.title = title;
    this.paint();
  }

  paint() {
    const el = $("#stale");
    const since = this.sinceMs;
    document.title = since === null ? this.title : `STALE — ${this.title}`;
    const link = $("#link");
    if (!el || !link) return;
    el.hidden = since === null;
    if (since === null) {
      link.title = "live data connection";
      return;
    }
    const at = new Date(since).toLocaleTimeString(undefined, { hour12: false });
    el.dataset.since = String(since / 1000);
    el.textContent = `Values stale since ${at} (${ago((Date.now() - since) / 1000)} ago): no data from the supervisor, reconnecting. Every value shown is the last one received.`;
    link.title = `live data connection lost at ${at}`;
  }
}
