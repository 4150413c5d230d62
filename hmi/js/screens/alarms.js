// Alarms (ISA-18.2): the annunciated ones (first-out first) with acknowledge, reset,
// shelve and unshelve, and the latest transitions with their actor; each with its
// priority's shape, colour and number (priority.js, ISA-101). Below them the journal's
// search and export (alarmjournal.js) and the alarm performance figures (alarmkpi.js).
import { get, post } from "../api.js";
import { alarmText, esc, fmtTime, showResult, $ } from "../dom.js";
import { t, tValue } from "../i18n.js";
import { priorityIcon, priorityOf } from "../priority.js";
import { bindJournal, journalHtml } from "./alarmjournal.js";
import { kpiChanged, kpiHtml, paintKpi } from "./alarmkpi.js";

const SHELVE_S = [
  ["15 min", 900],
  ["1 h", 3600],
  ["8 h", 28800],
]; // (SI units: the same in both languages)
const tx = (key, params) => esc(t(key, params));

/** An alarm's id, breakable after its dots and underscores only (never mid-word). */
const idHtml = (id) => esc(id).replace(/([._])/g, "$1<wbr>");

function sevClass(a) {
  if (a.state === "normal") return "";
  return `sev-${priorityOf(a.severity).name}`;
}

/** The shelve control of an active alarm: unshelve, or a duration and Shelve. */
function shelveControls(a) {
  if (a.shelved) return `<button type="button" class="small" data-act="unshelve">${tx("alarms.act.unshelve")}</button>`;
  const options = SHELVE_S.map(([l, s]) => `<option value="${s}">${l}</option>`).join("");
  return `<span class="shelve"><select class="small" aria-label="${tx("alarms.shelveFor", { id: a.id })}">${options}</select><button type="button" class="small" data-act="shelve">${tx("alarms.act.shelve")}</button></span>`;
}

// Five columns, each holding what belongs together (priority; the alarm, its first-out
// mark and its channel; its state with since when and who acknowledged; the message; the
// actions), so that the table fits a tablet's 800 px with its buttons in reach.
const activeHead = () =>
  ["priority", "alarm", "state", "message", "actions"].map((c) => `<th>${tx(`alarms.col.${c}`)}</th>`).join("");

function activeRow(a) {
  const shelved = a.shelved ? ` ${tx("alarms.shelvedUntil", { time: fmtTime(a.shelved_until) })}` : "";
  const acked = a.acked_by ? `<div class="muted">${tx("alarms.ackedBy", { user: a.acked_by })}</div>` : "";
  return `<tr class="${sevClass(a)}${a.shelved ? " shelved" : ""}" data-alarm="${esc(a.id)}">
    <td class="prio-cell">${priorityIcon(a.severity)} <span class="prio-name">${esc(tValue("priority", a.severity_name || priorityOf(a.severity).name))}</span></td>
    <td>${a.first_out ? `<b class="first-out">${tx("alarms.firstOut")}</b> ` : ""}<span class="alarm-id">${idHtml(a.id)}</span>
      <div class="muted">${esc(a.group || t("alarms.bench"))}</div></td>
    <td class="alarm-state">${esc(tValue("alarmState", a.state))}${shelved}<div class="muted">${tx("alarms.since", { time: fmtTime(a.activated_time) })}</div>${acked}</td>
    <td class="wrap">${esc(alarmText(a))}${a.detail ? ` <small class="muted" translate="no">(${esc(a.detail)})</small>` : ""}</td>
    <td class="actions"><div class="alarm-actions">
      <button type="button" class="small" data-act="acknowledge">${tx("alarms.act.acknowledge")}</button>
      <button type="button" class="small" data-act="reset">${tx("alarms.act.reset")}</button>
      ${shelveControls(a)}
    </div></td></tr>`;
}

function historyRow(e) {
  return `<tr><td class="time">${esc(fmtTime(e.time))}</td>
    <td>${priorityIcon(e.severity)} <span class="alarm-id">${idHtml(e.alarm)}</span><div class="muted">${esc(e.group || t("alarms.bench"))}</div></td>
    <td>${esc(tValue("transition", e.transition))}<div class="muted">${esc(tValue("alarmState", e.state))}</div></td>
    <td class="wrap">${esc(alarmText(e))}</td><td>${esc(e.actor || "")}</td></tr>`;
}

export async function render({ root, app }) {
  root.dataset.title = t("nav.alarms");
  root.innerHTML = `
    <h1>${tx("nav.alarms")}</h1>
    <p id="alarm-result" class="result" role="status" aria-live="polite" hidden></p>
    <section class="panel"><h2>${tx("alarms.active")}</h2><div id="alarm-active"></div></section>
    <section class="panel"><h2>${tx("alarms.history")}</h2><div id="alarm-history"></div></section>
    ${journalHtml(app)}
    ${kpiHtml()}`;
  const out = $("#alarm-result", root);
  let active = app.live.alarms;

  const paintActive = () => {
    const list = active.filter((a) => a.state !== "normal");
    list.sort((x, y) => Number(y.first_out) - Number(x.first_out) || (x.activated_time || 0) - (y.activated_time || 0));
    $("#alarm-active", root).innerHTML = list.length
      ? `<table class="grid alarms" id="alarm-table"><thead><tr>${activeHead()}</tr></thead><tbody>${list.map(activeRow).join("")}</tbody></table>`
      : `<p class="muted" id="alarm-none">${tx("alarms.none")}</p>`;
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
      ? `<table class="grid alarms" id="alarm-history-table"><thead><tr>${["time", "alarm", "transition", "message", "by"].map((c) => `<th>${tx(`alarms.col.${c}`)}</th>`).join("")}</tr></thead><tbody>${rows.map(historyRow).join("")}</tbody></table>`
      : `<p class="muted">${tx("alarms.noHistory")}</p>`;
  };

  root.addEventListener("click", async (ev) => {
    const b = ev.target.closest("button[data-act]");
    if (!b) return;
    const tr = b.closest("tr[data-alarm]");
    const id = tr.dataset.alarm;
    const act = b.dataset.act;
    const body = act === "shelve" ? { duration_s: Number(tr.querySelector("select").value) } : {};
    const answer = await post(`/api/alarms/${encodeURIComponent(id)}/${act}`, body);
    showResult(out, answer, t("alarms.done", { id, act: t(`alarms.act.${act}`) }));
    loadHistory();
  });

  paintActive();
  loadHistory();
  const journal = bindJournal(root, app);
  paintKpi(root, app.live);
  return {
    update(change) {
      if (kpiChanged(change)) paintKpi(root, app.live);
      if (change.kind === "alarms") {
        active = app.live.alarms;
        paintActive();
        loadHistory();
        journal.paint();
      }
    },
  };
}
