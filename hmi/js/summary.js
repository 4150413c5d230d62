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

/** A channels' count: its symbol and its words ("▶ 2 running"), or, compact, its symbol
 * and its number with the words in its tooltip. */
function channelsItem(name, sym, n, cls, compact) {
  const words = t(`summary.${name}`, { n, count: n });
  const text = compact ? `${n}` : words;
  const title = compact ? ` title="${esc(words)}"` : "";
  return item("#/", name, n, `<span class="sym" aria-hidden="true">${sym}</span> ${esc(text)}`, cls).replace("<a ", `<a${title} `);
}

/** The alarms' count: "12 alarms, 3 unack.", or, short, the count that asks for
 * someone ("3 unack.", else "12 alarms") with the whole in its tooltip. */
function alarmsItem(c, short) {
  const all = t("summary.alarms", { n: c.alarms, count: c.alarms });
  const unacked = c.unacknowledged ? t("summary.unacked", { n: c.unacknowledged }) : "";
  const words = unacked ? `${all}, ${unacked}` : all;
  const text = short ? unacked || all : words;
  const title = short ? ` title="${esc(words)}"` : "";
  return item("#/alarms", "alarms", c.alarms, esc(text), c.unacknowledged ? "abn" : "").replace("<a ", `<a${title} `);
}

/** The summary bar's HTML for the counts, at a level of the header's fit (headerfit.js):
 * from 1 the channel counts without their words, from 3 the alarms' count short. */
export function summaryHtml(c, level = 0) {
  const compact = level >= 1;
  const parts = [
    // The channels' total: in the counts' tooltips and for the tests, not in the bar's width
    // (the header must stay one line at 1366 px).
    `<span hidden data-count="channels" data-value="${c.channels}"></span>`,
    `<span hidden data-count="unacknowledged" data-value="${c.unacknowledged}"></span>`,
    channelsItem("running", "▶", c.running, "", compact),
    channelsItem("held", "❚❚", c.held, c.held ? "warn" : "", compact),
    channelsItem("faulted", "✖", c.faulted, c.faulted ? "abn" : "", compact),
    alarmsItem(c, level >= 3),
  ];
  // Per priority, only those present: its icon and its count (shape, colour, number).
  for (const p of PRIORITIES) {
    if (c[p.name]) parts.push(item("#/alarms", p.name, c[p.name], `${priorityIcon(p.min)}${c[p.name]}`, "prio-count"));
  }
  return parts.join("");
}

/** Repaint the summary element when its counts changed (the tags change many times a
 * second; the bar's HTML only when a count does). */
export function paintSummary(el, bench, live, level = 0) {
  const c = benchCounts(bench, live);
  const key = `${level} ${JSON.stringify(c)}`;
  if (el.dataset.key === key) return;
  el.dataset.key = key;
  el.innerHTML = summaryHtml(c, level);
  el.title = t("summary.title", c);
  el.setAttribute("aria-label", t("summary.aria", c));
}
