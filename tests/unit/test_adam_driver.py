"""ADAM-5000/TCP driver: its contract on both transports; on the virtual clock, through the
in-process link, its timeouts, outages and backoff; the pymodbus link's error mapping (fake
client); the simulated unit's answers; the registration's wiring.

The contract (:class:`TestDriverOnBothTransports`) runs each test on the in-process link
(virtual clock) and over Modbus TCP on loopback (real clock, marked ``integration``): the
same assertions whatever carries the requests (STYLE.md "Contract tests rerunnable on
hardware"). What only Modbus TCP has (a raw pymodbus client, pymodbus's own failures, a
silent server on wall time) is tested in ``tests/integration/test_adam.py``.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any, ClassVar

import pymodbus.client
import pytest
import yaml
from adam_rig import (
    TIMEOUT_S,
    AdamRig,
    inputs_all,
    make_unit,
    open_rig,
    reconnect_on_every_poll,
    seed002_inputs,
)
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from rig_transports import IN_PROCESS, clock_for, on_both_transports

import supervisor.devices.base as base
from supervisor.app import build_bench
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import DeviceIOError, DeviceTimeout
from supervisor.core.quality import Quality, Reason
from supervisor.devices.adam import KIND, unit_of
from supervisor.devices.adam.config import AdamDevice
from supervisor.devices.adam.driver import AdamDriver, AdamModule
from supervisor.devices.adam.protocol import lsb, raw_to_value
from supervisor.devices.adam.sim import AdamSimulator
from supervisor.devices.adam.transport import InProcessLink, PymodbusTcpLink
from supervisor.devices.adam.unit import AdamUnit
from supervisor.devices.kind import DriverWiring, SimWiring
from supervisor.devices.registry import bench_from_data, load_bench
from supervisor.fieldbus.modbus import (
    FC_READ_HOLDING_REGISTERS,
    FC_READ_INPUT_REGISTERS,
    ModbusExceptionAnswer,
)
from supervisor.sim.plant import make_plant


@pytest.fixture
async def bench(
    transport: str, virtual_clock: VirtualClock, monkeypatch: pytest.MonkeyPatch
) -> AsyncIterator[AdamRig]:
    """The seed 002 rig on ``transport`` (in process unless the test runs on both); it
    reconnects on every poll: these tests drive time by calling poll()."""
    reconnect_on_every_poll(monkeypatch)
    async with open_rig(transport, clock_for(transport, virtual_clock)) as rig:
        yield rig


@pytest.fixture
async def backoff_bench(virtual_clock: VirtualClock) -> AsyncIterator[AdamRig]:
    """The in-process rig with PolledDriver's real backoff (time moves only on virtual time)."""
    async with open_rig(IN_PROCESS, virtual_clock) as rig:
        yield rig


