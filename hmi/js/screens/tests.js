// Tests: past and running tests, one test's capacity and efficiency per cycle as plots,
// and the download of its result files (BDF CSV, Chadèche CSV, summary). Tests compared
// (issue 33 finding 10): V against Ah per half-cycle of one test's cycles, or of one cycle
// of the tests ticked in the list ("Compare"), and the capacity fade of a cell across its
// tests (GET /api/tests/{id}/curves, GET /api/fade).
import { get } from "../api.js";
import { esc, fmtDuration, fmtTime, $ } from "../dom.js";
import { simplePlot, timelinePlot, xyPlot } from "../chart.js";
import { fmtNumber, fmtSignificant, t as tr, tOr, tValue } from "../i18n.js";

const tx = (key, params) => esc(tr(key, params));

const TIMES = new Set(["started", "ended", "start", "end", "updated"]);

const fileUrl = (id, name) => `/api/tests/${encodeURIComponent(id)}/files/${encodeURIComponent(name)}`;

const fmtNum = (v, d = 3) => (typeof v === "number" ? (Math.abs(v) < 0.01 && v !== 0 ? fmtSignificant(v, 3) : fmtNumber(v, d)) : "—");

// --- tests compared -------------------------------------------------------------------------

/** Ah, or mAh for a small cell (a NiMH AA's 5 mAh cycle reads 5, not 0.005). */
function chargeUnit(values) {
  return values.some((v) => Math.abs(v) >= 1) ? { unit: "Ah", k: 1 } : { unit: "mAh", k: 1000 };
}

const halfName = (c) => `${tValue("quantity", c.half)}${c.index > 1 ? ` ${c.index}` : ""}`;

/**
 * V against Ah of curves ({label, pen, curve}: the API's {ah, v}), each half counted from
 * its start, on one chart in `el`; null (and a note) when there is none.
 */
function curvesPlot(el, title, items) {
  const drawn = items.filter((it) => it.curve.ah.length);
  if (!drawn.length) {
    el.innerHTML = `<p class="muted">${tx("compare.noCurve")}</p>`;
    return null;
  }
  const { unit, k } = chargeUnit(drawn.flatMap((it) => it.curve.ah));
  return xyPlot(el, {
    title,
    xLabel: tr("compare.chargeSinceHalf", { unit }),
    yLabel: tr("compare.voltageV"),
    curves: drawn.map((it) => ({ label: it.label, pen: it.pen, x: it.curve.ah.map((a) => a * k), y: it.curve.v, width: it.curve.half === "charge" ? 2 : 1.5 })),
  });
}

