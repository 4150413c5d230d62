// Tests: past and running tests, one test's capacity and efficiency per cycle as plots,
// and the download of its result files (BDF CSV, Chadèche CSV, summary).
import { get } from "../api.js";
import { esc, fmtDuration, fmtTime, $ } from "../dom.js";
import { simplePlot, timelinePlot } from "../chart.js";
import { fmtNumber, fmtSignificant, t as tr, tOr, tValue } from "../i18n.js";

const tx = (key, params) => esc(tr(key, params));

const TIMES = new Set(["started", "ended", "start", "end", "updated"]);

const fileUrl = (id, name) => `/api/tests/${encodeURIComponent(id)}/files/${encodeURIComponent(name)}`;

const fmtNum = (v, d = 3) => (typeof v === "number" ? (Math.abs(v) < 0.01 && v !== 0 ? fmtSignificant(v, 3) : fmtNumber(v, d)) : "—");

/** A field of a test's summary as its table shows it: times as dates, numbers in the
 * locale's format, yes/no, a state in the language. */
function fieldValue(k, v) {
  if (TIMES.has(k) && typeof v === "number") return fmtTime(v);
  if (k === "state") return tValue("chain", v);
  if (typeof v === "number" && !Number.isInteger(v)) return fmtNumber(v, 4);
  if (typeof v === "boolean") return v ? tr("value.yes") : tr("value.no");
  return v;
}

function fmtBytes(n) {
  if (typeof n !== "number") return "";
  return n > 1024 * 1024 ? `${fmtNumber(n / 1048576, 1)} ${tr("unit.MB")}` : n > 1024 ? `${fmtNumber(n / 1024, 1)} ${tr("unit.KB")}` : `${n} ${tr("unit.B")}`;
}

