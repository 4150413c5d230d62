// The fleet page (hmi/fleet.html): its session (the HMI's login screen and rules: a 401
// -> login, then back), its language switch, and the fleet polled once a second.
import { get, onUnauthorized, post } from "./api.js";
import { $, esc } from "./dom.js";
import { lang, onLangChange, setLang, t, translateStatic } from "./i18n.js";
import * as login from "./screens/login.js";
import { paint } from "./screens/fleet.js";

const POLL_MS = 1000;
const root = $("#main");
const app = {
  session: null,
  anonymousRead: false,
  scheduleSessionCheck() {},
  // (login.js restarts a bench page's live connection; the fleet polls instead)
  live: { stop() {}, _started: false },
};
let timer = null;
let last = null;

function onLogin() {
  return location.hash.startsWith("#/login");
}

function goLogin() {
  app.session = null;
  if (!onLogin()) location.hash = "#/login?next=%23%2F";
}
onUnauthorized(goLogin);

function paintWho() {
  const s = app.session;
  $("#top").hidden = !s;
  if (!s) return;
  $("#who").innerHTML = s.login === false ? esc(t("header.loginOff")) : `<span translate="no">${esc(s.user)}</span> (${esc(t(`role.${s.role}`))})`;
  $("#logout").hidden = s.login === false;
}

async function poll() {
  clearTimeout(timer);
  if (onLogin()) return;
  const answer = await get("/api/fleet");
  if (answer.ok) {
    last = answer.data;
    paint(root, last);
  } else if (answer.status !== 401) {
    $("#link").textContent = t("fleet.unreachable");
    $("#link").classList.add("abn");
  }
  timer = setTimeout(poll, POLL_MS);
}

async function route() {
  clearTimeout(timer);
  if (onLogin()) {
    $("#top").hidden = true;
    document.title = t("fleet.title");
    await login.render({ root, app, query: new URLSearchParams(location.hash.split("?")[1] || "") });
    return;
  }
  if (!app.session) {
    const answer = await get("/api/session", { no401: true });
    if (!answer.ok) return goLogin();
    app.session = answer.data;
  }
  document.title = t("fleet.title");
  paintWho();
  if (last) paint(root, last);
  poll();
}

$("#logout").addEventListener("click", async () => {
  await post("/api/logout", {}, { no401: true });
  goLogin();
});

const langButton = $("#lang");
function paintLangSwitch() {
  const other = lang() === "fr" ? "en" : "fr";
  langButton.textContent = other.toUpperCase();
  langButton.lang = other;
  langButton.dataset.lang = other;
  langButton.setAttribute("aria-label", `${other.toUpperCase()} ${other === "fr" ? "Français" : "English"}`);
}
translateStatic();
paintLangSwitch();
langButton.addEventListener("click", () => setLang(langButton.dataset.lang));
onLangChange(() => {
  paintLangSwitch();
  translateStatic();
  route();
});
window.addEventListener("hashchange", route);
route();
