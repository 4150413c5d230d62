// Charts with uPlot (installed from npm by `make hmi`, served at /vendor/uplot/).
// The minified build, loaded by index.html before the app (window.uPlot).
import { fmtDateTime, fmtSignificant, t, timeTicks } from "./i18n.js";

export const uPlot = window.uPlot;

// Grey lines for normal data (high-performance HMI); series told apart by dash and weight.
export const SERIES_STYLE = [
  { stroke: "#1f2a36", width: 2 },
  { stroke: "#5a6b7d", width: 1.5, dash: [6, 3] },
  { stroke: "#8a97a5", width: 1.5, dash: [2, 3] },
];

/** A width that fits the element (charts are redrawn at resize). */
export function widthOf(el) {
  return Math.max(300, Math.floor(el.getBoundingClientRect().width || 600) - 4);
}

/** Keep a chart as wide as its container. */
export function autoResize(chart, el, height) {
  const ro = new ResizeObserver(() => chart.setSize({ width: widthOf(el), height }));
  ro.observe(el);
  return () => ro.disconnect();
}

/** A legend's value in the locale's format; none is a dash. */
const legendValue = (u, v) => (v == null ? "—" : fmtSignificant(v, 6));
/**
 * An axis as wide as its widest tick label (uPlot's `size` hook, after its axis-autosize
 * example): a fixed 60 px let step names ("charge_cc_cv") run under the axis label
 * ("step"). The label's own band (labelSize) lies outside this size.
 */
export function fitAxisSize(u, values, axisIdx) {
  const axis = u.axes[axisIdx];
  // uPlot asks again (cycleNum 1, 2, …) until the sizes settle; before its first values
  // (null), the size it had.
  if (values === null || values === undefined) return axis._size ?? 40;
  let size = (axis.ticks?.size ?? 10) + (axis.gap ?? 5);
  const longest = (values ?? []).reduce((acc, v) => (String(v ?? "").length > acc.length ? String(v) : acc), "");
  if (longest) {
    u.ctx.font = axis.font[0];
    size += u.ctx.measureText(longest).width / (window.devicePixelRatio || 1);
  }
  return Math.max(40, Math.ceil(size) + 4);
}

/** Tick labels with enough digits for small values (mAh-sized Ah, efficiencies). */
const ticks = (u, vals) =>
  vals.map((v) => (v === null ? "" : Math.abs(v) >= 100 ? fmtSignificant(Math.round(v), 21) : fmtSignificant(v, 3)));

/**
 * A simple plot of arrays: lines, a stepped line (`stepped`: a timeline of steps) or bars
 * (`bars`, x ordinal: one group per cycle).
 */
export function simplePlot(el, { title, xLabel, yLabel, series, x, ys, height = 220, bars = false, stepped = false, yValues, integerX = false }) {
  // Cycles are whole numbers: ticks on integers only, half a cycle of room each side.
  const whole = integerX || bars;
  // Bars side by side: the first series left of its cycle, the second right of it.
  const pathsOf = (i) =>
    bars
      ? uPlot.paths.bars({ size: [series.length > 1 ? 0.35 : 0.6, 60], align: series.length > 1 ? (i ? 1 : -1) : 0 })
      : stepped
        ? uPlot.paths.stepped({ align: 1 })
        : undefined;
  const opts = {
    title,
    width: widthOf(el),
    height,
    scales: {
      x: whole ? { time: false, range: (u, min, max) => [min - 0.6, max + 0.6] } : { time: false },
      // Bars start at zero (a bar's length is its value).
      ...(bars ? { y: { range: (u, min, max) => [Math.min(0, min), max > 0 ? max * 1.1 : 1] } } : {}),
    },
    axes: [
      whole
        ? { label: xLabel, incrs: [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000], values: (u, vals) => vals.map((v) => (Number.isInteger(v) ? v : "")) }
        : { label: xLabel, values: ticks },
      { label: yLabel ?? series.map((s) => s.label).join(" / "), values: yValues ?? ticks, size: fitAxisSize },
    ],
    series: [
      { label: xLabel, value: legendValue },
      ...series.map((s, i) => ({
        label: s.label,
        value: legendValue,
        ...SERIES_STYLE[i % SERIES_STYLE.length],
        ...(bars || stepped ? { paths: pathsOf(i) } : {}),
        ...(bars ? { fill: i ? "#b9c2cc" : "#6f7a85", dash: undefined } : {}),
        points: { show: !bars && !stepped && x.length < 60 },
      })),
    ],
  };
  const chart = new uPlot(opts, [x, ...ys], el);
  return { chart, stop: autoResize(chart, el, height) };
}

