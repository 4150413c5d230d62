"""Issue 32 "Must show", in Debian's Chromium against a real ``supervisor run`` of the
simulated bench: a profile CSV (seed 002 figure 21's columns and Unix timestamps) loaded
onto ch4 from the Recipes screen — previewed, refused at its line and column when broken,
dry-run on ch4's own plant (PACK's finding 4), loaded, started — and ch4's trend then
drawing V, I, T and the BMS's cell min/max (CAN's finding 6).

The bench runs on the wall clock: the test waits for what it expects with timeouts."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from browserrig import Supervisor, login, screenshot, supervisor_fixture, wait_for

T0 = 1736943899.5500178
"""The first time of the seed's figure 21 (a Unix timestamp, as its Tk HMI wrote them)."""
STEP_S = 2.5
CURRENTS_A = (2.0, 5.0, 5.0, -3.0, -3.0, 0.0, 2.0, 2.0, 0.0)
"""A 4S 10 Ah pack's profile: charge, discharge, rest, charge; 20 s in all."""


def figure_21_profile() -> bytes:
    lines = ["Time,Voltage,Current,Temperature,BMS Faults,Cell Voltage,Cell Temperature"]
    for k, amps in enumerate(CURRENTS_A):
        lines.append(f"{T0 + k * STEP_S:.7f},14.8,{amps},25,No faults,3.7,25")
    return ("\n".join(lines) + "\n").encode()


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Supervisor]:
    yield from supervisor_fixture(tmp_path_factory.mktemp("profile-bench"))


def result(page: Any, selector: str = "#profile-result") -> str:
    page.wait_for_selector(f"{selector}:not([hidden])")
    page.wait_for_function(
        f"() => {{ const t = document.querySelector('{selector}').textContent;"
        " return t && !t.endsWith('…'); }"
    )
    return str(page.text_content(selector))


def upload(page: Any, name: str, data: bytes) -> None:
    page.set_input_files(
        "#profile-file", files=[{"name": name, "mimeType": "text/csv", "buffer": data}]
    )


def test_a_broken_profile_is_refused_at_its_line_and_column_and_cannot_be_loaded(
    page: Any, bench: Supervisor
) -> None:
    login(page, bench, "operator", "#/recipes")
    page.wait_for_selector("#profile-panel")
    upload(page, "broken.csv", b"Time (s),Current (A)\n0,2\n10,2 A\n20,0\n")
    page.wait_for_selector("#profile-errors li.refused")
    assert "broken.csv:3:4: '2 A' is not a number" in (page.text_content("#profile-errors") or "")
    assert page.is_disabled("#profile-load") and page.is_disabled("#profile-dryrun")


def test_a_profile_csv_is_loaded_onto_ch4_dry_run_started_and_ch4_s_trend_shows_v_i_t(
    page: Any, bench: Supervisor
) -> None:
    login(page, bench, "operator", "#/recipes")
    page.wait_for_selector("#profile-panel")
    page.select_option("#profile-channel", "ch4")
    upload(page, "sample_profile.csv", figure_21_profile())
    # The preview: its table (the current column, not the voltage), its chart, the notices.
    page.wait_for_selector("#profile-table tbody tr")
    currents = page.eval_on_selector_all(
        "#profile-table tbody tr", "rows => rows.map(r => Number(r.cells[1].textContent))"
    )
    assert currents == list(CURRENTS_A)
    assert "9 rows, " in (page.text_content("#profile-summary") or "")
    notices = page.text_content("#profile-notices") or ""
    assert "Unix timestamps" in notices and "lasts 20 s" in notices and "'Voltage'" in notices
    page.wait_for_selector("#profile-chart .uplot")
    # The dry run on ch4's plant, then the load and the start.
    page.click("#profile-dryrun")
    text = result(page)
    assert "dry run on ch4" in text and "completes" in text, text
    page.wait_for_selector("#profile-dry .uplot")
    screenshot(page, "recipes-profile")
    page.click("#profile-load")
    assert "loaded" in result(page)
    page.wait_for_selector("#profile-start:not([disabled])")
    page.click("#profile-start")
    assert "started" in result(page)
    page.click("#profile-goto")
    # ch4's screen: the chain runs the profile step, the trend grows with V, I and T.
    page.wait_for_selector("#chain li[data-step='profile']")
    page.wait_for_selector("#trend .uplot")
    points_before = int(page.get_attribute("#trend", "data-points") or 0)
    wait_for(
        "ch4's trend to grow",
        lambda: int(page.get_attribute("#trend", "data-points") or 0) > points_before + 3,
        timeout_s=30,
    )
    # V, I, T and the BMS's cell min/max (finding 6, CAN's branch), each drawn with values.
    series = str(page.get_attribute("#trend", "data-series")).split("|")
    assert series == ["voltage V", "current A", "temperature °C", "cell min V", "cell max V"]
    page.wait_for_function(
        "names => names.every(s =>"
        " (document.querySelector('#trend').dataset.valued || '').split('|').includes(s))",
        arg=series,
    )
    # I follows the profile (a charge of 2 or 5 A), V and T are the pack's.
    current = wait_for(
        "ch4's current to follow the profile",
        lambda: next(
            (v for v in [bench.tag("ch4.current")] if isinstance(v, float) and v > 1.0), None
        ),
        timeout_s=30,
    )
    assert 1.0 < current < 5.5
    assert 12.0 < bench.tag("pack.voltage") < 16.8
    assert isinstance(bench.tag("pack.temp"), float)
    assert 3.0 < bench.tag("bms.cell_min") <= bench.tag("bms.cell_max") < 4.2
    screenshot(page, "channel-ch4-profile")
