// Alarms (ISA-18.2): the annunciated ones (first-out first) with acknowledge, reset,
// shelve and unshelve, and the latest transitions with their actor.
import { get, post } from "../api.js";
import { esc, fmtTime, showResult, $ } from "../dom.js";

const SHELVE_S = [
  ["15 min", 900],
  ["1 h", 3600],
  ["8 h", 28800],
];

function sevClass(a) {
  if (a.state === "normal") return "";
  if (a.severity >= 700) return "sev-high";
  if (a.severity >= 500) return "sev-medium";
  return "sev-low";
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
      ? `<table class="grid" id="alarm-table"><thead><tr><th>first out</th><th>alarm</th><th>channel</th><th>severity</th><th>state</th><th>message</th><th>since</th><th>acked by</th><th>actions</th></tr></thead><tbody>
      ${list
        .map(
          (a) => `<tr class="${sevClass(a)}${a.shelved ? " shelved" : ""}" data-alarm="${esc(a.id)}">
          <td>${a.first_out ? '<b class="first-out">FIRST OUT</b>' : ""}</td>
          <td>${esc(a.id)}</td><td>${esc(a.group || "bench")}</td>
          <td>${esc(a.severity_name || a.severity)}</td>
          <td class="alarm-state">${esc(a.state)}${a.shelved ? ` (shelved until ${esc(fmtTime(a.shelved_until))})` : ""}</td>
          <td class="wrap">${esc(a.message)}</td><td>${esc(fmtTime(a.activated_time))}</td><td>${esc(a.acked_by || "")}</td>
          <td class="actions">
            <button type="button" class="small" data-act="acknowledge">Acknowledge</button>
            <button type="button" class="small" data-act="reset">Reset</button>
            ${
              a.shelved
                ? '<button type="button" class="small" data-act="unshelve">Unshelve</button>'
                : `<select class="small" aria-label="shelve for">${SHELVE_S.map(([l, s]) => `<option value="${s}">${l}</option>`).join("")}</select><button type="button" class="small" data-act="shelve">Shelve</button>`
            }
          </td></tr>`,
        )
        .join("")}</tbody></table>`
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
      ? `<table class="grid" id="alarm-history-table"><thead><tr><th>time</th><th>alarm</th><th>channel</th><th>transition</th><th>state</th><th>message</th><th>by</th></tr></thead><tbody>
        ${rows
          .map(
            (e) => `<tr><td>${esc(fmtTime(e.time))}</td><td>${esc(e.alarm)}</td><td>${esc(e.group || "bench")}</td><td>${esc(e.transition)}</td><td>${esc(e.state)}</td><td class="wrap">${esc(e.message)}</td><td>${esc(e.actor || "")}</td></tr>`,
          )
          .join("")}</tbody></table>`
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