/** A time axis for a duration: seconds, minutes or hours, whichever reads best. */
export function timeAxis(durationS) {
  if (durationS < 600) return { unit: "s", scale: 1 };
  if (durationS < 36000) return { unit: "min", scale: 60 };
  return { unit: "h", scale: 3600 };
}

/**
 * A run's timeline ({t_s, step, ...} events, as the dry run and a test's summary give
 * it) as a stepped plot of the step over time, ending at `durationS`.
 */
export function timelinePlot(el, timeline, durationS, title = t("plot.timeline")) {
  const tl = (timeline || []).filter((e) => e.step && typeof e.t_s === "number");
  if (!tl.length) return null;
  const stepNames = [];
  for (const e of tl) if (!stepNames.includes(e.step)) stepNames.push(e.step);
  const end = Math.max(durationS || 0, tl[tl.length - 1].t_s);
  const ax = timeAxis(end);
  return simplePlot(el, {
    title,
    xLabel: ax.unit,
    yLabel: t("plot.step"),
    series: [{ label: t("plot.step") }],
    x: [...tl.map((e) => e.t_s / ax.scale), end / ax.scale],
    ys: [[...tl.map((e) => stepNames.indexOf(e.step)), stepNames.indexOf(tl[tl.length - 1].step)]],
    height: 200,
    stepped: true,
    yValues: (u, vals) => vals.map((v) => (Number.isInteger(v) ? stepNames[v] ?? "" : "")),
  });
}

// --- trends (the channel screen): pens, sample and hold, a band per scale -----------------

/**
 * Trend pens, told apart by colour and by dash (never colour alone, ISA-101): a palette
 * readable by the colour-blind (after Okabe and Ito), dark enough on the trend's light grey
 * (3:1 at least), and none of them the alarm red nor the warning amber, which keep their
 * meaning on every screen.
 */
export const PENS = [
  { stroke: "#0a5fa8", dash: [] }, // blue, solid
  { stroke: "#8b3a9c", dash: [8, 4] }, // purple, dashed
  { stroke: "#00785a", dash: [2, 3] }, // green, dotted
  { stroke: "#1c1c1c", dash: [10, 3, 2, 3] }, // black, dash-dot
  { stroke: "#6a5410", dash: [4, 2] }, // olive brown, short dashes
  { stroke: "#2b8cbe", dash: [12, 4] }, // sky blue, long dashes
];

/**
 * Sample and hold: the historian stores changes only, so a tag's value is the one of its
 * last sample until the next. Each table ({before, t, v}: the sample before `start` or
 * null, then the samples' times and values, a value null where it was BAD) joined onto one
 * time axis, each column holding its pen's value at every time of the axis: null before
 * its first sample (nothing known) and from a null sample to the next (a gap, never a
 * value made up). With `end`, the last values hold until then (the end of the range the
 * historian was asked for: no change came before it).
 */
export function holdJoin(tables, start, end) {
  const times = new Set(end === undefined ? [] : [end]);
  for (const tb of tables) {
    if (tb.before) times.add(start);
    for (const x of tb.t) times.add(x);
  }
  const xs = [...times].sort((a, b) => a - b);
  const cols = tables.map((tb) => {
    const col = new Array(xs.length);
    let held = tb.before && typeof tb.before.value === "number" ? tb.before.value : null;
    let j = 0;
    for (let i = 0; i < xs.length; i++) {
      while (j < tb.t.length && tb.t[j] <= xs[i]) held = tb.v[j++];
      col[i] = held;
    }
    return col;
  });
  return [xs, ...cols];
}

const BAND_GAP = 0.08; // of a band's height, left empty between two bands

/** Where band `index` of `count` lies, as fractions of the plot's height from its bottom. */
function bandOf(index, count) {
  const share = 1 / count;
  return [(count - 1 - index + BAND_GAP / 2) * share, (count - index - BAND_GAP / 2) * share];
}

/**
 * A scale's range that puts its data [min, max] (padded) in band `index` of `count`
 * (0 at the top): every scale of a trend gets a strip of its own, so two pens never lie
 * on top of each other whatever their values (15 V on 0–30 and 25 °C on 0–50 did).
 */
