"""On a real clock a driver's poll starts when a scan is done (``PolledDriver.scan_sync``,
``ScanEngine.after_next_scan``): its work on the scan's event loop comes in the period's
first milliseconds, never at the moment the loop should wake for the next deadline (the
ADAM's poll callbacks took 1.5–13 ms on the loaded machine of issue 13)."""

from __future__ import annotations

import asyncio
from collections.abc import Mapping

from supervisor.core.clock import RealClock
from supervisor.core.driver import PointInfo, Sample
from supervisor.devices.base import PolledDriver
from supervisor.scan.engine import LogicPhase, ScanEngine
from supervisor.tags import TagDB

POINTS: Mapping[str, PointInfo] = {"x": PointInfo("x", "in", unit="V")}


class Recorded(PolledDriver):
    def __init__(self, clock: RealClock, events: list[str], period_s: float) -> None:
        super().__init__("dev", clock, period_s)
        self.events = events

    def points(self) -> Mapping[str, PointInfo]:
        return POINTS

    async def _connect(self) -> None:
        return None

    async def _read(self) -> dict[str, Sample]:
        self.events.append("poll")
        return {"x": Sample(1.0, t=self.clock.now())}

    async def _write(self, point: str, value: object) -> None:
        return None

    async def _safe(self) -> None:
        return None


async def test_every_poll_of_a_driver_starts_right_after_a_scan() -> None:
    events: list[str] = []
    clock = RealClock()
    # Polled at a period that is not the scan's: without the sync its polls would fall
    # anywhere in the scan period.
    driver = Recorded(clock, events, 0.013)
    engine = ScanEngine(
        clock,
        TagDB(),
        0.01,
        drivers=[driver],
        phases=[LogicPhase("look", lambda now, dt: events.append("scan"))],
    )
    after_next_scan = engine.after_next_scan

    async def watched() -> None:
        events.append("waits")
        await after_next_scan()
        events.append("scan done")

    engine.after_next_scan = watched  # type: ignore[method-assign]
    await engine.run(asyncio.Event(), max_scans=40)
    polls = [k for k, e in enumerate(events) if e == "poll"]
    assert len(polls) >= 10
    # The first poll is the engine's own, before the first scan (first images in); each
    # later one waited for a scan to end, then started at once.
    for k in polls[1:]:
        assert events[k - 1] == "scan done"
        last_wait = max(j for j in range(k) if events[j] == "waits")
        assert "scan" in events[last_wait:k]
