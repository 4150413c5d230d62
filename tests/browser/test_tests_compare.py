"""Issue 33, finding 10: tests compared on the Tests screen. Two finished tests of one
cell (their result files written by the results writer from a short simulated run, before
the supervisor starts): ticked in the list and compared at one cycle, their halves are
overlaid as V against Ah with a legend naming each test's curve and units on both axes;
one test's page overlays its cycles; the cell's capacity fade has a point per finished
cycle of each test, the tests' ids in its legend. As a viewer: reading is all it takes.
In Debian's Chromium against a real ``supervisor run`` of the simulated bench."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from axe import audit, blocking
from browserrig import Supervisor, login, screenshot, supervisor_fixture

from supervisor.core.records import ChainEvent
from supervisor.publish.provenance import TestMetadata
from supervisor.publish.results import ResultCollector
from supervisor.testing.records import make_record

CELL = "NIMH-AA-7"
TESTS = {"20261201-090000-ch0": 1.7962e9, "20261202-090000-ch0": 1.7963e9}  # id: start
CYCLES = 3
HALF_S = 60  # a charge: 0.3 A for 60 s, a row every 2 s; a discharge 4 s shorter each cycle
ROW_S = 2
CURRENT_A = 0.3


def simulated_test(results: Path, test_id: str, wall0: float, cycles_before: int) -> None:
    """Cycles of a NiMH cell: a charge raising the voltage, a discharge lowering it, each
    discharge shorter than the one before (the cell ageing, also across its tests)."""
    c = ResultCollector(
        "ch0", "short-cycle", test_id, results / test_id, metadata=TestMetadata(cell_id=CELL)
    )
    t = 0.0
    for cycle in range(1, CYCLES + 1):
        c.on_event(ChainEvent(t, wall0 + t, "ch0", "step", "starting step c", 0, "c", cycle))
        dch_s = HALF_S - 4 * (cycles_before + cycle)
        ah_in = ah_out = 0.0
        for kind, seconds, sign in (("CC_CHG", HALF_S, 1), ("CC_DCH", dch_s, -1)):
            for k in range(seconds // ROW_S + 1):
                s = float(k * ROW_S)
                frac = s / seconds
                if sign > 0:
                    ah_in = CURRENT_A * s / 3600
                else:
                    ah_out = CURRENT_A * s / 3600
                v = 1.25 + 0.2 * frac if sign > 0 else 1.40 - 0.25 * frac
                rec = make_record(current_cmd_a=sign * CURRENT_A, last_voltage_v=v)
                c.on_record(
                    replace(
                        rec,
                        t=t + s,
                        wall=wall0 + t + s,
                        test_time_s=t + s,
                        step_time_s=s,
                        cycle=cycle,
                        step_id="c" if sign > 0 else "d",
                        step_type=kind,
                        voltage_v=v,
                        current_a=sign * CURRENT_A,
                        cycle_charged_ah=ah_in,
                        cycle_discharged_ah=ah_out,
                        cycle_charged_wh=ah_in * 1.3,
                        cycle_discharged_wh=ah_out * 1.2,
                    )
                )
            t += seconds + ROW_S
    c.close("complete after the last cycle", "Complete", now=t)


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Supervisor]:
    workdir = tmp_path_factory.mktemp("compare-bench")
    results = workdir / "state" / "results"
    for n, (test_id, wall0) in enumerate(TESTS.items()):
        simulated_test(results, test_id, wall0, cycles_before=n * CYCLES)
    yield from supervisor_fixture(workdir)


def drawn(page: Any, selector: str) -> list[dict[str, Any]]:
    page.wait_for_selector(f"{selector} .uplot")
    page.wait_for_function(f"() => document.querySelector('{selector}').dataset.drawn")
    return json.loads(page.get_attribute(selector, "data-drawn") or "[]")


def legend(page: Any, selector: str) -> list[str]:
    """The curves named in the chart's legend (no x entry: its values are not shown)."""
    return page.eval_on_selector_all(
        f"{selector} .u-legend .u-series .u-label", "els => els.map(e => e.textContent)"
    )


