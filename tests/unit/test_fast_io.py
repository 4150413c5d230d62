"""Safety-relevant I/O is fast (DESIGN.md "Safety"): output writes leave when the scan queues
them, and the slot holding the e-stop sense is read at the scan rate while the thermocouples
stay slow.

- A write wakes the driver's own task, which sends it at once under the same I/O lock as its
  polls, without reading the inputs; on a virtual clock the engine sends it right after the
  scan that queued it. The latest value per point wins; a relay write is still verified by
  its read-back (which is published at once).
- An ADAM slot can have its own poll period; the driver polls at the fastest and reads only
  the slots that are due; every sample keeps its own acquisition time (stale per slot).
- End to end on virtual time: an e-stop press reaches the supply and the contactor within
  two 10 ms scans (it took up to two 200 ms ADAM polls).
"""

from __future__ import annotations

import asyncio

import pytest

from supervisor.core.clock import Clock, RealClock, VirtualClock
from supervisor.core.driver import Sample, Value
from supervisor.core.errors import DeviceIOError
from supervisor.core.quality import Quality, Reason
from supervisor.scan import LogicPhase, OutputBinding, ScanEngine
from supervisor.tags import TagDB, TagSpec
from supervisor.testing import RecordingDriver, wait_until


class TimedDriver(RecordingDriver):
    """Records the clock with every write; ``gate`` (when set) holds every read until the
    test opens it, and ``reads`` counts the reads that got through."""

    def __init__(self, clock: Clock, poll_period_s: float = 0.1) -> None:
        super().__init__("dev", clock, {"ai0": 1.0}, ["ao0", "ao1"], poll_period_s)
        self.timed_writes: list[tuple[float, str, Value]] = []
        self.gate: asyncio.Event | None = None
        self.reads = 0
        self.fail_writes = False

    async def _read(self) -> dict[str, Sample]:
        if self.gate is not None:
            await self.gate.wait()
        self.reads += 1
        return await super()._read()

    async def _write(self, point: str, value: Value) -> None:
        if self.fail_writes:
            raise DeviceIOError(self.name, f"{point}: write did not verify")
        self.timed_writes.append((self.clock.now(), point, value))
        await super()._write(point, value)


# --- PolledDriver: writes leave when they are queued ----------------------------------------------
async def test_a_write_is_sent_by_the_drivers_task_without_waiting_for_its_next_poll() -> None:
    # Real clock: the driver's own task sleeps until its next poll, an hour away; only the
    # wake-up from write() can get the value out (the bound is a hang detector, no timing).
    driver = TimedDriver(RealClock(), poll_period_s=3600.0)
    task = asyncio.create_task(driver.run())
    try:
        await wait_until(lambda: driver.polls == 1, "the first poll")
        driver.write("ao0", 2.5)
        await wait_until(lambda: driver.writes == [("ao0", 2.5)], "the write sent")
        assert (driver.polls, driver.reads) == (1, 1)  # sent without reading the inputs
        driver.write("ao1", True)
        await wait_until(lambda: ("ao1", True) in driver.writes, "a second write sent")
        assert driver.polls == 1
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_a_flush_waits_for_the_poll_in_progress_under_the_same_lock() -> None:
    driver = TimedDriver(VirtualClock())
    await driver.poll()
    driver.gate = asyncio.Event()
    polling = asyncio.create_task(driver.poll())  # stuck in its read
    await asyncio.sleep(0)
    driver.write("ao0", 1.0)
    flushing = asyncio.create_task(driver.flush())
    for _ in range(5):
        await asyncio.sleep(0)
    assert driver.writes == []  # the poll holds the I/O lock: nothing interleaves with it
    driver.gate.set()
    await asyncio.gather(polling, flushing)
    assert driver.writes == [("ao0", 1.0)]
    assert driver.reads == 2


async def test_the_latest_value_per_point_wins() -> None:
    driver = TimedDriver(VirtualClock())
    await driver.poll()
    driver.write("ao0", 1.0)
    driver.write("ao1", False)
    driver.write("ao0", 3.0)
    assert dict(driver.pending) == {"ao0": 3.0, "ao1": False}
    await driver.flush()
    assert driver.writes == [("ao0", 3.0), ("ao1", False)]
    assert driver.pending == {}
    await driver.flush()  # nothing queued: nothing sent
    assert len(driver.writes) == 2


async def test_a_flush_while_the_device_is_lost_keeps_the_writes_for_the_reconnect() -> None:
    driver = TimedDriver(VirtualClock())
    driver.fail = True
    await driver.poll()
    assert not driver.connected
    driver.write("ao0", 1.0)
    await driver.flush()  # not connected: connecting is the poll's job, with its backoff
    assert driver.writes == []
    assert dict(driver.pending) == {"ao0": 1.0}
    driver.fail = False
    driver._next_connect_t = float("-inf")
    await driver.poll()
    assert driver.writes == [("ao0", 1.0)]


async def test_a_write_that_fails_in_a_flush_is_a_failed_poll() -> None:
    driver = TimedDriver(VirtualClock())
    await driver.poll()
    driver.fail_writes = True
    driver.write("ao0", 1.0)
    await driver.flush()
    assert not driver.connected
    assert "did not verify" in driver.last_error
    sample = driver.image()["ai0"]
    assert (sample.quality, sample.reason) == (Quality.BAD, Reason.COMM_FAILURE)


async def test_on_a_virtual_clock_the_engine_sends_writes_right_after_the_scan() -> None:
    clock = VirtualClock()
    db = TagDB()
    driver = TimedDriver(clock, poll_period_s=1.0)  # polled at 0 s and 1 s only
    out = db.add(TagSpec("out", unit="A"))

    def request(now: float, dt: float) -> None:
        if now == pytest.approx(0.2):
            db.update(out, 4.0)

    engine = ScanEngine(
        clock,
        db,
        0.1,
        [driver],
        outputs=[OutputBinding(out, driver, "ao0")],
        phases=[LogicPhase("request", request)],
    )
    await engine.run_for(0.5)
    assert driver.timed_writes == [(pytest.approx(0.2), "ao0", 4.0)]  # the scan's instant
    assert driver.reads == 1  # no poll was added to send it
