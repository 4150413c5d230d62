"""BMS driver against the BMS simulator: python-can ``virtual`` bus in one process, and the
socketcand server with python-can's own socketcand client over 127.0.0.1."""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
from collections.abc import AsyncIterator, Callable, Iterator

import can
import pytest

from supervisor.core.clock import Clock, RealClock, VirtualClock
from supervisor.core.quality import Quality, Reason
from supervisor.devices import base
from supervisor.devices.bms.driver import (
    FAULT_CURRENT,
    FAULT_PACK_VOLTAGE,
    FAULT_REFUSED,
    FAULT_TEMPERATURE,
    POINTS,
    BmsDriver,
    socketcand_bus_factory,
)
from supervisor.devices.bms.protocol import BmsValues
from supervisor.devices.bms.sim import BmsSimulator, SocketcandServer

pytestmark = pytest.mark.integration

VALUES = BmsValues(
    pack_voltage_v=13.104,
    min_cell_v=3.271,
    max_cell_v=3.285,
    pack_current_a=-2.5,  # discharging
    min_temp_c=-1.5,
    max_temp_c=24.0,
    avg_temp_c=-0.7,
)
EXPECTED = {
    "pack_voltage": 13.104,
    "min_cell_voltage": 3.271,
    "max_cell_voltage": 3.285,
    "pack_current": -2.5,
    "min_temp": -1.5,
    "max_temp": 24.0,
    "avg_temp": -0.7,
}
MAX_POLLS = 500
"""Bound of every wait loop (each poll is followed by a short real sleep)."""

_channels = itertools.count()


async def poll_until(driver: BmsDriver, done: Callable[[], bool]) -> None:
    for _ in range(MAX_POLLS):
        await driver.poll()
        if done():
            return
        await asyncio.sleep(0.02)
    pytest.fail(f"condition not reached; image: {dict(driver.image())}")


def all_good(driver: BmsDriver) -> bool:
    return all(s.quality is Quality.GOOD for s in driver.image().values())


def values_of(driver: BmsDriver) -> dict[str, object]:
    return {name: driver.image()[name].value for name in EXPECTED}


@pytest.fixture
def channel(request: pytest.FixtureRequest) -> str:
    return f"bms-{request.node.name}-{next(_channels)}"


@pytest.fixture
def sim_bus(channel: str) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


@pytest.fixture
async def sim(sim_bus: can.BusABC) -> AsyncIterator[BmsSimulator]:
    """Simulator on real time, not started (start it once the driver listens)."""
    simulator = BmsSimulator(sim_bus, RealClock(), lambda: VALUES)
    yield simulator
    await simulator.stop()


def make_driver(channel: str, clock: Clock, silence_timeout_s: float | None = None) -> BmsDriver:
    return BmsDriver(
        "bms",
        clock,
        lambda: can.Bus(interface="virtual", channel=channel),
        silence_timeout_s=silence_timeout_s,
    )


@pytest.fixture
async def driver(channel: str) -> AsyncIterator[BmsDriver]:
    drv = make_driver(channel, RealClock())
    yield drv
    await drv.close()


@pytest.fixture
async def virtual_clock_driver(channel: str) -> AsyncIterator[tuple[BmsDriver, VirtualClock]]:
    clock = VirtualClock()
    drv = make_driver(channel, clock, silence_timeout_s=math.inf)
    yield drv, clock
    await drv.close()


async def test_driver_exposes_the_bms_points() -> None:
    assert set(POINTS) == {*EXPECTED, "frames_unknown", "frames_bad", "faults"}
    assert all(p.direction == "in" for p in POINTS.values())
    assert POINTS["pack_current"].unit == "A"
    assert POINTS["frames_bad"].dtype == "int"


async def test_driver_sees_the_simulator_values(driver: BmsDriver, sim: BmsSimulator) -> None:
    await driver.poll()
    assert driver.connected
    await sim.start()
    await poll_until(driver, lambda: all_good(driver))
    assert values_of(driver) == pytest.approx(EXPECTED)
    assert driver.image()["frames_unknown"].value == 0
    assert driver.image()["frames_bad"].value == 0