export async function render({ root, app, params }) {
  root.dataset.title = tr("nav.tests");
  const id = params[0] ? decodeURIComponent(params[0]) : "";
  root.innerHTML = `<h1>${tx("nav.tests")}</h1>
    <div class="tests-grid">
      <section class="panel" aria-label="${tx("tests.list")}"><div id="test-list"><p class="muted">…</p></div></section>
      ${id ? `<section class="panel" aria-label="${tx("tests.test", { id })}" id="test-detail"><p class="muted">…</p></section>` : ""}
    </div>`;
  const plots = [];
  const listEl = $("#test-list", root);
  let answer = null;
  // ``cell``: every test of that cell (GET /api/tests?cell=ID), else every test.
  const showList = async (cell) => {
    answer = await get(cell ? `/api/tests?cell=${encodeURIComponent(cell)}` : "/api/tests");
    const form = `<form id="cell-form" class="load"><label for="cell-filter">${tx("tests.ofCell")}</label>
      <input id="cell-filter" maxlength="64" value="${esc(cell)}" autocomplete="off" spellcheck="false">
      <button type="submit" id="cell-find">${tx("tests.find")}</button></form>`;
    if (!answer.ok) {
      listEl.innerHTML = `${form}<p class="refused" role="status">${esc(answer.data.reason || answer.data.error || `HTTP ${answer.status}`)}</p>`;
    } else {
      const rows = answer.data.tests || [];
      listEl.innerHTML = form + (rows.length
        ? `<table class="grid" id="test-table"><thead><tr>${["test", "channel", "cell", "recipe", "state", "started", "ended", "end", "files"].map((c) => `<th>${tx(`tests.col.${c}`)}</th>`).join("")}</tr></thead><tbody>
        ${rows
          .map(
            (t) => `<tr class="${t.state === "running" ? "running" : ""}${t.id === id ? " selected" : ""}">
            <td><a href="#/tests/${encodeURIComponent(t.id)}">${esc(t.id)}</a></td><td>${esc(t.channel)}</td><td>${esc(t.metadata?.cell_id || "")}</td><td>${esc(t.recipe)}</td>
            <td>${esc(tValue("chain", t.state))}</td><td>${esc(typeof t.started === "number" ? fmtTime(t.started) : t.started || "")}</td>
            <td>${esc(typeof t.ended === "number" ? fmtTime(t.ended) : t.ended || "")}</td><td>${esc(t.end_reason || "")}</td>
            <td>${(t.files || []).map((f) => `<a href="${fileUrl(t.id, f.name)}" download="${esc(f.name)}" class="dl">${esc(f.name)}</a>`).join(" ")}</td></tr>`,
          )
          .join("")}</tbody></table>`
        : `<p class="muted">${cell ? tx("tests.noneOfCell", { cell }) : tx("tests.none")}</p>`);
    }
    $("#cell-form", listEl).addEventListener("submit", (ev) => {
      ev.preventDefault();
      showList($("#cell-filter", listEl).value.trim());
    });
  };
  await showList("");
  if (id) {
    const d = await get(`/api/tests/${encodeURIComponent(id)}`);
    const el = $("#test-detail", root);
    if (!d.ok) {
      el.innerHTML = `<p class="refused">${esc(d.data.reason || d.data.error || `HTTP ${d.status}`)}</p>`;
    } else {
      const t = d.data;
      const cycles = t.cycles || [];
      const files = t.files || (answer.data?.tests || []).find((x) => x.id === id)?.files || [];
      const skip = new Set(["cycles", "files", "timeline", "events"]);
      el.innerHTML = `<h2>${esc(id)}</h2>
        <table class="grid kvt"><tbody>${Object.entries(t)
          .filter(([k, v]) => !skip.has(k) && (typeof v !== "object" || v === null))
          .map(([k, v]) => `<tr><th>${esc(tOr(`tests.field.${k}`, k))}</th><td>${esc(fieldValue(k, v))}</td></tr>`)
          .join("")}</tbody></table>
        ${
          t.metadata && Object.values(t.metadata).some((v) => v !== "" && v !== null)
            ? `<h3>${tx("tests.cellAndOperator")}</h3><table class="grid kvt" id="test-metadata"><tbody>${Object.entries(t.metadata)
                .map(([k, v]) => `<tr><th>${esc(tOr(`tests.field.${k}`, k))}</th><td class="wrap">${esc(v ?? "")}</td></tr>`)
                .join("")}</tbody></table>`
            : ""
        }
        <h3>${tx("tests.files")}</h3><ul class="links" id="test-files">${files
          .map((f) => `<li><a href="${fileUrl(id, f.name)}" download="${esc(f.name)}" class="dl">${esc(f.name)}</a> <small class="muted">${esc(f.kind || "")} ${fmtBytes(f.bytes)}</small></li>`)
          .join("")}</ul>
        <h3>${tx("tests.timeline")}</h3><div id="test-timeline" class="plot"></div>
        ${
          (t.timeline || []).length
            ? `<details><summary>${tx("tests.events", { n: t.timeline.length, count: t.timeline.length })}</summary><table class="grid" id="test-events"><thead><tr>${["time", "cycle", "step", "event"].map((c) => `<th>${tx(`tests.col.${c}`)}</th>`).join("")}</tr></thead><tbody>${t.timeline
                .map((e) => `<tr><td>${esc(fmtDuration(e.t_s))}</td><td>${esc(e.cycle ?? "")}</td><td>${esc(e.step ?? "")}</td><td class="wrap">${esc(e.text ?? e.kind ?? "")}</td></tr>`)
                .join("")}</tbody></table></details>`
            : ""
        }
        <h3>${tx("tests.perCycle")}</h3>
        ${
          cycles.length
            ? `<table class="grid"><thead><tr><th>${tx("tests.col.cycle")}</th><th>${tx("quantity.charge")} Ah</th><th>${tx("quantity.discharge")} Ah</th><th>${tx("tests.col.efficiency")}</th></tr></thead><tbody>${cycles
                .map((c) => `<tr><td>${esc(c.cycle)}</td><td>${fmtNum(c.charge_ah)}</td><td>${fmtNum(c.discharge_ah)}</td><td>${typeof c.efficiency === "number" ? `${fmtNumber(c.efficiency * 100, 1)} %` : "—"}</td></tr>`)
                .join("")}</tbody></table>
          <div id="test-capacity" class="plot"></div><div id="test-efficiency" class="plot"></div>`
            : `<p class="muted">${tx("tests.noCycle")}</p>`
        }`;
      const timeline = timelinePlot($("#test-timeline", el), t.timeline, t.duration_s);
      if (timeline) plots.push(timeline);
      if (cycles.length) {
        const x = cycles.map((c) => c.cycle);
        const big = cycles.some((c) => Math.abs(c.charge_ah || 0) >= 1 || Math.abs(c.discharge_ah || 0) >= 1);
        const k = big ? 1 : 1000;
        const unit = big ? "Ah" : "mAh";
        const scaled = (v) => (typeof v === "number" ? v * k : null);
        plots.push(
          simplePlot($("#test-capacity", el), {
            title: tr("tests.capacityPerCycle", { unit }),
            xLabel: tr("plot.cycle"),
            yLabel: unit,
            series: [{ label: `${tr("quantity.charge")} ${unit}` }, { label: `${tr("quantity.discharge")} ${unit}` }],
            x,
            ys: [cycles.map((c) => scaled(c.charge_ah)), cycles.map((c) => scaled(c.discharge_ah))],
            bars: true,
          }),
          simplePlot($("#test-efficiency", el), {
            title: tr("tests.efficiencyPerCycle"),
            xLabel: tr("plot.cycle"),
            yLabel: "%",
            series: [{ label: `${tr("tests.col.efficiency")} %` }],
            integerX: true,
            x,
            ys: [cycles.map((c) => (typeof c.efficiency === "number" ? c.efficiency * 100 : null))],
          }),
        );
      }
    }
  }
  return {
    destroy() {
      for (const p of plots) {
        p.stop();
        p.chart.destroy();
      }
    },
  };
}