# --- points and construction ---------------------------------------------------------------
def test_points() -> None:
    driver = AdamDriver(
        "adam1",
        VirtualClock(),
        PymodbusTcpLink("adam1", "127.0.0.1", 1),
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
    assert inputs_all(driver, Quality.BAD, Reason.NOT_CONNECTED)
    with pytest.raises(ValueError):
        driver.write("slot3.do0", 0.5)
    with pytest.raises(KeyError):
        driver.write("slot0.ai0", True)


def test_fast_polling_of_a_5017_warns(caplog: pytest.LogCaptureFixture) -> None:
    link = PymodbusTcpLink("fast", "127.0.0.1", 1)
    with caplog.at_level(logging.WARNING, logger="supervisor.devices.adam.driver"):
        AdamDriver("fast", VirtualClock(), link, {0: AdamModule("5018")}, poll_period_s=0.05)
    assert not caplog.records
    with caplog.at_level(logging.WARNING, logger="supervisor.devices.adam.driver"):
        AdamDriver("fast", VirtualClock(), link, {0: AdamModule("5017")}, poll_period_s=0.05)
    assert any("fast" in r.getMessage() and "5017" in r.getMessage() for r in caplog.records)


def test_links_refuse_bad_settings() -> None:
    unit = AdamUnit({0: "5017"})
    with pytest.raises(ValueError, match="unit_id"):
        PymodbusTcpLink("adam1", "127.0.0.1", 502, unit_id=256)
    with pytest.raises(ValueError, match="timeout_s"):
        PymodbusTcpLink("adam1", "127.0.0.1", 502, timeout_s=0.0)
    with pytest.raises(ValueError, match="timeout_s"):
        InProcessLink("adam1", VirtualClock(), unit, timeout_s=-1.0)


# --- the driver's contract: the same on the in-process link and over Modbus TCP ---------------
@on_both_transports
class TestDriverOnBothTransports:
    """Word and bit order, exception and short answers, outages and the safe state: what
    the unit answers reaches the driver the same way through either link (over TCP, after
    pymodbus on both ends)."""

    async def test_analog_values_arrive_in_volts_and_degc(self, bench: AdamRig) -> None:
        """Registers big-endian on the wire, both raw formats: what the unit encodes is what
        the driver decodes."""
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
        assert inputs_all(bench.driver, Quality.GOOD, Reason.NONE)

        # Values are live: sampled again on every read.
        bench.inputs[(0, 2)] = -3.5
        bench.inputs[(1, 0)] = 31.25
        await bench.driver.poll()
        img = bench.driver.image()
        assert img["slot0.ai2"].value == pytest.approx(-3.5, abs=lsb("5017"))
        assert img["slot1.tc0"].value == pytest.approx(31.25, abs=lsb("5018"))

    async def test_open_thermocouple_is_bad_sensor_failure(self, bench: AdamRig) -> None:
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

    async def test_relay_write_calls_callback_and_reads_back(self, bench: AdamRig) -> None:
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

    async def test_relay_that_does_not_follow_is_a_write_fault(self, bench: AdamRig) -> None:
        await bench.driver.poll()
        bench.unit.stick_relay(3, 1, False)
        bench.driver.write("slot3.do1", True)
        await bench.driver.poll()
        assert "write did not verify" in bench.driver.last_error
        assert not bench.driver.connected
        assert inputs_all(bench.driver, Quality.BAD, Reason.COMM_FAILURE)

    async def test_modbus_exception_on_one_slot_leaves_the_others_good(
        self, bench: AdamRig
    ) -> None:
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
        assert inputs_all(bench.driver, Quality.GOOD, Reason.NONE)

    async def test_exception_answer_names_the_request_and_its_meaning(self, bench: AdamRig) -> None:
        bench.unit.fail_next_reads(1, 0x04, slot=1)
        await bench.driver.poll()
        assert bench.driver.last_error == "slot1 FC03 @8x7: Modbus exception 0x04 (device failure)"

    async def test_modbus_exception_on_relay_slot(self, bench: AdamRig) -> None:
        await bench.driver.poll()
        bench.unit.fail_next_reads(1, 0x02, slot=3)
        await bench.driver.poll()
        img = bench.driver.image()
        assert img["slot3.do0_fb"].reason == Reason.DEVICE_ERROR
        assert img["slot0.ai0"].quality == Quality.GOOD

    async def test_the_link_passes_an_exception_answer_on_and_stays_connected(
        self, bench: AdamRig
    ) -> None:
        await bench.link.connect()
        with pytest.raises(ModbusExceptionAnswer) as info:
            await bench.link.read_registers(40, 8)  # nothing in slot 5
        assert info.value.code == 0x02
        assert bench.link.connected  # a refused request is no comm loss

    @pytest.mark.parametrize(
        ("slot", "points", "other", "message"),
        [
            (0, [f"slot0.ai{k}" for k in range(8)], "slot1.tc0", "7 registers back for 8"),
            (3, [f"slot3.do{k}_fb" for k in range(6)], "slot0.ai0", "0 coils back for 6"),
        ],
        ids=["registers", "coils"],
    )
    async def test_a_short_answer_makes_that_slot_bad(
        self, bench: AdamRig, slot: int, points: list[str], other: str, message: str
    ) -> None:
        await bench.driver.poll()
        bench.unit.short_next_reads(1, slot=slot)
        await bench.driver.poll()
        img = bench.driver.image()
        assert bench.driver.connected
        for point in points:
            assert (img[point].quality, img[point].reason) == (Quality.BAD, Reason.COMM_FAILURE)
        assert img[other].quality == Quality.GOOD
        assert message in bench.driver.last_error

        await bench.driver.poll()
        assert inputs_all(bench.driver, Quality.GOOD, Reason.NONE)

    async def test_lost_simulator_marks_everything_bad_then_recovers(self, bench: AdamRig) -> None:
        await bench.driver.poll()
        assert inputs_all(bench.driver, Quality.GOOD, Reason.NONE)
        served = bench.server.addresses()

        await bench.server.stop()
        await bench.driver.poll()
        assert not bench.driver.connected
        assert inputs_all(bench.driver, Quality.BAD, Reason.COMM_FAILURE)
        # Old values are kept for diagnostics, but never GOOD.
        assert bench.driver.image()["slot1.tc0"].value == pytest.approx(20.0, abs=lsb("5018"))

        await bench.driver.poll()  # reconnect attempt fails: still BAD
        assert inputs_all(bench.driver, Quality.BAD, Reason.COMM_FAILURE)

        await bench.server.start()
        assert bench.server.addresses() == served  # over TCP: the same port again
        bench.inputs[(0, 0)] = 1.5
        await bench.driver.poll()
        assert bench.driver.connected
        assert inputs_all(bench.driver, Quality.GOOD, Reason.NONE)
        assert bench.driver.image()["slot0.ai0"].value == pytest.approx(1.5, abs=lsb("5017"))

    async def test_relay_states_are_kept_across_an_outage(self, bench: AdamRig) -> None:
        await bench.driver.poll()
        bench.driver.write("slot3.do4", True)
        await bench.driver.poll()
        await bench.server.stop()
        await bench.server.start()
        await bench.driver.poll()  # finds its old link dead (the old value stays, BAD)
        assert bench.driver.image()["slot3.do4_fb"].value is True
        await bench.driver.poll()  # reconnects and reads the relay back
        assert bench.driver.connected
        assert bench.driver.image()["slot3.do4_fb"].value is True
        assert bench.driver.image()["slot3.do4_fb"].quality == Quality.GOOD

    async def test_safe_state_switches_every_relay_off(self, bench: AdamRig) -> None:
        await bench.driver.poll()
        for ch in (0, 3, 5):
            bench.driver.write(f"slot3.do{ch}", True)
        await bench.driver.poll()
        assert all(bench.unit.relay_state(3, ch) for ch in (0, 3, 5))

        bench.driver.write("slot3.do1", True)  # queued, dropped by the safe state
        await bench.driver.safe_state()
        assert not any(bench.unit.relay_state(3, ch) for ch in range(6))
        for ch in range(6):
            assert bench.relay_calls[(3, ch)][-1] is False
        await bench.driver.poll()
        assert all(bench.driver.image()[f"slot3.do{ch}_fb"].value is False for ch in range(6))

    async def test_safe_state_connects_when_needed_and_goes_on_past_failures(
        self, bench: AdamRig
    ) -> None:
        bench.unit.stick_relay(3, 0, True)  # welded contact
        await bench.driver.safe_state()  # never polled: connects by itself; logs, never raises
        assert bench.unit.relay_state(3, 0) is True
        assert not any(bench.unit.relay_state(3, ch) for ch in range(1, 6))
        assert all(bench.relay_calls[(3, ch)] == [False] for ch in range(1, 6))

    async def test_safe_state_without_device_does_not_raise(self, bench: AdamRig) -> None:
        await bench.server.stop()
        await bench.driver.safe_state()

    async def test_a_request_on_a_closed_link_is_refused(self, bench: AdamRig) -> None:
        with pytest.raises(DeviceIOError, match="not connected"):
            await bench.link.read_coils(48, 6)
        await bench.link.connect()
        await bench.link.close()
        with pytest.raises(DeviceIOError, match="not connected"):
            await bench.link.write_coil(48, True)
        assert bench.relay_calls == {}

    async def test_connect_logs_where_it_connected(
        self, bench: AdamRig, caplog: pytest.LogCaptureFixture
    ) -> None:
        with caplog.at_level(logging.INFO, logger="supervisor.devices.adam.driver"):
            await bench.driver.poll()
        assert f"adam1: connected to {bench.address}" in caplog.messages


# --- in process: samples on the injected clock ------------------------------------------------
async def test_samples_are_stamped_with_the_injected_clock(
    bench: AdamRig, virtual_clock: VirtualClock
) -> None:
    virtual_clock.advance(12.5)
    await bench.driver.poll()
    assert {s.t for s in bench.driver.image().values()} == {12.5}


# --- no answer: timeouts on the injected clock -------------------------------------------------
async def test_a_silent_unit_times_out_after_timeout_s_of_virtual_time(bench: AdamRig) -> None:
    await bench.driver.poll()
    bench.unit.mute()
    t0 = bench.clock.now()
    await bench.driver.poll()
    # One request waits its timeout (the first slot's read), then the poll gives up.
    assert bench.clock.now() == pytest.approx(t0 + TIMEOUT_S)
    assert not bench.driver.connected
    assert inputs_all(bench.driver, Quality.BAD, Reason.COMM_FAILURE)
    assert bench.driver.last_error == f"adam1: slot0 FC03 @0x8: no answer in {TIMEOUT_S} s"

    bench.unit.mute(False)
    await bench.driver.poll()
    assert bench.driver.connected
    assert inputs_all(bench.driver, Quality.GOOD, Reason.NONE)


async def test_a_silent_unit_loses_the_relay_write(bench: AdamRig) -> None:
    await bench.driver.poll()
    bench.unit.mute()
    bench.driver.write("slot3.do0", True)
    await bench.driver.poll()
    assert "slot3.do0 FC05 @48=1: no answer" in bench.driver.last_error
    assert bench.unit.relay_state(3, 0) is False
    assert bench.relay_calls == {}


async def test_timeout_raises_device_timeout_naming_the_request(bench: AdamRig) -> None:
    await bench.link.connect()
    bench.unit.mute()
    with pytest.raises(DeviceTimeout, match=r"^adam1: no answer in 0.5 s$"):
        await bench.link.read_registers(0, 8)
    with pytest.raises(DeviceTimeout, match=r"^adam1: no answer in 0.5 s$"):
        await bench.link.write_coil(48, True)
    assert bench.clock.now() == pytest.approx(2 * TIMEOUT_S)


# --- unplugged: refused connects, dropped links, backoff --------------------------------------
async def test_an_unplugged_unit_refuses_to_connect(bench: AdamRig) -> None:
    await bench.unit.stop()
    with pytest.raises(DeviceIOError, match="cannot connect to in-process simulator adam"):
        await bench.link.connect()
    assert not bench.link.connected


async def test_unplugging_drops_an_open_link_until_it_connects_again(bench: AdamRig) -> None:
    await bench.link.connect()
    assert bench.link.connected
    await bench.unit.stop()
    assert not bench.link.connected
    with pytest.raises(DeviceIOError, match=r"^adam1: not connected$"):
        await bench.link.read_coils(48, 6)

    # Back again: the old link stays dead (as a TCP connection would), a new one works.
    await bench.unit.start()
    assert not bench.link.connected
    with pytest.raises(DeviceIOError, match="not connected"):
        await bench.link.read_registers(0, 8)
    await bench.link.connect()
    assert await bench.link.read_coils(48, 6) == [False] * 6


async def test_driver_reconnects_with_polled_driver_backoff(
    backoff_bench: AdamRig, virtual_clock: VirtualClock
) -> None:
    b = backoff_bench
    await b.driver.poll()
    await b.unit.stop()

    await b.driver.poll()  # t = 0: the loss is seen, next attempt after BACKOFF_START_S
    assert (b.driver.connected, b.driver.failures) == (False, 1)
    assert "not connected" in b.driver.last_error

    virtual_clock.advance(base.BACKOFF_START_S / 2)
    await b.driver.poll()  # not due yet: no attempt
    assert b.driver.failures == 1

    virtual_clock.advance(base.BACKOFF_START_S / 2)
    await b.driver.poll()  # due: refused, the backoff doubles
    assert b.driver.failures == 2
    assert "cannot connect to in-process simulator adam" in b.driver.last_error

    await b.unit.start()
    virtual_clock.advance(2 * base.BACKOFF_START_S - 0.01)
    await b.driver.poll()  # the unit is back, but the next attempt is not due yet
    assert not b.driver.connected and b.driver.failures == 2
    virtual_clock.advance(0.01)
    await b.driver.poll()
    assert b.driver.connected
    assert inputs_all(b.driver, Quality.GOOD, Reason.NONE)


# --- the simulated unit's answers ---------------------------------------------------------------
def test_unit_serves_analog_values_as_holding_and_input_registers() -> None:
    unit = make_unit({(1, 2): 42.0}, {})
    holding = unit.read_registers(FC_READ_HOLDING_REGISTERS, 8, 7)
    assert holding == unit.read_registers(FC_READ_INPUT_REGISTERS, 8, 7)
    assert raw_to_value(holding[2], "5018") == pytest.approx(42.0, abs=lsb("5018"))
    # No callable value for channel 0 here: an open thermocouple reads the open-wire code.
    assert holding[0] == 0xFFFF


@pytest.mark.parametrize(
    ("request_", "code"),
    [
        (lambda u: u.read_registers(FC_READ_HOLDING_REGISTERS, 40, 8), 0x02),  # empty slot 5
        (lambda u: u.read_registers(FC_READ_HOLDING_REGISTERS, 8, 8), 0x02),  # no 8th channel
        (lambda u: u.read_registers(FC_READ_HOLDING_REGISTERS, 48, 1), 0x02),  # relay slot
        (lambda u: u.read_registers(6, 0, 1), 0x01),  # FC06 is no read
        (lambda u: u.read_registers(FC_READ_HOLDING_REGISTERS, 0, 0), 0x03),  # nothing asked
        (lambda u: u.write_registers(8, [1]), 0x02),  # analog inputs are read-only
        (lambda u: u.read_coils(0, 6), 0x02),  # slot 0 holds no relays
        (lambda u: u.write_coils(54, [True]), 0x02),  # a 5060 has 6 relays
    ],
)
def test_unit_refuses_what_it_does_not_hold(request_: Callable[[AdamUnit], Any], code: int) -> None:
    with pytest.raises(ModbusExceptionAnswer) as info:
        request_(make_unit(seed002_inputs(), {}))
    assert info.value.code == code


def test_unit_writes_several_relays_and_reads_them_back() -> None:
    calls: dict[tuple[int, int], list[bool]] = {}
    unit = make_unit(seed002_inputs(), calls)
    unit.write_coils(48, [True, False, True])  # FC15 calls the callbacks too
    assert calls == {(3, 0): [True], (3, 1): [False], (3, 2): [True]}
    assert unit.read_coils(48, 6) == [True, False, True, False, False, False]
    # Coils past the module's last relay, inside its slot, read False.
    assert unit.read_coils(48, 16)[6:] == [False] * 10


def test_unit_failing_callable_answers_device_failure(caplog: pytest.LogCaptureFixture) -> None:
    def broken() -> float:
        raise RuntimeError("sensor model failed")

    unit = AdamUnit({0: "5017"}, {(0, 0): broken})
    with pytest.raises(ModbusExceptionAnswer) as info:
        unit.read_registers(FC_READ_HOLDING_REGISTERS, 0, 8)
    assert info.value.code == 0x04
    assert any("callable failed (FC03 @0)" in m for m in caplog.messages)


def test_unit_fault_injection_counts_and_targets_slots() -> None:
    unit = make_unit(seed002_inputs(), {})
    unit.fail_next_reads(2, 0x06, slot=2)
    assert len(unit.read_registers(FC_READ_HOLDING_REGISTERS, 8, 7)) == 7  # slot 1: untouched
    for _ in range(2):
        with pytest.raises(ModbusExceptionAnswer, match=r"0x06 \(device busy\)"):
            unit.read_registers(FC_READ_HOLDING_REGISTERS, 16, 7)
    assert len(unit.read_registers(FC_READ_HOLDING_REGISTERS, 16, 7)) == 7
    with pytest.raises(ValueError, match="not a Modbus exception code"):
        unit.fail_next_reads(1, 0x09)


async def test_unit_outage_keeps_relays_and_counts() -> None:
    unit = make_unit(seed002_inputs(), {})
    await unit.start()
    unit.write_coils(49, [True])
    await unit.stop()
    await unit.stop()  # already unplugged: not a second outage
    assert (unit.running, unit.outages) == (False, 1)
    await unit.start()
    assert unit.relay_state(3, 1) is True
    assert unit.addresses() == []  # nothing listens


def test_unit_refuses_bad_layouts() -> None:
    with pytest.raises(ValueError, match=r"slot must be 0\.\.7"):
        AdamUnit({8: "5017"})
    with pytest.raises(ValueError, match="unknown ADAM module"):
        AdamUnit({0: "5051"})
    with pytest.raises(ValueError, match="not an analog module"):
        AdamUnit({3: "5060"}, raw_format={3: "twos"})
    with pytest.raises(ValueError, match="has no channel 7"):
        AdamUnit({1: "5018"}, {(1, 7): lambda: 20.0})
    with pytest.raises(ValueError, match="no relay module"):
        AdamUnit({0: "5017"}, relays={(0, 0): lambda state: None})


# --- the pymodbus link's error mapping (fake client, no socket) --------------------------------
class _Answer:
    """What pymodbus answers: bits, registers, or an exception response."""

    def __init__(
        self, bits: list[bool] | None = None, registers: list[int] | None = None, code: int = 0
    ) -> None:
        self.bits = bits or []
        self.registers = registers or []
        self.exception_code = code

    def isError(self) -> bool:  # pymodbus's name
        return self.exception_code != 0


class FakeClient:
    """Stands in for ``AsyncModbusTcpClient``: records how it was made and what it was asked,
    answers with ``outcome`` (an answer, or an exception to raise)."""

    made: ClassVar[list[FakeClient]] = []
    outcome: ClassVar[_Answer | BaseException] = _Answer()
    accept: ClassVar[bool] = True

    def __init__(self, host: str, **kwargs: Any) -> None:
        self.host = host
        self.kwargs = kwargs
        self.connected = False
        self.calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = []
        FakeClient.made.append(self)

    async def connect(self) -> bool:
        self.connected = FakeClient.accept
        return self.connected

    def close(self) -> None:
        self.connected = False

    async def _answer(self, name: str, *args: Any, **kwargs: Any) -> _Answer:
        self.calls.append((name, args, kwargs))
        if isinstance(FakeClient.outcome, BaseException):
            raise FakeClient.outcome
        return FakeClient.outcome

    async def read_coils(self, *args: Any, **kwargs: Any) -> _Answer:
        return await self._answer("read_coils", *args, **kwargs)

    async def read_holding_registers(self, *args: Any, **kwargs: Any) -> _Answer:
        return await self._answer("read_holding_registers", *args, **kwargs)

    async def read_input_registers(self, *args: Any, **kwargs: Any) -> _Answer:
        return await self._answer("read_input_registers", *args, **kwargs)

    async def write_coil(self, *args: Any, **kwargs: Any) -> _Answer:
        return await self._answer("write_coil", *args, **kwargs)


@pytest.fixture
def fake_client(monkeypatch: pytest.MonkeyPatch) -> type[FakeClient]:
    # The master imports pymodbus's client when it connects (not with the Modbus codes).
    monkeypatch.setattr(pymodbus.client, "AsyncModbusTcpClient", FakeClient)
    monkeypatch.setattr(FakeClient, "made", [])
    monkeypatch.setattr(FakeClient, "outcome", _Answer())
    monkeypatch.setattr(FakeClient, "accept", True)
    return FakeClient


async def test_pymodbus_link_turns_off_pymodbus_retries_and_reconnects(
    fake_client: type[FakeClient],
) -> None:
    link = PymodbusTcpLink("adam1", "10.0.0.5", 502, unit_id=3, timeout_s=0.7)
    await link.connect()
    (client,) = fake_client.made
    assert client.host == "10.0.0.5"
    assert client.kwargs == {
        "port": 502,
        "name": "adam1",
        "timeout": 0.7,
        "retries": 0,
        "reconnect_delay": 0,
    }
    assert link.connected and link.address == "10.0.0.5:502"
    await link.connect()  # again: the old client is closed, a new one made
    assert len(fake_client.made) == 2 and not fake_client.made[0].connected
    await link.close()
    assert not link.connected


async def test_pymodbus_link_asks_with_the_unit_id_and_the_analog_function(
    fake_client: type[FakeClient],
) -> None:
    link = PymodbusTcpLink("adam1", "10.0.0.5", 502, unit_id=3)
    await link.connect()
    fake_client.outcome = _Answer(registers=[0x1234, 0xFFFF], bits=[True, False] + [False] * 6)
    assert await link.read_registers(8, 2) == [0x1234, 0xFFFF]
    # pymodbus pads coils to whole bytes: the link answers only the coils asked for.
    assert await link.read_coils(48, 2) == [True, False]
    await link.write_coil(50, True)
    assert fake_client.made[0].calls == [
        ("read_holding_registers", (8,), {"count": 2, "device_id": 3}),  # FC03 today
        ("read_coils", (48,), {"count": 2, "device_id": 3}),
        ("write_coil", (50, True), {"device_id": 3}),
    ]


@pytest.mark.parametrize(
    ("raised", "error", "message"),
    [
        (ConnectionException("Connection lost"), DeviceIOError, "Connection lost"),
        (
            ModbusIOException("No response received after 0 retries, continue with next request"),
            DeviceTimeout,
            "^adam1: no answer in 0.5 s$",
        ),
        (ModbusIOException("Unable to decode frame"), DeviceIOError, "Unable to decode frame"),
        (ModbusException("unexpected"), DeviceIOError, "unexpected"),
        (TimeoutError(), DeviceTimeout, "^adam1: no answer in 0.5 s$"),
    ],
)
async def test_pymodbus_link_maps_pymodbus_failures(
    fake_client: type[FakeClient], raised: BaseException, error: type[Exception], message: str
) -> None:
    link = PymodbusTcpLink("adam1", "10.0.0.5", 502, timeout_s=0.5)
    await link.connect()
    fake_client.outcome = raised
    with pytest.raises(error, match=message) as info:
        await link.read_registers(0, 8)
    if error is DeviceIOError:
        assert not isinstance(info.value, DeviceTimeout)


async def test_pymodbus_link_exception_answer_carries_the_code(
    fake_client: type[FakeClient],
) -> None:
    link = PymodbusTcpLink("adam1", "10.0.0.5", 502)
    await link.connect()
    fake_client.outcome = _Answer(code=0x02)
    with pytest.raises(ModbusExceptionAnswer) as info:
        await link.read_coils(0, 6)
    assert info.value.code == 0x02
    assert str(info.value) == "Modbus exception 0x02 (illegal address)"
    # A refused request is no comm loss: not a SupervisorError, the link stays open.
    assert not isinstance(info.value, DeviceIOError)
    assert link.connected


async def test_pymodbus_link_never_lets_pymodbus_reconnect_by_itself(
    fake_client: type[FakeClient],
) -> None:
    link = PymodbusTcpLink("adam1", "10.0.0.5", 502)
    with pytest.raises(DeviceIOError, match=r"^adam1: not connected$"):
        await link.read_coils(48, 6)
    await link.connect()
    fake_client.made[0].connected = False  # the server went away
    with pytest.raises(DeviceIOError, match=r"^adam1: not connected$"):
        await link.read_coils(48, 6)
    assert fake_client.made[0].calls == []
    fake_client.accept = False
    with pytest.raises(DeviceIOError, match=r"^adam1: cannot connect to 10.0.0.5:502$"):
        await link.connect()
    assert not link.connected


async def test_driver_names_the_request_in_link_errors(fake_client: type[FakeClient]) -> None:
    clock = VirtualClock()
    driver = AdamDriver(
        "adam1", clock, PymodbusTcpLink("adam1", "10.0.0.5", 502), {0: AdamModule("5017")}
    )
    fake_client.outcome = TimeoutError()
    await driver.poll()
    assert driver.last_error == "adam1: slot0 FC03 @0x8: no answer in 1.0 s"
    fake_client.outcome = ConnectionException("Connection lost")
    clock.advance(base.BACKOFF_START_S)
    await driver.poll()
    assert driver.last_error.startswith("adam1: slot0 FC03 @0x8: ")
    assert "Connection lost" in driver.last_error
    await driver.close()


# --- registration: which link and which simulator the composition root gets -------------------
def _seed002_adam(root: Path) -> tuple[Any, AdamDevice]:
    cfg = load_bench(root / "io_maps" / "sim.yaml")
    dev = cfg.devices["adam"]
    assert isinstance(dev, AdamDevice)
    return cfg, dev


async def test_registration_links_the_driver_to_its_simulator_in_process(root: Path) -> None:
    cfg, dev = _seed002_adam(root)
    clock = VirtualClock()
    plant = make_plant(cfg.simulation, clock)
    assert KIND.build_simulator is not None
    sim = KIND.build_simulator("adam", dev, SimWiring(clock, cfg, plant, in_process=True))
    assert isinstance(sim, AdamUnit)
    assert sim.addresses() == []  # nothing served
    driver = KIND.build_driver("adam", dev, DriverWiring(clock, cfg, sim))
    assert isinstance(driver, AdamDriver)

    await sim.start()
    await driver.poll()
    img = driver.image()
    assert driver.connected
    # The I/O map's simulation section: voltage board on slot0.ai1 (1:10), e-stop sense on
    # slot0.ai2 (5 V while healthy), the pack thermocouple on slot1.tc0.
    assert img["slot0.ai1"].value == pytest.approx(plant.pack_voltage_v * 0.1, abs=lsb("5017"))
    assert img["slot0.ai2"].value == pytest.approx(5.0, abs=lsb("5017"))
    assert img["slot1.tc0"].value == pytest.approx(plant.pack_temperature_c, abs=lsb("5018"))
    driver.write("slot3.do0", True)  # the battery contactor coil
    driver.write("slot3.do5", True)  # a first heartbeat toggle for its watchdog relay
    await driver.poll()
    assert plant.contactor_closed
    await driver.close()
    await sim.stop()


def test_registration_serves_the_unit_and_links_over_tcp_otherwise(root: Path) -> None:
    cfg, dev = _seed002_adam(root)
    clock = VirtualClock()
    assert KIND.build_simulator is not None
    sim = KIND.build_simulator("adam", dev, SimWiring(clock, cfg, make_plant(None, clock)))
    assert isinstance(sim, AdamSimulator)
    assert unit_of(sim) is sim.unit
    assert sim.addresses() == ["ADAM-5000/TCP adam: modbus tcp 127.0.0.1:5020"]
    driver = KIND.build_driver("adam", dev, DriverWiring(clock, cfg))
    assert isinstance(driver, AdamDriver)
    link = driver.link
    assert isinstance(link, PymodbusTcpLink)
    assert (link.address, link.unit_id, link.timeout_s) == ("127.0.0.1:5020", 1, 0.5)
    with pytest.raises(TypeError, match="not an ADAM simulator"):
        unit_of(object())  # type: ignore[arg-type]


async def test_a_bench_built_in_process_scans_the_unit_on_virtual_time(root: Path) -> None:
    """The composition root with ``in_process=True``: nothing listens, the driver calls the
    unit, and a lost unit is detected and recovered on virtual time."""
    data = yaml.safe_load((root / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["devices"] = {"adam": data["devices"]["adam"]}
    data["tags"] = [t for t in data["tags"] if t["device"] == "adam"]
    data["channels"] = []
    clock = VirtualClock()
    bench = build_bench(bench_from_data(data), clock, in_process=True)
    assert bench.sim is not None
    unit = bench.sim.devices["adam"]
    assert isinstance(unit, AdamUnit)
    assert bench.sim.addresses() == []
    db = bench.db
    await bench.start()
    try:
        await bench.engine.run_for(1.0)
        assert db["adam.connected"].value is True
        assert db["pack.voltage"].good and db["estop.ok"].value is True
        assert db["pack.voltage"].as_float() == pytest.approx(
            bench.sim.plant.pack_voltage_v, abs=10 * lsb("5017")
        )

        await unit.stop()
        await bench.engine.run_for(2.0)
        assert db["adam.connected"].value is False and not db["pack.voltage"].good

        await unit.start()
        await bench.engine.run_for(2.0)
        assert db["adam.connected"].value is True and db["pack.voltage"].good
    finally:
        await bench.shutdown()
