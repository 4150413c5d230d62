// Alarm priorities as ISA-101 wants them seen: shape, colour and number together, so a
// priority reads without colour (a colour-blind operator, a washed-out panel). The
// numbers are the severities the supervisor sends (supervisor/safety/alarms.py Severity,
// the OPC UA 1–1000 scale); the names are the ones it sends beside them (severity_name).
import { esc } from "./dom.js";
import { t } from "./i18n.js";

// Highest first. Shapes: a square, a triangle, a diamond, a circle — four outlines that
// differ at icon size; colours from the red of an alarm down to a violet, never green
// or grey (grey is "normal" on these screens). The colours themselves are in hmi.css
// (.prio-NAME: the Content-Security-Policy allows no inline style); they are named here
// for the summary's and the tests' sake.
export const PRIORITIES = [
  { name: "critical", rank: 1, min: 900, shape: "square", colour: "#c8102e", ink: "#fff" },
  { name: "high", rank: 2, min: 700, shape: "triangle", colour: "#e36c0a", ink: "#000" },
  { name: "medium", rank: 3, min: 500, shape: "diamond", colour: "#f2c500", ink: "#000" },
  { name: "low", rank: 4, min: 0, shape: "circle", colour: "#6b4fa8", ink: "#fff" },
];

/** The priority of a severity (a number, or a name such as "high"). */
export function priorityOf(severity) {
  if (typeof severity === "string" && Number.isNaN(Number(severity))) {
    return PRIORITIES.find((p) => p.name === severity.toLowerCase()) || PRIORITIES.at(-1);
  }
  const n = Number(severity) || 0;
  return PRIORITIES.find((p) => n >= p.min) || PRIORITIES.at(-1);
}

const SHAPES = {
  square: '<rect data-shape="square" x="2" y="2" width="16" height="16" rx="1"/>',
  triangle: '<polygon data-shape="triangle" points="10,1 19,18 1,18"/>',
  diamond: '<polygon data-shape="diamond" points="10,0 20,10 10,20 0,10"/>',
  circle: '<circle data-shape="circle" cx="10" cy="10" r="9"/>',
};

/** An inline SVG icon of a severity's priority: its shape in its colour, its rank inside. */
export function priorityIcon(severity) {
  const p = priorityOf(severity);
  // The triangle's number sits lower: its centre of area is below the box's.
  const y = p.shape === "triangle" ? 15.5 : 14.5;
  return `<svg class="prio prio-${p.name}" viewBox="0 0 20 20" width="20" height="20" role="img" aria-label="${esc(t("priority.aria", { rank: p.rank, name: t(`priority.${p.name}`) }))}">${SHAPES[p.shape]}<text x="10" y="${y}" text-anchor="middle" aria-hidden="true">${p.rank}</text></svg>`;
}