/** The discharge capacity per cycle of every test of `cell` (oldest first), in `el`. */
async function fadePlot(el, cell) {
  const r = await get(`/api/fade?cell=${encodeURIComponent(cell)}`);
  if (!r.ok) {
    el.innerHTML = `<p class="muted">${esc(r.data.reason || r.data.error || `HTTP ${r.status}`)}</p>`;
    return null;
  }
  const tests = r.data.tests.filter((t) => t.cumulative_cycle.length);
  if (!tests.length) {
    el.innerHTML = `<p class="muted">${tx("compare.noFinishedCycle", { cell })}</p>`;
    return null;
  }
  const { unit, k } = chargeUnit(tests.flatMap((t) => t.discharge_ah));
  // x: the cell's cumulative cycle (its earlier tests' cycles first): fade follows the
  // cycles a cell went through, not the calendar (ADR 0044); each test's date is in its label.
  return xyPlot(el, {
    title: tr("compare.fadeOfCell", { cell }),
    xLabel: tr("compare.cumulativeCycle"),
    yLabel: tr("compare.dischargeCapacity", { unit }),
    integerX: true,
    points: true,
    curves: tests.map((t, i) => ({
      label: `${t.id}${typeof t.started === "number" ? ` (${fmtTime(t.started)})` : ""}`,
      pen: i,
      x: t.cumulative_cycle,
      y: t.discharge_ah.map((a) => a * k),
    })),
  });
}

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
      <section class="panel" aria-label="${tx("compare.label")}" id="test-compare" hidden></section>
      ${id ? `<section class="panel" aria-label="${tx("tests.test", { id })}" id="test-detail"><p class="muted">…</p></section>` : ""}
    </div>`;
  const plots = [];
  const listPlots = []; // the list's fade chart, redrawn with the list
  const comparePlots = [];
  const keep = (arr, p) => p && arr.push(p);
  const drop = (arr) => arr.splice(0).forEach((p) => (p.stop(), p.chart.destroy()));
  const picked = new Set(); // the tests ticked for comparison
  let compareCycle = 1;
  const compareEl = $("#test-compare", root);
  // One cycle of each test ticked, its halves overlaid (a curve per test's half).
  const compare = async (cycle) => {
    drop(comparePlots);
    compareEl.hidden = false;
    if (!Number.isInteger(cycle) || cycle < 1) {
      compareEl.innerHTML = `<p class="refused" role="status">${tx("compare.needCycle")}</p>`;
      return;
    }
    compareCycle = cycle;
    const ids = [...picked];
    if (!ids.length) {
      compareEl.innerHTML = `<p class="refused" role="status">${tx("compare.needTests")}</p>`;
      return;
    }
    const answers = await Promise.all(ids.map((t) => get(`/api/tests/${encodeURIComponent(t)}/curves?cycles=${cycle}`)));
    const notes = [];
    const items = [];
    answers.forEach((r, i) => {
      if (!r.ok) notes.push(`${ids[i]}: ${r.data.reason || r.data.error || `HTTP ${r.status}`}`);
      else if (!r.data.curves.length) notes.push(tr("compare.noCycle", { id: ids[i], cycle }));
      for (const c of r.ok ? r.data.curves : []) items.push({ label: `${ids[i]} ${tr("compare.cycleN", { cycle })} ${halfName(c)}`, pen: i, curve: c });
    });
    compareEl.innerHTML = `<h2>${tx("compare.title", { cycle, n: ids.length, count: ids.length })}</h2>
      ${notes.length ? `<p class="muted" role="status">${notes.map(esc).join("; ")}</p>` : ""}
      <div id="compare-curves" class="plot"></div>`;
    keep(comparePlots, curvesPlot($("#compare-curves", compareEl), tr("compare.vsChargeCycle", { cycle }), items));
  };
  const listEl = $("#test-list", root);
  let answer = null;
  // ``cell``: every test of that cell (GET /api/tests?cell=ID), else every test.
  const showList = async (cell) => {
    drop(listPlots);
    answer = await get(cell ? `/api/tests?cell=${encodeURIComponent(cell)}` : "/api/tests");
    const form = `<form id="cell-form" class="load"><label for="cell-filter">${tx("tests.ofCell")}</label>
      <input id="cell-filter" maxlength="64" value="${esc(cell)}" autocomplete="off" spellcheck="false">
      <button type="submit" id="cell-find">${tx("tests.find")}</button></form>`;
    if (!answer.ok) {
      listEl.innerHTML = `${form}<p class="refused" role="status">${esc(answer.data.reason || answer.data.error || `HTTP ${answer.status}`)}</p>`;
    } else {
      const rows = answer.data.tests || [];
      listEl.innerHTML = form + (rows.length
        ? `<table class="grid" id="test-table"><thead><tr>${["compare", "test", "channel", "cell", "recipe", "state", "started", "ended", "end"].map((c) => `<th>${tx(`tests.col.${c}`)}</th>`).join("")}<th class="files">${tx("tests.col.files")}</th></tr></thead><tbody>
        ${rows
          .map(
            (t) => `<tr class="${t.state === "running" ? "running" : ""}${t.id === id ? " selected" : ""}">
            <td><input type="checkbox" class="compare-pick" value="${esc(t.id)}" aria-label="${tx("compare.pick", { id: t.id })}"${picked.has(t.id) ? " checked" : ""}></td>
            <td><a href="#/tests/${encodeURIComponent(t.id)}">${esc(t.id)}</a></td><td>${esc(t.channel)}</td><td>${esc(t.metadata?.cell_id || "")}</td><td>${esc(t.recipe)}</td>
            <td>${esc(tValue("chain", t.state))}</td><td>${esc(typeof t.started === "number" ? fmtTime(t.started) : t.started || "")}</td>
            <td>${esc(typeof t.ended === "number" ? fmtTime(t.ended) : t.ended || "")}</td><td>${esc(t.end_reason || "")}</td>
            <td class="files">${(t.files || []).map((f) => `<a href="${fileUrl(t.id, f.name)}" download="${esc(f.name)}" class="dl">${esc(f.name)}</a>`).join(" ")}</td></tr>`,
          )
          .join("")}</tbody></table>
        <form id="compare-form" class="load"><label for="compare-cycle">${tx("compare.cycle")}</label>
        <input id="compare-cycle" type="number" min="1" step="1" value="${esc(compareCycle)}">
        <button type="submit" id="compare-go">${tx("compare.go")}</button>
        <span class="muted">${tx("compare.hint")}</span></form>
        ${cell ? '<div id="cell-fade" class="plot"></div>' : ""}`
        : `<p class="muted">${cell ? tx("tests.noneOfCell", { cell }) : tx("tests.none")}</p>`);
      for (const box of listEl.querySelectorAll(".compare-pick")) {
        box.addEventListener("change", () => (box.checked ? picked.add(box.value) : picked.delete(box.value)));
      }
      $("#compare-form", listEl)?.addEventListener("submit", (ev) => {
        ev.preventDefault();
        compare(Number($("#compare-cycle", listEl).value));
      });
      if (cell && rows.length) keep(listPlots, await fadePlot($("#cell-fade", listEl), cell));
    }
    $("#cell-form", listEl).addEventListener("submit", (ev) => {
      ev.preventDefault();
      showList($("#cell-filter", listEl).value.trim());
    });
  };
  // The detail's V against Ah (its cycles spread over the test) and its cell's fade.
  let detailCell = ""; // the cell of the test shown, if its metadata name one
  const detailCurves = async (testId) => {
    const el = $("#test-curves", root);
    if (!el) return;
    const r = await get(`/api/tests/${encodeURIComponent(testId)}/curves`);
    if (!r.ok) {
      el.innerHTML = `<p class="muted">${esc(r.data.reason || r.data.error || `HTTP ${r.status}`)}</p>`;
    } else {
      const chosen = r.data.cycles;
      const items = r.data.curves.map((c) => ({ label: `${tr("compare.cycleN", { cycle: c.cycle })} ${halfName(c)}`, pen: chosen.indexOf(c.cycle), curve: c }));
      const shown = chosen.length < r.data.cycles_total ? ` ${tr("compare.shownOf", { n: chosen.length, total: r.data.cycles_total })}` : "";
      keep(plots, curvesPlot(el, `${tr("compare.vsChargePerCycle")}${shown}`, items));
    }
    const fadeEl = $("#test-fade", root);
    if (fadeEl && detailCell) keep(plots, await fadePlot(fadeEl, detailCell));
  };
  await showList("");
  if (id) {
    const d = await get(`/api/tests/${encodeURIComponent(id)}`);
    const el = $("#test-detail", root);
    if (!d.ok) {
      el.innerHTML = `<p class="refused">${esc(d.data.reason || d.data.error || `HTTP ${d.status}`)}</p>`;
    } else {
      const t = d.data;
      detailCell = t.metadata?.cell_id || "";
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
        }
        <h3>${tx("compare.vsChargePerCycle")}</h3><div id="test-curves" class="plot"></div>
        ${t.metadata?.cell_id ? `<h3>${tx("compare.fadeOfCell", { cell: t.metadata.cell_id })}</h3><div id="test-fade" class="plot"></div>` : ""}`;
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
  if (id) await detailCurves(id);
  return {
    destroy() {
      drop(plots);
      drop(listPlots);
      drop(comparePlots);
    },
  };
}
