"""``scan.realtime_priority``: the scan's thread runs at a real-time priority (SCHED_FIFO)
while the engine runs on a real clock, and goes back to what it had after; a refusal is
one warning that says what grants it, and the scan runs anyway (ADR 0023)."""

from __future__ import annotations

import asyncio
import logging
import os
import threading

import pytest

from supervisor.core.clock import RealClock, VirtualClock
from supervisor.core.errors import ConfigErrors
from supervisor.core.gate import ScanGate
from supervisor.core.realtime import GRANT_HINT, RealtimePriority
from supervisor.devices.registry import REGISTRY
from supervisor.scan.engine import GateCloser, LogicPhase, ScanEngine
from supervisor.tags import TagDB


def _can_raise() -> bool:
    """Whether this process may take SCHED_FIFO (root, CAP_SYS_NICE or RLIMIT_RTPRIO)."""
    if not hasattr(os, "sched_setscheduler"):
        return False
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        return False
    os.sched_setscheduler(0, before[0], before[1])
    return True


def _seen_by_the_scan(engine: ScanEngine, seen: list[tuple[int, int, int]]) -> None:
    def look(now: float, dt: float) -> None:
        seen.append(
            (
                threading.get_native_id(),
                os.sched_getscheduler(0),
                os.sched_getparam(0).sched_priority,
            )
        )

    engine.phases.append(LogicPhase("look", look))


@pytest.mark.skipif(not _can_raise(), reason="this process may not take a real-time priority")
async def test_the_scans_run_at_the_real_time_priority_and_the_thread_gets_its_own_back_after() -> (
    None
):
    engine = ScanEngine(RealClock(), TagDB(), 0.01)
    engine.realtime = RealtimePriority(20)
    seen: list[tuple[int, int, int]] = []
    _seen_by_the_scan(engine, seen)
    before = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority

    await engine.run(asyncio.Event(), max_scans=3)

    assert len(seen) == 3
    assert {(policy, prio) for _, policy, prio in seen} == {(os.SCHED_FIFO, 20)}
    assert engine.stats.realtime_priority is None  # it ran at 20; it is back now
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == before


@pytest.mark.skipif(not _can_raise(), reason="this process may not take a real-time priority")
def test_the_gate_closer_runs_at_the_scans_priority_when_the_scan_got_it() -> None:
    engine = ScanEngine(RealClock(), TagDB(), 0.01)
    engine.realtime = RealtimePriority(20)
    engine.stats.realtime_priority = 20  # what run() sets once its thread was raised
    seen: list[tuple[int, int]] = []
    real_enter = RealtimePriority.enter

    def spy(self: RealtimePriority) -> bool:
        ok = real_enter(self)
        seen.append((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority))
        return ok

    closer = GateCloser(engine, ScanGate())
    RealtimePriority.enter = spy  # type: ignore[method-assign]
    try:
        closer.start()
        for _ in range(200):
            if seen:
                break
            threading.Event().wait(0.01)
    finally:
        RealtimePriority.enter = real_enter  # type: ignore[method-assign]
        closer.stop()
    assert seen == [(os.SCHED_FIFO, 20)]


async def test_a_refused_priority_is_one_warning_saying_what_grants_it_and_the_scan_runs_anyway(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def refuse(_pid: int, _policy: int, _param: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    engine = ScanEngine(RealClock(), TagDB(), 0.01)
    engine.realtime = RealtimePriority(20, setscheduler=refuse)
    seen: list[tuple[int, int, int]] = []
    _seen_by_the_scan(engine, seen)

    with caplog.at_level(logging.WARNING, logger="supervisor.core.realtime"):
        await engine.run(asyncio.Event(), max_scans=3)

    assert len(seen) == 3
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "scan: real-time priority 20 refused" in warnings[0]
    assert "Operation not permitted" in warnings[0]
    assert "runs at normal priority" in warnings[0]
    assert GRANT_HINT in warnings[0]
    assert engine.stats.realtime_priority is None
    assert engine.stats.realtime_refused is not None
    assert "Operation not permitted" in engine.stats.realtime_refused


async def test_a_virtual_clock_never_asks_for_a_real_time_priority() -> None:
    asked: list[int] = []

    def record(_pid: int, policy: int, _param: object) -> None:
        asked.append(policy)

    engine = ScanEngine(VirtualClock(), TagDB(), 0.01)
    engine.realtime = RealtimePriority(20, setscheduler=record)
    await engine.run(asyncio.Event(), max_scans=3)
    assert asked == []
    assert engine.stats.count == 3


def test_a_priority_outside_1_to_99_is_refused_with_its_place_in_the_io_map() -> None:
    text = "bench: b\nscan:\n  period_s: 0.01\n  realtime_priority: 100\n"
    with pytest.raises(ConfigErrors) as err:
        REGISTRY.load_bench_text(text, "bench.yaml")
    message = str(err.value)
    assert "bench.yaml:4" in message
    assert "realtime_priority" in message
