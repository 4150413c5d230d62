// The header's one line on a 1366 px panel (ISA-101: the bench summary on every screen,
// without taking height from the screens). What the line holds varies — the language, the
// user's name, a channel's entry in the nav, the link's word, how many priorities have
// alarms and their counts — so no fixed width is safe (CI found one: a scan stall beside
// the e-stop and the failed logins pushed "Log out" onto a second line). When the line
// would wrap, words give way, least needed first; every count stays, the words go to
// tooltips:
//   1. the channel counts' words ("▶ 2 running" → "▶ 2");
//   2. the user's role and the channel's name in the nav ("Channel ch2" → "ch2");
//   3. the alarm count's words: the unacknowledged count alone when there are some.
// On a tablet, where the header wraps anyway, it is drawn at the last level. Measured
// only when something on the header's line changed, not on every live update.

export const FIT_LEVELS = 3;

export class HeaderFit {
  /** `paint(level)` draws the summary at a level (0: every word). */
  constructor(top, paint) {
    this.top = top;
    this.paint = paint;
    this.level = 0;
    this._key = "";
  }

  /** Forget the last fit (the language changed: every width did). */
  reset() {
    this._key = "";
  }

  /** Fit the header for `counts` (the summary's figures, as a string). */
  fit(counts) {
    if (this.top.hidden) return;
    const others = Array.from(this.top.children, (c) => (c.id === "summary" || c.hidden ? "" : c.textContent)).join("|");
    const key = `${window.innerWidth}|${counts}|${others}`;
    if (key === this._key) return;
    this._key = key;
    for (let level = 0; level <= FIT_LEVELS; level += 1) {
      this.level = level;
      this.top.classList.toggle("fit-2", level >= 2);
      this.paint(level);
      if (!this.wraps()) return;
    }
  }

  /** Whether the header takes more than one line: its last part (the session's controls)
   * below its first (the bench's name), or the summary itself on two lines. */
  wraps() {
    const first = this.top.firstElementChild.getBoundingClientRect();
    const last = this.top.lastElementChild.getBoundingClientRect();
    const summary = this.top.querySelector("#summary")?.getBoundingClientRect();
    return last.top >= first.bottom - 2 || (summary !== undefined && summary.height > 1.8 * first.height);
  }
}
