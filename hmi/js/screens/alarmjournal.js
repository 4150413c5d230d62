// The Alarms screen's journal (issue 34): every transition of the alarm model searched by
// time, channel, alarm, actor and transition (GET /api/alarms/journal, docs/alarms.md), the
// newest first on screen, and the same search as a CSV download (format=csv).
import { get } from "../api.js";
import { alarmText, esc, fmtTime } from "../dom.js";
import { lang, t, tValue } from "../i18n.js";
import { PRIORITIES, priorityIcon } from "../priority.js";

const TRANSITIONS = ["activated", "cleared", "acknowledged", "reset", "shelved", "unshelved", "silenced"];
const DAY_S = 86400;
export const BENCH_CHANNEL = "-"; // the select's value for the bench's own alarms (channel=)

/** A time as an <input type="datetime-local"> holds it (local time, seconds). */
export function localInput(unixS) {
  const d = new Date(unixS * 1000);
  const p = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())}T${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}`;
}

/** An <input type="datetime-local">'s value as Unix seconds (its time is local), or "". */
export function unixOfInput(value) {
  if (!value) return "";
  const ms = new Date(value).getTime();
  return Number.isFinite(ms) ? String(Math.floor(ms / 1000)) : "";
}

export function journalHtml(app) {
  const tx = (k, p) => esc(t(k, p));
  const channels = (app.bench?.channels || []).map((c) => `<option value="${esc(c.name)}">${esc(c.name)}</option>`).join("");
  const transitions = TRANSITIONS.map((v) => `<option value="${v}">${esc(tValue("transition", v))}</option>`).join("");
  const alarms = Array.from(new Set((app.live.alarms || []).map((a) => a.id)))
    .sort()
    .map((id) => `<option value="${esc(id)}"></option>`)
    .join("");
  return `<section class="panel journal" id="alarm-journal" aria-labelledby="alarm-journal-title">
    <h2 id="alarm-journal-title">${tx("journal.title")}</h2>
    <form id="journal-form" class="filters">
      <label>${tx("journal.since")} <input type="datetime-local" step="1" id="journal-since" name="since"></label>
      <label>${tx("journal.until")} <input type="datetime-local" step="1" id="journal-until" name="until"></label>
      <label>${tx("journal.channel")} <select id="journal-channel" name="channel">
        <option value="">${tx("journal.anyChannel")}</option><option value="${BENCH_CHANNEL}">${tx("alarms.bench")}</option>${channels}</select></label>
      <label>${tx("journal.alarm")} <input id="journal-alarm" name="alarm" list="journal-alarm-ids" autocomplete="off" size="14" translate="no"></label>
      <datalist id="journal-alarm-ids">${alarms}</datalist>
      <label>${tx("journal.actor")} <input id="journal-actor" name="actor" autocomplete="off" size="14" placeholder="hmi:…" translate="no"></label>
      <label>${tx("journal.transition")} <select id="journal-transition" name="transition"><option value="">${tx("journal.anyTransition")}</option>${transitions}</select></label>
      <span class="filter-actions"><button type="submit" id="journal-search" class="primary">${tx("journal.search")}</button>
      <a id="journal-export" class="button-link" href="/api/alarms/journal?format=csv" download="alarm-journal.csv">${tx("journal.export")}</a></span>
    </form>
    <p id="journal-count" class="muted" role="status" aria-live="polite"></p>
    <div id="journal-results"></div></section>`;
}

/** The journal's query string of the form's filters (without format). */
export function journalQuery(form) {
  const q = new URLSearchParams();
  const v = (name) => form.elements[name].value.trim();
  const since = unixOfInput(v("since"));
  const until = unixOfInput(v("until"));
  if (since) q.set("since", since);
  if (until) q.set("until", until);
  const channel = v("channel");
  if (channel) q.set("channel", channel === BENCH_CHANNEL ? "" : channel);
  for (const name of ["alarm", "actor", "transition"]) if (v(name)) q.set(name, v(name));
  return q;
}

/** The message in the screens' language where it can be: the journal carries the
 * supervisor's English text only, so a message that is the very text of an alarm the page
 * knows (with its code and params) reads as that alarm's; any other is marked English. */
function messageCell(e, alarms) {
  const same = alarms.find((a) => a.id === e.alarm && a.message === e.message && a.code);
  if (lang() === "en" || same) return `<td class="wrap">${esc(same ? alarmText(same) : e.message)}</td>`;
  return `<td class="wrap" lang="en">${esc(e.message)}</td>`;
}

// (data-alarm-id, not data-alarm: that one marks the active alarms' rows, which the
// screens and their tests look for anywhere on the page)
function row(e, alarms) {
  // (the journal names the priority: "critical", or a number the supervisor has no name for)
  const known = PRIORITIES.some((p) => p.name === e.priority);
  const icon = known ? priorityIcon(e.priority) : "";
  return `<tr data-alarm-id="${esc(e.alarm)}" data-transition="${esc(e.transition)}" data-priority="${esc(e.priority)}">
    <td class="time">${esc(fmtTime(e.time))}</td>
    <td class="prio-cell">${icon} <span class="prio-name">${esc(tValue("priority", e.priority))}</span></td>
    <td><span class="alarm-id" translate="no">${esc(e.alarm).replace(/([._])/g, "$1<wbr>")}</span><div class="muted">${esc(e.channel || t("alarms.bench"))}</div></td>
    <td>${esc(tValue("transition", e.transition))}</td>
    ${messageCell(e, alarms)}
    <td translate="no">${esc(e.actor)}</td></tr>`;
}

function table(entries, alarms) {
  const cols = ["time", "priority", "alarm", "transition", "message", "by"];
  const head = cols.map((c) => `<th scope="col">${esc(t(`alarms.col.${c}`))}</th>`).join("");
  const rows = entries.slice().reverse().map((e) => row(e, alarms)).join("");
  return `<table class="grid alarms" id="journal-table"><caption class="sr-only">${esc(t("journal.title"))}</caption><thead><tr>${head}</tr></thead><tbody>${rows}</tbody></table>`;
}

/** Wire the form: a search on submit (and one now, the last 24 h); the export link is
 * always the search on screen, as CSV. ``paint()``: the rows again, with the alarms the
 * page knows now. */
export function bindJournal(root, app) {
  const form = root.querySelector("#journal-form");
  const out = root.querySelector("#journal-results");
  const status = root.querySelector("#journal-count");
  const link = root.querySelector("#journal-export");
  form.elements.since.value = localInput(Math.floor(Date.now() / 1000) - DAY_S);
  let gen = 0;
  let shown = [];
  const search = async () => {
    const q = journalQuery(form);
    const mine = ++gen;
    root.querySelector("#alarm-journal").setAttribute("aria-busy", "true");
    const answer = await get(`/api/alarms/journal?${q}`);
    if (mine !== gen) return;
    root.querySelector("#alarm-journal").removeAttribute("aria-busy");
    q.set("format", "csv");
    link.href = `/api/alarms/journal?${q}`;
    root.querySelector("#alarm-journal").dataset.searched = String(mine);
    if (!answer.ok) {
      status.className = "refused";
      status.textContent = t("journal.refused", { reason: answer.data?.reason || `HTTP ${answer.status}` });
      shown = [];
      out.innerHTML = "";
      return;
    }
    const d = answer.data;
    status.className = "muted";
    status.textContent = `${t("journal.count", { n: d.count, count: d.count })}${d.truncated ? ` ${t("journal.truncated")}` : ""}`;
    shown = d.entries;
    paint();
  };
  // The rows again (no new request) when the page learns the alarms' codes: the live
  // connection's first alarms can come after the first search's answer.
  const paint = () => {
    out.innerHTML = shown.length ? table(shown, app.live.alarms || []) : `<p class="muted" id="journal-none">${esc(t("journal.none"))}</p>`;
  };
  form.addEventListener("submit", (ev) => {
    ev.preventDefault();
    search();
  });
  search();
  return { search, paint };
}
