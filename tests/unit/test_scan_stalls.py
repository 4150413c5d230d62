"""A stall of the scan is always counted and alarmed (issue 9): a scan that starts late
because the event loop was held between two scans — which ``scan.overruns`` cannot see, no
scan having run long.

On the virtual clock a held loop is the clock moved while the engine waits for its next
deadline (``held_once``): exactly what a callback that blocked the loop for that long looks
like to the scan. The watch thread that logs a stall while it lasts needs a real clock: in
tests/integration/test_recipe_load_keeps_the_scan.py.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from commandrig import recipe

from supervisor.app import Bench
from supervisor.commands import Command, Verb
from supervisor.core.clock import VirtualClock
from supervisor.safety import AlarmState
from supervisor.scan import LogicPhase, ScanEngine
from supervisor.scan.engine import STALL_MIN_S, stall_after_s
from supervisor.tags import TagDB
from supervisor.testing import run_scans


def held_once(monkeypatch: pytest.MonkeyPatch, e: ScanEngine, seconds: float) -> None:
    """The engine's wait for the deadline after its next scan ends ``seconds`` late, as if
    something held the event loop that long."""
    clock = e.clock
    assert isinstance(clock, VirtualClock)
    real = clock.sleep_until
    after = e.stats.count + 1

    async def held(t: float) -> None:
        await real(t)
        if e.stats.count >= after:
            monkeypatch.setattr(clock, "sleep_until", real)
            clock.advance(seconds)

    monkeypatch.setattr(clock, "sleep_until", held)


def engine(period_s: float = 0.1) -> tuple[VirtualClock, TagDB, ScanEngine, list[float]]:
    clock, db = VirtualClock(), TagDB()
    starts: list[float] = []
    e = ScanEngine(
        clock, db, period_s, phases=[LogicPhase("t", lambda now, dt: starts.append(now))]
    )
    return clock, db, e, starts


def test_a_stall_is_a_start_later_than_two_periods_and_at_least_a_quarter_second() -> None:
    assert stall_after_s(0.1) == STALL_MIN_S == 0.25
    assert stall_after_s(0.01) == 0.25  # a fast scan does not alarm on a garbage collection
    assert stall_after_s(1.0) == 2.0


async def test_a_scan_that_starts_late_counts_a_stall_and_no_overrun(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _, db, e, starts = engine()
    await e.run_for(1.0)
    held_once(monkeypatch, e, 6.8)  # issue 9: a 20 MB recipe parsed on the loop
    await e.run_for(1.0)
    assert db["scan.stalls"].value == 1
    assert db["scan.stall_max_s"].value == pytest.approx(6.8)
    assert db["scan.overruns"].value == 0  # no scan ran long: none ran at all
    # The late scan runs at once; the deadlines missed meanwhile are skipped, not burst.
    assert starts[11] == pytest.approx(1.1 + 6.8)
    assert e.stats.skipped == 68
    await e.run_for(0.3)
    assert starts[12] - starts[11] == pytest.approx(0.1)
    assert db["scan.stalls"].value == 1


async def test_a_start_late_by_less_than_the_threshold_is_no_stall(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _, db, e, _ = engine()
    await e.run_for(0.5)
    held_once(monkeypatch, e, 0.2)  # within max(2 periods, 0.25 s)
    await e.run_for(0.5)
    assert db["scan.stalls"].value == 0
    assert db["scan.stall_max_s"].value == 0.0


async def test_the_lateness_of_this_scan_is_published_and_back_to_0_on_the_next(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _, db, e, _ = engine()
    seen: list[float] = []
    e.phases.append(LogicPhase("see", lambda now, dt: seen.append(db["scan.stall_s"].as_float())))
    await e.run_for(0.3)
    held_once(monkeypatch, e, 1.0)
    await e.run_for(0.3)
    await e.run_for(0.2)
    assert seen[:4] == [0.0, 0.0, 0.0, 0.0]
    assert seen[4] == pytest.approx(1.0)  # seen by the late scan's own phases
    assert seen[5:] == [0.0, 0.0]
    assert db["scan.stalls"].value == 1


async def test_every_stall_is_counted_and_the_worst_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    _, db, e, _ = engine()
    for seconds in (0.5, 3.0, 1.0):
        held_once(monkeypatch, e, seconds)
        await e.run_for(0.5)
    assert db["scan.stalls"].value == 3
    assert db["scan.stall_max_s"].value == pytest.approx(3.0)


async def test_moving_the_clock_between_two_runs_is_no_stall() -> None:
    clock, db, e, _ = engine()
    await e.run_for(0.5)
    clock.advance(10.0)  # a test (or a dry run) starting a new run later
    await e.run_for(0.5)
    assert db["scan.stalls"].value == 0


# --- the supervision alarm ---------------------------------------------------------------------
async def test_a_stall_raises_the_scan_stall_alarm_which_clears_and_waits_for_an_ack(
    bench: Bench, monkeypatch: pytest.MonkeyPatch
) -> None:
    alarms = bench.alarms
    assert alarms is not None
    alarm = alarms["scan.stall"]
    assert alarm.state is AlarmState.NORMAL and not alarm.latched and alarm.group == ""
    held_once(monkeypatch, bench.engine, 6.8)
    await run_scans(bench.engine, 2)  # the second one late
    assert alarm.state is AlarmState.ACTIVE_UNACKED
    assert alarm.message == (
        "scan started 6.80 s late: its event loop was held between two scans"
        " (stall 1 since start; see the log)"
    )
    await run_scans(bench.engine, 1)  # back on time: the condition is gone ...
    assert alarm.state is AlarmState.RETURNED_UNACKED  # ... the alarm still annunciated
    result = bench.commands.execute(Command.alarm("scan.stall", Verb.ACKNOWLEDGE))
    assert result.accepted, result
    assert alarm.state is AlarmState.NORMAL
    kinds = [ev.transition.value for ev in alarms.history if ev.alarm_id == "scan.stall"]
    assert kinds == ["activated", "cleared", "acknowledged"]


async def test_the_stall_alarm_is_no_trip_a_channel_still_starts(
    bench: Bench, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    held_once(monkeypatch, bench.engine, 3.0)
    await run_scans(bench.engine, 2)
    assert bench.alarms is not None and bench.alarms["scan.stall"].active
    start = Command.channel("ch0", Verb.START, recipe=recipe(tmp_path))
    assert bench.commands.execute(start).accepted