async def test_a_value_carries_the_arrival_time_of_its_frame(
    virtual_clock_driver: tuple[BmsDriver, VirtualClock], sim: BmsSimulator
) -> None:
    driver, clock = virtual_clock_driver
    clock.advance(7.0)
    await driver.poll()
    await sim.start()
    await poll_until(driver, lambda: all_good(driver))
    clock.advance(0.05)
    await driver.poll()
    assert driver.image()["pack_voltage"].t == 7.0
    assert driver.image()["frames_bad"].t == 7.05


async def test_short_frames_are_counted_as_bad_and_leave_the_value(
    driver: BmsDriver, sim: BmsSimulator
) -> None:
    await driver.poll()
    await sim.start()
    await poll_until(driver, lambda: all_good(driver))
    sim.send_raw(0x2B0, bytes.fromhex("42C800"))  # short
    sim.send_raw(0x1B0, b"")
    await poll_until(driver, lambda: driver.image()["frames_bad"].value == 2)
    assert driver.image()["pack_current"].value == pytest.approx(-2.5)
    assert driver.image()["frames_unknown"].value == 0
    assert any("42c800" in line.replace(" ", "") for line in driver.raw_log)


async def test_unknown_ids_are_counted_not_fatal(driver: BmsDriver, sim: BmsSimulator) -> None:
    await driver.poll()
    await sim.start()
    sim.send_raw(0x123, b"\x01\x02")
    sim.send_raw(0x1B0, bytes(8), extended=True)  # same number, extended: not a DBC frame
    await poll_until(
        driver, lambda: all_good(driver) and driver.image()["frames_unknown"].value == 2
    )
    assert driver.connected
    assert driver.image()["frames_bad"].value == 0
    assert values_of(driver) == pytest.approx(EXPECTED)


async def test_pausing_the_simulator_makes_each_value_stale_after_its_own_period(
    virtual_clock_driver: tuple[BmsDriver, VirtualClock], sim: BmsSimulator
) -> None:
    driver, clock = virtual_clock_driver
    await driver.poll()
    await sim.start()
    await poll_until(driver, lambda: all_good(driver))
    sim.paused = True
    await driver.poll()  # drain what was sent before the pause

    clock.advance(0.5)  # > 3 × 100 ms, < 3 × 1000 ms
    await driver.poll()
    image = driver.image()
    assert (image["pack_current"].quality, image["pack_current"].reason) == (
        Quality.BAD,
        Reason.STALE,
    )
    assert image["pack_current"].value == pytest.approx(-2.5)  # kept for diagnostics
    assert image["pack_voltage"].quality is Quality.GOOD
    assert image["avg_temp"].quality is Quality.GOOD

    clock.advance(3.0)
    await driver.poll()
    for name in EXPECTED:
        assert (driver.image()[name].quality, driver.image()[name].reason) == (
            Quality.BAD,
            Reason.STALE,
        ), name
    assert driver.connected  # stale, not a lost link (silence timeout disabled here)

    sim.paused = False
    await poll_until(driver, lambda: all_good(driver))


