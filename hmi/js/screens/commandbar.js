// A channel's command bar (issue 33, finding 2): load a recipe, the chain's commands, Auto
// and Manual, the manual setpoint, and forcing (engineers). Each button follows the state:
// the supervisor says which commands its command path would accept now and why not
// (GET /api/channels/{ch}/commands, the command path's own checks), asked again when the
// channel's state, mode, enable, trip or the alarms change. A button the path would refuse
// is aria-disabled (still focusable: a tap or a click shows the reason, nothing is sent)
// with the reason as its tooltip. Commands that end or close a test, and forcing, ask
// first in a dialog naming the channel and the test (docs/adr/0039-command-bar.md).
import { api, get, post, put } from "../api.js";
import { esc, showResult, $, $$ } from "../dom.js";
import { t as tr, tValue } from "../i18n.js";

// The chain's commands, each labelled by its catalogue key verb.NAME (i18n.js).
export const VERBS = ["start", "hold", "resume", "advance", "stop", "abort", "reset", "acknowledge"].map((v) => [v, `verb.${v}`]);

/** What each confirmed command does, for its dialog (channel, test, state filled in):
 * its title verb.NAME and its text confirm.NAME in the catalogue. */
const CONFIRM = {
  stop: { title: "verb.stop", text: "confirm.stop" },
  abort: { title: "verb.abort", text: "confirm.abort" },
  reset: { title: "verb.reset", text: "confirm.reset" },
  force: { title: "verb.force", text: "confirm.force" },
};

/** The bar's HTML (the Commands panel's content). */
export function commandBarHtml(viewer) {
  const tx = (key) => esc(tr(key));
  return `<h2>${tx("commands.title")}</h2>
      ${viewer ? `<p class="muted">${tx("commands.viewer")}</p>` : ""}
      <form id="load-form" class="load">
        <label for="load-recipe">${tx("commands.recipe")}</label>
        <input id="load-recipe" list="recipe-list" placeholder="recipes/capacity-test.yaml" required>
        <datalist id="recipe-list"></datalist>
        <label for="load-params">${tx("commands.parameters")} <small class="muted">${tx("commands.parametersHint")}</small></label>
        <textarea id="load-params" rows="3" spellcheck="false"></textarea>
        <label for="load-cell">${tx("commands.cell")} <small class="muted">${tx("commands.cellHint")}</small></label>
        <input id="load-cell" maxlength="64" pattern="[A-Za-z0-9 ._:/+\\-]*" autocomplete="off" spellcheck="false">
        <label for="load-comment">${tx("commands.comment")} <small class="muted">${tx("commands.commentHint")}</small></label>
        <textarea id="load-comment" rows="2" maxlength="500"></textarea>
        <button type="submit" id="cmd-load" data-bar="load">${tx("commands.load")}</button>
      </form>
      <div class="buttons" role="group" aria-label="${tx("commands.chain")}">
        ${VERBS.map(([v, l]) => `<button type="button" data-verb="${v}" data-bar="${v}" id="cmd-${v}">${tx(l)}</button>`).join("")}
      </div>
      <div class="buttons" role="group" aria-label="${tx("commands.mode")}">
        <button type="button" id="cmd-auto" data-mode="auto" data-bar="mode_auto">${tx("commands.auto")}</button>
        <button type="button" id="cmd-manual" data-mode="manual" data-bar="mode_manual">${tx("commands.manual")}</button>
      </div>
      <form id="manual-form" class="manual">
        <label for="manual-current">${tx("commands.manualCurrent")}</label>
        <input id="manual-current" type="number" step="0.001" required>
        <button type="submit" id="cmd-manual-current" data-bar="manual_current">${tx("commands.set")}</button>
        <button type="button" id="cmd-enable" data-enable="true" data-bar="enable_on">${tx("commands.enable")}</button>
        <button type="button" id="cmd-disable" data-enable="false" data-bar="enable_off">${tx("commands.disable")}</button>
      </form>
      <form id="force-form" class="force" hidden>
        <label for="force-tag">${tx("commands.forceTag")} <small class="muted">${tx("commands.forceHint")}</small></label>
        <input id="force-tag" list="force-tags" required autocomplete="off" spellcheck="false">
        <datalist id="force-tags"></datalist>
        <label for="force-value">${tx("commands.value")}</label>
        <input id="force-value" required autocomplete="off" spellcheck="false">
        <span class="buttons">
          <button type="submit" id="cmd-force" data-bar="force">${tx("verb.force")}</button>
          <button type="button" id="cmd-unforce" data-bar="force">${tx("verb.unforce")}</button>
        </span>
      </form>
      <p id="cmd-result" class="result" role="status" aria-live="polite" hidden></p>
      <dialog id="cmd-confirm" class="confirm" aria-labelledby="cmd-confirm-title" aria-describedby="cmd-confirm-text">
        <h2 id="cmd-confirm-title"></h2>
        <p id="cmd-confirm-what"></p>
        <p id="cmd-confirm-text"></p>
        <div class="buttons">
          <button type="button" id="cmd-confirm-yes"></button>
          <button type="button" id="cmd-confirm-no" autofocus>${tx("common.cancel")}</button>
        </div>
      </dialog>`;
}

