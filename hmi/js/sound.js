// The audible alert (issue 12; seed 001's end-of-test buzzer): two tones for an alarm
// (repeated while one of high priority waits: alarmsound.js), a rising triple at the end of
// a test. On by default (issue 33 finding 7: an alarm at 3 a.m. must be heard), switched
// off in the header and remembered by the browser. WebAudio plays only after a user
// gesture on the page (the login's click is one; a reload with a session has none yet):
// until then `blocked` is true and the header says "click to allow sound"; the first
// click or key press anywhere resumes it.
const KEY = "hmi.sound";

export class Sound {
  constructor() {
    this.enabled = localStorage.getItem(KEY) !== "off";
    this.ctx = null;
    this.played = []; // what was played, for the browser tests: [{kind, at, alarms}]
    this.onChange = null; // the header shows whether sound is blocked
    const unblock = () => {
      if (this.ctx && this.ctx.state === "suspended") this.ctx.resume().finally(() => this._changed());
      else this._changed();
    };
    document.addEventListener("pointerdown", unblock, true);
    document.addEventListener("keydown", unblock, true);
  }

  /** Sound is on but the browser still waits for a click (or a key) on the page. */
  get blocked() {
    if (!this.enabled) return false;
    if (this.ctx) return this.ctx.state === "suspended";
    return navigator.userActivation ? !navigator.userActivation.hasBeenActive : false;
  }

  _changed() {
    if (this.onChange) this.onChange();
  }

  setEnabled(on) {
    this.enabled = on;
    localStorage.setItem(KEY, on ? "on" : "off");
    if (on) this._context();
    this._changed();
  }

  _context() {
    if (!this.ctx && window.AudioContext && !this.blocked) {
      this.ctx = new AudioContext();
      this.ctx.onstatechange = () => this._changed();
    }
    return this.ctx;
  }

  _tones(freqsHz, toneS) {
    const ctx = this._context();
    if (!ctx) return;
    let t = ctx.currentTime;
    for (const f of freqsHz) {
      const osc = ctx.createOscillator();
      const gain = ctx.createGain();
      osc.frequency.value = f;
      gain.gain.setValueAtTime(0.2, t);
      gain.gain.exponentialRampToValueAtTime(0.001, t + toneS);
      osc.connect(gain).connect(ctx.destination);
      osc.start(t);
      osc.stop(t + toneS);
      t += toneS * 1.1;
    }
  }

  /** Two tones for the alarms `ids` (recorded with them). */
  alarm(ids = []) {
    if (!this.enabled) return;
    this.played.push({ kind: "alarm", at: Date.now(), alarms: ids });
    this._tones([880, 660, 880, 660], 0.18);
  }

  endOfTest() {
    if (!this.enabled) return;
    this.played.push({ kind: "end", at: Date.now() });
    this._tones([523, 659, 784], 0.3);
  }
}
