// Login: the same users and roles as OPC UA. After it, back to the page the operator was
// on (the `next` hash), so an expired session loses no place.
import { post, reasonOf } from "../api.js";
import { $, esc } from "../dom.js";
import { t } from "../i18n.js";

export async function render({ root, app, query }) {
  root.dataset.title = t("login.title");
  const tx = (key) => esc(t(key));
  const next = query.get("next") || "#/";
  root.innerHTML = `
    <form class="login panel" id="login-form" autocomplete="on">
      <h1>${tx("app.name")}</h1>
      <p class="muted">${query.get("expired") ? tx("login.expired") : tx("login.intro")}</p>
      <label for="login-user">${tx("login.user")}</label>
      <input id="login-user" name="user" autocomplete="username" required autofocus>
      <label for="login-password">${tx("login.password")}</label>
      <input id="login-password" name="password" type="password" autocomplete="current-password" required>
      <button type="submit" class="primary" id="login-submit">${tx("login.submit")}</button>
      <p id="login-result" class="result" role="status" hidden></p>
      ${app.anonymousRead ? `<button type="button" id="login-anonymous">${tx("login.anonymous")}</button>` : ""}
    </form>`;
  const anonymous = $("#login-anonymous", root);
  if (anonymous)
    anonymous.addEventListener("click", () => {
      // hmi.anonymous_read: the screens answer a visitor as a viewer; any command asks
      // for a login (401), which brings the visitor back here.
      app.session = { user: "visitor", role: "viewer", login: true, anonymous: true };
      location.hash = next.startsWith("#") && !next.startsWith("#/login") ? next : "#/";
    });
  const form = $("#login-form", root);
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const out = $("#login-result", root);
    const answer = await post(
      "/api/login",
      { user: form.user.value, password: form.password.value },
      { no401: true },
    );
    if (!answer.ok) {
      out.hidden = false;
      out.classList.add("refused");
      out.textContent = t("login.refused", { reason: reasonOf(answer) });
      form.password.select();
      return;
    }
    app.session = { login: true, ...answer.data };
    app.scheduleSessionCheck();
    // A fresh session: the live connection re-authenticates with its cookie.
    app.live.stop();
    app.live._started = false;
    location.hash = next.startsWith("#") && !next.startsWith("#/login") ? next : "#/";
  });
  return null;
}
