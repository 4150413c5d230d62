// The optional audible alert (issue 12; seed 001's end-of-test buzzer): two tones on a
// new alarm, a rising triple at the end of a test. Off by default, switched in the header
// and remembered by the browser. WebAudio needs a user gesture first: the switch is one.
const KEY = "hmi.sound";

export class Sound {
  constructor() {
    this.enabled = localStorage.getItem(KEY) === "on";
    this.ctx = null;
    this.played = []; // what was played, for the browser tests: [{kind, at}]
  }

  setEnabled(on) {
    this.enabled = on;
    localStorage.setItem(KEY, on ? "on" : "off");
    if (on) this._context();
  }

  _context() {
    if (!this.ctx && window.AudioContext) this.ctx = new AudioContext();
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

  alarm() {
    if (!this.enabled) return;
    this.played.push({ kind: "alarm", at: Date.now() });
    this._tones([880, 660, 880, 660], 0.18);
  }

  endOfTest() {
    if (!this.enabled) return;
    this.played.push({ kind: "end", at: Date.now() });
    this._tones([523, 659, 784], 0.3);
  }
}
