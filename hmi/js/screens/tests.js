// Tests: past and running tests, one test's capacity and efficiency per cycle as plots,
// and the download of its result files (BDF CSV, Chadèche CSV, summary).
import { get } from "../api.js";
import { esc, fmtDuration, fmtTime, $ } from "../dom.js";
import { simplePlot, timelinePlot } from "../chart.js";

const TIMES = new Set(["started", "ended", "start", "end", "updated"]);

const fileUrl = (id, name) => `/api/tests/${encodeURIComponent(id)}/files/${encodeURIComponent(name)}`;

const fmtNum = (v, d = 3) => (typeof v === "number" ? (Math.abs(v) < 0.01 && v !== 0 ? v.toPrecision(3) : v.toFixed(d)) : "—");

function fmtBytes(n) {
  if (typeof n !== "number") return "";
  return n > 1024 * 1024 ? `${(n / 1048576).toFixed(1)} MB` : n > 1024 ? `${(n / 1024).toFixed(1)} KB` : `${n} B`;
}

export async function render({ root, app, params }) {
  root.dataset.title = "Tests";
  const id = params[0] ? decodeURIComponent(params[0]) : "";
  root.innerHTML = `<h1>Tests</h1>
    <div class="tests-grid">
      <section class="panel" aria-label="Test list"><div id="test-list"><p class="muted">…</p></div></section>
      ${id ? `<section class="panel" aria-label="Test ${esc(id)}" id="test-detail"><p class="muted">…</p></section>` : ""}
    </div>`;
  const plots = [];
  const listEl = $("#test-list", root);
  let answer = null;
  // ``cell``: every test of that cell (GET /api/tests?cell=ID), else every test.
  const showList = async (cell) => {
    answer = await get(cell ? `/api/tests?cell=${encodeURIComponent(cell)}` : "/api/tests");
    const form = `<form id="cell-form" class="load"><label for="cell-filter">Tests of cell</label>
      <input id="cell-filter" maxlength="64" value="${esc(cell)}" autocomplete="off" spellcheck="false">
      <button type="submit" id="cell-find">Find</button></form>`;
    if (!answer.ok) {
      listEl.innerHTML = `${form}<p class="refused" role="status">${esc(answer.data.reason || answer.data.error || `HTTP ${answer.status}`)}</p>`;
    } else {
      const rows = answer.data.tests || [];
      listEl.innerHTML = form + (rows.length
        ? `<table class="grid" id="test-table"><thead><tr><th>test</th><th>channel</th><th>cell</th><th>recipe</th><th>state</th><th>started</th><th>ended</th><th>end</th><th>files</th></tr></thead><tbody>
        ${rows
          .map(
            (t) => `<tr class="${t.state === "running" ? "running" : ""}${t.id === id ? " selected" : ""}">
            <td><a href="#/tests/${encodeURIComponent(t.id)}">${esc(t.id)}</a></td><td>${esc(t.channel)}</td><td>${esc(t.metadata?.cell_id || "")}</td><td>${esc(t.recipe)}</td>
            <td>${esc(t.state)}</td><td>${esc(typeof t.started === "number" ? fmtTime(t.started) : t.started || "")}</td>
            <td>${esc(typeof t.ended === "number" ? fmtTime(t.ended) : t.ended || "")}</td><td>${esc(t.end_reason || "")}</td>
            <td>${(t.files || []).map((f) => `<a href="${fileUrl(t.id, f.name)}" download="${esc(f.name)}" class="dl">${esc(f.name)}</a>`).join(" ")}</td></tr>`,
          )
          .join("")}</tbody></table>`
        : `<p class="muted">${cell ? `No test of cell ${esc(cell)}.` : "No tests yet."}</p>`);
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
          .map(([k, v]) => `<tr><th>${esc(k)}</th><td>${esc(TIMES.has(k) && typeof v === "number" ? fmtTime(v) : typeof v === "number" && !Number.isInteger(v) ? v.toFixed(4) : v)}</td></tr>`)
          .join("")}</tbody></table>
        ${
          t.metadata && Object.values(t.metadata).some((v) => v !== "" && v !== null)
            ? `<h3>Cell and operator</h3><table class="grid kvt" id="test-metadata"><tbody>${Object.entries(t.metadata)
                .map(([k, v]) => `<tr><th>${esc(k)}</th><td class="wrap">${esc(v ?? "")}</td></tr>`)
                .join("")}</tbody></table>`
            : ""
        }
        <h3>Files</h3><ul class="links" id="test-files">${files
          .map((f) => `<li><a href="${fileUrl(id, f.name)}" download="${esc(f.name)}" class="dl">${esc(f.name)}</a> <small class="muted">${esc(f.kind || "")} ${fmtBytes(f.bytes)}</small></li>`)
          .join("")}</ul>
        <h3>Timeline</h3><div id="test-timeline" class="plot"></div>
        ${
          (t.timeline || []).length
            ? `<details><summary>${t.timeline.length} events</summary><table class="grid" id="test-events"><thead><tr><th>time</th><th>cycle</th><th>step</th><th>event</th></tr></thead><tbody>${t.timeline
                .map((e) => `<tr><td>${esc(fmtDuration(e.t_s))}</td><td>${esc(e.cycle ?? "")}</td><td>${esc(e.step ?? "")}</td><td class="wrap">${esc(e.text ?? e.kind ?? "")}</td></tr>`)
                .join("")}</tbody></table></details>`
            : ""
        }
        <h3>Per cycle</h3>
        ${
          cycles.length
            ? `<table class="grid"><thead><tr><th>cycle</th><th>charge Ah</th><th>discharge Ah</th><th>efficiency</th></tr></thead><tbody>${cycles
                .map((c) => `<tr><td>${esc(c.cycle)}</td><td>${fmtNum(c.charge_ah)}</td><td>${fmtNum(c.discharge_ah)}</td><td>${typeof c.efficiency === "number" ? (c.efficiency * 100).toFixed(1) + " %" : "—"}</td></tr>`)
                .join("")}</tbody></table>
          <div id="test-capacity" class="plot"></div><div id="test-efficiency" class="plot"></div>`
            : '<p class="muted">No complete cycle.</p>'
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
            title: `Capacity per cycle (${unit})`,
            xLabel: "cycle",
            yLabel: unit,
            series: [{ label: `charge ${unit}` }, { label: `discharge ${unit}` }],
            x,
            ys: [cycles.map((c) => scaled(c.charge_ah)), cycles.map((c) => scaled(c.discharge_ah))],
            bars: true,
          }),
          simplePlot($("#test-efficiency", el), {
            title: "Coulombic efficiency per cycle (%)",
            xLabel: "cycle",
            yLabel: "%",
            series: [{ label: "efficiency %" }],
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
