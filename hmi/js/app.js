// The HMI's single page: hash routes (#/, #/channel/ch0, #/alarms, #/recipes,
// #/recipes/NAME, #/tests, #/tests/ID, #/diagnostics, #/audit, #/login?next=...), one live data
// connection shared by every screen, and the session (a 401 anywhere -> login, then back
// to the same hash).
import { get, post, onUnauthorized } from "./api.js";
import { Live } from "./live.js";
import { $, alarmText, esc } from "./dom.js";
import { Sound } from "./sound.js";
import { AlarmSound } from "./alarmsound.js";
import { StaleDisplay } from "./stale.js";
import { benchCounts, paintSummary } from "./summary.js";
import { HeaderFit } from "./headerfit.js";
import { priorityIcon } from "./priority.js";
import * as i18n from "./i18n.js";
import { lang, onLangChange, setLang, t, translateStatic } from "./i18n.js";
import * as login from "./screens/login.js";
import * as overview from "./screens/overview.js";
import * as channel from "./screens/channel.js";
import * as alarms from "./screens/alarms.js";
import * as recipes from "./screens/recipes.js";
import * as tests from "./screens/tests.js";
import * as diagnostics from "./screens/diagnostics.js";
import * as audit from "./screens/audit.js";

const ROUTES = [
  [/^\/login$/, login, "login"],
  [/^\/?$/, overview, "overview"],
  [/^\/channel\/([^/]+)$/, channel, "channel"],
  [/^\/alarms$/, alarms, "alarms"],
  [/^\/recipes(?:\/(.+))?$/, recipes, "recipes"],
  [/^\/tests(?:\/(.+))?$/, tests, "tests"],
  [/^\/diagnostics$/, diagnostics, "diagnostics"],
  [/^\/audit$/, audit, "audit"],
];

// How long after its announced expiry the page checks its session.
const SESSION_SLACK_S = 0.5;

const app = {
  live: new Live(),
  session: null, // {user, role, login}
  bench: null,
  tagNames: new Set(), // every tag of the bench (from /api/tags at start)
  anonymousRead: false, // the supervisor lets a visitor see without logging in
  screen: null,
  sound: new Sound(),
  alarmSound: null, // the repeating alarm sound and its silence (alarmsound.js)
  stale: new StaleDisplay(),
  i18n, // the language and its formats (the browser tests read its catalogues)
  goLogin,
};
app.alarmSound = new AlarmSound(app.sound);
window.hmi = app; // for the browser tests and for a curious engineer's console

