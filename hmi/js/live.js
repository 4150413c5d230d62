// Live data: one WebSocket (/api/ws) gives a snapshot of every tag, then deltas at the
// publish rate (only the tags changed), the alarms when they change and the bench's events.
// A page left open for days must keep working: on a close (supervisor restarted, network
// gone) it reconnects by itself with a capped exponential backoff, and the new snapshot
// replaces the old image, so nothing stale survives a reconnect.
import { get } from "./api.js";

const BACKOFF_FIRST_S = 0.5;
const BACKOFF_MAX_S = 10;
// Before the supervisor has /api/ws (or when it refuses the upgrade) the page still shows
// values: it polls /api/tags at this period until the WebSocket comes back.
const POLL_PERIOD_S = 1.0;

export class Live {
  constructor() {
    this.tags = new Map(); // name -> {value, unit, quality, reason, source_time, version, ...}
    this.version = 0;
    this.alarms = [];
    this.events = []; // latest bench events, newest last
    this.state = "connecting"; // connecting | live | polling | down
    this.listeners = new Set();
    this._backoffS = BACKOFF_FIRST_S;
    this._ws = null;
    this._pollTimer = null;
    this._retryTimer = null;
    this._stopped = false;
    this.onDisconnect = null; // app.js checks the session then (a 401 before the upgrade)
    this.onReconnect = null; // ... and after a reconnect (a restarted supervisor forgot it)
    this.stats = { messages: 0, reconnects: 0, lastMessageAt: 0 };
  }

  /** fn({kind: "tags"|"alarms"|"event"|"state", names?: string[]}) on each change. */
  subscribe(fn) {
    this.listeners.add(fn);
    return () => this.listeners.delete(fn);
  }

  value(name) {
    const t = this.tags.get(name);
    return t ? t.value : undefined;
  }

  _emit(change) {
    for (const fn of this.listeners) {
      try {
        fn(change);
      } catch (err) {
        console.error("live listener failed", err);
      }
    }
  }

  _setState(state) {
    if (state !== this.state) {
      this.state = state;
      this._emit({ kind: "state" });
    }
  }

  start() {
    this._stopped = false;
    this._lost = false; // a connection of this start was lost (then: onReconnect)
    this._connect();
  }

  stop() {
    this._stopped = true;
    clearTimeout(this._retryTimer);
    clearInterval(this._pollTimer);
    this._pollTimer = null;
    if (this._ws) this._ws.close();
    this._setState("connecting");
  }

  _connect() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    let ws;
    try {
      ws = new WebSocket(`${proto}//${location.host}/api/ws`);
    } catch {
      this._retry();
      return;
    }
    this._ws = ws;
    let opened = false;
    ws.onopen = () => {
      opened = true;
    };
    ws.onmessage = (ev) => {
      this._backoffS = BACKOFF_FIRST_S;
      this._stopPolling();
      this._onMessage(ev.data);
    };
    ws.onclose = () => {
      if (this._ws !== ws) return;
      this._ws = null;
      if (this._stopped) return;
      this.stats.reconnects += 1;
      this._lost = true;
      // While the page polls, the polls say whether values come (a failed retry of the
      // WebSocket is no news): "polling" only after a poll that answered.
      if (!this._pollTimer) this._setState("down");
      if (this.onDisconnect) this.onDisconnect(opened);
      this._retry();
    };
  }

  _retry() {
    if (this._stopped) return;
    // No WebSocket for now: keep the values coming by polling meanwhile.
    this._startPolling();
    const jitter = 0.8 + Math.random() * 0.4;
    this._retryTimer = setTimeout(() => this._connect(), this._backoffS * 1000 * jitter);
    this._backoffS = Math.min(this._backoffS * 2, BACKOFF_MAX_S);
  }

  _onMessage(text) {
    let msg;
    try {
      msg = JSON.parse(text);
    } catch {
      return;
    }
    this.stats.messages += 1;
    this.stats.lastMessageAt = Date.now();
    if (msg.type === "snapshot") {
      this.tags = new Map(Object.entries(msg.tags || {}));
      this.version = msg.version || 0;
      this._setState("live");
      this._emit({ kind: "tags", names: null });
      if (this._lost && this.onReconnect) this.onReconnect();
      this._lost = false;
    } else if (msg.type === "delta") {
      const names = Object.keys(msg.tags || {});
      for (const name of names) this.tags.set(name, msg.tags[name]);
      this.version = msg.version || this.version;
      this._setState("live");
      if (names.length) this._emit({ kind: "tags", names });
    } else if (msg.type === "alarms") {
      this.alarms = msg.alarms || [];
      this._emit({ kind: "alarms" });
    } else if (msg.type === "event") {
      this.events.push(msg.event);
      if (this.events.length > 200) this.events.splice(0, this.events.length - 200);
      this._emit({ kind: "event", event: msg.event });
    }
  }

  _startPolling() {
    if (this._pollTimer) return;
    const poll = async () => {
      const [tags, alarms] = await Promise.all([
        get("/api/tags", { no401: true }),
        get("/api/alarms", { no401: true }),
      ]);
      if (!this._pollTimer) return; // the WebSocket came back meanwhile
      if (tags.ok && Array.isArray(tags.data)) {
        const names = [];
        for (const t of tags.data) {
          const old = this.tags.get(t.name);
          if (!old || old.version !== t.version) names.push(t.name);
          this.tags.set(t.name, t);
        }
        this._setState("polling");
        if (names.length) this._emit({ kind: "tags", names });
      } else {
        this._setState("down");
      }
      if (alarms.ok && Array.isArray(alarms.data.active)) {
        const before = JSON.stringify(this.alarms);
        this.alarms = alarms.data.active;
        if (JSON.stringify(this.alarms) !== before) this._emit({ kind: "alarms" });
      }
    };
    this._pollTimer = setInterval(poll, POLL_PERIOD_S * 1000);
    poll();
  }

  _stopPolling() {
    if (this._pollTimer) {
      clearInterval(this._pollTimer);
      this._pollTimer = null;
    }
  }
}
