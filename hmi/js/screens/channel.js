// Channel: live values, the step chain (from the compiled program, never re-parsed here),
// V/I/T trends and the series /api/bench adds for the channel (its BMS's cell min/max)
// (historian for the past, live points for now; drawn as held steps, a pen per tag with
// its colour, axis and band, pens to pick; drag to zoom, buttons to pan) and the
// command bar (commandbar.js: buttons that follow the state, confirmations).
import { get } from "../api.js";
import { bindTags, esc, unitLabel, $, $$ } from "../dom.js";
import { t as tr, tValue } from "../i18n.js";
import { PENS, holdJoin, trendChart } from "../chart.js";
import { paintTile } from "./overview.js";
import { commandBarHtml, mountCommandBar } from "./commandbar.js";

export { parseParameters } from "./commandbar.js";

const SPANS_S = [
  ["5 min", 300],
  ["30 min", 1800],
  ["2 h", 7200],
  ["8 h", 28800],
];
const TREND_HEIGHT = 320;
const MAX_LIVE_POINTS = 20000;
const REDRAW_MS = 500;
const HOLD_S = 1.0;

function value(label, tag, attrs = "") {
  return `<div class="kv"><span>${esc(label)}</span><b data-tag="${esc(tag)}" ${attrs}></b></div>`;
}

