// Charts with uPlot (installed from npm by `make hmi`, served at /vendor/uplot/).
import uPlot from "/vendor/uplot/uPlot.esm.js";

export { uPlot };

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

/** A simple x/y line (or bar-like stepped) plot of arrays. */
export function simplePlot(el, { title, xLabel, series, x, ys, height = 220, time = false, bars = false }) {
  const opts = {
    title,
    width: widthOf(el),
    height,
    scales: { x: { time } },
    axes: [{ label: xLabel }, { label: series.map((s) => s.label).join(" / ") }],
    series: [
      { label: xLabel },
      ...series.map((s, i) => ({
        label: s.label,
        ...SERIES_STYLE[i % SERIES_STYLE.length],
        ...(bars ? { paths: uPlot.paths.bars({ size: [0.6, 40] }), fill: i ? "#b9c2cc" : "#5a6b7d" } : {}),
        points: { show: bars ? false : x.length < 60 },
      })),
    ],
  };
  const chart = new uPlot(opts, [x, ...ys], el);
  return { chart, stop: autoResize(chart, el, height) };
}
