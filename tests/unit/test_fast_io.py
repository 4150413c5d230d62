"""Safety-relevant I/O is fast (docs/design.md "Safety"): output writes leave when the scan queues
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
import logging
from collections.abc import AsyncIterator, Mapping
from pathlib import Path
from typing import Any

import pytest
import yaml
from adam_rig import AdamRig, open_rig, reconnect_on_every_poll
from rig_transports import IN_PROCESS

from supervisor.app import Bench, build_bench
from supervisor.config.models import BenchConfig
from supervisor.core.clock import Clock, RealClock, VirtualClock
from supervisor.core.driver import Sample, Value
from supervisor.core.errors import ConfigErrors, DeviceIOError
from supervisor.core.quality import Quality, Reason
from supervisor.devices.adam.config import AdamDevice
from supervisor.devices.adam.driver import AdamDriver, AdamModule
from supervisor.devices.adam.transport import InProcessLink
from supervisor.devices.adam.unit import AdamUnit
from supervisor.devices.registry import bench_from_data
from supervisor.scan import InputBinding, LogicPhase, OutputBinding, ScanEngine
from supervisor.tags import TagDB, TagSpec
from supervisor.testing import RecordingDriver, wait_until

ROOT = Path(__file__).resolve().parents[2]


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


# --- the ADAM relay: verified, its read-back published at once -----------------------------------
@pytest.fixture
async def adam(
    virtual_clock: VirtualClock, monkeypatch: pytest.MonkeyPatch
) -> AsyncIterator[AdamRig]:
    reconnect_on_every_poll(monkeypatch)
    async with open_rig(IN_PROCESS, virtual_clock) as rig:
        await rig.driver.poll()
        yield rig


async def test_an_adam_relay_write_is_verified_and_its_read_back_published_at_once(
    adam: AdamRig, virtual_clock: VirtualClock
) -> None:
    virtual_clock.advance(0.05)
    polls = adam.driver.polls
    adam.driver.write("slot3.do0", True)
    await adam.driver.flush()
    assert adam.unit.relay_state(3, 0) is True
    assert adam.relay_calls == {(3, 0): [True]}
    fb = adam.driver.image()["slot3.do0_fb"]
    assert (fb.value, fb.quality, fb.t) == (True, Quality.GOOD, pytest.approx(0.05))
    assert adam.driver.polls == polls  # no input read


async def test_an_adam_relay_that_does_not_follow_fails_the_flush(adam: AdamRig) -> None:
    adam.unit.stick_relay(3, 0, False)
    adam.driver.write("slot3.do0", True)
    await adam.driver.flush()
    assert "did not verify" in adam.driver.last_error
    assert not adam.driver.connected
    assert adam.driver.image()["slot3.do0_fb"].quality is Quality.BAD


# --- ADAM slots at their own period ------------------------------------------------------------
def fast_and_slow(clock: VirtualClock) -> tuple[AdamUnit, AdamDriver]:
    """Seed 002 layout: slot 0 (5017: the e-stop sense) and slot 3 (relays) every 10 ms,
    the thermocouple slots at the driver's default 0.2 s."""
    modules = {0: "5017", 1: "5018", 2: "5018", 3: "5060"}
    analog = {(s, ch): (lambda: 20.0) for s in (1, 2) for ch in range(7)}
    unit = AdamUnit(modules, analog)
    link = InProcessLink("adam", clock, unit, timeout_s=0.5)
    driver = AdamDriver(
        "adam",
        clock,
        link,
        {
            0: AdamModule("5017", poll_period_s=0.01),
            1: AdamModule("5018"),
            2: AdamModule("5018"),
            3: AdamModule("5060", poll_period_s=0.01),
        },
        poll_period_s=0.2,
    )
    return unit, driver


async def poll_for(driver: AdamDriver, clock: VirtualClock, duration_s: float) -> None:
    """Poll at the driver's own period for ``duration_s`` of virtual time."""
    for _ in range(round(duration_s / driver.poll_period_s)):
        clock.advance(driver.poll_period_s)
        await driver.poll()


async def test_the_driver_polls_at_its_fastest_slot_and_reads_each_slot_when_due(
    virtual_clock: VirtualClock,
) -> None:
    unit, driver = fast_and_slow(virtual_clock)
    await unit.start()
    assert driver.poll_period_s == 0.01
    assert [driver.slot_period_s(s) for s in (0, 1, 2, 3)] == [0.01, 0.2, 0.2, 0.01]
    await driver.poll()  # t = 0: everything is read after a connect
    await poll_for(driver, virtual_clock, 0.15)
    img = driver.image()
    # The fast slots were read at the last poll, the thermocouples at t = 0 only.
    assert img["slot0.ai2"].t == pytest.approx(0.15)
    assert img["slot3.do0_fb"].t == pytest.approx(0.15)
    assert img["slot1.tc0"].t == 0.0 and img["slot2.tc6"].t == 0.0
    await poll_for(driver, virtual_clock, 0.06)  # past 0.2 s: the thermocouples are due
    img = driver.image()
    assert img["slot1.tc0"].t == pytest.approx(0.2) and img["slot2.tc0"].t == pytest.approx(0.2)
    assert img["slot0.ai2"].t == pytest.approx(0.21)
    await driver.close()


