"""A test's summary.json tells the truth: how long the test ran, why it ended, and an
efficiency only where a cycle has one (users' finding 8). Virtual clock, one simulated
Chadèche channel."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from supervisor.app import Bench, build_bench
from supervisor.app.dryrun import dry_run_config
from supervisor.chains.states import State
from supervisor.core.clock import VirtualClock
from supervisor.publish.results import (
    CYCLES_SUFFIX,
    LIVE_CYCLES_KEPT,
    LIVE_EVENTS_KEPT,
    TIMELINE_SUFFIX,
)

pytestmark = pytest.mark.integration

_OPEN: list[Bench] = []


@pytest.fixture(autouse=True)
async def _shutdown_benches() -> AsyncIterator[None]:
    yield
    while _OPEN:
        await _OPEN.pop().shutdown()


async def loaded(tmp_path: Path, text: str, soc: float = 0.5) -> Bench:
    path = tmp_path / "r.yaml"
    path.write_text(text, encoding="utf-8")
    b = build_bench(dry_run_config("nimh-aa", 2.0, soc, 1.0), VirtualClock())
    _OPEN.append(b)
    b.load_recipe("ch0", path, results_dir=tmp_path / "results", test_id="t1")
    await b.engine.run_for(3.0)
    return b


def summary(tmp_path: Path) -> dict[str, Any]:
    path = tmp_path / "results" / "t1" / "summary.json"
    data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return data


CHARGE_ONLY = "recipe: r\nsteps:\n  - {id: c, charge: 300 mA, duration: 600 s}\n"


async def test_an_aborted_test_lasts_until_its_abort_and_says_who_aborted_it(
    tmp_path: Path,
) -> None:
    b = await loaded(tmp_path, CHARGE_ONLY)
    b.runners["ch0"].command("start", actor="alice")
    await b.engine.run_for(35.0)
    b.runners["ch0"].command("abort", actor="bob")
    await b.engine.run_for(2.0)
    assert b.runners["ch0"].state is State.ABORTED
    s = summary(tmp_path)
    assert s["duration_s"] == pytest.approx(35.0, abs=1.0)  # was the last record's time: 0.0
    assert s["end_reason"] == "aborted: abort by bob"  # was "done"
    assert (s["state"], s["complete"]) == ("Aborted", True)
    (cycle,) = s["cycles"]
    assert cycle["coulombic_efficiency"] is None and cycle["energy_efficiency"] is None
    assert cycle["efficiency_note"] == "cycle 1 did not finish (aborted: abort by bob)"


async def test_a_stopped_test_says_it_was_stopped_and_by_whom(tmp_path: Path) -> None:
    b = await loaded(tmp_path, CHARGE_ONLY)
    b.runners["ch0"].command("start")
    await b.engine.run_for(20.0)
    b.runners["ch0"].command("stop", actor="carol")
    await b.engine.run_for(2.0)
    s = summary(tmp_path)
    assert (s["state"], s["end_reason"]) == ("Stopped", "stopped: stop by carol")


async def test_a_completed_test_names_its_last_step_and_cycle(tmp_path: Path) -> None:
    b = await loaded(tmp_path, CHARGE_ONLY)
    b.runners["ch0"].command("start")
    await b.engine.run_for(700.0)
    s = summary(tmp_path)
    assert s["state"] == "Complete" and s["complete"] is True
    assert s["end_reason"] == (
        "complete after step c of cycle 1: duration elapsed; end of steps; cycle 1 of 1 done"
    )
    assert s["duration_s"] == pytest.approx(600.0, abs=1.0)


async def test_a_charge_only_test_has_no_efficiency(tmp_path: Path) -> None:
    b = await loaded(tmp_path, CHARGE_ONLY)
    b.runners["ch0"].command("start")
    await b.engine.run_for(700.0)
    (cycle,) = summary(tmp_path)["cycles"]
    assert cycle["charge_capacity_ah"] == pytest.approx(0.3 * 600 / 3600, rel=0.01)
    assert cycle["coulombic_efficiency"] is None  # was 0
    assert cycle["energy_efficiency"] is None
    assert cycle["efficiency_note"] == "cycle 1 has no discharge"


async def test_a_partial_cycle_has_no_efficiency(tmp_path: Path) -> None:
    b = await loaded(
        tmp_path,
        "recipe: r\ncycles: 3\nsteps:\n"
        "  - {id: d, discharge: 400 mA, duration: 3600 s}\n"
        "  - {id: c, charge: 400 mA, duration: 3600 s}\n",
        soc=0.9,
    )
    b.runners["ch0"].command("start")
    await b.engine.run_for(3600.0 + 9.0)  # 9 s into the charge
    b.runners["ch0"].command("abort")
    await b.engine.run_for(2.0)
    (cycle,) = summary(tmp_path)["cycles"]
    assert cycle["discharge_capacity_ah"] > 100 * cycle["charge_capacity_ah"] > 0
    assert cycle["coulombic_efficiency"] is None  # was about 400
    assert cycle["efficiency_note"].startswith("cycle 1 did not finish")


async def test_a_full_cycle_has_its_efficiencies_and_no_note(tmp_path: Path) -> None:
    b = await loaded(
        tmp_path,
        "recipe: r\ncycles: 2\nsteps:\n"
        "  - {id: c, charge: 300 mA, duration: 60 s}\n"
        "  - {id: d, discharge: 200 mA, duration: 60 s}\n",
    )
    b.runners["ch0"].command("start")
    await b.engine.run_for(100.0 + 60.0)  # cycle 1 done, cycle 2 in its charge
    b.runners["ch0"].command("abort")
    await b.engine.run_for(2.0)
    first, second = summary(tmp_path)["cycles"]
    assert first["complete"] is True and first["efficiency_note"] is None
    assert first["coulombic_efficiency"] == pytest.approx(0.2 / 0.3, rel=0.05)
    assert 0 < first["energy_efficiency"] < first["coulombic_efficiency"]
    assert second["complete"] is False and second["coulombic_efficiency"] is None


async def test_a_recipe_loaded_but_never_started_leaves_no_file(tmp_path: Path) -> None:
    b = await loaded(tmp_path, CHARGE_ONLY)
    await b.engine.run_for(60.0)
    b.load_recipe("ch0", tmp_path / "r.yaml", results_dir=tmp_path / "results", test_id="t2")
    await b.shutdown()
    _OPEN.remove(b)
    assert not (tmp_path / "results").exists()  # was a 0-byte BDF file, and more


async def test_the_summary_of_a_test_under_way_is_on_disk_marked_incomplete(
    tmp_path: Path,
) -> None:
    # A supervisor killed outright (SIGKILL) writes nothing more: what is on disk must
    # already be a summary, rewritten at every step change.
    b = await loaded(
        tmp_path,
        "recipe: r\nsteps:\n"
        "  - {id: c, charge: 300 mA, duration: 60 s}\n"
        "  - {id: rest, rest: 600 s}\n",
    )
    b.runners["ch0"].command("start")
    await b.engine.run_for(30.0)
    s = summary(tmp_path)
    assert (s["complete"], s["state"], s["end_reason"]) == (False, "Running", "")
    await b.engine.run_for(40.0)
    s = summary(tmp_path)
    assert s["timeline"][-1]["text"].startswith("starting step 2 rest")
    assert s["duration_s"] == pytest.approx(60.0, abs=1.0)
    assert s["cycles"][0]["efficiency_note"] == "cycle 1 is under way"
    assert not list((tmp_path / "results" / "t1").glob("*.tmp"))  # replaced atomically


async def test_a_clean_shutdown_says_supervisor_stopped_and_leaves_the_test_resumable(
    tmp_path: Path,
) -> None:
    b = await loaded(tmp_path, CHARGE_ONLY)
    b.runners["ch0"].command("start")
    await b.engine.run_for(42.0)
    await b.shutdown()
    _OPEN.remove(b)
    s = summary(tmp_path)
    assert s["end_reason"] == "supervisor stopped"
    assert s["complete"] is False  # it comes back Held at the next start
    assert s["duration_s"] == pytest.approx(42.0, abs=1.0)


async def test_a_test_aborted_by_a_trip_names_the_alarm(tmp_path: Path) -> None:
    b = await loaded(tmp_path, CHARGE_ONLY)
    assert b.alarms is not None
    # A trip that aborts (as the e-stop does), raised by its owner.
    trip = b.alarms.declare("ch0.test_trip", group="ch0", latched=True, action="abort")
    b.runners["ch0"].command("start")
    await b.engine.run_for(10.0)
    b.alarms.set(trip, True, "e-stop: estop.ok is false (circuit open)")
    await b.engine.run_for(2.0)
    s = summary(tmp_path)
    assert s["state"] == "Aborted"
    assert s["end_reason"] == "aborted: channel trip: e-stop: estop.ok is false (circuit open)"


def jsonl(tmp_path: Path, suffix: str) -> list[dict[str, Any]]:
    path = tmp_path / "results" / "t1" / f"t1{suffix}"
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


async def test_a_long_live_test_keeps_a_bounded_timeline_while_every_event_reaches_its_file(
    tmp_path: Path,
) -> None:
    # Issue 13 (ADR 0022): 150 cycles of two 2 s steps, 300 step changes, on a bench.
    b = await loaded(
        tmp_path,
        "recipe: r\ncycles: 150\nsteps:\n"
        "  - {id: c, charge: 300 mA, duration: 2 s}\n"
        "  - {id: d, discharge: 300 mA, duration: 2 s}\n",
    )
    b.runners["ch0"].command("start")
    await b.engine.run_for(610.0)
    assert b.runners["ch0"].state is State.COMPLETE
    s = summary(tmp_path)
    events = jsonl(tmp_path, TIMELINE_SUFFIX)
    starts = [e for e in events if e["text"].startswith("starting step")]
    assert [(e["cycle"], e["step"]) for e in starts] == [
        (n, step) for n in range(1, 151) for step in ("c", "d")
    ]
    assert len(s["timeline"]) == LIVE_EVENTS_KEPT
    assert s["timeline_omitted"] == len(events) - LIVE_EVENTS_KEPT
    assert s["timeline"][: LIVE_EVENTS_KEPT // 2] == events[: LIVE_EVENTS_KEPT // 2]
    assert s["timeline"][LIVE_EVENTS_KEPT // 2 :] == events[-LIVE_EVENTS_KEPT // 2 :]
    cycles = jsonl(tmp_path, CYCLES_SUFFIX)
    assert [c["cycle"] for c in cycles] == list(range(1, 151))
    assert all(c["complete"] for c in cycles)
    assert s["cycles_omitted"] == 150 - LIVE_CYCLES_KEPT
    assert s["cycles"][-1] == cycles[-1]
