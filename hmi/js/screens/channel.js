// Channel: live values, the step chain (from the compiled program, never re-parsed here),
// V/I/T trends and the series /api/bench adds for the channel (its BMS's cell min/max)
// (historian for the past, live points for now; drag to zoom, buttons to pan) and the
// commands, each refusal shown with its reason.
import { get, post, put } from "../api.js";
import { bindTags, esc, showResult, $, $$ } from "../dom.js";
import { uPlot, widthOf, autoResize } from "../chart.js";
import { paintTile } from "./overview.js";

const SPANS_S = [
  ["5 min", 300],
  ["30 min", 1800],
  ["2 h", 7200],
  ["8 h", 28800],
];
const TREND_HEIGHT = 260;
const MAX_LIVE_POINTS = 20000;
const REDRAW_MS = 500;
const HOLD_S = 1.0;

const VERBS = [
  ["start", "Start"],
  ["hold", "Hold"],
  ["resume", "Resume"],
  ["advance", "Advance"],
  ["stop", "Stop"],
  ["abort", "Abort"],
  ["reset", "Reset"],
  ["acknowledge", "Acknowledge"],
];

function value(label, tag, attrs = "") {
  return `<div class="kv"><span>${esc(label)}</span><b data-tag="${esc(tag)}" ${attrs}></b></div>`;
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
      errors.push(`parameters line ${i + 1}: expected name = value, got ${JSON.stringify(s)}`);
      return;
    }
    const raw = m[2].trim();
    out[m[1]] = /^-?\d+(\.\d+)?(e-?\d+)?$/i.test(raw) ? Number(raw) : raw;
  });
  return { parameters: out, errors };
}