export function bandRange(index, count, min, max) {
  // No value in view: no range, and uPlot hides the axis.
  if (min == null || max == null || !Number.isFinite(min) || !Number.isFinite(max)) return [null, null];
  // A flat line still gets a span: 5 % of its value, and never less than 0.1 of its unit.
  const pad = max > min ? (max - min) * 0.08 : Math.max(Math.abs(max) * 0.05, 0.1);
  const lo = min - pad;
  const hi = max + pad;
  const [b0, b1] = bandOf(index, count);
  const full = (hi - lo) / (b1 - b0);
  return [lo - b0 * full, lo - b0 * full + full];
}

const TICK_SPACING_PX = 14; // between two tick labels of a band (12 px text), at least
const MAX_TICKS = 5; // in a band: more would be a grid to read, not a scale

/**
 * Round ticks (1, 2, 2.5 or 5 × 10^k) inside band `index` of `count` of [min, max], as
 * many as fit in the band's `heightPx` at TICK_SPACING_PX apart (two to MAX_TICKS).
 */
export function bandSplits(index, count, min, max, heightPx = 200) {
  const [b0, b1] = bandOf(index, count);
  const lo = min + b0 * (max - min);
  const hi = min + b1 * (max - min);
  const fit = Math.min(MAX_TICKS, Math.max(2, Math.round(((b1 - b0) * heightPx) / TICK_SPACING_PX)));
  const raw = (hi - lo) / fit;
  const mag = 10 ** Math.floor(Math.log10(raw));
  const incr = [1, 2, 2.5, 5, 10].map((m) => m * mag).find((s) => s >= raw);
  const out = [];
  // (a tick on the band's edge stays, whatever the rounding of the range)
  for (let k = Math.ceil(lo / incr - 1e-9); k * incr <= hi + incr * 1e-9; k++) out.push(+(k * incr).toPrecision(12));
  return out;
}

/**
 * A trend: `pens` ({label, scale, unit}) on a time axis, drawn as steps (a value holds
 * until its next change, as the historian stores it), each pen in its colour and dash,
 * each scale with its own axis in its pen's colour and a band of its own; a legend with
 * the values under the cursor (`showLatest()`: the latest values, the cursor away); a pen
 * shown or hidden by `setPen(i, on)` (the screen's pen selection) or a click in the
 * legend, `onPens(shown)` told of either.
 */
export function trendChart(el, { pens, height, hidden = [], onSelect = () => {}, onPens = () => {} }) {
  const scales = [...new Set(pens.map((p) => p.scale))];
  // The bands follow the scales that have a pen shown with a value to draw (a sensor not
  // fitted takes no room), in the pens' order.
  let valued = [];
  const findValued = (u) => {
    valued = u.series.map((s, i) => i > 0 && u.data[i].some((v) => v != null));
  };
  const shownScales = (u) => scales.filter((k) => u.series.some((s, i) => valued[i] && s.show && s.scale === k));
  const place = (u, k) => {
    const shown = shownScales(u);
    return [Math.max(0, shown.indexOf(k)), Math.max(1, shown.length)];
  };
  const step = uPlot.paths.stepped({ align: 1 });
  const opts = {
    width: widthOf(el),
    height,
    cursor: { drag: { x: true, y: false } },
    scales: {
      x: { time: true },
      ...Object.fromEntries(scales.map((k) => [k, { range: (u, min, max) => bandRange(...place(u, k), min, max) }])),
    },
    series: [
      // The time under the cursor as the tables write it (the locale's order, 24 h).
      { label: t("trend.time"), value: (u, v) => (v == null ? "—" : fmtDateTime(v)) },
      ...pens.map((p, i) => ({
        label: p.label,
        scale: p.scale,
        show: !hidden.includes(p.label),
        stroke: PENS[i % PENS.length].stroke,
        dash: PENS[i % PENS.length].dash,
        width: 2,
        paths: step,
        points: { show: false },
        // In the legend: no value is a dash, not an empty cell.
        value: (u, v) => (v == null ? "—" : fmtSignificant(v, 6)),
      })),
    ],
    axes: [
      // Time ticks in the locale's format and 24 h, as the tables (issue 33, finding 6).
      { values: timeTicks },
      ...scales.map((k, n) => {
        const first = pens.findIndex((p) => p.scale === k);
        const colour = PENS[first % PENS.length].stroke;
        return {
          scale: k,
          label: pens[first].unit || k,
          side: n % 2 ? 1 : 3,
          stroke: colour,
          labelFont: "bold 12px system-ui, sans-serif",
          grid: { stroke: "rgba(31, 42, 54, 0.1)", width: 1 },
          ticks: { stroke: colour, width: 1, size: 5 },
          splits: (u, i, min, max) => bandSplits(...place(u, k), min, max, u.bbox.height / devicePixelRatio),
          values: (u, splits) => splits.map((v) => fmtSignificant(v, 6)),
          size: 56,
        };
      }),
    ],
    legend: { live: true },
    hooks: {
      setData: [findValued],
      // Each scale's range as drawn (a test maps times and values to the canvas with it).
      draw: [(u) => (el.dataset.scales = JSON.stringify(Object.fromEntries(Object.entries(u.scales).map(([k, sc]) => [k, [sc.min, sc.max]]))))],
      setSelect: [(u) => u.select.width > 0 && onSelect(u)],
      // A pen hidden or shown: the others' bands follow, the screen's selection too.
      setSeries: [
        (u, i, o) => {
          if (o?.show == null) return;
          u.redraw();
          onPens(u.series.slice(1).map((s) => s.show));
        },
      ],
    },
  };
  const chart = new uPlot(opts, [[], ...pens.map(() => [])], el);
  const setPen = (i, on) => chart.setSeries(i + 1, { show: on });
  // The legend gives the values under the cursor; the cursor away, the latest ones.
  const showLatest = () => {
    if (!(chart.cursor.left >= 0) && chart.data[0].length) chart.setLegend({ idx: chart.data[0].length - 1 });
  };
  return { chart, setPen, showLatest, stop: autoResize(chart, el, height) };
}

