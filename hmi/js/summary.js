// The bench summary in the header of every screen (ISA-101 level 1: the whole bench at a
// glance): channels running, held and faulted, and the active alarms by priority, each
// count a link to where it is dealt with. Colour only for what needs someone: faulted
// channels and unacknowledged alarms in the alarm colour, held ones in the warning colour.
import { esc } from "./dom.js";
import { PRIORITIES, priorityIcon, priorityOf } from "./priority.js";
import { t } from "./i18n.js";

const HELD = new Set(["Holding", "Held"]);
const RUNNING = new Set(["Running", "Resuming", "Stopping", "Aborting"]);
const MOVING = new Set(["charging", "discharging"]);

/** What a channel is doing, for the summary: "faulted" (a latched trip), "held", "running"
 * (its chain runs, or it is driven in Manual), else "idle". A faulted channel is counted
 * as faulted only, whatever its chain's state: each channel in exactly one count. */
export function channelKind(ch, live) {
  const t = ch.tags;
  const fault = live.value(t.fault);
  const state = live.value(t.channel_state);
  if ((typeof fault === "string" && fault !== "") || state === "faulted") return "faulted";
  const chain = String(live.value(t.state) ?? "");
  if (HELD.has(chain)) return "held";
  if (RUNNING.has(chain) || MOVING.has(state)) return "running";
  return "idle";
}

/** The summary's counts: {channels, running, held, faulted, idle, alarms, unacknowledged,
 * shelved, critical, high, medium, low}. Shelved alarms are not counted as active. */
export function benchCounts(bench, live) {
  const counts = { channels: 0, running: 0, held: 0, faulted: 0, idle: 0 };
  for (const ch of bench?.channels || []) {
    counts.channels += 1;
    counts[channelKind(ch, live)] += 1;
  }
  const raised = live.alarms.filter((a) => a.state !== "normal");
  const active = raised.filter((a) => !a.shelved);
  counts.alarms = active.length;
  counts.unacknowledged = active.filter((a) => a.state.includes("unacknowledged")).length;
  counts.shelved = raised.length - active.length;
  for (const p of PRIORITIES) counts[p.name] = 0;
  for (const a of active) counts[priorityOf(a.severity).name] += 1;
  return counts;
}

const item = (href, name, value, text, cls = "") =>
  `<a href="${href}" class="sum${cls ? ` ${cls}` : ""}" data-count="${name}" data-value="${value}">${text}</a>`;

/** The summary bar's HTML for the counts. */
export function summaryHtml(c) {
  const unacked = c.unacknowledged ? `, ${t("summary.unacked", { n: c.unacknowledged })}` : "";
  const parts = [
    // The channels' total: in the counts' tooltips and for the tests, not in the bar's width
    // (the header must stay one line at 1366 px).
    `<span hidden data-count="channels" data-value="${c.channels}"></span>`,
    `<span hidden data-count="unacknowledged" data-value="${c.unacknowledged}"></span>`,
    item("#/", "running", c.running, `<span class="sym" aria-hidden="true">▶</span> ${t("summary.running", { n: c.running, count: c.running })}`),
    item("#/", "held", c.held, `<span class="sym" aria-hidden="true">❚❚</span> ${t("summary.held", { n: c.held, count: c.held })}`, c.held ? "warn" : ""),
    item("#/", "faulted", c.faulted, `<span class="sym" aria-hidden="true">✖</span> ${t("summary.faulted", { n: c.faulted, count: c.faulted })}`, c.faulted ? "abn" : ""),
    item("#/alarms", "alarms", c.alarms, `${t("summary.alarms", { n: c.alarms, count: c.alarms })}${unacked}`, c.unacknowledged ? "abn" : ""),
  ];
  // Per priority, only those present: its icon and its count (shape, colour, number).
  for (const p of PRIORITIES) {
    if (c[p.name]) parts.push(item("#/alarms", p.name, c[p.name], `${priorityIcon(p.min)}${c[p.name]}`, "prio-count"));
  }
  return parts.join("");
}

/** Repaint the summary element when its counts changed (the tags change many times a
 * second; the bar's HTML only when a count does). */
export function paintSummary(el, bench, live) {
  const c = benchCounts(bench, live);
  const key = JSON.stringify(c);
  if (el.dataset.key === key) return;
  el.dataset.key = key;
  el.innerHTML = summaryHtml(c);
  el.title = t("summary.title", c);
  el.setAttribute("aria-label", t("summary.aria", c));
}
