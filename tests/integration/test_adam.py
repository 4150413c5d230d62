"""ADAM-5000/TCP over real Modbus TCP on 127.0.0.1: the pymodbus link against the pymodbus
server around the simulated unit.

Only what is about Modbus TCP itself lives here: framing (short answers, exception answers
over the wire), bit and word order end to end, pymodbus's own failures (refused, lost, no
answer) as the link maps them, a reconnect after the server restarts on the same port, and
a raw pymodbus client against the simulator. Everything else about the driver runs on the
virtual clock through the in-process link: ``tests/unit/test_adam_driver.py``.
"""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field

import pytest
from pymodbus.client import AsyncModbusTcpClient

import supervisor.devices.base as base
from supervisor.core.clock import RealClock
from supervisor.core.errors import DeviceIOError, DeviceTimeout
from supervisor.core.quality import Quality, Reason
from supervisor.devices.adam.driver import AdamDriver, AdamModule
from supervisor.devices.adam.protocol import ModbusExceptionAnswer, lsb
from supervisor.devices.adam.sim import AdamSimulator
from supervisor.devices.adam.transport import PymodbusTcpLink
from supervisor.devices.adam.unit import AdamUnit

pytestmark = pytest.mark.integration

TIMEOUT_S = 0.5
SILENT_TIMEOUT_S = 0.2
"""The one test that waits for a timeout on wall time waits this long."""

# Seed 002 layout: 5017 (slot 0), two 5018 (slots 1, 2; slot 2 in two's complement), 5060.
MODULES = {0: "5017", 1: "5018", 2: "5018", 3: "5060"}
FORMATS = {2: "twos"}


@dataclass
class Bench:
    sim: AdamSimulator
    link: PymodbusTcpLink
    driver: AdamDriver
    inputs: dict[tuple[int, int], float | None] = field(default_factory=dict)
    relay_calls: dict[tuple[int, int], list[bool]] = field(default_factory=dict)

    @property
    def unit(self) -> AdamUnit:
        return self.sim.unit


def _make_unit(
    bench_inputs: dict[tuple[int, int], float | None], calls: dict[tuple[int, int], list[bool]]
) -> AdamUnit:
    def source(key: tuple[int, int]) -> Callable[[], float | None]:
        return lambda: bench_inputs.get(key)

    def sink(key: tuple[int, int]) -> Callable[[bool], None]:
        return lambda state: calls.setdefault(key, []).append(state)

    analog = {
        (slot, ch): source((slot, ch))
        for slot, kind in MODULES.items()
        if kind != "5060"
        for ch in range(8 if kind == "5017" else 7)
    }
    relays = {(3, ch): sink((3, ch)) for ch in range(6)}
    return AdamUnit(MODULES, analog, relays, raw_format=FORMATS)