export async function render({ root, app, params }) {
  const name = decodeURIComponent(params[0]);
  const ch = app.bench.channels.find((c) => c.name === name);
  if (!ch) {
    root.innerHTML = `<p class="refused">${esc(tr("channel.unknown", { ch: name }))} <a href="#/">${esc(tr("nav.overview"))}</a></p>`;
    return null;
  }
  root.dataset.title = name;
  const t = ch.tags;
  const p = `${name}.`;
  const viewer = app.session?.role === "viewer";
  const none = esc(tr("value.none"));
  root.innerHTML = `
  <div class="channel-head tile" id="tile-${esc(name)}">
    <h1>${esc(name)} <small class="muted">${esc(ch.description || "")}</small></h1>
    <span class="activity big" id="ch-activity"></span>
    <span class="chain-state">${esc(tr("tile.chain"))} <span class="state" data-tag="${esc(t.state)}" data-enum="chain" id="ch-state"></span></span>
    <span class="muted">${esc(tr("channel.recipe"))} <b data-tag="${p}chain.recipe" data-empty="${none}"></b></span>
    <span class="muted">${esc(tr("channel.test"))} <b data-tag="${p}chain.test_id" data-empty="${none}"></b></span>
    <div class="progress"><div class="bar" role="progressbar" aria-label="${esc(tr("channel.progress"))}" aria-valuemin="0" aria-valuemax="100"><div class="fill"></div></div>
      <span class="eta">${esc(tr("tile.eta"))} <span class="eta-text">—</span></span></div>
    <div class="tile-alarm" aria-live="polite"></div>
  </div>
  <div class="channel-grid">
    <section class="panel trend-panel" aria-label="${esc(tr("trend.title"))}">
      <div class="trend-bar">
        <h2>${esc(tr("trend.title"))} <small class="muted">${esc(tr("trend.dragToZoom"))}</small></h2>
        <div class="buttons" role="group" aria-label="${esc(tr("trend.range"))}">
          ${SPANS_S.map(([l, s]) => `<button type="button" class="small" data-span="${s}">${l}</button>`).join("")}
          <button type="button" class="small" id="trend-left" aria-label="${esc(tr("trend.panLeft"))}">◀</button>
          <button type="button" class="small" id="trend-right" aria-label="${esc(tr("trend.panRight"))}">▶</button>
          <button type="button" class="small" id="trend-out" aria-label="${esc(tr("trend.zoomOut"))}">−</button>
          <button type="button" class="small" id="trend-live" aria-pressed="true">${esc(tr("trend.live"))}</button>
        </div>
        <fieldset class="pens" id="trend-pens"><legend>${esc(tr("trend.pens"))}</legend></fieldset>
      </div>
      <div id="trend" class="trend" data-points="0"></div>
    </section>
    <section class="panel values" aria-label="${esc(tr("channel.liveValues"))}">
      <div class="nums">
        <div><span class="big" data-tag="${esc(t.voltage)}" data-fmt="n3"></span><small>${esc(tr("quantity.voltage"))}</small></div>
        <div><span class="big" data-tag="${esc(t.current)}" data-fmt="n3"></span><small>${esc(tr("quantity.current"))}</small></div>
        <div><span class="big" data-tag="${esc(t.temperature)}" data-fmt="n1"></span><small>${esc(tr("quantity.temperature"))}</small></div>
        <div><span class="big" data-tag="${esc(t.charge)}" data-fmt="n4" id="ch-charge"></span><small>${esc(tr("quantity.charge"))}</small></div>
      </div>
      ${value(tr("channel.step"), t.step, `data-empty="${none}" id="ch-step"`)}
      ${value(tr("channel.cycle"), `${p}chain.cycle`)}
      ${value(tr("channel.stepTime"), `${p}chain.step_time`, 'data-fmt="dur" id="ch-step-time"')}
      ${value(tr("channel.testTime"), `${p}chain.test_time`, 'data-fmt="dur"')}
      ${value(tr("channel.lastTransition"), `${p}chain.last_transition`, `data-empty="${none}" id="ch-last-transition" class="wrap"`)}
      ${value(tr("channel.lastCommand"), `${p}chain.last_command`, `data-empty="${none}" id="ch-last-command" class="wrap"`)}
      ${value(tr("channel.interlock"), `${p}chain.interlock`, `data-empty="${none}" data-abn="nonempty"`)}
      ${value(tr("channel.trip"), `${p}fault`, `data-empty="${none}" data-abn="nonempty"`)}
      ${value(tr("channel.cell"), `${p}chain.cell_id`, `data-empty="${none}" id="ch-cell"`)}
      ${value(tr("channel.power"), `${p}power`, 'data-fmt="n3"')}
      ${value(tr("channel.netCharge"), `${p}charge_ah`, 'data-fmt="n3"')}
      ${value(tr("channel.charged"), `${p}charged_ah`, 'data-fmt="n3"')}
      ${value(tr("channel.discharged"), `${p}discharged_ah`, 'data-fmt="n3"')}
      ${value(tr("channel.currentCmd"), `${p}current_cmd`, 'data-fmt="n3"')}
      ${value(tr("channel.clamped"), `${p}clamped`, `data-true="${esc(tr("channel.clampedYes"))}" data-false="${esc(tr("value.no"))}" data-abn="true" id="ch-clamped"`)}
      ${value(tr("channel.manualSetpoint"), `${p}manual_current`, 'data-fmt="n3" id="ch-manual-current"')}
      ${value(tr("channel.outputEnabled"), `${p}enable`, `data-true="${esc(tr("value.yes"))}" data-false="${esc(tr("value.no"))}"`)}
    </section>
    <section class="panel commands" aria-label="${esc(tr("commands.title"))}">
      ${commandBarHtml(viewer)}
    </section>
    <section class="panel chain-panel" aria-label="${esc(tr("channel.stepChain"))}">
      <h2>${esc(tr("channel.stepChain"))}</h2>
      <div id="chain" class="chain-wrap"><p class="muted">…</p></div>
    </section>
  </div>`;

  const refresh = bindTags(root, app.live);
  const head = $(".channel-head", root);
  const paintHead = () => paintTile(head, ch, app.live);
  paintHead();

  // --- commands (commandbar.js) ---------------------------------------------------------
  const bar = mountCommandBar({ root, app, name, ch, onLoaded: () => loadProgram() });

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
      chainEl.innerHTML = `<p class="muted" id="chain-none">${esc(answer.data.reason || answer.data.error || tr("channel.noRecipe"))}</p>`;
      return;
    }
    program = answer.data;
    chainEl.innerHTML = `<p class="muted">${esc(program.recipe || "")}</p><ol class="chain" translate="no">${(program.steps || [])
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
  // the scale it names: one axis (and one band) per scale.
  const extra = ch.trend || [];
  const trendTags = [t.voltage, t.current, t.temperature, ...extra.map((s) => s.tag)];
  const emptyData = () => [[], ...trendTags.map(() => [])];
  let spanS = 300;
  let following = true;
  let data = emptyData();
  let dirty = false;
  // The units: the live snapshot's, or (a screen opened before the snapshot came) the
  // historian's answer's; the chart is made at the first answer, its pens named with them.
  const unitOf = (tag, answer) => unitLabel(app.live.tags.get(tag)?.unit || (answer?.ok && answer.data.unit) || "");
  const pensOf = (answers) => [
    { label: `${tr("quantity.voltage")} ${unitOf(t.voltage, answers[0])}`.trim(), scale: "V", unit: unitOf(t.voltage, answers[0]) || "V" },
    { label: `${tr("quantity.current")} ${unitOf(t.current, answers[1])}`.trim(), scale: "A", unit: unitOf(t.current, answers[1]) || "A" },
    {
      label: `${tr("quantity.temperature")} ${unitOf(t.temperature, answers[2])}`.trim(),
      scale: "T",
      unit: unitOf(t.temperature, answers[2]) || "°C",
    },
    ...extra.map((s) => ({ label: `${tValue("mimic.row", s.label)} ${unitLabel(s.unit)}`.trim(), scale: s.scale, unit: `${s.scale} ${unitLabel(s.unit)}`.trim() })),
  ];
  let seriesLabels = [];
  let trend = null;
  let destroyed = false;
  // The pens an operator hid on this channel stay hidden on the next visit (this browser).
  const pensKey = `hmi.trend.hidden.${name}`;
  const hiddenPens = () => {
    try {
      const list = JSON.parse(localStorage.getItem(pensKey) || "[]");
      return Array.isArray(list) ? list : [];
    } catch {
      return [];
    }
  };
  // The pen selection: a labelled check box per pen, with its colour and dash.
  const penBox = (pen, i) => {
    const label = document.createElement("label");
    label.className = "pen";
    const box = document.createElement("input");
    box.type = "checkbox";
    box.id = `trend-pen-${i}`;
    box.dataset.pen = pen.label;
    box.checked = !hiddenPens().includes(pen.label);
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.setAttribute("aria-hidden", "true");
    swatch.style.borderTopColor = PENS[i % PENS.length].stroke;
    const dash = PENS[i % PENS.length].dash;
    swatch.style.borderTopStyle = !dash.length ? "solid" : dash[0] <= 2 ? "dotted" : "dashed";
    label.append(box, swatch, pen.label);
    $("#trend-pens", root).append(label);
    box.addEventListener("change", () => trend.setPen(i, box.checked));
    return box;
  };
  const makeTrend = (answers) => {
    const pens = pensOf(answers);
    seriesLabels = pens.map((pen) => pen.label);
    trendEl.dataset.series = seriesLabels.join("|");
    const boxes = pens.map(penBox);
    const onPens = (shown) => {
      shown.forEach((on, i) => (boxes[i].checked = on));
      localStorage.setItem(pensKey, JSON.stringify(pens.filter((_, i) => !shown[i]).map((pen) => pen.label)));
    };
    trend = trendChart(trendEl, {
      pens,
      height: TREND_HEIGHT,
      hidden: hiddenPens(),
      onSelect: () => setFollowing(false),
      onPens,
    });
  };
  const setFollowing = (on) => {
    following = on;
    $("#trend-live", root).setAttribute("aria-pressed", String(on));
  };
  const redraw = () => {
    if (!trend) return;
    const chart = trend.chart;
    trendEl.dataset.points = String(data[0].length);
    // The series that have a value to draw (a test reads it; cheap: stops at the first).
    trendEl.dataset.valued = seriesLabels.filter((_, i) => data[i + 1].some((v) => v !== null)).join("|");
    chart.setData(data, false);
    if (following) {
      const now = Date.now() / 1000;
      chart.setScale("x", { min: now - spanS, max: now });
    }
    trend.showLatest();
  };
  async function loadHistory() {
    const end = Date.now() / 1000;
    const start = end - spanS;
    const answers = await Promise.all(
      trendTags.map((tag) => get(`/api/history?tag=${encodeURIComponent(tag)}&start=${start}&end=${end}`)),
    );
    // Changes only (raw) or per-interval means (a long range): held until the next either way.
    const tables = answers.map((a) => {
      if (!a.ok) return { before: null, t: [], v: [] };
      const rows = a.data.samples || (a.data.buckets || []).map((b) => ({ t: b.t, value: b.mean, quality: b.quality }));
      // A BAD value is a gap until the next good one, as in the live points.
      const good = (r) => (r && r.quality !== "BAD" && typeof r.value === "number" ? r.value : null);
      const before = a.data.before;
      return {
        before: before ? { t: before.t, value: good(before) } : null,
        t: rows.map((r) => r.t),
        v: rows.map(good),
      };
    });
    if (destroyed) return; // the screen left while the historian answered
    if (!trend) makeTrend(answers);
    const keep = data; // live points that came in meanwhile stay
    // Held until `end` (now): the historian saw no change since the last sample.
    const joined = holdJoin(tables, start, end);
    const lastT = joined[0].length ? joined[0][joined[0].length - 1] : -Infinity;
    data = joined;
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
    if (!trend) return;
    const chart = trend.chart;
    const { min, max } = chart.scales.x;
    const d = (max - min) * frac;
    setFollowing(false);
    chart.setScale("x", { min: min + d, max: max + d });
  };
  $("#trend-left", root).addEventListener("click", () => shift(-0.5));
  $("#trend-right", root).addEventListener("click", () => shift(0.5));
  $("#trend-out", root).addEventListener("click", () => {
    if (!trend) return;
    const chart = trend.chart;
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
    trendChart: () => trend?.chart, // (the browser tests read its time axis)
    update(change) {
      bar.update(change);
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
      destroyed = true;
      bar.destroy();
      clearInterval(timer);
      trend?.stop();
      trend?.chart.destroy();
    },
  };
}
