"""A live test's record is its files; its memory is bounded (issue 13, ADR 0022).

Every timeline event reaches ``<id>.timeline.jsonl`` as it happens and every cycle reaches
``<id>.cycles.jsonl`` once it is over, while the collector (and so ``summary.json``, the
Tests screen) keeps only the first and the latest ones, whatever the test's length. A
resumed test goes on appending to the same files and keeps in memory what it would have
kept without the restart. Made-up events and records; no clock, no timing.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.records import ChainEvent, Record
from supervisor.publish.results import (
    CYCLES_SUFFIX,
    LIVE_CYCLES_KEPT,
    LIVE_EVENTS_KEPT,
    SUMMARY_FORMAT,
    TIMELINE_SUFFIX,
    ResultCollector,
    read_jsonl,
    read_timeline,
)
from supervisor.testing.records import make_record

WALL = 1.7e9
REC = make_record(wall=WALL, current_cmd_a=0.05, last_voltage_v=1.3)


def step_event(t: float, cycle: int) -> ChainEvent:
    step = "c" if int(t) % 2 == 0 else "d"
    return ChainEvent(t, WALL + t, "ch0", "step", f"starting step {step} (t={t:g})", 0, step, cycle)


def record(t: float, cycle: int) -> Record:
    # Cycle figures grow within a cycle: 1 mAh charged, then discharged, per second.
    ah = 0.001 * (t % 10)
    return replace(
        REC,
        t=t,
        wall=WALL + t,
        test_time_s=t,
        cycle=cycle,
        cycle_charged_ah=ah,
        cycle_discharged_ah=ah * 0.9,
        cycle_charged_wh=ah * 1.3,
        cycle_discharged_wh=ah * 1.1,
    )


def run(c: ResultCollector, seconds: range, seconds_per_cycle: int = 10) -> None:
    """A step change and a record every second, a new cycle every ``seconds_per_cycle``."""
    for t in seconds:
        cycle = t // seconds_per_cycle + 1
        c.on_record(record(float(t), cycle))
        c.on_event(step_event(float(t), cycle))


def timeline_rows(folder: Path) -> list[dict[str, Any]]:
    return list(read_jsonl(folder / f"t1{TIMELINE_SUFFIX}"))


def cycle_rows(folder: Path) -> list[dict[str, Any]]:
    return list(read_jsonl(folder / f"t1{CYCLES_SUFFIX}"))


def everything(seconds: range, end_reason: str, state: str) -> dict[str, Any]:
    """The summary of the same test by a collector that keeps everything in memory."""
    whole = ResultCollector("ch0", "r", "t1", None, events_kept=None, cycles_kept=None)
    run(whole, seconds)
    return whole.summary(end_reason, state)


@settings(max_examples=30, deadline=None)
@given(
    n_s=st.integers(min_value=0, max_value=400),
    events_kept=st.integers(min_value=1, max_value=40),
    cycles_kept=st.integers(min_value=1, max_value=12),
    ends=st.sampled_from(
        [
            ("complete after step d of cycle 40: end", "Complete"),
            ("aborted: abort by bob", "Aborted"),
        ]
    ),
)
def test_a_live_tests_memory_stays_bounded_while_every_event_and_cycle_reaches_its_file(
    n_s: int, events_kept: int, cycles_kept: int, ends: tuple[str, str]
) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "t1"
        c = ResultCollector(
            "ch0", "r", "t1", folder, events_kept=events_kept, cycles_kept=cycles_kept
        )
        run(c, range(n_s))
        assert len(c.kept_timeline) <= events_kept
        assert len(c.cycles) <= cycles_kept
        s = c.close(*ends)
        whole = everything(range(n_s), *ends)
        if n_s == 0:
            assert not folder.exists()  # never started: no file
            return
        # Nothing lost: the files hold what a collector keeping everything would show.
        assert timeline_rows(folder) == whole["timeline"]
        assert cycle_rows(folder) == whole["cycles"]
        # The summary: the first half and the latest half, and the count between them.
        kept = (
            whole["timeline"][: events_kept // 2]
            + whole["timeline"][len(whole["timeline"]) - (len(s["timeline"]) - events_kept // 2) :]
        )
        assert s["timeline"] == kept if len(whole["timeline"]) > events_kept else whole["timeline"]
        assert s["timeline_omitted"] == len(whole["timeline"]) - len(s["timeline"])
        assert s["cycles_omitted"] == len(whole["cycles"]) - len(s["cycles"])
        assert all(row in whole["cycles"] for row in s["cycles"])
        assert s["format"] == SUMMARY_FORMAT == 3


def test_the_default_bounds_are_a_live_tests_and_a_long_test_stays_within_them(
    tmp_path: Path,
) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path / "t1")
    run(c, range(5000))  # 5000 step changes, 500 cycles
    assert len(c.kept_timeline) == LIVE_EVENTS_KEPT
    assert len(c.cycles) == LIVE_CYCLES_KEPT  # the one under way among them
    c.checkpoint("Running", now=5000.0)
    s = json.loads((tmp_path / "t1" / "summary.json").read_text(encoding="utf-8"))
    assert len(s["timeline"]) == LIVE_EVENTS_KEPT
    assert s["timeline_omitted"] == 5000 - LIVE_EVENTS_KEPT
    assert s["timeline_omitted_at"] == LIVE_EVENTS_KEPT // 2
    assert s["cycles_omitted"] == 500 - LIVE_CYCLES_KEPT
    assert len(timeline_rows(tmp_path / "t1")) == 5000
    assert [r["cycle"] for r in cycle_rows(tmp_path / "t1")] == list(range(1, 500))
    c.close("aborted: abort by bob", "Aborted")


def test_a_cycle_reaches_its_file_once_it_is_over_and_the_one_under_way_waits(
    tmp_path: Path,
) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path / "t1")
    run(c, range(25))  # cycles 1 and 2 over, cycle 3 under way
    rows = cycle_rows(tmp_path / "t1")
    assert [(r["cycle"], r["complete"]) for r in rows] == [(1, True), (2, True)]
    assert rows[0]["charge_capacity_ah"] == 0.009  # its last record's figures
    c.close("", "Running", complete=False)  # the supervisor stops, the test may resume
    assert len(cycle_rows(tmp_path / "t1")) == 2
    again = ResultCollector("ch0", "r", "t1", tmp_path / "t1")
    again.resume(first_t=0.0)
    again.close("aborted: abort by bob", "Aborted")
    last = cycle_rows(tmp_path / "t1")[-1]
    assert (last["cycle"], last["complete"]) == (3, False)
    assert last["efficiency_note"] == "cycle 3 did not finish (aborted: abort by bob)"


@settings(max_examples=20, deadline=None)
@given(n_s=st.integers(min_value=1, max_value=300), cut_s=st.integers(min_value=1, max_value=300))
def test_a_resumed_test_goes_on_appending_and_keeps_what_it_would_have_kept(
    n_s: int, cut_s: int
) -> None:
    cut_s = min(cut_s, n_s)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "t1"
        first = ResultCollector("ch0", "r", "t1", folder, events_kept=20, cycles_kept=6)
        run(first, range(cut_s))
        first.checkpoint("Running", now=float(cut_s))
        first.abandon()  # the process dies
        again = ResultCollector("ch0", "r", "t1", folder, events_kept=20, cycles_kept=6)
        again.resume(first_t=0.0)  # the same clock axis: nothing away
        run(again, range(cut_s, n_s))
        s = again.close("aborted: abort by bob", "Aborted", now=float(n_s))

        straight = ResultCollector("ch0", "r", "t1", None, events_kept=20, cycles_kept=6)
        run(straight, range(n_s))
        expected = straight.summary("aborted: abort by bob", "Aborted", now=float(n_s))
        whole = everything(range(n_s), "aborted: abort by bob", "Aborted")
        assert timeline_rows(folder) == whole["timeline"]
        assert cycle_rows(folder) == whole["cycles"]
        for key in ("timeline", "timeline_omitted", "timeline_omitted_at", "cycles_omitted"):
            assert s[key] == expected[key], key
        assert s["cycles"] == expected["cycles"]
        assert s["records"] == n_s


def test_a_summary_of_format_2_resumed_gives_its_timeline_and_cycles_to_the_new_files(
    tmp_path: Path,
) -> None:
    # What a supervisor before ADR 0022 left of a test under way: all in summary.json.
    folder = tmp_path / "t1"
    old = ResultCollector("ch0", "r", "t1", folder, events_kept=None, cycles_kept=None)
    run(old, range(25))
    legacy = old.summary("", "Running", complete=False)
    legacy["format"] = 2  # keeping everything, it has no "…_omitted" counts either
    old.abandon()
    for name in (f"t1{TIMELINE_SUFFIX}", f"t1{CYCLES_SUFFIX}"):
        (folder / name).unlink()
    (folder / "summary.json").write_text(json.dumps(legacy), encoding="utf-8")

    again = ResultCollector("ch0", "r", "t1", folder)
    again.resume(first_t=0.0)
    run(again, range(25, 40))
    again.close("aborted: abort by bob", "Aborted")
    whole = everything(range(40), "aborted: abort by bob", "Aborted")
    assert timeline_rows(folder) == whole["timeline"]
    assert cycle_rows(folder) == whole["cycles"]
    assert list(read_timeline(folder)) == whole["timeline"]


def test_a_line_cut_short_by_a_power_cut_is_skipped_and_the_next_lines_are_whole(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "t1"
    first = ResultCollector("ch0", "r", "t1", folder)
    run(first, range(3))
    first.abandon()
    path = folder / f"t1{TIMELINE_SUFFIX}"
    with path.open("a", encoding="utf-8") as f:
        f.write('{"test_time_s": 3.0, "ki')  # the power went
    again = ResultCollector("ch0", "r", "t1", folder)
    again.resume(first_t=0.0)
    run(again, range(3, 5))
    again.close("aborted: abort by bob", "Aborted")
    assert [e["test_time_s"] for e in read_jsonl(path)] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert len(path.read_text(encoding="utf-8").splitlines()) == 6  # the broken one kept


def test_events_before_the_first_record_wait_for_it_and_then_reach_the_file(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "t1"
    c = ResultCollector("ch0", "r", "t1", folder)
    c.on_event(ChainEvent(0.0, WALL, "ch0", "state", "Idle → Running (start by alice)"))
    c.checkpoint("Running", now=0.0)
    assert [p.name for p in folder.iterdir()] == ["summary.json"]  # no data file yet
    c.on_record(record(0.0, 1))
    assert [e["text"] for e in timeline_rows(folder)] == ["Idle → Running (start by alice)"]
    c.close("aborted: abort by bob", "Aborted")


def test_a_test_that_ends_before_its_first_record_has_its_timeline_file(tmp_path: Path) -> None:
    folder = tmp_path / "t1"
    c = ResultCollector("ch0", "r", "t1", folder)
    c.on_event(ChainEvent(0.0, WALL, "ch0", "state", "Idle → Running (start by alice)"))
    c.on_event(ChainEvent(0.0, WALL, "ch0", "state", "Running → Held (permissive lost)"))
    c.close("aborted: abort by bob", "Aborted")
    assert len(timeline_rows(folder)) == 2
    assert cycle_rows(folder) == []


def test_a_dry_run_without_a_folder_keeps_nothing_for_a_file() -> None:
    c = ResultCollector("ch0", "r", "t1", None, events_kept=4, cycles_kept=2)
    run(c, range(1000))
    assert c._unwritten_events == [] and c._unwritten_cycles == []
    assert len(c.kept_timeline) == 4


@settings(max_examples=30, deadline=None)
@given(
    n_s=st.integers(min_value=1, max_value=200),
    cycles_kept=st.integers(min_value=1, max_value=12),
    every_s=st.integers(min_value=1, max_value=15),
)
def test_the_summary_at_every_checkpoint_shows_each_cycle_as_it_stands_then(
    n_s: int, cycles_kept: int, every_s: int
) -> None:
    """The dicts of finished cycles are made once and reused: each summary still shows
    every kept cycle exactly as its figures stand at that moment."""
    c = ResultCollector("ch0", "r", "t1", None, cycles_kept=cycles_kept)
    for t in range(n_s):
        run(c, range(t, t + 1))
        if t % every_s == 0:
            fresh = [cy.as_dict() for _, cy in sorted(c.cycles.items())]
            assert c.summary("", "Running", complete=False)["cycles"] == fresh
    whole = everything(range(n_s), "aborted: abort by bob", "Aborted")
    s = c.summary("aborted: abort by bob", "Aborted")
    assert all(row in whole["cycles"] for row in s["cycles"])
    assert s["cycles"] == [
        cy.as_dict("aborted: abort by bob") for _, cy in sorted(c.cycles.items())
    ]
