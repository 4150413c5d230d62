"""Issue 32, finding 6 ("Show Graphs" of seed 002 plots the cells): in Debian's Chromium, the
channel screen of the BMS's channel (ch4 of io_maps/sim.yaml) draws the cells' lowest and
highest voltage beside V, I and T, named in its legend, with values from the simulated BMS."""

from __future__ import annotations

from typing import Any

from browserrig import Supervisor, screenshot


def test_the_bms_channel_s_trend_shows_the_cell_min_and_max(
    as_operator: Any, bench: Supervisor
) -> None:
    page = as_operator
    page.click("#tile-ch4")
    page.wait_for_selector("#trend[data-series]")
    series = str(page.get_attribute("#trend", "data-series")).split("|")
    assert series == ["voltage V", "current A", "temperature °C", "cell min V", "cell max V"]
    page.wait_for_selector("#trend .u-legend")
    legend = page.eval_on_selector_all(
        "#trend .u-legend .u-series .u-label", "els => els.map(e => e.textContent)"
    )
    assert {"cell min V", "cell max V"} <= set(legend)
    # Values drawn, not only named: the simulated BMS's cells of the 4S pack.
    page.wait_for_function(
        "() => ['cell min V', 'cell max V'].every(s =>"
        " (document.querySelector('#trend').dataset.valued || '').split('|').includes(s))"
    )
    cell = bench.tag("bms.cell_min")
    assert 3.0 < cell < 4.2
    screenshot(page, "channel-bms-trend")


def test_a_channel_without_a_bms_draws_v_i_and_t_only(as_operator: Any) -> None:
    page = as_operator
    page.click("#tile-ch0")
    page.wait_for_selector("#trend[data-series]")
    series = str(page.get_attribute("#trend", "data-series")).split("|")
    assert [s.split(" ")[0] for s in series] == ["voltage", "current", "temperature"]