function parseHash() {
  const raw = location.hash.replace(/^#/, "") || "/";
  const [path, query = ""] = raw.split("?");
  return { path, query: new URLSearchParams(query), raw };
}

/** The login screen, remembering where the page was (its hash) to come back after. */
function goLogin() {
  const here = parseHash();
  if (here.path === "/login") return;
  const had = app.session && app.session.login !== false && !app.session.anonymous;
  app.session = null;
  location.hash = `#/login?next=${encodeURIComponent("#" + here.raw)}${had ? "&expired=1" : ""}`;
}

onUnauthorized(() => {
  // With login off there is no session to lose: a 401 cannot come from it.
  if (!app.session || app.session.login !== false) goLogin();
});

async function loadSession() {
  const answer = await get("/api/session", { no401: true });
  if (answer.ok) {
    app.session = answer.data;
    scheduleSessionCheck();
    return true;
  }
  if (answer.status === 401) app.anonymousRead = answer.data?.anonymous_read === true;
  if (answer.status === 404) {
    // A supervisor without sessions: everyone on the loopback API operates.
    app.session = { user: "anonymous", role: "operator", login: false };
    return true;
  }
  app.session = null;
  return false;
}

/** The bench's layout: /api/bench, or (older supervisors) guessed from the tag names. */
async function loadBench() {
  const [answer, tags] = await Promise.all([get("/api/bench"), get("/api/tags")]);
  const names = tags.ok && Array.isArray(tags.data) ? tags.data.map((t) => t.name) : [];
  app.tagNames = new Set(names);
  if (answer.ok && Array.isArray(answer.data.channels)) return normaliseBench(answer.data);
  const channels = names
    .filter((n) => /^ch\d+\.voltage$/.test(n))
    .map((n) => n.split(".")[0])
    .map((ch) => ({ name: ch, tags: {} }));
  const devices = names
    .filter((n) => n.endsWith(".connected"))
    .map((n) => ({ name: n.split(".")[0], health_tag: n }));
  // No mimic without /api/bench: only the registry knows which device is the supply or
  // the BMS (issue 29: a supply named "psu" lost its rows when the screens guessed).
  return normaliseBench({ bench: "bench", channels, devices, mimic: {} });
}

function normaliseBench(b) {
  const tagNames = (ch, given) => ({
    voltage: `${ch}.voltage`,
    current: `${ch}.current`,
    temperature: `${ch}.temperature`,
    charge: `${ch}.chain.charge_ah`,
    state: `${ch}.chain.state`,
    channel_state: `${ch}.state`,
    current_cmd: `${ch}.current_cmd`,
    mode: `${ch}.mode`,
    step: `${ch}.chain.step`,
    progress: `${ch}.chain.progress`,
    eta: `${ch}.chain.eta_s`,
    fault: `${ch}.fault`,
    // /api/bench names every tag (null where the channel has none): keep its answer.
    ...(given || {}),
  });
  return {
    ...b,
    channels: (b.channels || []).map((c) => ({ ...c, tags: tagNames(c.name, c.tags) })),
    devices: b.devices || [],
    mimic: b.mimic || {},
  };
}

function paintHeader() {
  const top = $("#top");
  const s = app.session;
  top.hidden = !s;
  if (!s) return;
  $("#bench-name").textContent = app.bench?.bench || "bench";
  // The role in a part of its own: the header's fit may leave it to the tooltip.
  const who = $("#who");
  const role = s.login === false ? "" : ` (${t(`role.${s.role}`)})`;
  who.innerHTML = s.login === false ? esc(t("header.loginOff")) : `<span translate="no">${esc(s.user)}</span><span class="role">${esc(role)}</span>`;
  who.title = s.login === false ? "" : `${s.user}${role}`;
  $("#logout").hidden = s.login === false;
  const { path } = parseHash();
  const current = ROUTES.find(([re]) => re.test(path))?.[2];
  for (const a of document.querySelectorAll("[data-nav]")) {
    if (a.dataset.nav === current) a.setAttribute("aria-current", "page");
    else a.removeAttribute("aria-current");
  }
  paintChannelNav(current === "channel" ? decodeURIComponent(path.split("/")[2] || "") : "");
  // The audit trail is an engineer's (without logins, loopback only: everyone's); nobody
  // else gets its link (its address still answers them with the server's refusal).
  $("#nav-audit").hidden = !(s.role === "engineer" || s.login === false);
}

/** On a channel's screen the nav names that channel, highlighted (not Overview, which it
 * is not); elsewhere the entry is hidden. */
function paintChannelNav(name) {
  const a = $("#nav-channel");
  if (!a) return;
  a.hidden = !name;
  if (!name) return;
  // Its words and, for the header's fit, the name alone (one of the two shown: hmi.css).
  a.innerHTML = `<span class="nav-long">${esc(t("nav.channel", { ch: name }))}</span><span class="nav-short">${esc(name)}</span>`;
  a.title = t("nav.channel", { ch: name });
  a.href = `#/channel/${encodeURIComponent(name)}`;
}

function paintLink() {
  const el = $("#link");
  const labels = { live: "link.live", polling: "link.polling", down: "link.down", connecting: "link.connecting" };
  // An open connection that has gone silent is no longer "live" (stale.js).
  el.textContent = app.stale.silent ? t("link.noData") : labels[app.live.state] ? t(labels[app.live.state]) : app.live.state;
  el.classList.toggle("abn", app.live.state === "down" || app.stale.silent);
  repaintSummary(); // its word is on the header's line too
}

/** The bench summary of the header (summary.js), on every screen but the login. */
const headerFit = new HeaderFit($("#top"), (level) => paintSummary($("#summary"), app.bench, app.live, level));
function repaintSummary() {
  if (app.bench) headerFit.fit(JSON.stringify(benchCounts(app.bench, app.live)));
}
window.addEventListener("resize", repaintSummary);

function paintAlarmCount() {
  const active = app.live.alarms.filter((a) => a.state !== "normal" && !a.shelved);
  const unacked = active.filter((a) => a.state.includes("unacknowledged"));
  const el = $("#alarm-count");
  el.textContent = active.length ? String(active.length) : "";
  el.classList.toggle("abn", unacked.length > 0);
  // The alarm sound: once for a new alarm, repeating for high priorities (alarmsound.js),
  // for the logged-in user (a silence is theirs).
  app.alarmSound.setUser(app.session?.user || "");
  app.alarmSound.setRepeat(app.session?.alarm_sound_repeat_s);
  app.alarmSound.update(app.session ? app.live.alarms : []);
  const banner = $("#banner");
  const first = unacked[0];
  banner.hidden = !first || parseHash().path === "/login";
  if (first) {
    // The alarm's priority by shape and colour here too (ISA-101), not only on its screen.
    $("#banner-text").innerHTML = `${priorityIcon(first.severity)} <a href="#/alarms">${esc(first.first_out ? `${t("alarms.firstOut")} ` : "")}${esc(first.id)}: ${esc(alarmText(first))}</a>${unacked.length > 1 ? ` ${esc(t("banner.more", { n: unacked.length - 1, count: unacked.length - 1 }))}` : ""}`;
  }
}

// End of test: a channel's chain reaching Complete plays the end-of-test sound (seed 001).
const lastState = new Map();
function watchEnds(names) {
  for (const ch of app.bench?.channels || []) {
    const name = ch.tags.state;
    if (names && !names.includes(name)) continue;
    const v = app.live.value(name);
    const before = lastState.get(name);
    if (before !== undefined && before !== v && v === "Complete") app.sound.endOfTest();
    lastState.set(name, v);
  }
}

app.live.subscribe((change) => {
  if (change.kind === "state") {
    app.stale.follow(app.live.state);
    paintLink();
  }
  if (change.kind === "alarms") paintAlarmCount();
  if (change.kind === "tags") watchEnds(change.names);
  if (change.kind === "tags") app.stale.fresh();
  if (change.kind === "tags" || change.kind === "alarms") repaintSummary();
  if (app.screen?.update) app.screen.update(change);
});

// A restarted supervisor has forgotten every session: back to login, then to this page.
app.live.onReconnect = async () => {
  if (app.session && app.session.login !== false && !app.session.anonymous) {
    const answer = await get("/api/session", { no401: true });
    if (answer.status === 401) goLogin();
  }
};

app.live.onDisconnect = async () => {
  // A WebSocket refused before its upgrade (401) looks like any lost connection: ask.
  if (app.session && app.session.login !== false && !app.session.anonymous) {
    const answer = await get("/api/session", { no401: true });
    if (answer.status === 401) goLogin();
  }
};

// Routes can overlap (a hash change while the previous screen still loads): only the
// latest one renders.
let routeGen = 0;

async function route() {
  const gen = ++routeGen;
  const here = parseHash();
  const found = ROUTES.find(([re]) => re.test(here.path)) || ROUTES[1];
  const [re, mod] = found;
  if (mod !== login && !app.session && !(await loadSession())) {
    if (gen === routeGen) goLogin();
    return;
  }
  if (mod !== login && !app.bench) app.bench = await loadBench();
  if (gen !== routeGen) return;
  if (mod !== login && !app.live._started) {
    app.live._started = true;
    app.live.start();
  }
  if (app.screen?.destroy) app.screen.destroy();
  app.screen = null;
  // Each screen gets a <main> of its own: an answer that arrives after the operator left
  // lands in the old, detached tree (not in the next screen's, nor on null), and the
  // listeners a screen put on its root leave with it (a second visit to a screen must not
  // answer one click twice).
  const old = $("#main");
  const root = old.cloneNode(false);
  old.replaceWith(root);
  root.className = `screen-${found[2]}`;
  paintHeader();
  paintAlarmCount();
  repaintSummary();
  const params = here.path.match(re).slice(1);
  const screen = (await mod.render({ root, app, params, query: here.query })) || null;
  if (gen !== routeGen) {
    if (screen?.destroy) screen.destroy();
    return;
  }
  app.screen = screen;
  app.stale.setTitle(`${root.dataset.title || found[2]} — ${t("app.title")}`);
}

$("#logout").addEventListener("click", async () => {
  await post("/api/logout", {}, { no401: true });
  app.session = null;
  app.live.stop();
  app.live._started = false;
  location.hash = "#/login";
});

const sound = $("#sound");
sound.checked = app.sound.enabled;
sound.addEventListener("change", () => {
  app.sound.setEnabled(sound.checked);
  paintAlarmCount();
});

// On the alarm banner's line: "Alarm sounding — Silence" while a high-priority alarm
// repeats on this screen, and "sound blocked" while the browser waits for a gesture before
// it plays anything (a reload has had none; the login's click is one). The header's
// switch says it too, in its tooltip: the header's one line has no room for more.
function paintSounding() {
  const blocked = app.sound.blocked && Boolean(app.session);
  $("#alarm-silence").hidden = !app.alarmSound.active;
  $("#sound-blocked").hidden = !blocked;
  const label = $("#sound").closest("label");
  label.classList.toggle("blocked", blocked);
  label.title = blocked ? t("sound.blockedTitle") : t("sound.title");
}
app.alarmSound.onChange = paintSounding;
app.sound.onChange = paintSounding;
$("#alarm-silence").addEventListener("click", async () => {
  const answer = await app.alarmSound.silence();
  if (answer && !answer.ok) $("#alarm-silence").title = answer.data?.reason || t("sound.notSilenced");
});

// The session expires after hmi.session_timeout_s without a request (the WebSocket's
// messages do not count). The page asks again just after the time the supervisor gave:
// still open (another request used it) -> ask again later; expired -> the login screen,
// keeping the page's place. No periodic polling: it would keep an unattended panel's
// session open for ever.
let sessionTimer = null;
function scheduleSessionCheck() {
  clearTimeout(sessionTimer);
  const s = app.session;
  if (!s || s.login === false || typeof s.expires_s !== "number") return;
  sessionTimer = setTimeout(async () => {
    if (parseHash().path === "/login") return;
    const answer = await get("/api/session", { no401: true });
    if (answer.status === 401) goLogin();
    else if (answer.ok) {
      app.session = { ...app.session, ...answer.data };
      scheduleSessionCheck();
    }
  }, (s.expires_s + SESSION_SLACK_S) * 1000);
}
app.scheduleSessionCheck = scheduleSessionCheck;

// The language (i18n.js): the static page's texts now, and the switch in the header; a
// change repaints the header and renders the screen again in the new language.
// The switch is a button naming the other language in that language (never translated:
// whoever cannot read this one must find theirs), compact for the header's one line.
const LANGUAGE_NAMES = { en: "English", fr: "Français" };
const langButton = $("#lang");
function paintLangSwitch() {
  const other = lang() === "fr" ? "en" : "fr";
  langButton.textContent = other.toUpperCase();
  langButton.lang = other;
  langButton.dataset.lang = other;
  langButton.title = LANGUAGE_NAMES[other];
  langButton.setAttribute("aria-label", `${other.toUpperCase()} ${LANGUAGE_NAMES[other]}`);
}
translateStatic();
paintLangSwitch();
langButton.addEventListener("click", () => setLang(langButton.dataset.lang));
onLangChange(() => {
  paintLangSwitch();
  translateStatic();
  const el = $("#summary");
  if (el) delete el.dataset.key;
  headerFit.reset();
  paintLink();
  app.stale.paint();
  route();
});

window.addEventListener("hashchange", route);
app.stale.onChange = paintLink;
paintLink();
route();