async def test_a_silent_bus_is_a_lost_link_and_is_reopened(
    channel: str, sim: BmsSimulator, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(base, "BACKOFF_START_S", 0.05)
    clock = VirtualClock()
    driver = make_driver(channel, clock)  # default silence timeout: 3 × 1 s
    try:
        await driver.poll()
        await sim.start()
        await poll_until(driver, lambda: all_good(driver))
        sim.paused = True
        await driver.poll()
        clock.advance(3.5)
        await driver.poll()
        assert not driver.connected
        for name in EXPECTED:
            assert driver.image()[name].reason is Reason.COMM_FAILURE, name

        sim.paused = False
        clock.advance(0.1)  # past the backoff
        for _ in range(MAX_POLLS):
            clock.advance(0.01)
            await driver.poll()
            if all_good(driver):
                break
            await asyncio.sleep(0.02)
        assert all_good(driver)
        assert driver.connected
    finally:
        await driver.close()


async def test_write_is_refused_the_bms_has_no_outputs(driver: BmsDriver) -> None:
    with pytest.raises(KeyError):
        driver.write("pack_current", 1.0)


# --- the seed's frames (annex IV): padded to 8 bytes, plausibility --------------------------

ANNEX_IV = {  # seed 002 annex IV, verbatim (8 bytes each)
    0x1B0: "00 C3 50 A0 03 00 05 F0",  # 12 800.16 V, cells 0.768 / 1.52 V
    0x2B0: "00 00 00 64 00 00 00 00",  # float32 bits 0x64: 1.4e-43 A
    0x3B0: "00 64 00 32 00 19 00 00",  # min 10.0 > max 5.0 degC, avg 2.5
}
PLAUSIBLE = {  # the same layout, a 4S pack at rest, padded to 8 bytes as a controller does
    0x1B0: "00 00 39 D0 0E 6A 0E 7E",  # 14.8 V, cells 3.69 / 3.71 V
    0x2B0: "C0 A0 00 00 00 00 00 00",  # -5.0 A
    0x3B0: "FF F1 00 F0 00 C8 00 00",  # -1.5 / 24.0 / 20.0 degC
}


def send_frames(sim: BmsSimulator, frames: dict[int, str]) -> None:
    for frame_id, text in frames.items():
        sim.send_raw(frame_id, bytes.fromhex(text))


def image_of(driver: BmsDriver) -> dict[str, tuple[object, Quality, Reason]]:
    return {n: (s.value, s.quality, s.reason) for n, s in driver.image().items()}


async def test_the_annex_iv_frames_padded_to_8_bytes_decode_and_the_implausible_are_bad(
    virtual_clock_driver: tuple[BmsDriver, VirtualClock],
    sim: BmsSimulator,
    caplog: pytest.LogCaptureFixture,
) -> None:
    driver, _ = virtual_clock_driver
    await driver.poll()
    for _ in range(5):  # five rounds of the same frames: one warning per point, not five
        send_frames(sim, ANNEX_IV)
        await poll_until(driver, lambda: driver.image()["pack_voltage"].value is not None)
    await poll_until(driver, lambda: driver.image()["avg_temp"].value is not None)
    image = driver.image()
    bad = (Quality.BAD, Reason.OUT_OF_RANGE)
    assert image["pack_voltage"].value == pytest.approx(12800.16)
    assert (image["pack_voltage"].quality, image["pack_voltage"].reason) == bad
    assert image["pack_current"].value == pytest.approx(1.4e-43, rel=0.01)
    assert (image["pack_current"].quality, image["pack_current"].reason) == bad
    for name in ("min_temp", "max_temp", "avg_temp"):
        assert (image[name].quality, image[name].reason) == bad, name
    # The cells, 0.768 V and 1.52 V, break no rule of theirs.
    assert image["min_cell_voltage"].value == pytest.approx(0.768)
    assert image["min_cell_voltage"].quality is Quality.GOOD
    assert image["max_cell_voltage"].quality is Quality.GOOD
    assert image["frames_bad"].value == 0  # 8 bytes each: decoded, none refused
    assert image["faults"].value == FAULT_PACK_VOLTAGE | FAULT_CURRENT | FAULT_TEMPERATURE
    warnings = [r.getMessage() for r in caplog.records if "implausible" in r.getMessage()]
    assert len(warnings) == 5  # pack voltage, current, three temperatures: once each
    assert any("12800.16 V outside [0, 1000]" in w for w in warnings)


async def test_a_plausible_sample_padded_to_8_bytes_is_good_and_ends_the_episode(
    virtual_clock_driver: tuple[BmsDriver, VirtualClock],
    sim: BmsSimulator,
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="supervisor.devices.bms.driver")
    driver, _ = virtual_clock_driver
    await driver.poll()
    send_frames(sim, ANNEX_IV)
    await poll_until(driver, lambda: driver.image()["faults"].value != 0)
    send_frames(sim, PLAUSIBLE)
    await poll_until(driver, lambda: all_good(driver) and driver.image()["faults"].value == 0)
    assert {n: driver.image()[n].value for n in EXPECTED} == pytest.approx(
        {
            "pack_voltage": 14.8,
            "min_cell_voltage": 3.69,
            "max_cell_voltage": 3.71,
            "pack_current": -5.0,
            "min_temp": -1.5,
            "max_temp": 24.0,
            "avg_temp": 20.0,
        }
    )
    assert sum("plausible again" in r.getMessage() for r in caplog.records) == 5


async def test_padded_frames_refused_when_extra_bytes_are_not_allowed_are_logged_once(
    channel: str, sim: BmsSimulator, caplog: pytest.LogCaptureFixture
) -> None:
    driver = BmsDriver(
        "bms",
        VirtualClock(),
        lambda: can.Bus(interface="virtual", channel=channel),
        silence_timeout_s=math.inf,
        allow_extra_bytes=False,
    )
    try:
        await driver.poll()
        for _ in range(3):
            send_frames(sim, PLAUSIBLE)
        # 0x1B0 is 8 bytes in the DBC: only 0x2B0 and 0x3B0 are refused.
        await poll_until(driver, lambda: driver.image()["frames_bad"].value == 6)
        assert driver.image()["pack_current"].value is None
        assert driver.image()["faults"].value & FAULT_REFUSED
        refused = [r for r in caplog.records if "bad frame" in r.getMessage()]
        assert len(refused) == 2  # once per identifier
        assert "PackCurrent (0x2B0) has 8 bytes, DBC says 4" in refused[0].getMessage()
    finally:
        await driver.close()


# --- socketcand ---------------------------------------------------------------------------


@pytest.fixture
async def socketcand_server() -> AsyncIterator[SocketcandServer]:
    server = SocketcandServer("127.0.0.1", 0)
    await server.start()
    yield server
    await server.stop()
    server.bus.shutdown()


async def test_socketcand_values_arrive_survive_a_server_restart(
    socketcand_server: SocketcandServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(base, "BACKOFF_START_S", 0.05)
    server = socketcand_server
    simulator = BmsSimulator(server.bus, RealClock(), lambda: VALUES)
    driver = BmsDriver(
        "bms",
        RealClock(),
        socketcand_bus_factory("127.0.0.1", server.port),
        silence_timeout_s=0.5,
    )
    try:
        await simulator.start()
        await poll_until(driver, lambda: all_good(driver))
        assert values_of(driver) == pytest.approx(EXPECTED)

        port = server.port
        await server.stop()
        await poll_until(
            driver, lambda: driver.image()["pack_voltage"].reason is Reason.COMM_FAILURE
        )
        assert all(s.quality is Quality.BAD for s in driver.image().values())

        await server.start()
        assert server.port == port
        await poll_until(driver, lambda: all_good(driver))
        assert values_of(driver) == pytest.approx(EXPECTED)
    finally:
        await driver.close()
        await simulator.stop()


async def test_socketcand_client_frames_reach_the_server_bus(
    socketcand_server: SocketcandServer,
) -> None:
    client = await asyncio.to_thread(socketcand_bus_factory("127.0.0.1", socketcand_server.port))
    try:
        client.send(
            can.Message(arbitration_id=0x2B0, data=bytes.fromhex("42C80000"), is_extended_id=False)
        )
        msg = None
        for _ in range(MAX_POLLS):
            msg = socketcand_server.bus.recv(timeout=0)
            if msg is not None:
                break
            await asyncio.sleep(0.01)
        assert msg is not None
        assert (msg.arbitration_id, bytes(msg.data), msg.is_extended_id) == (
            0x2B0,
            bytes.fromhex("42C80000"),
            False,
        )
    finally:
        client.shutdown()
