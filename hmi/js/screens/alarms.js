// Alarms (ISA-18.2): the annunciated ones (first-out first) with acknowledge, reset,
// shelve and unshelve, and the latest transitions with their actor; each with its
// priority's shape, colour and number (priority.js, ISA-101).
import { get, post } from "../api.js";
import { esc, fmtTime, showResult, $ } from "../dom.js";
import { priorityIcon, priorityOf } from "../priority.js";

const SHELVE_S = [
  ["15 min", 900],
  ["1 h", 3600],
  ["8 h", 28800],
];

/** An alarm's id, breakable after its dots and underscores only (never mid-word). */
const idHtml = (id) => esc(id).replace(/([._])/g, "$1<wbr>");

function sevClass(a) {
  if (a.state === "normal") return "";
  return `sev-${priorityOf(a.severity).name}`;
}

/** The shelve control of an active alarm: unshelve, or a duration and Shelve. */
function shelveControls(a) {
  if (a.shelved) return '<button type="button" class="small" data-act="unshelve">Unshelve</button>';
  const options = SHELVE_S.map(([l, s]) => `<option value="${s}">${l}</option>`).join("");
  return `<span class="shelve"><select class="small" aria-label="shelve ${esc(a.id)} for">${options}</select><button type="button" class="small" data-act="shelve">Shelve</button></span>`;
}

// Five columns, each holding what belongs together (priority; the alarm, its first-out
// mark and its channel; its state with since when and who acknowledged; the message; the
// actions), so that the table fits a tablet's 800 px with its buttons in reach.
const ACTIVE_HEAD = "<th>priority</th><th>alarm</th><th>state</th><th>message</th><th>actions</th>";

function activeRow(a) {
  const shelved = a.shelved ? ` (shelved until ${esc(fmtTime(a.shelved_until))})` : "";
  const acked = a.acked_by ? `<div class="muted">acked by ${esc(a.acked_by)}</div>` : "";
  return `<tr class="${sevClass(a)}${a.shelved ? " shelved" : ""}" data-alarm="${esc(a.id)}">
    <td class="prio-cell">${priorityIcon(a.severity)} <span class="prio-name">${esc(a.severity_name || priorityOf(a.severity).name)}</span></td>
    <td>${a.first_out ? '<b class="first-out">FIRST OUT</b> ' : ""}<span class="alarm-id">${idHtml(a.id)}</span>
      <div class="muted">${esc(a.group || "bench")}</div></td>
    <td class="alarm-state">${esc(a.state)}${shelved}<div class="muted">since ${esc(fmtTime(a.activated_time))}</div>${acked}</td>
    <td class="wrap">${esc(a.message)}${a.detail ? ` <small class="muted">(${esc(a.detail)})</small>` : ""}</td>
    <td class="actions"><div class="alarm-actions">
      <button type="button" class="small" data-act="acknowledge">Acknowledge</button>
      <button type="button" class="small" data-act="reset">Reset</button>
      ${shelveControls(a)}
    </div></td></tr>`;
}

function historyRow(e) {
  return `<tr><td class="time">${esc(fmtTime(e.time))}</td>
    <td>${priorityIcon(e.severity)} <span class="alarm-id">${idHtml(e.alarm)}</span><div class="muted">${esc(e.group || "bench")}</div></td>
    <td>${esc(e.transition)}<div class="muted">${esc(e.state)}</div></td>
    <td class="wrap">${esc(e.message)}</td><td>${esc(e.actor || "")}</td></tr>`;
}

export async function render({ root, app }) {
  root.dataset.title = "Alarms";
  root.innerHTML = `
    <h1>Alarms</h1>
    <p id="alarm-result" class="result" role="status" aria-live="polite" hidden></p>
    <section class="panel"><h2>Active</h2><div id="alarm-active"></div></section>
    <section class="panel"><h2>History</h2><div id="alarm-history"></div></section>`;
  const out = $("#alarm-result", root);
  let active = app.live.alarms;

  const paintActive = () => {
    const list = active.filter((a) => a.state !== "normal");
    list.sort((x, y) => Number(y.first_out) - Number(x.first_out) || (x.activated_time || 0) - (y.activated_time || 0));
    $("#alarm-active", root).innerHTML = list.length
      ? `<table class="grid alarms" id="alarm-table"><thead><tr>${ACTIVE_HEAD}</tr></thead><tbody>${list.map(activeRow).join("")}</tbody></table>`
      : '<p class="muted" id="alarm-none">No active alarms.</p>';
  };

  const loadHistory = async () => {
    const answer = await get("/api/alarms?limit=200");
    if (!answer.ok) return;
    if (app.live.state !== "live") {
      active = answer.data.active || [];
      paintActive();
    }
    const rows = (answer.data.history || []).slice().reverse();
    $("#alarm-history", root).innerHTML = rows.length
      ? `<table class="grid alarms" id="alarm-history-table"><thead><tr><th>time</th><th>alarm</th><th>transition</th><th>message</th><th>by</th></tr></thead><tbody>${rows.map(historyRow).join("")}</tbody></table>`
      : '<p class="muted">No alarm transitions yet.</p>';
  };

  root.addEventListener("click", async (ev) => {
    const b = ev.target.closest("button[data-act]");
    if (!b) return;
    const tr = b.closest("tr[data-alarm]");
    const id = tr.dataset.alarm;
    const act = b.dataset.act;
    const body = act === "shelve" ? { duration_s: Number(tr.querySelector("select").value) } : {};
    const answer = await post(`/api/alarms/${encodeURIComponent(id)}/${act}`, body);
    showResult(out, answer, `${id}: ${act} done`);
    loadHistory();
  });

  paintActive();
  loadHistory();
  return {
    update(change) {
      if (change.kind === "alarms") {
        active = app.live.alarms;
        paintActive();
        loadHistory();
      }
    },
  };
}