@pytest.fixture
async def bench(monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[Bench]:
    # Reconnect on every poll: the tests drive time by calling poll(), never by sleeping.
    monkeypatch.setattr(base, "BACKOFF_START_S", 0.0)
    monkeypatch.setattr(base, "BACKOFF_MAX_S", 0.0)
    inputs: dict[tuple[int, int], float | None] = {(0, ch): 0.0 for ch in range(8)}
    inputs.update({(slot, ch): 20.0 for slot in (1, 2) for ch in range(7)})
    calls: dict[tuple[int, int], list[bool]] = {}
    sim = AdamSimulator(_make_unit(inputs, calls), port=0)
    await sim.start()
    link = PymodbusTcpLink("adam1", sim.host, sim.port, timeout_s=TIMEOUT_S)
    driver = AdamDriver(
        "adam1",
        RealClock(),
        link,
        {s: AdamModule(k, FORMATS.get(s, "offset")) for s, k in MODULES.items()},
    )
    try:
        yield Bench(sim, link, driver, inputs, calls)
    finally:
        await driver.close()
        await sim.stop()


def _inputs_all(driver: AdamDriver, quality: Quality, reason: Reason) -> bool:
    return all(s.quality == quality and s.reason == reason for s in driver.image().values())


async def _until(pred: Callable[[], bool], what: str, limit_s: float = 5.0) -> None:
    """Wait for the event loop to deliver a socket event (a bound, not a timing claim)."""
    deadline = time.monotonic() + limit_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting: {what}")
        await asyncio.sleep(0.01)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# --- word and bit order end to end ------------------------------------------------------------
async def test_analog_values_arrive_in_volts_and_degc(bench: Bench) -> None:
    """Registers big-endian on the wire, both raw formats: what the unit encodes is what the
    driver decodes after pymodbus on both ends."""
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


async def test_relay_write_calls_callback_and_reads_back(bench: Bench) -> None:
    """Coil bit order: FC05 on coil 50 is relay 2 of slot 3, and FC01 unpacks it there."""
    await bench.driver.poll()
    bench.driver.write("slot3.do2", True)
    await bench.driver.poll()
    assert bench.relay_calls == {(3, 2): [True]}
    assert bench.unit.relay_state(3, 2) is True
    img = bench.driver.image()
    assert img["slot3.do2_fb"].value is True
    assert img["slot3.do2_fb"].quality == Quality.GOOD
    assert img["slot3.do1_fb"].value is False

    bench.driver.write("slot3.do2", False)
    await bench.driver.poll()
    assert bench.relay_calls == {(3, 2): [True, False]}
    assert bench.driver.image()["slot3.do2_fb"].value is False


# --- framing: exception answers and short answers over the wire -------------------------------
async def test_modbus_exception_on_one_slot_leaves_the_others_good(bench: Bench) -> None:
    await bench.driver.poll()
    bench.unit.fail_next_reads(1, 0x04, slot=1)
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
    bench.unit.fail_next_reads(1, 0x02, slot=3)
    await bench.driver.poll()
    img = bench.driver.image()
    assert img["slot3.do0_fb"].reason == Reason.DEVICE_ERROR
    assert img["slot0.ai0"].quality == Quality.GOOD


async def test_short_read_makes_that_slot_bad(bench: Bench) -> None:
    await bench.driver.poll()
    bench.unit.short_next_reads(1, slot=0)
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


async def test_short_coil_answer_over_the_wire(bench: Bench) -> None:
    await bench.driver.poll()
    bench.unit.short_next_reads(1, slot=3)
    await bench.driver.poll()
    assert bench.driver.image()["slot3.do0_fb"].reason == Reason.COMM_FAILURE
    assert "0 coils back for 6" in bench.driver.last_error


# --- the pymodbus link's failures, from the real library --------------------------------------
async def test_pymodbus_link_exception_answer_over_the_wire(bench: Bench) -> None:
    await bench.link.connect()
    with pytest.raises(ModbusExceptionAnswer) as info:
        await bench.link.read_registers(40, 8)  # nothing in slot 5
    assert info.value.code == 0x02
    assert bench.link.connected  # a refused request is no comm loss


async def test_pymodbus_link_refused_and_lost(bench: Bench) -> None:
    nobody = PymodbusTcpLink("adam2", "127.0.0.1", _free_port(), timeout_s=TIMEOUT_S)
    with pytest.raises(DeviceIOError, match=r"^adam2: cannot connect to 127\.0\.0\.1:\d+$"):
        await nobody.connect()
    assert not nobody.connected

    await bench.link.connect()
    await bench.sim.stop()
    await _until(lambda: not bench.link.connected, "the link sees the server gone")
    with pytest.raises(DeviceIOError, match=r"^adam1: not connected$"):
        await bench.link.read_coils(48, 6)


async def test_a_silent_server_is_a_timeout(bench: Bench) -> None:
    """pymodbus reports a request without answer in words ("No response …") that the link
    must recognise; only the real library can say whether it still does. Wall time: one
    ``SILENT_TIMEOUT_S``."""
    link = PymodbusTcpLink("adam1", bench.sim.host, bench.sim.port, timeout_s=SILENT_TIMEOUT_S)
    await link.connect()
    bench.unit.mute()
    try:
        with pytest.raises(DeviceTimeout, match=rf"^adam1: no answer in {SILENT_TIMEOUT_S} s$"):
            await link.read_registers(0, 8)
        bench.unit.mute(False)
        assert len(await link.read_registers(0, 8)) == 8
    finally:
        await link.close()


# --- outage: the server restarts on the same port ----------------------------------------------
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


async def test_relay_states_are_kept_across_a_server_outage(bench: Bench) -> None:
    await bench.driver.poll()
    bench.driver.write("slot3.do4", True)
    await bench.driver.poll()
    await bench.sim.stop()
    await bench.sim.start()
    await bench.driver.poll()
    assert bench.driver.image()["slot3.do4_fb"].value is True


# --- a foreign Modbus client against the simulator ---------------------------------------------
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


def test_server_refuses_a_bad_unit_id() -> None:
    with pytest.raises(ValueError, match="unit_id"):
        AdamSimulator(AdamUnit({0: "5017"}), unit_id=300)
