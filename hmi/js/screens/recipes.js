// Recipes: the list, the YAML in an editor with line numbers, validation errors shown at
// their line (the supervisor's own messages, as `supervisor check`), and a dry-run preview
// (timeline, duration, capacity per cycle) before anything is saved or started.
// Load profile (seed 002's Tk HMI, issue 32): a profile CSV uploaded or picked from the
// recipes folder, previewed (table, chart, what the reader noticed), refused at its file,
// line and column, dry-run on the chosen channel, loaded onto it and started.
import { get, post, put, reasonOf } from "../api.js";
import { esc, fmtDuration, fmtTime, showResult, $ } from "../dom.js";
import { simplePlot, timeAxis, timelinePlot } from "../chart.js";
import { fmtNumber, t } from "../i18n.js";

const tx = (key, params) => esc(t(key, params));

export async function render({ root, app, params }) {
  root.dataset.title = t("nav.recipes");
  const current = params[0] ? decodeURIComponent(params[0]) : "";
  root.innerHTML = `
    <h1>${tx("nav.recipes")}</h1>
    <div class="recipes-grid">
      <section class="panel" aria-label="${tx("recipes.listLabel")}"><h2>${tx("recipes.list")}</h2><div id="recipe-list"><p class="muted">…</p></div>
        <button type="button" id="recipe-new">${tx("recipes.new")}</button></section>
      <section class="panel editor-panel" aria-label="${tx("recipes.editor")}">
        <div class="editor-bar">
          <label for="recipe-name">${tx("recipes.name")}</label><input id="recipe-name" value="${esc(current)}" placeholder="${tx("recipes.namePlaceholder")}" required>
          <label class="file">${tx("recipes.uploadYaml")} <input type="file" id="recipe-file" accept=".yaml,.yml,text/yaml"></label>
        </div>
        <div class="editor" id="editor">
          <pre class="gutter" id="gutter" aria-hidden="true"></pre>
          <textarea id="recipe-text" spellcheck="false" wrap="off" aria-label="${tx("recipes.yaml")}" aria-describedby="recipe-errors"></textarea>
        </div>
        <ul id="recipe-errors" class="errors" aria-live="polite"></ul>
        <div class="buttons">
          <button type="button" id="recipe-validate">${tx("recipes.validate")}</button>
          <label for="dry-params">${tx("commands.parameters")}</label><input id="dry-params" placeholder="${tx("recipes.paramsPlaceholder")}" size="24">
          <button type="button" id="recipe-dryrun">${tx("recipes.dryRun")}</button>
          <button type="button" id="recipe-save" class="primary">${tx("recipes.save")}</button>
          <label><input type="checkbox" id="recipe-overwrite"> ${tx("recipes.overwrite")}</label>
        </div>
        <p id="recipe-result" class="result" role="status" aria-live="polite" hidden></p>
      </section>
      <section class="panel preview" aria-label="${tx("recipes.dryRunPreview")}" id="preview" hidden>
        <h2>${tx("recipes.dryRun")}</h2>
        <p id="dry-summary"></p>
        <div id="dry-timeline" class="plot"></div>
        <div id="dry-cycles" class="plot"></div>
        <div id="dry-trace" class="plot"></div>
      </section>
      <section class="panel preview" aria-label="${tx("profile.title")}" id="profile-panel">
        <h2>${tx("profile.title")}</h2>
        <div class="editor-bar">
          <label class="file">${tx("profile.uploadCsv")} <input type="file" id="profile-file" accept=".csv,.txt,text/csv"></label>
          <label for="profile-pick">${tx("profile.fromFolder")}</label><select id="profile-pick"><option value="">—</option></select>
          <label for="profile-channel">${tx("profile.channel")}</label><select id="profile-channel"></select>
        </div>
        <p id="profile-summary" class="muted">${tx("profile.none")}</p>
        <ul id="profile-errors" class="errors" aria-live="polite"></ul>
        <ul id="profile-notices" aria-live="polite"></ul>
        <div id="profile-chart" class="plot"></div>
        <div id="profile-table-wrap"></div>
        <div class="buttons">
          <button type="button" id="profile-dryrun" disabled>${tx("recipes.dryRun")}</button>
          <button type="button" id="profile-load" disabled>${tx("profile.load")}</button>
          <button type="button" id="profile-start" class="primary" disabled>${tx("verb.start")}</button>
        </div>
        <p id="profile-result" class="result" role="status" aria-live="polite" hidden></p>
        <div id="profile-dry" class="plot"></div>
      </section>
    </div>`;
  const text = $("#recipe-text", root);
  const gutter = $("#gutter", root);
  const errorsEl = $("#recipe-errors", root);
  const out = $("#recipe-result", root);
  const nameInput = $("#recipe-name", root);
  let errorLines = new Map();
  const plots = [];

  const paintGutter = () => {
    const n = text.value.split("\n").length;
    let html = "";
    for (let i = 1; i <= n; i++) {
      const err = errorLines.get(i);
      html += err ? `<span class="err" title="${esc(err)}" data-line="${i}">${i} !</span>\n` : `${i}\n`;
    }
    gutter.innerHTML = html;
    gutter.scrollTop = text.scrollTop;
  };
  text.addEventListener("input", () => {
    paintGutter();
  });
  text.addEventListener("scroll", () => {
    gutter.scrollTop = text.scrollTop;
  });

  const goToLine = (line) => {
    const lines = text.value.split("\n");
    const start = lines.slice(0, line - 1).reduce((s, l) => s + l.length + 1, 0);
    text.focus();
    text.setSelectionRange(start, start + (lines[line - 1] || "").length);
    const lh = parseFloat(getComputedStyle(text).lineHeight) || 18;
    text.scrollTop = Math.max(0, (line - 3) * lh);
  };

  const showErrors = (errors) => {
    errorLines = new Map();
    for (const e of errors) {
      if (e.line) errorLines.set(e.line, (errorLines.get(e.line) ? errorLines.get(e.line) + "; " : "") + e.message);
    }
    errorsEl.innerHTML = errors
      .map(
        (e) =>
          `<li class="refused">${e.line ? `<a href="#" data-line="${e.line}">${tx("recipes.line", { line: e.line })}${e.column ? `:${e.column}` : ""}</a>: ` : ""}${esc(e.message)}</li>`,
      )
      .join("");
    paintGutter();
  };
  errorsEl.addEventListener("click", (ev) => {
    const a = ev.target.closest("a[data-line]");
    if (!a) return;
    ev.preventDefault();
    goToLine(Number(a.dataset.line));
  });

  /** Errors of an answer: 422 {errors:[{line,column,message}]} or a reason. */
  const errorsOf = (answer) =>
    Array.isArray(answer.data.errors) ? answer.data.errors : [{ message: answer.data.reason || answer.data.error || `HTTP ${answer.status}` }];

  const validate = async () => {
    const answer = await post("/api/recipes/validate", { text: text.value, name: nameInput.value || undefined });
    if (answer.ok && answer.data.ok !== false) {
      showErrors([]);
      const prm = (answer.data.parameters || []).map((x) => (typeof x === "string" ? x : x.name)).join(", ");
      showResult(out, { ok: true, data: { reason: `${t("recipes.valid", { steps: answer.data.steps ?? "?" })}${prm ? t("recipes.validParams", { names: prm }) : ""}` } });
    } else {
      showErrors(errorsOf(answer));
      showResult(out, { ok: false, status: answer.status, data: { reason: t("recipes.errors", { n: errorsOf(answer).length, count: errorsOf(answer).length }) } });
    }
    return answer;
  };

  const parseDryParams = () => {
    const o = {};
    for (const part of $("#dry-params", root).value.split(",")) {
      const [k, ...v] = part.split("=");
      if (k.trim() && v.length) {
        const raw = v.join("=").trim();
        o[k.trim()] = /^-?\d+(\.\d+)?$/.test(raw) ? Number(raw) : raw;
      }
    }
    return o;
  };

  const dryRun = async () => {
    showResult(out, { ok: true, data: { reason: t("recipes.dryRunning") } });
    const answer = await post("/api/recipes/dryrun", { text: text.value, parameters: parseDryParams() });
    if (!answer.ok || answer.data.ok === false) {
      showErrors(errorsOf(answer));
      showResult(out, answer);
      return;
    }
    showErrors([]);
    const d = answer.data;
    const summary = t("recipes.drySummary", {
      duration: fmtDuration(d.duration_s),
      end: d.end_reason || "—",
      n: (d.cycles || []).length,
      count: (d.cycles || []).length,
    });
    // The status line stays (it said "dry run…": it now says how it went), and the
    // preview, right under the editor, is brought into view (issue 33, finding 6: it
    // vanished and the result sat below the fold).
    showResult(out, { ok: true, data: { reason: t("recipes.dryDone", { summary }) } });
    const preview = $("#preview", root);
    preview.hidden = false;
    $("#dry-summary", root).textContent = summary;
    while (plots.length) {
      const pl = plots.pop();
      pl.stop();
      pl.chart.destroy();
    }
    const ax = timeAxis(d.duration_s || 0);
    const timeline = timelinePlot($("#dry-timeline", root), d.timeline, d.duration_s);
    if (timeline) plots.push(timeline);
    const cycles = d.cycles || [];
    if (cycles.length) {
      const big = cycles.some((c) => Math.abs(c.charge_ah || 0) >= 1 || Math.abs(c.discharge_ah || 0) >= 1);
      const k = big ? 1 : 1000;
      const unit = big ? "Ah" : "mAh";
      plots.push(
        simplePlot($("#dry-cycles", root), {
          title: t("recipes.predictedCapacity", { unit }),
          xLabel: t("plot.cycle"),
          yLabel: unit,
          series: [{ label: `${t("quantity.charge")} ${unit}` }, { label: `${t("quantity.discharge")} ${unit}` }],
          x: cycles.map((c) => c.cycle),
          ys: [cycles.map((c) => (c.charge_ah ?? 0) * k), cycles.map((c) => (c.discharge_ah ?? 0) * k)],
          bars: true,
        }),
      );
    }
    const tr = d.trace;
    if (tr && tr.t_s && tr.t_s.length) {
      plots.push(
        simplePlot($("#dry-trace", root), {
          title: t("recipes.predictedVI"),
          xLabel: ax.unit,
          series: [{ label: "V" }, { label: "A" }],
          x: tr.t_s.map((s) => s / ax.scale),
          ys: [tr.voltage_v, tr.current_a],
        }),
      );
    }
    out.scrollIntoView({ block: "start" });
  };

  const save = async () => {
    const name = nameInput.value.trim();
    if (!name) {
      showResult(out, { ok: false, status: 400, data: { reason: t("recipes.needName") } });
      nameInput.focus();
      return;
    }
    const answer = await put(`/api/recipes/${encodeURIComponent(name)}`, {
      text: text.value,
      overwrite: $("#recipe-overwrite", root).checked,
    });
    if (answer.status === 422) {
      showErrors(errorsOf(answer));
      showResult(out, { ok: false, status: 422, data: { reason: t("recipes.notSaved") } });
      return;
    }
    showErrors([]);
    showResult(out, answer, t("recipes.saved", { name }));
    if (answer.ok) loadList();
  };

  const loadList = async () => {
    const answer = await get("/api/recipes");
    const el = $("#recipe-list", root);
    if (!answer.ok) {
      el.innerHTML = `<p class="muted">${esc(answer.data.reason || answer.data.error || `HTTP ${answer.status}`)}</p>`;
      return;
    }
    el.innerHTML = `<ul class="links" id="recipe-items">${(answer.data.recipes || [])
      .map(
        (r) => `<li><a href="#/recipes/${encodeURIComponent(r.name)}" ${r.name === current ? 'aria-current="page"' : ""}>${esc(r.name)}</a>
        <small class="muted">${esc(r.title || "")} ${r.modified ? esc(fmtTime(r.modified)) : ""}</small></li>`,
      )
      .join("")}</ul>`;
  };

  const loadRecipe = async (name) => {
    const answer = await get(`/api/recipes/${encodeURIComponent(name)}`);
    if (!answer.ok) {
      showResult(out, answer);
      return;
    }
    text.value = answer.data.text || "";
    paintGutter();
  };

  $("#recipe-validate", root).addEventListener("click", validate);
  $("#recipe-dryrun", root).addEventListener("click", dryRun);
  $("#recipe-save", root).addEventListener("click", save);
  $("#recipe-new", root).addEventListener("click", () => {
    location.hash = "#/recipes";
  });
  $("#recipe-file", root).addEventListener("change", async (ev) => {
    const file = ev.target.files[0];
    if (!file) return;
    text.value = await file.text();
    if (!nameInput.value) nameInput.value = file.name.replace(/\.ya?ml$/i, "");
    paintGutter();
    validate();
  });

  const profile = profilePanel(root, app);
  paintGutter();
  loadList();
  if (current) loadRecipe(current);
  return {
    destroy() {
      while (plots.length) plots.pop().stop();
      profile.destroy();
    },
  };
}

