"""``ScanFirstLoop``: the scan's event loop runs a scan that falls due before its next
callback, not after every callback ready in the same turn (which an event loop runs
before any timer, the engine's wake-up included: issue 13's start jitter)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from supervisor.core.clock import RealClock
from supervisor.scan.engine import LogicPhase, ScanEngine, ScanFirstLoop
from supervisor.tags import TagDB

BUSY_S = 0.004
"""Each callback of the burst holds the loop this long: ten of them span several
deadlines of a 10 ms scan."""


def _busy() -> None:
    end = time.monotonic() + BUSY_S
    while time.monotonic() < end:
        pass


async def _burst_then_stop(
    engine: ScanEngine, events: list[str], stop: asyncio.Event, n: int = 10
) -> None:
    loop = asyncio.get_running_loop()
    await asyncio.sleep(0.05)  # a few scans first

    def one(i: int) -> Callable[[], None]:
        def run() -> None:
            events.append(f"cb{i}")
            _busy()

        return run

    def schedule() -> None:
        for i in range(n):  # all ready in the same turn of the loop
            loop.call_soon(one(i))

    loop.call_soon(schedule)
    await asyncio.sleep(0.1)
    stop.set()


def _run_on(loop_factory: Callable[[], asyncio.AbstractEventLoop]) -> tuple[list[str], list[float]]:
    events: list[str] = []
    deadlines: list[float] = []
    engine: ScanEngine

    def look(now: float, dt: float) -> None:
        events.append("scan")
        if engine.next_deadline is not None:
            deadlines.append(engine.next_deadline)

    engine = ScanEngine(RealClock(), TagDB(), 0.01, phases=[LogicPhase("look", look)])

    async def main() -> None:
        stop = asyncio.Event()
        await asyncio.gather(engine.run(stop), _burst_then_stop(engine, events, stop))

    with asyncio.Runner(loop_factory=loop_factory) as runner:
        runner.run(main())
    return events, deadlines


def _burst(events: list[str]) -> list[str]:
    first = events.index("cb0")
    last = events.index("cb9")
    return events[first : last + 1]


def test_a_scan_falling_due_runs_between_two_callbacks_ready_in_the_same_turn() -> None:
    events, _ = _run_on(ScanFirstLoop)
    assert "scan" in _burst(events)


def test_on_a_plain_loop_the_same_burst_runs_to_its_end_before_the_scan() -> None:
    # What the loop above changes: the engine's wake-up is a timer, after the ready ones.
    events, _ = _run_on(asyncio.SelectorEventLoop)
    assert "scan" not in _burst(events)


def test_the_loop_and_the_engine_never_run_the_scan_of_one_deadline_twice() -> None:
    _, deadlines = _run_on(ScanFirstLoop)
    # Each scan after the first was the one of the deadline set after the scan before it.
    assert len(deadlines) >= 10
    assert deadlines == sorted(set(deadlines))
