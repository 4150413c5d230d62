// Diagnostics: devices and their comm health, scan statistics, publisher queues, spool.
// From /api/diagnostics when the supervisor has it; the live tags (scan.*, DEV.*,
// historian.*) stay on screen either way.
import { get } from "../api.js";
import { bindTags, esc, $ } from "../dom.js";
import { fmtSignificant, t } from "../i18n.js";

const isObj = (v) => v && typeof v === "object" && !Array.isArray(v);

/** A {value, description} pair (a tag's value with what it means) or anything else. */
const isTagValue = (v) => isObj(v) && "value" in v;

function fmt(v) {
  if (v === null || v === undefined) return "—";
  if (isTagValue(v)) return fmt(v.value);
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : fmtSignificant(v, 4);
  if (typeof v === "boolean") return v ? t("value.yes") : t("value.no");
  if (Array.isArray(v)) return v.map(fmt).join(", ");
  if (isObj(v)) return Object.entries(v).map(([k, x]) => `${k} ${fmt(x)}`).join(", ");
  return String(v);
}

/** One cell: nested objects as lines "name value" (the description as a tooltip). */
function cell(v) {
  if (isObj(v) && !isTagValue(v) && Object.values(v).some((x) => isObj(x))) {
    return Object.entries(v)
      .map(([k, x]) => `<div class="sub" title="${esc(isTagValue(x) ? x.description || "" : "")}"><span class="muted">${esc(k)}</span> ${esc(fmt(x))}</div>`)
      .join("");
  }
  return esc(fmt(v));
}

function table(id, rows, abnormal = () => false) {
  if (!rows || !rows.length) return `<p class="muted">${esc(t("value.none"))}</p>`;
  const cols = Array.from(new Set(rows.flatMap((r) => Object.keys(r))));
  // (translate="no": the supervisor's own field names, not the screen's words)
  return `<table class="grid" id="${id}" translate="no"><thead><tr>${cols.map((c) => `<th>${esc(c)}</th>`).join("")}</tr></thead><tbody>
    ${rows.map((r) => `<tr class="${abnormal(r) ? "abn" : ""}">${cols.map((c) => `<td>${cell(r[c])}</td>`).join("")}</tr>`).join("")}</tbody></table>`;
}

function kvTable(id, obj) {
  if (!isObj(obj)) return `<p class="muted">${esc(t("value.none"))}</p>`;
  return `<table class="grid kvt" id="${id}" translate="no"><tbody>${Object.entries(obj)
    .map(([k, v]) => `<tr><th>${esc(k)}</th><td>${cell(v)}</td></tr>`)
    .join("")}</tbody></table>`;
}

export async function render({ root, app }) {
  root.dataset.title = t("nav.diagnostics");
  const tx = (key) => esc(t(key));
  const names = Array.from(app.tagNames.size ? app.tagNames : app.live.tags.keys());
  const liveRows = (prefixes) =>
    names
      .filter((n) => prefixes.some((pre) => n.startsWith(pre)))
      .map((n) => `<tr><th>${esc(n)}</th><td data-tag="${esc(n)}"${n.endsWith(".connected") ? ` data-true="${tx("value.yes")}" data-false="${tx("value.NO")}" data-abn="false"` : ""}${/(errors|failures|dropped|overruns|stalls)$/.test(n) ? ' data-abn="nonzero"' : ""}></td></tr>`)
      .join("");
  root.innerHTML = `
    <h1>${tx("nav.diagnostics")}</h1>
    <div class="diag-grid">
      <section class="panel wide"><h2>${tx("diag.devices")}</h2><div id="diag-devices"><p class="muted">…</p></div></section>
      <section class="panel"><h2>${tx("diag.scan")}</h2><div id="diag-scan"></div></section>
      <section class="panel wide"><h2>${tx("diag.publishers")}</h2><div id="diag-publishers"></div></section>
      <section class="panel"><h2>${tx("diag.spool")}</h2><div id="diag-spool"></div></section>
      <section class="panel"><h2>${tx("diag.live")}</h2>
        <table class="grid kvt" id="diag-live" translate="no"><tbody>${liveRows(["scan.", "historian.", "hmi.", "influx.", "opcua.", "retain."])}${app.bench.devices
          .map((d) => liveRows([`${d.name}.connected`, `${d.name}.comm_failures`]))
          .join("")}</tbody></table></section>
    </div>`;
  const refresh = bindTags(root, app.live);
  // An answer that arrives after the operator left the screen has nothing to fill (its
  // elements are gone): dropped, not written into null. Left before the first answer,
  // the screen was never handed to the router (render still awaited it): no destroy
  // came, so the tables' presence is the test.
  let left = false;
  const load = async () => {
    const answer = await get("/api/diagnostics");
    if (left || !$("#diag-devices", root)) return;
    if (!answer.ok) {
      $("#diag-devices", root).innerHTML = `<p class="muted">${esc(answer.data.reason || answer.data.error || t("diag.unavailable", { status: answer.status }))}</p>`;
      return;
    }
    const d = answer.data;
    $("#diag-devices", root).innerHTML = table("diag-devices-table", d.devices, (r) => r.connected === false || (r.quality && r.quality !== "GOOD"));
    $("#diag-scan", root).innerHTML = kvTable("diag-scan-table", d.scan);
    $("#diag-publishers", root).innerHTML = table("diag-publishers-table", d.publishers, (r) => Number(r.dropped) > 0);
    $("#diag-spool", root).innerHTML = isObj(d.spool) ? kvTable("diag-spool-table", d.spool) : table("diag-spool-table", d.spool || []);
  };
  await load();
  const timer = setInterval(load, 2000);
  return {
    update(change) {
      if (change.kind === "tags") refresh(change.names);
    },
    destroy() {
      left = true;
      clearInterval(timer);
    },
  };
}