/** "name = value" lines into {name: value} (numbers stay text: units such as "0.5 C"). */
export function parseParameters(text) {
  const out = {};
  const errors = [];
  text.split("\n").forEach((line, i) => {
    const s = line.trim();
    if (!s || s.startsWith("#")) return;
    const m = s.match(/^([A-Za-z_][\w.]*)\s*[=:]\s*(.+)$/);
    if (!m) {
      errors.push(tr("commands.parameterLine", { line: i + 1, got: JSON.stringify(s) }));
      return;
    }
    const raw = m[2].trim();
    out[m[1]] = /^-?\d+(\.\d+)?(e-?\d+)?$/i.test(raw) ? Number(raw) : raw;
  });
  return { parameters: out, errors };
}

/**
 * Wire the bar rendered by commandBarHtml inside `root`. `onLoaded()` after a recipe is
 * loaded. Returns {update(change), destroy()} for the channel screen to call.
 */
export function mountCommandBar({ root, app, name, ch, onLoaded }) {
  const t = ch.tags;
  const p = `${name}.`;
  const out = $("#cmd-result", root);
  const bar = $("section.commands", root) || root;
  const dialog = $("#cmd-confirm", root);
  const base = `/api/channels/${encodeURIComponent(name)}`;
  let answers = null; // the last GET …/commands answer's "commands"
  let info = {}; // … and its channel's state, recipe and test
  let asking = null;
  let askAgain = false;
  let gone = false;

  const busy = (text) => {
    out.hidden = false;
    out.classList.remove("refused", "accepted");
    out.textContent = text;
  };

  // --- which buttons the command path would accept now ----------------------------------
  // Not known (before the first answer, or the supervisor did not answer): every button
  // goes, and the supervisor checks the command when it is given.
  const paint = () => {
    for (const b of $$("[data-bar]", bar)) {
      const a = answers?.[b.dataset.bar];
      const ok = !a || a.accepted;
      b.setAttribute("aria-disabled", String(!ok));
      if (ok) b.removeAttribute("title");
      else b.title = a.reason;
    }
    // Forcing is for engineers: the form is shown only to whom the path would let force.
    $("#force-form", root).hidden = !answers?.force?.accepted;
  };
  const ask = async () => {
    if (asking) {
      askAgain = true;
      return asking;
    }
    asking = (async () => {
      do {
        askAgain = false;
        const answer = await get(`${base}/commands`);
        if (gone) return;
        answers = answer.ok && answer.data.commands ? answer.data.commands : null;
        info = answers ? answer.data : info;
        paint();
        bar.dataset.asked = String(Number(bar.dataset.asked || 0) + 1);
      } while (askAgain && !gone);
    })();
    try {
      await asking;
    } finally {
      asking = null;
    }
  };
  paint();
  ask();
  // The tags the command path's checks read (state, mode, enable, trip, the chain's alarm,
  // its recipe and test); the bench's alarms come as their own change.
  const watched = new Set(
    [t.state, t.mode, t.enable, t.fault, t.alarm, t.recipe, t.test_id].filter(Boolean),
  );

  /** Does the button say no? Then its refusal is shown, worded as one sent, and nothing
   * is sent. Before the first answer nothing is known: the command goes, and the
   * supervisor checks it as it checks every command. */
  const refusedAhead = (b) => {
    const a = answers?.[b?.dataset.bar];
    if (!a || a.accepted) return false;
    showResult(out, { ok: false, status: a.status || 409, data: { reason: a.reason } });
    return true;
  };

  // --- confirmations ---------------------------------------------------------------------
  let onYes = null;
  const confirmThen = (key, what, action) => {
    const c = CONFIRM[key];
    // The live values (the freshest), else what the supervisor said with its answer.
    const live = (tag, known) => (tag && app.live.value(tag) !== undefined ? app.live.value(tag) : known);
    const test = live(t.test_id, info.test_id) || tr("value.none");
    const recipe = live(t.recipe, info.recipe) || tr("value.none");
    const state = tValue("chain", live(t.state, info.state)) || tr("value.unknown");
    const title = tr(c.title);
    $("#cmd-confirm-title", root).textContent = tr("confirm.title", { verb: title, ch: name, test });
    $("#cmd-confirm-what", root).textContent =
      `${what ? `${what} — ` : ""}${tr("confirm.what", { ch: name, test, recipe, state })}`;
    $("#cmd-confirm-text", root).textContent = tr(c.text);
    $("#cmd-confirm-yes", root).textContent = tr("confirm.yes", { verb: title, ch: name });
    onYes = action;
    dialog.showModal();
  };
  $("#cmd-confirm-no", root).addEventListener("click", () => dialog.close());
  dialog.addEventListener("close", () => {
    onYes = null;
  });
  $("#cmd-confirm-yes", root).addEventListener("click", () => {
    const action = onYes;
    dialog.close();
    if (action) action();
  });

  // --- the commands ----------------------------------------------------------------------
  const command = async (verb, args = {}) => {
    busy(`${tr(`verb.${verb}`)}…`);
    const answer = await post(`${base}/commands/${verb}`, args);
    showResult(out, answer);
    ask();
    return answer;
  };
  // The test's metadata (docs/recipes.md "Test records"): given fields only; the server checks them.
  const metadata = () => {
    const m = {};
    const cell = $("#load-cell", root).value.trim();
    const comment = $("#load-comment", root).value.trim();
    if (cell) m.cell_id = cell;
    if (comment) m.comment = comment;
    return m;
  };
  const finished = () => ["Complete", "Stopped", "Aborted"].includes(app.live.value(t.state) ?? info.state);
  for (const b of $$("[data-verb]", bar))
    b.addEventListener("click", () => {
      if (refusedAhead(b)) return;
      const verb = b.dataset.verb;
      const send = () => command(verb, verb === "start" ? metadata() : {});
      // Stop and Abort end a test; Reset closes a finished one: asked first.
      if (verb === "stop" || verb === "abort" || (verb === "reset" && finished())) confirmThen(verb, "", send);
      else send();
    });
  for (const b of $$("[data-mode]", bar))
    b.addEventListener("click", () => {
      if (!refusedAhead(b)) command("mode", { value: b.dataset.mode });
    });
  for (const b of $$("[data-enable]", bar))
    b.addEventListener("click", () => {
      if (!refusedAhead(b)) command("enable", { value: b.dataset.enable === "true" });
    });
  $("#manual-form", root).addEventListener("submit", (ev) => {
    ev.preventDefault();
    if (refusedAhead($("#cmd-manual-current", root))) return;
    command("manual_current", { value: Number($("#manual-current", root).value) });
  });

  // --- forcing (engineers): through the same command path, asked first -------------------
  const forceTags = $("#force-tags", root);
  for (const tagName of app.live.tags.keys()) {
    if (!tagName.startsWith(p)) continue;
    const o = document.createElement("option");
    o.value = tagName;
    forceTags.append(o);
  }
  $("#force-form", root).addEventListener("submit", (ev) => {
    ev.preventDefault();
    if (refusedAhead($("#cmd-force", root))) return;
    const tag = $("#force-tag", root).value.trim();
    const value = $("#force-value", root).value;
    confirmThen("force", tr("confirm.forceWhat", { tag, value }), async () => {
      busy(`${tr("verb.force")}…`);
      showResult(out, await put(`/api/tags/${encodeURIComponent(tag)}/force`, { value }));
      ask();
    });
  });
  $("#cmd-unforce", root).addEventListener("click", async () => {
    if (refusedAhead($("#cmd-unforce", root))) return;
    const tag = $("#force-tag", root).value.trim();
    busy(`${tr("verb.unforce")}…`);
    showResult(out, await api("DELETE", `/api/tags/${encodeURIComponent(tag)}/force`, {}));
    ask();
  });

  // --- loading a recipe ------------------------------------------------------------------
  const recipeInput = $("#load-recipe", root);
  const paramsInput = $("#load-params", root);
  $("#load-form", root).addEventListener("submit", async (ev) => {
    ev.preventDefault();
    if (refusedAhead($("#cmd-load", root))) return;
    const { parameters, errors } = parseParameters(paramsInput.value);
    if (errors.length) {
      showResult(out, { ok: false, status: 400, data: { reason: errors.join("; ") } });
      return;
    }
    busy(tr("commands.loading"));
    const answer = await put(`${base}/recipe`, {
      file: recipeInput.value.trim(),
      parameters,
      ...metadata(),
    });
    showResult(out, answer, tr("commands.loaded"));
    ask();
    if (answer.ok && onLoaded) onLoaded();
  });
  // The recipes the supervisor knows (if it lists them), their parameters when chosen.
  const known = new Map();
  get("/api/recipes").then((answer) => {
    if (gone || !answer.ok || !Array.isArray(answer.data.recipes)) return;
    const list = $("#recipe-list", root);
    for (const r of answer.data.recipes) {
      known.set(r.file || r.name, r);
      const o = document.createElement("option");
      o.value = r.file || r.name;
      o.label = r.title || r.name;
      list.append(o);
    }
  });
  recipeInput.addEventListener("change", async () => {
    const r = known.get(recipeInput.value);
    if (!r || paramsInput.value.trim()) return;
    const text = await get(`/api/recipes/${encodeURIComponent(r.name)}`);
    if (!text.ok) return;
    const v = await post("/api/recipes/validate", { text: text.data.text, name: r.name });
    if (v.ok && Array.isArray(v.data.parameters)) {
      paramsInput.value = v.data.parameters
        .map((prm) => (typeof prm === "string" ? `${prm} = ` : `${prm.name} = ${prm.default ?? prm.value ?? ""}`))
        .join("\n");
    }
  });

  return {
    update(change) {
      if (change.kind === "alarms" || change.kind === "state") ask();
      else if (change.kind === "tags" && (!change.names || change.names.some((n) => watched.has(n)))) ask();
    },
    destroy() {
      gone = true;
      if (dialog.open) dialog.close();
    },
  };
}
