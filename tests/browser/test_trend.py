"""Issue 33, finding 1 (the trend draws ramps that never happened): in Debian's Chromium, the
channel screen's trend draws a tag's value held until its next change (the historian stores
changes only), its pens in distinct colours and dashes with a legend, each scale with its
own axis and a band of its own (ch4's 15 V and 25 °C no longer lie on top of each other),
pens the operator picks, and the whole trend visible without scrolling at 1366×768.

What is drawn is read from the chart's canvas (the pixels of a pen's colour), not from the
chart's own bookkeeping."""

from __future__ import annotations

import itertools
import json
import statistics
import time
from typing import Any

from browserrig import SCREENS, VIEWPORT, Supervisor, login, screenshot, wait_for

ALARM_RED = "rgb(200, 16, 46)"  # --alarm of hmi.css: never a pen's colour

# The canvas rows (CSS px from the canvas's top) where a colour is drawn, in the columns
# [x0, x1) (CSS px): each pixel within `tol` of the colour (anti-aliasing blends edges).
PIXELS_JS = """
([sel, rgb, x0, x1, tol]) => {
  const canvas = document.querySelector(sel + ' canvas');
  const k = canvas.width / canvas.getBoundingClientRect().width;
  const ctx = canvas.getContext('2d');
  const [r, g, b] = rgb.match(/\\d+/g).map(Number);
  const ys = [];
  const left = Math.round(x0 * k), w = Math.max(1, Math.round((x1 - x0) * k));
  const img = ctx.getImageData(left, 0, w, canvas.height).data;
  for (let y = 0; y < canvas.height; y++)
    for (let x = 0; x < w; x++) {
      const i = (y * w + x) * 4;
      const d = Math.hypot(img[i] - r, img[i + 1] - g, img[i + 2] - b);
      if (d <= tol) { ys.push(y / k); break; }
    }
  return ys;
}
"""

# The four samples of ch0.current in a trend of the screen's own module: 0 from
# 15:14:18, -0.2 from 15:15:18 (60 s later), drawn on a chart 800 px wide.
STEP_JS = """
async () => {
  const { trendChart, holdJoin } = await import('/static/js/chart.js');
  const el = document.createElement('div');
  el.id = 'step-probe';
  el.style.width = '800px';
  document.body.prepend(el);
  const t0 = Date.UTC(2026, 11, 5, 15, 14, 18) / 1000;
  const pens = [{ label: 'current A', scale: 'A', unit: 'A' }];
  const { chart } = trendChart(el, { pens, height: 300 });
  chart.setData(holdJoin([{ before: null, t: [t0, t0 + 60], v: [0, -0.2] }], t0, t0 + 70), false);
  chart.setScale('x', { min: t0 - 10, max: t0 + 70 });
  await new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)));
  const over = el.querySelector('.u-over').getBoundingClientRect();
  const box = el.querySelector('canvas').getBoundingClientRect();
  const at = (v, s) =>
    chart.valToPos(v, s) + (s === 'x' ? over.left - box.left : over.top - box.top);
  return {
    mid: at(t0 + 30, 'x'), held: at(0, 'A'), ramp: at(-0.1, 'A'), after: at(-0.2, 'A'),
    late: at(t0 + 65, 'x'),
    colour: getComputedStyle(el.querySelector('.u-series:nth-child(2) .u-marker')).borderColor,
  };
}
"""


def rows_of(page: Any, sel: str, colour: str, x0: float, x1: float) -> list[float]:
    return list(page.evaluate(PIXELS_JS, [sel, colour, x0, x1, 60]))


def pen_colours(page: Any) -> dict[str, str]:
    """The legend's pens: label → its marker's colour."""
    return dict(
        page.eval_on_selector_all(
            "#trend .u-legend .u-series",
            "rows => rows.slice(1).map(r => [r.querySelector('.u-label').textContent,"
            " getComputedStyle(r.querySelector('.u-marker')).borderColor])",
        )
    )


def plot_box(page: Any) -> dict[str, float]:
    """The plot area (uPlot's .u-over) in CSS px from the canvas's top left."""
    return dict(
        page.evaluate(
            "() => { const o = document.querySelector('#trend .u-over').getBoundingClientRect();"
            " const c = document.querySelector('#trend canvas').getBoundingClientRect();"
            " return {left: o.left - c.left, right: o.right - c.left,"
            " top: o.top - c.top, bottom: o.bottom - c.top}; }"
        )
    )


def open_channel(page: Any, bench: Supervisor, name: str) -> None:
    login(page, bench, "operator", f"#/channel/{name}")
    wait_for_trend(page)


def wait_for_trend(page: Any) -> None:
    page.wait_for_selector("#trend .u-legend")
    page.wait_for_function(
        "() => (document.querySelector('#trend').dataset.valued || '').startsWith('voltage')"
    )
    page.wait_for_timeout(600)  # a redraw of the chart (every 0.5 s) after the values came