async def test_stale_detection_works_per_slot(virtual_clock: VirtualClock) -> None:
    """A tag on a slow slot goes stale on that slot's own acquisition time, although the
    driver itself answers every 10 ms."""
    unit, driver = fast_and_slow(virtual_clock)
    await unit.start()
    db = TagDB()
    sense = db.add(TagSpec("estop.ok", unit="V"))
    temp = db.add(TagSpec("pack.temp", unit="degC"))
    engine = ScanEngine(
        virtual_clock,
        db,
        0.01,
        [driver],
        inputs=[
            InputBinding(sense, driver, "slot0.ai2", None, 0.05),
            InputBinding(temp, driver, "slot1.tc0", None, 0.05),  # read every 0.2 s
        ],
    )
    await engine.run_for(0.1)
    assert sense.good
    assert temp.quality is Quality.BAD and temp.reason is Reason.STALE
    await driver.close()


def test_a_5017_read_faster_than_it_converts_warns_only_when_not_chosen_for_its_slot(
    caplog: pytest.LogCaptureFixture,
) -> None:
    link = InProcessLink("adam", VirtualClock(), AdamUnit({0: "5017"}))
    with caplog.at_level(logging.INFO, logger="supervisor.devices.adam.driver"):
        AdamDriver("adam", VirtualClock(), link, {0: AdamModule("5017", poll_period_s=0.01)})
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("on purpose" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="supervisor.devices.adam.driver"):
        AdamDriver("adam", VirtualClock(), link, {0: AdamModule("5017")}, poll_period_s=0.01)
    assert any("values repeat" in r.getMessage() for r in caplog.records)


def test_a_module_refuses_a_poll_period_that_is_not_a_positive_number() -> None:
    for bad in (0.0, -1.0, float("nan"), True):
        with pytest.raises(ValueError, match="poll_period_s"):
            AdamModule("5017", poll_period_s=bad)  # type: ignore[arg-type]


def adam_entry(**changes: Any) -> dict[str, Any]:
    entry: dict[str, Any] = {
        "driver": "adam5000tcp",
        "host": "192.168.0.10",
        "poll_period_s": 0.2,
        "modules": {0: {"kind": "5017", "poll_period_s": 0.01}, 1: {"kind": "5018"}},
    }
    entry.update(changes)
    return entry


def bench_with(adam_device: Mapping[str, Any]) -> BenchConfig:
    return bench_from_data({"bench": "fast", "devices": {"adam": dict(adam_device)}})


def test_an_io_map_gives_a_slot_its_own_poll_period() -> None:
    dev = bench_with(adam_entry()).devices["adam"]
    assert isinstance(dev, AdamDevice)
    assert (dev.slot_period_s(0), dev.slot_period_s(1), dev.fastest_period_s) == (0.01, 0.2, 0.01)


def test_an_io_map_refuses_a_slot_read_no_faster_than_it_goes_stale() -> None:
    modules = {0: {"kind": "5017"}, 1: {"kind": "5018", "poll_period_s": 2.0}}
    with pytest.raises(ConfigErrors, match=r"slot 1 is read every 2 s.*stale_after_s \(1 s\)"):
        bench_with(adam_entry(modules=modules))


# --- end to end on virtual time: the e-stop press at a 10 ms scan --------------------------------
def seed002_in_process(period_s: float) -> BenchConfig:
    """sim.yaml's ADAM + EA and the EA channel (no BMS, no Chadèche stack)."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["devices"] = {k: data["devices"][k] for k in ("adam", "ea", "bms")}
    data["tags"] = [t for t in data["tags"] if t["device"] in ("adam", "ea", "bms")]
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    data["scan"] = {"period_s": period_s}
    return bench_from_data(data)


@pytest.fixture
async def charging(virtual_clock: VirtualClock) -> AsyncIterator[Bench]:
    bench = build_bench(seed002_in_process(0.01), virtual_clock, in_process=True)
    await bench.start()
    try:
        bench.db.write("ch4.manual_current", 2.0)
        bench.db.write("ch4.enable", True)
        await bench.engine.run_for(1.0)
        assert bench.sim is not None
        plant = bench.sim.plant
        assert plant.contactor_closed and plant.supply.output_on
        assert plant.pack_current_a == pytest.approx(2.0, abs=0.01)
        yield bench
    finally:
        await bench.shutdown()


async def test_an_estop_press_opens_the_contactor_and_kills_the_supply_within_two_scans(
    charging: Bench,
) -> None:
    assert charging.sim is not None
    plant = charging.sim.plant
    charging.sim.press_estop(True)  # between two scans, as PUT /api/sim/estop does
    await charging.engine.run_for(2 * 0.01)
    assert charging.db["ch4.output_cmd"].value is False
    assert not plant.supply.output_on
    assert not plant.contactor_closed
    assert plant.pack_current_a == 0.0
