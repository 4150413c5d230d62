// The alarm sound (issue 33 finding 7; seed 001's tester kept sounding until someone
// acted): an unacknowledged alarm of high or critical priority (ISA-18.2, as the alarms
// carry it: severity 700 and up) sounds again every REPEAT_S until it is acknowledged,
// shelved or silenced on this screen. Medium and low ones sound once, when they appear.
// A silence is this screen's and this user's (another operator's screen still sounds),
// covers the alarm occurrences sounding when it was pressed (a new alarm, or the same one
// activated again, sounds again), and is recorded by the supervisor with its actor
// (POST /api/alarms/silence: the alarms' history, beside the acknowledgements).
import { post } from "./api.js";
import { priorityOf } from "./priority.js";

export const REPEATING = new Set(["critical", "high"]);
export const REPEAT_S = 10; // bearable at 3 a.m., short enough that nobody misses it

/** One occurrence of an alarm: its id and when it was activated. The supervisor converts
 * its monotonic activation time to wall time at each answer, which moves it by
 * microseconds: compared within SAME_S, far below a scan (an alarm activated again has
 * been seen clear by a scan in between). */
const occurrence = (a) => [a.id, Number(a.activated_time) || 0];
const SAME_S = 0.01;
const storeKey = (user) => `hmi.silenced.${user}`;

/** Occurrences: alarm id -> activation time. */
class Occurrences extends Map {
  static of(alarms) {
    return new Occurrences(alarms.map(occurrence));
  }

  holds(a) {
    const [id, t] = occurrence(a);
    return this.has(id) && Math.abs(this.get(id) - t) < SAME_S;
  }
}

function loadSilenced(user) {
  try {
    const pairs = JSON.parse(localStorage.getItem(storeKey(user)) || "[]");
    return new Occurrences(Array.isArray(pairs) ? pairs : []);
  } catch {
    return new Occurrences();
  }
}

export class AlarmSound {
  constructor(sound, { repeatS = REPEAT_S } = {}) {
    this.sound = sound;
    this.repeatS = repeatS;
    this.user = "";
    this.silenced = new Occurrences(); // what this user silenced (kept per user)
    this.known = new Occurrences(); // what was already announced once
    this.sounding = []; // the alarms that repeat now
    this.timer = null;
    this.onChange = null; // the header repaints the Silence button
  }

  /** How often the sound repeats (``hmi.alarm_sound_repeat_s``, from the session). */
  setRepeat(seconds) {
    const s = Number(seconds);
    if (!(s > 0) || s === this.repeatS) return;
    this.repeatS = s;
    if (this.timer !== null) {
      clearInterval(this.timer);
      this.timer = null;
      this._schedule();
    }
  }

  /** The logged-in user whose silences count (another user's are not theirs). */
  setUser(user) {
    if (user === this.user) return;
    this.user = user || "";
    this.silenced = loadSilenced(this.user);
    this.known = new Occurrences();
  }

  /** The live alarms changed (or the sound switch did): who sounds now. */
  update(alarms) {
    const unacked = (alarms || []).filter(
      (a) => a.state !== "normal" && !a.shelved && a.state.includes("unacknowledged"),
    );
    const fresh = unacked.filter((a) => !this.known.holds(a) && !this.silenced.holds(a));
    this.known = Occurrences.of(unacked);
    this.sounding = unacked.filter((a) => REPEATING.has(priorityOf(a.severity).name) && !this.silenced.holds(a));
    if (fresh.length) this.sound.alarm(fresh.map((a) => a.id));
    this._schedule();
  }

  get active() {
    return this.sound.enabled && this.sounding.length > 0;
  }

  _schedule() {
    const want = this.active;
    if (want && this.timer === null) {
      this.timer = setInterval(() => {
        if (this.active) this.sound.alarm(this.sounding.map((a) => a.id));
      }, this.repeatS * 1000);
    } else if (!want && this.timer !== null) {
      clearInterval(this.timer);
      this.timer = null;
    }
    if (this.onChange) this.onChange();
  }

  /** Silence what sounds now, on this screen, for this user; the supervisor records it.
   * Resolves to the supervisor's answer. Refused (no session): nothing is silenced. */
  async silence() {
    const now = this.sounding;
    if (!now.length) return null;
    const answer = await post("/api/alarms/silence", { alarms: now.map((a) => a.id) });
    // Unreachable (status 0): silenced all the same — a sound nobody can stop helps no
    // one; the supervisor's own log shows the connection lost.
    if (!answer.ok && answer.status !== 0) return answer;
    for (const a of now) this.silenced.set(...occurrence(a));
    // Only the occurrences still unacknowledged are worth keeping.
    for (const [id] of this.silenced) if (!this.known.has(id)) this.silenced.delete(id);
    localStorage.setItem(storeKey(this.user), JSON.stringify([...this.silenced]));
    const silenced = Occurrences.of(now);
    this.sounding = this.sounding.filter((a) => !silenced.holds(a));
    this._schedule();
    return answer;
  }
}