def test_a_value_is_held_until_its_next_change_drawn_as_a_step_not_a_ramp(
    as_operator: Any,
) -> None:
    page = as_operator
    probe = page.evaluate(STEP_JS)
    # Half way through the 60 s rest the current is still 0 (its last sample), not -0.1.
    ys = rows_of(page, "#step-probe", probe["colour"], probe["mid"] - 15, probe["mid"] + 15)
    assert ys, "the pen is not drawn half way between the two samples"
    assert all(abs(y - probe["held"]) <= 3 for y in ys), (ys, probe)
    assert not any(abs(y - probe["ramp"]) <= 3 for y in ys)
    # After the change, -0.2 holds.
    ys = rows_of(page, "#step-probe", probe["colour"], probe["late"] - 4, probe["late"] + 4)
    assert ys and all(abs(y - probe["after"]) <= 3 for y in ys), (ys, probe)


def to_canvas(page: Any, t: float, value: float, scale: str) -> tuple[float, float]:
    """A time and a value of `scale` as CSS px on the trend's canvas, by the ranges drawn."""
    scales = json.loads(str(page.get_attribute("#trend", "data-scales")))
    box = plot_box(page)
    (x0, x1), (y0, y1) = scales["x"], scales[scale]
    x = box["left"] + (t - x0) / (x1 - x0) * (box["right"] - box["left"])
    y = box["bottom"] - (value - y0) / (y1 - y0) * (box["bottom"] - box["top"])
    return x, y


def test_the_channel_s_trend_holds_each_stored_value_until_the_next_change(
    page: Any, bench: Supervisor
) -> None:
    """The issue's case on the bench: ch1 in manual at -0.2 A for a while, then at 0 A; the
    historian keeps the changes only, and the trend loaded from it draws -0.2 A held until
    the next change, never a ramp between the two."""
    start = time.time()
    try:
        for tag, value in (("ch1.manual_current", -0.2), ("ch1.enable", True)):
            status, body = bench.call("PUT", f"/api/tags/{tag}", {"value": value})
            assert status == 200, body
        wait_for("ch1 discharging", lambda: bench.tag("ch1.current") < -0.15)
        time.sleep(12)  # a rest between two changes that the historian does not sample
    finally:
        bench.call("PUT", "/api/tags/ch1.enable", {"value": False})
        bench.call("PUT", "/api/tags/ch1.manual_current", {"value": 0.0})
    wait_for("ch1 at rest", lambda: abs(bench.tag("ch1.current")) < 0.01)

    def stored() -> list[dict[str, Any]]:
        status, body = bench.call("GET", f"/api/history?tag=ch1.current&start={start - 5}")
        assert status == 200, body
        found = [s for s in body["samples"] if s["value"] is not None]
        # Stored once the return to rest is (the historian writes in batches).
        back = any(s["value"] < -0.15 for s in found) and abs(found[-1]["value"]) < 0.01
        return found if back else []

    samples = wait_for("the historian to store the return to rest", stored, timeout_s=30)
    # The longest wait between two stored changes at least 0.1 A apart.
    pairs = [(a, b) for a, b in itertools.pairwise(samples) if abs(b["value"] - a["value"]) >= 0.1]
    assert pairs, samples
    a, b = max(pairs, key=lambda p: p[1]["t"] - p[0]["t"])
    open_channel(page, bench, "ch1")
    colour = pen_colours(page)["current A"]
    mid_t = (a["t"] + b["t"]) / 2
    x, held = to_canvas(page, mid_t, a["value"], "A")
    # Wide enough on the canvas to look between the two changes (12 s asked; a loaded
    # machine may see the channel stopped sooner by its own protection: any span that
    # holds the probe below will do, the time it lasted is not what is tested).
    xa, _ = to_canvas(page, a["t"], a["value"], "A")
    xb, _ = to_canvas(page, b["t"], b["value"], "A")
    assert xb - xa > 24, ([(round(s["t"] - start, 2), s["value"]) for s in samples], xa, xb)
    _, ramp = to_canvas(page, mid_t, (a["value"] + b["value"]) / 2, "A")
    assert abs(held - ramp) > 10, (held, ramp)  # far enough apart to tell
    ys = rows_of(page, "#trend", colour, x - 6, x + 6)
    assert ys, "the current is not drawn between the two changes"
    assert all(abs(y - held) <= 3 for y in ys), (ys, held, ramp)


def test_pens_joined_from_changes_hold_their_values_at_each_other_s_times(
    as_operator: Any,
) -> None:
    page = as_operator
    joined = page.evaluate(
        """async () => {
          const { holdJoin } = await import('/static/js/chart.js');
          return holdJoin([
            { before: { t: 90, value: 3.2 }, t: [110, 130], v: [3.3, null] },
            { before: null, t: [105, 120], v: [0, -0.2] },
          ], 100, 140);
        }"""
    )
    # Times of both pens; each holds its last value; null before its first sample (nothing
    # known) and from a BAD sample on (a gap, never a value made up).
    # The last values hold until the end of the range asked (no change came before it).
    assert joined == [
        [100, 105, 110, 120, 130, 140],
        [3.2, 3.2, 3.3, 3.3, None, None],
        [None, 0, 0, -0.2, -0.2, -0.2],
    ]