// (symbols and SI units: the same in both languages)
const PROFILE_FIELDS = [
  ["t_s", "t (s)"],
  ["current_a", "I (A)"],
  ["v_min", "V min"],
  ["v_max", "V max"],
  ["i_min", "I min"],
  ["i_max", "I max"],
  ["t_min", "T min"],
  ["t_max", "T max"],
];

/** A profile's number in the locale's format, its digits as given (up to 6 significant). */
const fmtPlain = (v) => (Number.isInteger(v) ? String(v) : fmtNumber(v, Math.min(6, Math.max(0, (String(v).split(".")[1] || "").length))));

/** A file's bytes as base64: the server finds its encoding (UTF-8 or CP1252) as from a file. */
async function base64Of(file) {
  const bytes = new Uint8Array(await file.arrayBuffer());
  let bin = "";
  for (let i = 0; i < bytes.length; i += 0x8000) bin += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
  return btoa(bin);
}

/** The "Load profile" panel: its state is the profile's source and the recipe made of it. */
function profilePanel(root, app) {
  const el = (id) => $(`#${id}`, root);
  const out = el("profile-result");
  const plots = [];
  let source = null; // {csv_base64, name} or {file}
  let made = null; // the preview's answer
  const channel = () => el("profile-channel").value;
  const buttons = ["profile-dryrun", "profile-load", "profile-start"].map(el);
  const clearPlots = () => {
    while (plots.length) {
      const pl = plots.pop();
      pl.stop();
      pl.chart.destroy();
    }
  };
  const enable = (ok) => {
    buttons[0].disabled = buttons[1].disabled = !ok;
    buttons[2].disabled = true; // after a load only
  };

  const channels = (app.bench?.channels || []).map((c) => c.name);
  el("profile-channel").innerHTML = channels.map((n) => `<option value="${esc(n)}">${esc(n)}</option>`).join("");

  const showTable = (rows, total) => {
    const used = PROFILE_FIELDS.filter(([k]) => rows.some((r) => r[k] !== null && r[k] !== undefined));
    const more = total > rows.length ? `<caption>${tx("profile.firstRows", { n: rows.length, total })}</caption>` : "";
    el("profile-table-wrap").innerHTML = `<table class="grid" id="profile-table">${more}
      <thead><tr>${used.map(([, h]) => `<th>${esc(h)}</th>`).join("")}</tr></thead>
      <tbody>${rows.map((r) => `<tr>${used.map(([k]) => `<td>${typeof r[k] === "number" ? fmtPlain(r[k]) : esc(r[k] ?? "")}</td>`).join("")}</tr>`).join("")}</tbody></table>`;
  };

  const preview = async () => {
    if (!source) return;
    enable(false);
    made = null;
    clearPlots();
    el("profile-table-wrap").innerHTML = "";
    el("profile-notices").innerHTML = "";
    el("profile-errors").innerHTML = "";
    el("profile-summary").textContent = t("profile.reading");
    const answer = await post("/api/profiles/preview", { ...source, channel: channel() || undefined });
    if (!answer.ok) {
      const errors = Array.isArray(answer.data.errors) ? answer.data.errors : [{ text: reasonOf(answer) }];
      el("profile-errors").innerHTML = errors.map((e) => `<li class="refused">${esc(e.text || e.message)}</li>`).join("");
      el("profile-summary").textContent = t("profile.refused");
      return;
    }
    made = answer.data;
    el("profile-summary").textContent = t("profile.summary", { rows: made.rows, duration: fmtDuration(made.duration_s), recipe: made.recipe });
    el("profile-notices").innerHTML = made.notices.map((n) => `<li class="notice">${esc(n)}</li>`).join("");
    showTable(made.table, made.rows);
    const ax = timeAxis(made.duration_s || 0);
    plots.push(
      simplePlot(el("profile-chart"), {
        title: t("profile.chartTitle"),
        xLabel: ax.unit,
        series: [{ label: "A" }],
        x: made.chart.t_s.map((t) => t / ax.scale),
        ys: [made.chart.current_a],
        stepped: true,
      }),
    );
    enable(true);
  };

  const dryRun = async () => {
    if (!made) return;
    showResult(out, { ok: true, data: { reason: t("recipes.dryRunning") } });
    const answer = await post("/api/recipes/dryrun", { text: made.text, name: made.recipe, channel: channel() });
    if (!answer.ok || answer.data.ok === false) {
      showResult(out, { ...answer, ok: false });
      return;
    }
    const d = answer.data;
    const outcome = d.finished ? t("profile.completes") : t("profile.doesNotComplete");
    showResult(out, { ok: true, data: { reason: t("profile.dryResult", { ch: channel(), duration: fmtDuration(d.duration_s), outcome, end: d.end_reason || "—" }) } });
    out.dataset.dryrun = d.finished ? "finished" : "unfinished";
    const tr = d.trace;
    if (tr && tr.t_s && tr.t_s.length) {
      const ax = timeAxis(d.duration_s || 0);
      plots.push(
        simplePlot(el("profile-dry"), {
          title: t("profile.dryTitle"),
          xLabel: ax.unit,
          series: [{ label: "V" }, { label: "A" }],
          x: tr.t_s.map((s) => s / ax.scale),
          ys: [tr.voltage_v, tr.current_a],
        }),
      );
    }
    out.scrollIntoView({ block: "start" });
  };

  const load = async () => {
    if (!source) return;
    showResult(out, { ok: true, data: { reason: t("profile.loading", { ch: channel() }) } });
    const answer = await post("/api/profiles/load", { ...source, channel: channel() });
    showResult(out, answer, t("profile.loaded", { recipe: made?.recipe || t("profile.profile"), ch: channel() }));
    delete out.dataset.dryrun;
    buttons[2].disabled = !answer.ok;
  };

  const start = async () => {
    const ch = channel();
    showResult(out, { ok: true, data: { reason: t("profile.starting", { ch }) } });
    const answer = await post(`/api/channels/${encodeURIComponent(ch)}/commands/start`, {});
    showResult(out, answer, t("profile.started", { ch }));
    if (answer.ok) {
      out.insertAdjacentHTML("beforeend", ` <a href="#/channel/${encodeURIComponent(ch)}" id="profile-goto">${tx("profile.see", { ch })}</a>`);
    }
  };

  const listProfiles = async () => {
    const answer = await get("/api/profiles");
    if (!answer.ok) return;
    el("profile-pick").innerHTML =
      `<option value="">—</option>` +
      (answer.data.profiles || []).map((p) => `<option value="${esc(p.name)}">${esc(p.name)}</option>`).join("");
  };

  el("profile-file").addEventListener("change", async (ev) => {
    const file = ev.target.files[0];
    if (!file) return;
    source = { csv_base64: await base64Of(file), name: file.name };
    el("profile-pick").value = "";
    preview();
  });
  el("profile-pick").addEventListener("change", (ev) => {
    source = ev.target.value ? { file: ev.target.value } : null;
    preview();
  });
  el("profile-channel").addEventListener("change", preview);
  buttons[0].addEventListener("click", dryRun);
  buttons[1].addEventListener("click", async () => {
    await load();
    listProfiles();
  });
  buttons[2].addEventListener("click", start);
  listProfiles();
  return { destroy: clearPlots };
}
