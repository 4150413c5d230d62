// Recipes: the list, the YAML in an editor with line numbers, validation errors shown at
// their line (the supervisor's own messages, as `supervisor check`), and a dry-run preview
// (timeline, duration, capacity per cycle) before anything is saved or started.
import { get, post, put } from "../api.js";
import { esc, fmtDuration, fmtTime, showResult, $ } from "../dom.js";
import { simplePlot, timeAxis, timelinePlot } from "../chart.js";

export async function render({ root, app, params }) {
  root.dataset.title = "Recipes";
  const current = params[0] ? decodeURIComponent(params[0]) : "";
  root.innerHTML = `
    <h1>Recipes</h1>
    <div class="recipes-grid">
      <section class="panel" aria-label="Recipe list"><h2>List</h2><div id="recipe-list"><p class="muted">…</p></div>
        <button type="button" id="recipe-new">New recipe</button></section>
      <section class="panel editor-panel" aria-label="Editor">
        <div class="editor-bar">
          <label for="recipe-name">Name</label><input id="recipe-name" value="${esc(current)}" placeholder="my-recipe" required>
          <label class="file">Upload YAML <input type="file" id="recipe-file" accept=".yaml,.yml,text/yaml"></label>
        </div>
        <div class="editor" id="editor">
          <pre class="gutter" id="gutter" aria-hidden="true"></pre>
          <textarea id="recipe-text" spellcheck="false" wrap="off" aria-label="Recipe YAML" aria-describedby="recipe-errors"></textarea>
        </div>
        <ul id="recipe-errors" class="errors" aria-live="polite"></ul>
        <div class="buttons">
          <button type="button" id="recipe-validate">Validate</button>
          <label for="dry-params">Parameters</label><input id="dry-params" placeholder="name=value, …" size="24">
          <button type="button" id="recipe-dryrun">Dry run</button>
          <button type="button" id="recipe-save" class="primary">Save</button>
          <label><input type="checkbox" id="recipe-overwrite"> overwrite</label>
        </div>
        <p id="recipe-result" class="result" role="status" aria-live="polite" hidden></p>
      </section>
      <section class="panel preview" aria-label="Dry run preview" id="preview" hidden>
        <h2>Dry run</h2>
        <p id="dry-summary"></p>
        <div id="dry-timeline" class="plot"></div>
        <div id="dry-cycles" class="plot"></div>
        <div id="dry-trace" class="plot"></div>
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
          `<li class="refused">${e.line ? `<a href="#" data-line="${e.line}">line ${e.line}${e.column ? `:${e.column}` : ""}</a>: ` : ""}${esc(e.message)}</li>`,
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
      showResult(out, { ok: true, data: { reason: `valid: ${answer.data.steps ?? "?"} steps${prm ? `, parameters ${prm}` : ""}` } });
    } else {
      showErrors(errorsOf(answer));
      showResult(out, { ok: false, status: answer.status, data: { reason: `${errorsOf(answer).length} error(s), see their lines` } });
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
    showResult(out, { ok: true, data: { reason: "dry run…" } });
    const answer = await post("/api/recipes/dryrun", { text: text.value, parameters: parseDryParams() });
    if (!answer.ok || answer.data.ok === false) {
      showErrors(errorsOf(answer));
      showResult(out, answer);
      return;
    }
    showErrors([]);
    const d = answer.data;
    out.hidden = true;
    $("#preview", root).hidden = false;
    $("#dry-summary", root).textContent = `predicted duration ${fmtDuration(d.duration_s)}, end: ${d.end_reason || "—"}, ${(d.cycles || []).length} cycle(s)`;
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
          title: `Predicted capacity per cycle (${unit})`,
          xLabel: "cycle",
          yLabel: unit,
          series: [{ label: `charge ${unit}` }, { label: `discharge ${unit}` }],
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
          title: "Predicted voltage and current",
          xLabel: ax.unit,
          series: [{ label: "V" }, { label: "A" }],
          x: tr.t_s.map((s) => s / ax.scale),
          ys: [tr.voltage_v, tr.current_a],
        }),
      );
    }
  };

  const save = async () => {
    const name = nameInput.value.trim();
    if (!name) {
      showResult(out, { ok: false, status: 400, data: { reason: "give the recipe a name" } });
      nameInput.focus();
      return;
    }
    const answer = await put(`/api/recipes/${encodeURIComponent(name)}`, {
      text: text.value,
      overwrite: $("#recipe-overwrite", root).checked,
    });
    if (answer.status === 422) {
      showErrors(errorsOf(answer));
      showResult(out, { ok: false, status: 422, data: { reason: "not saved: fix the errors at their lines" } });
      return;
    }
    showErrors([]);
    showResult(out, answer, `saved ${name}`);
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

  paintGutter();
  loadList();
  if (current) loadRecipe(current);
  return {
    destroy() {
      while (plots.length) plots.pop().stop();
    },
  };
}