// --- tests compared (the Tests screen, issue 33 finding 10) ---------------------------------

/**
 * Curves that each have their own x values ({x, y}, x rising: V against Ah) on one x axis:
 * the sorted union of their x, each column null where its curve has no point (uPlot joins
 * a curve's points across those gaps: `spanGaps`).
 */
export function xyJoin(curves) {
  const xs = [...new Set(curves.flatMap((c) => c.x))].sort((a, b) => a - b);
  const at = new Map(xs.map((x, i) => [x, i]));
  const cols = curves.map((c) => {
    const col = new Array(xs.length).fill(null);
    c.x.forEach((x, k) => (col[at.get(x)] = c.y[k]));
    return col;
  });
  return [xs, ...cols];
}

/**
 * Curves overlaid ({label, x, y, pen?, width?}: pen, an index into PENS, colour and dash
 * together so a curve is never told by colour alone) with their labels in a legend and
 * units on both axes (`xLabel`, `yLabel` name them). `points`: a marker at every point (a
 * capacity per cycle). `integerX`: whole-number ticks (cycles).
 */
export function xyPlot(el, { title, xLabel, yLabel, curves, height = 300, points = false, integerX = false }) {
  const opts = {
    title,
    width: widthOf(el),
    height,
    scales: { x: { time: false } },
    axes: [
      integerX
        ? { label: xLabel, incrs: [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000], values: (u, vals) => vals.map((v) => (Number.isInteger(v) ? v : "")) }
        : { label: xLabel, values: ticks },
      { label: yLabel, values: ticks, size: 60 },
    ],
    // The legend names the curves; the values under the cursor are mostly gaps here.
    legend: { live: false },
    hooks: {
      // Each curve's label and points, and the axes' labels (drawn on the canvas, not in
      // the page), as drawn: a test reads them here.
      draw: [
        (u) => {
          el.dataset.drawn = JSON.stringify(u.series.slice(1).map((s, i) => ({ label: s.label, points: u.data[i + 1].filter((v) => v != null).length })));
          el.dataset.axes = JSON.stringify(u.axes.map((a) => a.label));
        },
      ],
    },
    series: [
      { label: xLabel },
      ...curves.map((c, i) => {
        const pen = PENS[(c.pen ?? i) % PENS.length];
        return {
          label: c.label,
          stroke: pen.stroke,
          dash: pen.dash,
          width: c.width ?? 2,
          spanGaps: true,
          points: { show: points, size: 6, stroke: pen.stroke, fill: pen.stroke },
        };
      }),
    ],
  };
  const chart = new uPlot(opts, xyJoin(curves), el);
  return { chart, stop: autoResize(chart, el, height) };
}
