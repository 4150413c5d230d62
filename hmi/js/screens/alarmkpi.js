// The Alarms screen's alarm performance panel (issue 34): the ISA-18.2 / EEMUA 191 figures
// the supervisor publishes as alarms.* tags (supervisor/safety/kpi.py, docs/alarms.md),
// live from the screens' one data connection, each beside the target the reference gives
// and a word saying whether it is within it (never the colour alone).
import { esc } from "../dom.js";
import { fmtNumber, t } from "../i18n.js";

const FLOOD_COUNT = 10; // kpi.py FLOOD_COUNT: more than this many in 10 minutes is a flood

const count = (v) => (Number.isFinite(Number(v)) ? String(Math.round(Number(v))) : "—");
const seconds = (v) => `${fmtNumber(v, 0)} s`;
const percent = (v) => `${fmtNumber(v, 1)} %`;
const yesNo = (v) => (v === true ? t("value.yes") : v === false ? t("value.no") : "—");

// Each figure: its tag, how its value is written, its target's text key (none: the
// reference gives no target) and when it is over the target.
const FIGURES = [
  ["alarms.per_10min", count, "kpi.target.per10min", (v) => v > 2],
  ["alarms.per_10min_last", count, "kpi.target.per10min", (v) => v > 2],
  ["alarms.per_day", count, "kpi.target.perDay", (v) => v > 300],
  ["alarms.in_flood", yesNo, "kpi.target.inFlood", (v) => v === true],
  ["alarms.flood_s", seconds, null, null],
  ["alarms.flood_pct", percent, "kpi.target.floodPct", (v) => v >= 1],
  ["alarms.stale", count, "kpi.target.zero", (v) => v > 0],
  ["alarms.chattering", count, "kpi.target.zero", (v) => v > 0],
  ["alarms.kpi_dropped", count, "kpi.target.zero", (v) => v > 0],
];

// The priority distribution's usual shares (docs/alarms.md; none given for medium).
const PRIORITIES = [
  ["critical", "kpi.target.pct5"],
  ["high", "kpi.target.pct15"],
  ["medium", null],
  ["low", "kpi.target.pct80"],
];

const key = (tag) => tag.replace(/^alarms\./, "").replace(/\./g, "_");

/** The panel's frame: the figures are painted in by paintKpi. */
export function kpiHtml() {
  const tx = (k, p) => esc(t(k, p));
  const rows = FIGURES.map(
    ([tag]) => `<tr data-row="${tag}"><th scope="row">${tx(`kpi.${key(tag)}`)}</th>
      <td class="num" data-kpi="${tag}">—</td><td class="target"></td><td class="verdict"></td></tr>`,
  ).join("");
  const prio = PRIORITIES.map(
    ([p, target]) => `<tr><th scope="row">${tx(`priority.${p}`)}</th>
      <td class="num" data-kpi="alarms.priority.${p}">—</td><td class="num" data-kpi="alarms.priority.${p}_pct">—</td>
      <td class="target">${target ? tx(target) : "—"}</td></tr>`,
  ).join("");
  return `<section class="panel kpi" id="alarm-kpi" aria-labelledby="alarm-kpi-title">
    <h2 id="alarm-kpi-title">${tx("kpi.title")}</h2>
    <p class="muted">${tx("kpi.hint", { n: FLOOD_COUNT })}</p>
    <div class="kpi-grid">
      <table class="grid kpi-table" id="kpi-figures"><caption class="sr-only">${tx("kpi.figures")}</caption>
        <thead><tr><th scope="col">${tx("kpi.col.figure")}</th><th scope="col">${tx("kpi.col.value")}</th><th scope="col">${tx("kpi.col.target")}</th><th scope="col">${tx("kpi.col.verdict")}</th></tr></thead>
        <tbody>${rows}</tbody></table>
      <div>
        <table class="grid kpi-table" id="kpi-priorities"><caption>${tx("kpi.priorities")}</caption>
          <thead><tr><th scope="col">${tx("alarms.col.priority")}</th><th scope="col">${tx("kpi.col.count")}</th><th scope="col">${tx("kpi.col.share")}</th><th scope="col">${tx("kpi.col.target")}</th></tr></thead>
          <tbody>${prio}</tbody></table>
        <p id="kpi-chattering-ids" class="muted" hidden></p>
        <div id="kpi-top"></div>
      </div>
    </div></section>`;
}

function formatOf(tag) {
  const figure = FIGURES.find(([name]) => name === tag);
  if (figure) return figure[1];
  return tag.endsWith("_pct") ? percent : count;
}

/** The top ten (alarms.top, JSON [{id, count}]) as a table, or a line when empty. */
function topHtml(text) {
  let top = [];
  try {
    top = JSON.parse(text || "[]");
  } catch {
    top = [];
  }
  if (!Array.isArray(top) || !top.length) return `<p class="muted" id="kpi-top-none">${esc(t("kpi.topNone"))}</p>`;
  const rows = top
    .map((e, i) => `<tr><td class="num">${i + 1}</td><td class="alarm-id" translate="no">${esc(e.id)}</td><td class="num" data-top="${esc(e.id)}">${esc(count(e.count))}</td></tr>`)
    .join("");
  return `<table class="grid kpi-table" id="kpi-top-table"><caption>${esc(t("kpi.top"))}</caption>
    <thead><tr><th scope="col">${esc(t("kpi.col.rank"))}</th><th scope="col">${esc(t("alarms.col.alarm"))}</th><th scope="col">${esc(t("kpi.col.count"))}</th></tr></thead>
    <tbody>${rows}</tbody></table>`;
}

/** Paint the figures from the live tags (`live.value(name)`). */
export function paintKpi(root, live) {
  const panel = root.querySelector("#alarm-kpi");
  if (!panel) return;
  for (const cell of panel.querySelectorAll("[data-kpi]")) {
    const v = live.value(cell.dataset.kpi);
    cell.dataset.value = v === undefined || v === null ? "" : String(v);
    cell.textContent = v === undefined || v === null ? "—" : formatOf(cell.dataset.kpi)(v);
  }
  for (const [tag, , target, over] of FIGURES) {
    const row = panel.querySelector(`tr[data-row="${tag}"]`);
    const v = live.value(tag);
    row.querySelector(".target").textContent = target ? t(target, { n: FLOOD_COUNT }) : "—";
    const verdict = row.querySelector(".verdict");
    const known = v !== undefined && v !== null && over;
    const bad = known && over(v);
    verdict.textContent = known ? t(bad ? "kpi.over" : "kpi.within") : "";
    row.classList.toggle("abn", Boolean(bad));
  }
  const ids = String(live.value("alarms.chattering_ids") || "");
  const chattering = panel.querySelector("#kpi-chattering-ids");
  chattering.hidden = !ids;
  chattering.textContent = ids ? t("kpi.chatteringIds", { ids }) : "";
  const top = live.value("alarms.top");
  const holder = panel.querySelector("#kpi-top");
  if (holder.dataset.text !== String(top)) {
    holder.dataset.text = String(top);
    holder.innerHTML = topHtml(top);
  }
}

/** Does a live change touch the figures? */
export const kpiChanged = (change) => change.kind === "tags" && (!change.names || change.names.some((n) => n.startsWith("alarms.")));
