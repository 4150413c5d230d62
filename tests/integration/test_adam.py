"""ADAM-5000/TCP driver against the pymodbus simulator over real sockets on 127.0.0.1."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from dataclasses import dataclass, field

import pytest
from pymodbus.client import AsyncModbusTcpClient

import supervisor.devices.base as base
from supervisor.core.clock import RealClock
from supervisor.core.quality import Quality, Reason
from supervisor.devices.adam.driver import AdamDriver, AdamModule
from supervisor.devices.adam.protocol import lsb
from supervisor.devices.adam.sim import AdamSimulator

pytestmark = pytest.mark.integration

TIMEOUT_S = 0.5

# Seed 002 layout: 5017 (slot 0), two 5018 (slots 1, 2; slot 2 in two's complement), 5060.
MODULES = {0: "5017", 1: "5018", 2: "5018", 3: "5060"}
FORMATS = {2: "twos"}


@dataclass
class Bench:
    sim: AdamSimulator
    driver: AdamDriver
    inputs: dict[tuple[int, int], float | None] = field(default_factory=dict)
    relay_calls: dict[tuple[int, int], list[bool]] = field(default_factory=dict)


def _make_sim(bench_inputs: dict[tuple[int, int], float | None], calls: dict, port: int = 0):
    def source(key: tuple[int, int]):
        return lambda: bench_inputs.get(key)

    def sink(key: tuple[int, int]):
        return lambda state: calls.setdefault(key, []).append(state)

    analog = {
        (slot, ch): source((slot, ch))
        for slot, kind in MODULES.items()
        if kind != "5060"
        for ch in range(8 if kind == "5017" else 7)
    }
    relays = {(3, ch): sink((3, ch)) for ch in range(6)}
    return AdamSimulator(MODULES, analog, relays, raw_format=FORMATS, port=port)


@pytest.fixture
async def bench(monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[Bench]:
    # Reconnect on every poll: the tests drive time by calling poll(), never by sleeping.
    monkeypatch.setattr(base, "BACKOFF_START_S", 0.0)
    monkeypatch.setattr(base, "BACKOFF_MAX_S", 0.0)
    inputs: dict[tuple[int, int], float | None] = {(0, ch): 0.0 for ch in range(8)}
    inputs.update({(slot, ch): 20.0 for slot in (1, 2) for ch in range(7)})
    calls: dict[tuple[int, int], list[bool]] = {}
    sim = _make_sim(inputs, calls)
    await sim.start()
    driver = AdamDriver(
        "adam1",
        RealClock(),
        sim.host,
        sim.port,
        {s: AdamModule(k, FORMATS.get(s, "offset")) for s, k in MODULES.items()},
        timeout_s=TIMEOUT_S,
    )
    try:
        yield Bench(sim, driver, inputs, calls)
    finally:
        await driver.close()
        await sim.stop()


def _inputs_all(driver: AdamDriver, quality: Quality, reason: Reason) -> bool:
    return all(s.quality == quality and s.reason == reason for s in driver.image().values())


def test_points() -> None:
    driver = AdamDriver(
        "adam1",
        RealClock(),
        "127.0.0.1",
        1,
        {0: AdamModule("5017"), 1: AdamModule("5018"), 3: AdamModule("5060")},
    )
    pts = driver.points()
    assert [n for n in pts if n.startswith("slot0.")] == [f"slot0.ai{k}" for k in range(8)]
    assert [n for n in pts if n.startswith("slot1.")] == [f"slot1.tc{k}" for k in range(7)]
    assert pts["slot0.ai3"].unit == "V" and pts["slot0.ai3"].direction == "in"
    assert pts["slot1.tc6"].unit == "degC"
    assert pts["slot3.do5"].direction == "out" and pts["slot3.do5"].dtype == "bool"
    assert pts["slot3.do5_fb"].direction == "in" and pts["slot3.do5_fb"].dtype == "bool"
    assert "slot3.do6" not in pts
    # Before any poll every input is BAD, never connected.
    assert _inputs_all(driver, Quality.BAD, Reason.NOT_CONNECTED)
    with pytest.raises(ValueError):
        driver.write("slot3.do0", 0.5)
    with pytest.raises(KeyError):
        driver.write("slot0.ai0", True)


def test_fast_polling_of_a_5017_warns(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="supervisor.devices.adam.driver"):
        AdamDriver("fast", RealClock(), "127.0.0.1", 1, {0: AdamModule("5018")}, poll_period_s=0.05)
    assert not caplog.records
    with caplog.at_level(logging.WARNING, logger="supervisor.devices.adam.driver"):
        AdamDriver("fast", RealClock(), "127.0.0.1", 1, {0: AdamModule("5017")}, poll_period_s=0.05)
    assert any("fast" in r.getMessage() and "5017" in r.getMessage() for r in caplog.records)


async def test_analog_values_arrive_in_volts_and_degc(bench: Bench) -> None:
    bench.inputs[(0, 2)] = 4.0  # e.g. LEM at +300 A
    bench.inputs[(1, 0)] = 25.0
    bench.inputs[(2, 6)] = -20.5  # two's complement slot
    await bench.driver.poll()
    img = bench.driver.image()
    assert bench.driver.connected
    assert img["slot0.ai2"].quality == Quality.GOOD
    assert img["slot0.ai2"].value == pytest.approx(4.0, abs=lsb("5017"))
    assert img["slot1.tc0"].value == pytest.approx(25.0, abs=lsb("5018"))
    assert img["slot2.tc6"].value == pytest.approx(-20.5, abs=lsb("5018", "twos"))
    assert img["slot3.do0_fb"].value is False
    assert _inputs_all(bench.driver, Quality.GOOD, Reason.NONE)

    # Values are live: sampled again on every read.
    bench.inputs[(0, 2)] = -3.5
    bench.inputs[(1, 0)] = 31.25
    await bench.driver.poll()
    img = bench.driver.image()
    assert img["slot0.ai2"].value == pytest.approx(-3.5, abs=lsb("5017"))
    assert img["slot1.tc0"].value == pytest.approx(31.25, abs=lsb("5018"))


async def test_open_thermocouple_is_bad_sensor_failure(bench: Bench) -> None:
    bench.inputs[(1, 3)] = None
    bench.inputs[(2, 4)] = None
    await bench.driver.poll()
    img = bench.driver.image()
    for point in ("slot1.tc3", "slot2.tc4"):
        assert img[point].value is None
        assert img[point].quality == Quality.BAD
        assert img[point].reason == Reason.SENSOR_FAILURE
    assert img["slot1.tc2"].quality == Quality.GOOD

    bench.inputs[(1, 3)] = 22.0
    await bench.driver.poll()
    assert bench.driver.image()["slot1.tc3"].quality == Quality.GOOD
    assert bench.driver.image()["slot1.tc3"].value == pytest.approx(22.0, abs=lsb("5018"))


async def test_relay_write_calls_callback_and_reads_back(bench: Bench) -> None:
    await bench.driver.poll()
    bench.driver.write("slot3.do2", True)
    await bench.driver.poll()
    assert bench.relay_calls == {(3, 2): [True]}
    assert bench.sim.relay_state(3, 2) is True
    img = bench.driver.image()
    assert img["slot3.do2_fb"].value is True
    assert img["slot3.do2_fb"].quality == Quality.GOOD
    assert img["slot3.do1_fb"].value is False

    bench.driver.write("slot3.do2", False)
    await bench.driver.poll()
    assert bench.relay_calls == {(3, 2): [True, False]}
    assert bench.driver.image()["slot3.do2_fb"].value is False


async def test_relay_that_does_not_follow_is_a_write_fault(bench: Bench) -> None:
    await bench.driver.poll()
    bench.sim.stick_relay(3, 1, False)
    bench.driver.write("slot3.do1", True)
    await bench.driver.poll()
    assert "write did not verify" in bench.driver.last_error
    assert not bench.driver.connected
    assert _inputs_all(bench.driver, Quality.BAD, Reason.COMM_FAILURE)


async def test_modbus_exception_on_one_slot_leaves_the_others_good(bench: Bench) -> None:
    await bench.driver.poll()
    bench.sim.fail_next_reads(1, 0x04, slot=1)
    await bench.driver.poll()
    img = bench.driver.image()
    assert bench.driver.connected
    for point, sample in img.items():
        if point.startswith("slot1."):
            assert (sample.quality, sample.reason) == (Quality.BAD, Reason.DEVICE_ERROR)
        else:
            assert (sample.quality, sample.reason) == (Quality.GOOD, Reason.NONE), point
    assert "0x04" in bench.driver.last_error
    assert any("exception 0x04" in line for line in bench.driver.raw_log)

    await bench.driver.poll()
    assert _inputs_all(bench.driver, Quality.GOOD, Reason.NONE)


async def test_modbus_exception_on_relay_slot(bench: Bench) -> None:
    await bench.driver.poll()
    bench.sim.fail_next_reads(1, 0x02, slot=3)
    await bench.driver.poll()
    img = bench.driver.image()
    assert img["slot3.do0_fb"].reason == Reason.DEVICE_ERROR
    assert img["slot0.ai0"].quality == Quality.GOOD


async def test_short_read_makes_that_slot_bad(bench: Bench) -> None:
    await bench.driver.poll()
    bench.sim.short_next_reads(1, slot=0)
    await bench.driver.poll()
    img = bench.driver.image()
    assert bench.driver.connected
    assert all(
        img[f"slot0.ai{k}"].quality == Quality.BAD
        and img[f"slot0.ai{k}"].reason == Reason.COMM_FAILURE
        for k in range(8)
    )
    assert img["slot1.tc0"].quality == Quality.GOOD
    assert "7 registers back for 8" in bench.driver.last_error

    await bench.driver.poll()
    assert _inputs_all(bench.driver, Quality.GOOD, Reason.NONE)


async def test_lost_simulator_marks_everything_bad_then_recovers(bench: Bench) -> None:
    await bench.driver.poll()
    assert _inputs_all(bench.driver, Quality.GOOD, Reason.NONE)
    port = bench.sim.port

    await bench.sim.stop()
    await bench.driver.poll()
    assert not bench.driver.connected
    assert _inputs_all(bench.driver, Quality.BAD, Reason.COMM_FAILURE)
    # Old values are kept for diagnostics, but never GOOD.
    assert bench.driver.image()["slot1.tc0"].value == pytest.approx(20.0, abs=lsb("5018"))

    await bench.driver.poll()  # reconnect attempt fails: still BAD
    assert _inputs_all(bench.driver, Quality.BAD, Reason.COMM_FAILURE)

    await bench.sim.start()
    assert bench.sim.port == port
    bench.inputs[(0, 0)] = 1.5
    await bench.driver.poll()
    assert bench.driver.connected
    assert _inputs_all(bench.driver, Quality.GOOD, Reason.NONE)
    assert bench.driver.image()["slot0.ai0"].value == pytest.approx(1.5, abs=lsb("5017"))


async def test_safe_state_switches_every_relay_off(bench: Bench) -> None:
    await bench.driver.poll()
    for ch in (0, 3, 5):
        bench.driver.write(f"slot3.do{ch}", True)
    await bench.driver.poll()
    assert all(bench.sim.relay_state(3, ch) for ch in (0, 3, 5))

    bench.driver.write("slot3.do1", True)  # queued, dropped by the safe state
    await bench.driver.safe_state()
    assert not any(bench.sim.relay_state(3, ch) for ch in range(6))
    for ch in range(6):
        assert bench.relay_calls[(3, ch)][-1] is False
    await bench.driver.poll()
    assert all(bench.driver.image()[f"slot3.do{ch}_fb"].value is False for ch in range(6))


async def test_safe_state_connects_when_needed_and_goes_on_past_failures(bench: Bench) -> None:
    bench.sim.stick_relay(3, 0, True)  # welded contact
    await bench.driver.safe_state()  # never polled: connects by itself; logs, never raises
    assert bench.sim.relay_state(3, 0) is True
    assert not any(bench.sim.relay_state(3, ch) for ch in range(1, 6))
    assert all(bench.relay_calls[(3, ch)] == [False] for ch in range(1, 6))


async def test_safe_state_without_device_does_not_raise(bench: Bench) -> None:
    await bench.sim.stop()
    await bench.driver.safe_state()


async def test_analog_values_are_served_by_fc03_and_fc04(bench: Bench) -> None:
    bench.inputs[(1, 2)] = 42.0
    client = AsyncModbusTcpClient(bench.sim.host, port=bench.sim.port, timeout=TIMEOUT_S)
    try:
        assert await client.connect()
        holding = await client.read_holding_registers(8, count=7, device_id=1)
        inputs = await client.read_input_registers(8, count=7, device_id=1)
        assert not holding.isError() and not inputs.isError()
        assert holding.registers == inputs.registers
        assert len(holding.registers) == 7
        # Nothing in slot 5; a 5018 has no 8th channel; analog inputs are read-only.
        empty = await client.read_holding_registers(40, count=8, device_id=1)
        assert empty.isError() and empty.exception_code == 0x02
        eighth = await client.read_holding_registers(8, count=8, device_id=1)
        assert eighth.isError() and eighth.exception_code == 0x02
        write = await client.write_register(8, 1, device_id=1)
        assert write.isError() and write.exception_code == 0x02
        # FC15 on the relay slot calls the callbacks too.
        coils = await client.write_coils(48, [True, False, True], device_id=1)
        assert not coils.isError()
        assert bench.relay_calls == {(3, 0): [True], (3, 1): [False], (3, 2): [True]}
        back = await client.read_coils(48, count=6, device_id=1)
        assert list(back.bits[:6]) == [True, False, True, False, False, False]
    finally:
        client.close()
