// Charts with uPlot (installed from npm by `make hmi`, served at /vendor/uplot/).
// The minified build, loaded by index.html before the app (window.uPlot).
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

/** Tick labels with enough digits for small values (mAh-sized Ah, efficiencies). */
const ticks = (u, vals) => vals.map((v) => (v === null ? "" : Math.abs(v) >= 100 ? v.toFixed(0) : +v.toPrecision(3)));

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
      { label: yLabel ?? series.map((s) => s.label).join(" / "), values: yValues ?? ticks, size: 60 },
    ],
    series: [
      { label: xLabel },
      ...series.map((s, i) => ({
        label: s.label,
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
export function timelinePlot(el, timeline, durationS, title = "Timeline: step over time") {
  const tl = (timeline || []).filter((e) => e.step && typeof e.t_s === "number");
  if (!tl.length) return null;
  const stepNames = [];
  for (const e of tl) if (!stepNames.includes(e.step)) stepNames.push(e.step);
  const end = Math.max(durationS || 0, tl[tl.length - 1].t_s);
  const ax = timeAxis(end);
  return simplePlot(el, {
    title,
    xLabel: ax.unit,
    yLabel: "step",
    series: [{ label: "step" }],
    x: [...tl.map((e) => e.t_s / ax.scale), end / ax.scale],
    ys: [[...tl.map((e) => stepNames.indexOf(e.step)), stepNames.indexOf(tl[tl.length - 1].step)]],
    height: 200,
    stepped: true,
    yValues: (u, vals) => vals.map((v) => (Number.isInteger(v) ? stepNames[v] ?? "" : "")),
  });
}