export async function render({ root, app, params }) {
  const name = decodeURIComponent(params[0]);
  const ch = app.bench.channels.find((c) => c.name === name);
  if (!ch) {
    root.innerHTML = `<p class="refused">Unknown channel ${esc(name)}. <a href="#/">Overview</a></p>`;
    return null;
  }
  root.dataset.title = name;
  const t = ch.tags;
  const p = `${name}.`;
  const viewer = app.session?.role === "viewer";
  root.innerHTML = `
  <div class="channel-head tile" id="tile-${esc(name)}">
    <h1>${esc(name)} <small class="muted">${esc(ch.description || "")}</small></h1>
    <span class="activity big" id="ch-activity"></span>
    <span class="chain-state">chain: <span class="state" data-tag="${esc(t.state)}" id="ch-state"></span></span>
    <span class="muted">recipe <b data-tag="${p}chain.recipe" data-empty="none"></b></span>
    <span class="muted">test <b data-tag="${p}chain.test_id" data-empty="none"></b></span>
    <div class="progress"><div class="bar" role="progressbar" aria-label="progress" aria-valuemin="0" aria-valuemax="100"><div class="fill"></div></div>
      <span class="eta">ETA <span class="eta-text">—</span></span></div>
    <div class="tile-alarm" aria-live="polite"></div>
  </div>
  <div class="channel-grid">
    <section class="panel values" aria-label="Live values">
      <div class="nums">
        <div><span class="big" data-tag="${esc(t.voltage)}" data-fmt="n3"></span><small>voltage</small></div>
        <div><span class="big" data-tag="${esc(t.current)}" data-fmt="n3"></span><small>current</small></div>
        <div><span class="big" data-tag="${esc(t.temperature)}" data-fmt="n1"></span><small>temperature</small></div>
        <div><span class="big" data-tag="${esc(t.charge)}" data-fmt="n4" id="ch-charge"></span><small>charge</small></div>
      </div>
      ${value("step", t.step, 'data-empty="none" id="ch-step"')}
      ${value("cycle", `${p}chain.cycle`)}
      ${value("step time", `${p}chain.step_time`, 'data-fmt="dur" id="ch-step-time"')}
      ${value("test time", `${p}chain.test_time`, 'data-fmt="dur"')}
      ${value("last transition", `${p}chain.last_event`, 'data-empty="none" id="ch-last-event" class="wrap"')}
      ${value("interlock", `${p}chain.interlock`, 'data-empty="none" data-abn="nonempty"')}
      ${value("trip", `${p}fault`, 'data-empty="none" data-abn="nonempty"')}
      ${value("cell", `${p}chain.cell_id`, 'data-empty="none" id="ch-cell"')}
      ${value("power", `${p}power`, 'data-fmt="n3"')}
      ${value("net charge counter", `${p}charge_ah`, 'data-fmt="n3"')}
      ${value("charged counter", `${p}charged_ah`, 'data-fmt="n3"')}
      ${value("discharged counter", `${p}discharged_ah`, 'data-fmt="n3"')}
      ${value("current command", `${p}current_cmd`, 'data-fmt="n3"')}
      ${value("clamped by a limit", `${p}clamped`, 'data-true="yes: less than asked flows" data-false="no" data-abn="true" id="ch-clamped"')}
      ${value("manual setpoint", `${p}manual_current`, 'data-fmt="n3" id="ch-manual-current"')}
      ${value("output enabled", `${p}enable`, 'data-true="yes" data-false="no"')}
    </section>
    <section class="panel commands" aria-label="Commands">
      <h2>Commands</h2>
      ${viewer ? '<p class="muted">You are logged in as a viewer: the supervisor refuses commands (the reason is shown).</p>' : ""}
      <form id="load-form" class="load">
        <label for="load-recipe">Recipe</label>
        <input id="load-recipe" list="recipe-list" placeholder="recipes/capacity-test.yaml" required>
        <datalist id="recipe-list"></datalist>
        <label for="load-params">Parameters <small class="muted">(name = value, one a line)</small></label>
        <textarea id="load-params" rows="3" spellcheck="false"></textarea>
        <label for="load-cell">Cell id <small class="muted">(up to 64 of A–Z a–z 0–9 space . _ : / + -; sent with Load and Start)</small></label>
        <input id="load-cell" maxlength="64" pattern="[A-Za-z0-9 ._:/+\-]*" autocomplete="off" spellcheck="false">
        <label for="load-comment">Comment <small class="muted">(up to 500 characters)</small></label>
        <textarea id="load-comment" rows="2" maxlength="500"></textarea>
        <button type="submit" id="cmd-load">Load recipe</button>
      </form>
      <div class="buttons" role="group" aria-label="Chain commands">
        ${VERBS.map(([v, l]) => `<button type="button" data-verb="${v}" id="cmd-${v}">${l}</button>`).join("")}
      </div>
      <div class="buttons" role="group" aria-label="Mode">
        <button type="button" id="cmd-auto" data-mode="auto">Auto</button>
        <button type="button" id="cmd-manual" data-mode="manual">Manual</button>
      </div>
      <form id="manual-form" class="manual">
        <label for="manual-current">Manual current (A)</label>
        <input id="manual-current" type="number" step="0.001" required>
        <button type="submit" id="cmd-manual-current">Set</button>
        <button type="button" id="cmd-enable" data-enable="true">Enable</button>
        <button type="button" id="cmd-disable" data-enable="false">Disable</button>
      </form>
      <p id="cmd-result" class="result" role="status" aria-live="polite" hidden></p>
    </section>
    <section class="panel chain-panel" aria-label="Step chain">
      <h2>Step chain</h2>
      <div id="chain" class="chain-wrap"><p class="muted">…</p></div>
    </section>
    <section class="panel trend-panel" aria-label="Trend">
      <h2>Trend <small class="muted">drag to zoom</small></h2>
      <div class="buttons" role="group" aria-label="Trend range">
        ${SPANS_S.map(([l, s]) => `<button type="button" class="small" data-span="${s}">${l}</button>`).join("")}
        <button type="button" class="small" id="trend-left" aria-label="pan left">◀</button>
        <button type="button" class="small" id="trend-right" aria-label="pan right">▶</button>
        <button type="button" class="small" id="trend-out" aria-label="zoom out">−</button>
        <button type="button" class="small" id="trend-live" aria-pressed="true">Live</button>
      </div>
      <div id="trend" class="trend" data-points="0"></div>
    </section>
  </div>`;

  const refresh = bindTags(root, app.live);
  const head = $(".channel-head", root);
  const out = $("#cmd-result", root);
  const paintHead = () => paintTile(head, ch, app.live);
  paintHead();

  // --- commands -------------------------------------------------------------------------
  const command = async (verb, args = {}) => {
    out.hidden = false;
    out.classList.remove("refused", "accepted");
    out.textContent = `${verb}…`;
    const answer = await post(`/api/channels/${encodeURIComponent(name)}/commands/${verb}`, args);
    showResult(out, answer);
    return answer;
  };
  // The test's metadata (docs/recipes.md "Test records"): given fields only; the server checks them.
  const metadata = () => {
    const out = {};
    const cell = $("#load-cell", root).value.trim();
    const comment = $("#load-comment", root).value.trim();
    if (cell) out.cell_id = cell;
    if (comment) out.comment = comment;
    return out;
  };
  for (const b of $$("[data-verb]", root))
    b.addEventListener("click", () => command(b.dataset.verb, b.dataset.verb === "start" ? metadata() : {}));
  for (const b of $$("[data-mode]", root))
    b.addEventListener("click", () => command("mode", { value: b.dataset.mode }));
  for (const b of $$("[data-enable]", root))
    b.addEventListener("click", () => command("enable", { value: b.dataset.enable === "true" }));
  $("#manual-form", root).addEventListener("submit", (ev) => {
    ev.preventDefault();
    command("manual_current", { value: Number($("#manual-current", root).value) });
  });
  const recipeInput = $("#load-recipe", root);
  const paramsInput = $("#load-params", root);
  $("#load-form", root).addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const { parameters, errors } = parseParameters(paramsInput.value);
    if (errors.length) {
      showResult(out, { ok: false, status: 400, data: { reason: errors.join("; ") } });
      return;
    }
    out.hidden = false;
    out.classList.remove("refused", "accepted");
    out.textContent = "loading…";
    const answer = await put(`/api/channels/${encodeURIComponent(name)}/recipe`, {
      file: recipeInput.value.trim(),
      parameters,
      ...metadata(),
    });
    showResult(out, answer, "recipe loaded");
    if (answer.ok) loadProgram();
  });
  // The recipes the supervisor knows (if it lists them), their parameters when chosen.
  const known = new Map();
  get("/api/recipes").then((answer) => {
    if (!answer.ok || !Array.isArray(answer.data.recipes)) return;
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

  // --- step chain -----------------------------------------------------------------------
  const chainEl = $("#chain", root);
  let program = null;
  const paintActive = () => {
    const step = app.live.value(t.step);
    const index = app.live.value(`${p}chain.step_index`);
    for (const li of $$("li[data-step]", chainEl)) {
      const active = program && (li.dataset.step === step || (step === undefined && Number(li.dataset.index) === index));
      li.classList.toggle("active", !!active);
      if (active) li.setAttribute("aria-current", "step");
      else li.removeAttribute("aria-current");
    }
  };
  async function loadProgram() {
    const answer = await get(`/api/channels/${encodeURIComponent(name)}/program`);
    if (!answer.ok) {
      program = null;
      chainEl.innerHTML = `<p class="muted" id="chain-none">${esc(answer.data.reason || answer.data.error || "no recipe loaded")}</p>`;
      return;
    }
    program = answer.data;
    chainEl.innerHTML = `<p class="muted">${esc(program.recipe || "")}</p><ol class="chain">${(program.steps || [])
      .map(
        (s) => `<li data-step="${esc(s.name)}" data-index="${esc(s.index)}">
          <b>${esc(s.name)}</b> <span class="muted">${esc(s.kind || "")}</span>
          ${(s.transitions || []).map((tr) => `<div class="tr">→ <b>${esc(tr.to)}</b> ${esc(tr.condition || "")}</div>`).join("")}
        </li>`,
      )
      .join("")}</ol>`;
    paintActive();
  }
  loadProgram();
  let recipeSeen = app.live.value(`${p}chain.recipe`);
  let testSeen = app.live.value(`${p}chain.test_id`);

  // --- trend ----------------------------------------------------------------------------
  const trendEl = $("#trend", root);
  // Beside V, I and T, what the bench adds for this channel (a BMS's cell min/max), each on
  // the scale it names: one axis per scale.
  const extra = ch.trend || [];
  const trendTags = [t.voltage, t.current, t.temperature, ...extra.map((s) => s.tag)];
  const emptyData = () => [[], ...trendTags.map(() => [])];
  const EXTRA_STROKES = ["#2f7d4f", "#b05a1e", "#6b4fa0", "#1e7a8a"];
  let spanS = 300;
  let following = true;
  let data = emptyData();
  let dirty = false;
  let chart = null;
  let stopResize = () => {};
  const unitOf = (tag) => app.live.tags.get(tag)?.unit || "";
  const extraScales = [...new Set(extra.map((s) => s.scale))];
  const seriesLabels = [
    `voltage ${unitOf(t.voltage)}`,
    `current ${unitOf(t.current)}`,
    `temperature ${unitOf(t.temperature)}`,
    ...extra.map((s) => `${s.label} ${s.unit || ""}`.trim()),
  ];
  trendEl.dataset.series = seriesLabels.join("|");
  const makeChart = () => {
    const opts = {
      width: widthOf(trendEl),
      height: TREND_HEIGHT,
      cursor: { drag: { x: true, y: false } },
      scales: { x: { time: true }, V: {}, A: {}, T: {}, ...Object.fromEntries(extraScales.map((k) => [k, {}])) },
      series: [
        {},
        { label: seriesLabels[0], scale: "V", stroke: "#1f2a36", width: 2, spanGaps: true },
        { label: seriesLabels[1], scale: "A", stroke: "#5a6b7d", width: 1.5, dash: [6, 3], spanGaps: true },
        { label: seriesLabels[2], scale: "T", stroke: "#8a97a5", width: 1.5, dash: [2, 3], spanGaps: true },
        ...extra.map((s, i) => ({
          label: seriesLabels[3 + i],
          scale: s.scale,
          stroke: EXTRA_STROKES[i % EXTRA_STROKES.length],
          width: 1.5,
          spanGaps: true,
        })),
      ],
      axes: [
        {},
        { scale: "V", label: "V" },
        { scale: "A", label: "A", side: 1, grid: { show: false } },
        { scale: "T", label: "°C", side: 1, grid: { show: false } },
        ...extraScales.map((k) => {
          const unit = extra.find((s) => s.scale === k)?.unit || "";
          return { scale: k, label: `${k} ${unit}`.trim(), side: 1, grid: { show: false } };
        }),
      ],
      hooks: {
        setSelect: [
          (u) => {
            if (u.select.width > 0) setFollowing(false);
          },
        ],
      },
    };
    chart = new uPlot(opts, data, trendEl);
    stopResize = autoResize(chart, trendEl, TREND_HEIGHT);
  };
  const setFollowing = (on) => {
    following = on;
    $("#trend-live", root).setAttribute("aria-pressed", String(on));
  };
  const redraw = () => {
    if (!chart) return;
    trendEl.dataset.points = String(data[0].length);
    // The series that have a value to draw (a test reads it; cheap: stops at the first).
    trendEl.dataset.valued = seriesLabels.filter((_, i) => data[i + 1].some((v) => v !== null)).join("|");
    chart.setData(data, false);
    if (following) {
      const now = Date.now() / 1000;
      chart.setScale("x", { min: now - spanS, max: now });
    }
  };
  async function loadHistory() {
    const end = Date.now() / 1000;
    const start = end - spanS;
    const answers = await Promise.all(
      trendTags.map((tag) => get(`/api/history?tag=${encodeURIComponent(tag)}&start=${start}&end=${end}`)),
    );
    const tables = answers.map((a) => {
      if (!a.ok) return [[], []];
      const rows = a.data.samples || (a.data.buckets || []).map((b) => ({ t: b.t, value: b.mean }));
      const xs = [];
      const ys = [];
      for (const r of rows) {
        xs.push(r.t);
        ys.push(typeof r.value === "number" ? r.value : null);
      }
      return [xs, ys];
    });
    const keep = data; // live points that came in meanwhile stay
    const joined = tables.some((tb) => tb[0].length) ? uPlot.join(tables) : emptyData();
    const lastT = joined[0].length ? joined[0][joined[0].length - 1] : -Infinity;
    data = joined.map((col) => Array.from(col));
    for (let i = 0; i < keep[0].length; i++) {
      if (keep[0][i] > lastT) for (let k = 0; k < keep.length; k++) data[k].push(keep[k][i]);
    }
    redraw();
  }
  // A live point on each change of a trend's tag, and (sample and hold, as a SCADA trend
  // does) at least every HOLD_S: a value that does not change is still the current one.
  const livePoint = (names, now) => {
    if (names && !trendTags.some((n) => names.includes(n))) return;
    let ts = now || 0;
    const row = trendTags.map((n) => {
      const tag = app.live.tags.get(n);
      if (!now && tag?.source_time) ts = Math.max(ts, tag.source_time);
      return tag && typeof tag.value === "number" && tag.quality !== "BAD" ? tag.value : null;
    });
    ts = ts || Date.now() / 1000;
    const n = data[0].length;
    if (n && ts <= data[0][n - 1]) return; // same instant (a repeated snapshot)
    data[0].push(ts);
    row.forEach((v, i) => data[i + 1].push(v));
    if (data[0].length > MAX_LIVE_POINTS) data = data.map((col) => col.slice(-MAX_LIVE_POINTS));
    dirty = true;
  };
  makeChart();
  loadHistory();
  const timer = setInterval(() => {
    const now = Date.now() / 1000;
    const n = data[0].length;
    if (app.live.state === "live" && (!n || now - data[0][n - 1] >= HOLD_S)) livePoint(null, now);
    if (dirty || following) {
      dirty = false;
      redraw();
    }
  }, REDRAW_MS);
  for (const b of $$("[data-span]", root))
    b.addEventListener("click", () => {
      spanS = Number(b.dataset.span);
      setFollowing(true);
      loadHistory();
    });
  const shift = (frac) => {
    const { min, max } = chart.scales.x;
    const d = (max - min) * frac;
    setFollowing(false);
    chart.setScale("x", { min: min + d, max: max + d });
  };
  $("#trend-left", root).addEventListener("click", () => shift(-0.5));
  $("#trend-right", root).addEventListener("click", () => shift(0.5));
  $("#trend-out", root).addEventListener("click", () => {
    const { min, max } = chart.scales.x;
    const mid = (min + max) / 2;
    const half = max - min;
    setFollowing(false);
    chart.setScale("x", { min: mid - half, max: mid + half });
  });
  $("#trend-live", root).addEventListener("click", () => {
    setFollowing(true);
    redraw();
  });

  return {
    trendPoints: () => data[0].length,
    update(change) {
      if (change.kind === "tags") {
        refresh(change.names);
        livePoint(change.names);
        const recipe = app.live.value(`${p}chain.recipe`);
        const test = app.live.value(`${p}chain.test_id`);
        if (recipe !== recipeSeen || test !== testSeen) {
          recipeSeen = recipe;
          testSeen = test;
          loadProgram();
        }
        paintActive();
      }
      paintHead();
    },
    destroy() {
      clearInterval(timer);
      stopResize();
      chart?.destroy();
    },
  };
}