def axis_labels(page: Any, selector: str) -> list[str]:
    """The x and y axes' labels (uPlot draws them on its canvas: the chart notes them)."""
    return json.loads(page.get_attribute(selector, "data-axes") or "[]")


def test_one_cycle_of_the_tests_ticked_is_overlaid_with_a_legend_and_units(
    page: Any, bench: Supervisor
) -> None:
    login(page, bench, "viewer", "#/tests")
    page.wait_for_selector("#test-table")
    for test_id in TESTS:
        page.check(f".compare-pick[value='{test_id}']")
    page.fill("#compare-cycle", "2")
    page.click("#compare-go")
    curves = drawn(page, "#compare-curves")
    # One curve per selected test's cycle half: its charge and its discharge.
    want = [f"{t} cycle 2 {half}" for t in TESTS for half in ("charge", "discharge")]
    assert [c["label"] for c in curves] == want
    assert legend(page, "#compare-curves") == want
    assert all(c["points"] > 5 for c in curves), curves
    assert axis_labels(page, "#compare-curves") == [
        "charge since the half began (mAh)",
        "voltage (V)",
    ]
    screenshot(page, "tests-compare")
    assert not blocking(audit(page)), "axe: serious or critical violations"


def test_a_tests_page_overlays_its_cycles_and_its_cells_fade(page: Any, bench: Supervisor) -> None:
    first = next(iter(TESTS))
    login(page, bench, "viewer", f"#/tests/{first}")
    curves = drawn(page, "#test-curves")
    assert [c["label"] for c in curves] == [
        f"cycle {n} {half}" for n in range(1, CYCLES + 1) for half in ("charge", "discharge")
    ]
    assert axis_labels(page, "#test-curves") == ["charge since the half began (mAh)", "voltage (V)"]
    fade = drawn(page, "#test-fade")
    # A point per finished cycle of each test, each test a series named by its id.
    assert [c["points"] for c in fade] == [CYCLES] * len(TESTS)
    assert [label.split(" ")[0] for label in legend(page, "#test-fade")] == list(TESTS)
    assert axis_labels(page, "#test-fade") == [
        "cycle of the cell, cumulative (cycles)",
        "discharge capacity (mAh)",
    ]
    screenshot(page, "tests-curves-fade")


def test_the_fade_of_the_cell_found_in_the_list(page: Any, bench: Supervisor) -> None:
    login(page, bench, "viewer", "#/tests")
    page.fill("#cell-filter", CELL)
    page.click("#cell-find")
    fade = drawn(page, "#cell-fade")
    assert [c["points"] for c in fade] == [CYCLES] * len(TESTS)
    status, body = bench.call("GET", f"/api/fade?cell={CELL}", user="viewer")
    assert status == 200, body
    # The second test's cycles follow the first's: 1..3, then 4..6, each fading.
    xs = [t["cumulative_cycle"] for t in body["tests"]]
    assert xs == [[1, 2, 3], [4, 5, 6]]
    caps = [a for t in body["tests"] for a in t["discharge_ah"]]
    assert caps == sorted(caps, reverse=True) and len(set(caps)) == len(caps)


def test_the_comparison_fits_an_800_px_tablet(page: Any, bench: Supervisor) -> None:
    page.set_viewport_size({"width": 800, "height": 1180})
    login(page, bench, "viewer", "#/tests")
    page.wait_for_selector("#test-table")
    for test_id in TESTS:
        page.check(f".compare-pick[value='{test_id}']")
    page.click("#compare-go")
    assert len(drawn(page, "#compare-curves")) == 2 * len(TESTS)  # cycle 1 by default
    screenshot(page, "tests-compare-tablet")
    width = page.evaluate(
        "() => document.documentElement.scrollWidth - document.documentElement.clientWidth"
    )
    wide = page.eval_on_selector_all(
        "#main *",
        "els => els.filter(e => e.getBoundingClientRect().right > 801).slice(0, 8)"
        ".map(e => `${e.tagName}#${e.id}.${e.className}`)",
    )
    assert width == 0, f"the page is {width} px wider than the tablet: {wide}"