def test_every_scale_s_data_lies_in_a_band_of_its_own_with_its_ticks(as_operator: Any) -> None:
    """For every number of scales shown (1 to 6) and every place, with data flat or not,
    negative, small or large: the data (its range) fills a band of its own, the bands do
    not overlap, and the ticks lie in the band."""
    page = as_operator
    bands = page.evaluate(
        """async () => {
          const { bandRange, bandSplits } = await import('/static/js/chart.js');
          const data = [
            [15, 15], [-0.2, 0], [24.9, 25.3], [3.778, 3.782], [-300, 300], [1e-4, 3e-4], [0, 0],
          ];
          const out = [];
          for (let count = 1; count <= 6; count++)
            for (let index = 0; index < count; index++)
              for (const [lo, hi] of data) {
                const [min, max] = bandRange(index, count, lo, hi);
                const frac = (v) => (v - min) / (max - min);  // 0 at the plot's bottom
                const ticks = bandSplits(index, count, min, max, 240);
                out.push({ count, index, lo: frac(lo), hi: frac(hi), ticks: ticks.map(frac) });
              }
          return out;
        }"""
    )
    for b in bands:
        count, index = b["count"], b["index"]
        bottom, top = (count - 1 - index) / count, (count - index) / count
        assert bottom < b["lo"] <= b["hi"] < top, b
        assert len(b["ticks"]) >= 1, b
        assert all(bottom <= t <= top for t in b["ticks"]), b


def test_ch4_s_pens_are_distinct_with_a_legend_and_voltage_and_temperature_apart(
    page: Any, bench: Supervisor
) -> None:
    open_channel(page, bench, "ch4")
    colours = pen_colours(page)
    assert list(colours) == [
        "voltage V",
        "current A",
        "temperature °C",
        "cell min V",
        "cell max V",
    ]
    assert len(set(colours.values())) == len(colours), colours
    assert ALARM_RED not in colours.values()
    # 15 V and 25 °C: each in its own band, far apart on the canvas (they coincided on
    # 0–30 and 0–50), read at the right end of the plot where the live values are.
    box = plot_box(page)
    rows = {
        pen: rows_of(page, "#trend", colours[pen], box["right"] - 200, box["right"] - 2)
        for pen in ("voltage V", "temperature °C")
    }
    assert all(rows.values()), rows
    v_y = statistics.median(rows["voltage V"])
    t_y = statistics.median(rows["temperature °C"])
    assert abs(v_y - t_y) > 30, (v_y, t_y)
    assert all(box["top"] <= y <= box["bottom"] for y in (v_y, t_y))
    screenshot(page, "channel-ch4-trend-pens")


def test_an_operator_picks_the_pens_and_the_choice_stays(page: Any, bench: Supervisor) -> None:
    open_channel(page, bench, "ch0")
    colours = pen_colours(page)
    box = plot_box(page)
    current = colours["current A"]
    assert rows_of(page, "#trend", current, box["left"] + 2, box["right"] - 2)
    page.get_by_role("checkbox", name="current A").uncheck()
    page.wait_for_timeout(300)
    classes = page.eval_on_selector_all(
        "#trend .u-legend .u-series", "rows => rows.map(r => r.className)"
    )
    assert "u-off" in classes[2] and "u-off" not in classes[1], classes
    assert not rows_of(page, "#trend", current, box["left"] + 2, box["right"] - 2)
    # The legend picks too (a click on a pen's name), and the boxes follow it.
    page.click("#trend .u-legend .u-series:nth-child(2) .u-label")
    assert not page.is_checked("#trend-pens input[data-pen='voltage V']")
    assert not rows_of(page, "#trend", colours["voltage V"], box["left"] + 2, box["right"] - 2)
    # Back on the channel later: the same pens hidden.
    page.goto(f"{bench.base}/#/channel/ch1")
    wait_for_trend(page)
    page.goto("about:blank")  # a full load: the screen made again
    page.goto(f"{bench.base}/#/channel/ch0")
    wait_for_trend(page)
    assert not page.is_checked("#trend-pens input[data-pen='voltage V']")
    assert not page.is_checked("#trend-pens input[data-pen='current A']")
    assert page.is_checked("#trend-pens input[data-pen='temperature °C']")


def test_the_trend_is_fully_visible_without_scrolling_at_1366x768(
    page: Any, bench: Supervisor
) -> None:
    open_channel(page, bench, "ch0")
    assert page.viewport_size == VIEWPORT
    box = page.evaluate(
        "() => { const p = document.querySelector('.trend-panel').getBoundingClientRect();"
        " return {top: p.top, bottom: p.bottom, height: innerHeight, scrollY}; }"
    )
    assert box["scrollY"] == 0
    assert box["top"] >= 0 and box["bottom"] <= box["height"], box
    SCREENS.mkdir(parents=True, exist_ok=True)
    path = SCREENS / "channel-trend-1366x768.png"
    page.screenshot(path=str(path))  # the viewport only: what the operator sees
    print(f"screenshot: {path}")
