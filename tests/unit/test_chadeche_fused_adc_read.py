"""The simulated Chadèche bus answers the driver's ADC read in one call
(``SimChadecheBus.transfer``; docs/adr/0018-scan-performance.md, "Dry run"): exactly what
stepping the board (``SimBoard.advance``) then handling the transfer (``SimBoard.handle``)
gives, with the cell stepped and read in one call when it can be. The same replies,
history, counters, cells (bit for bit), thermometer readings, fault reports and errors,
whatever the clock, the commands and the faults do; the lock is free after each call.
The ADC reply is kept while the ADC input stays in the span of voltages its code stands
for (``adc_code_span_v``), which is exactly the codec's."""

from __future__ import annotations

import logging
import math
import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.core.errors import DeviceIOError
from supervisor.devices.chadeche.protocol import (
    ADC_MAX_CODE,
    ADC_READ,
    Chip,
    DacChannel,
    adc_code_span_v,
    dac_transfer,
    encode_adc_reply,
    encode_latch,
    voltage_to_adc_code,
)
from supervisor.devices.chadeche.sim import SimBoard, SimChadecheBus
from supervisor.sim.battery import NiMHCell


class PlainCell:
    """A cell model with neither a thermal state nor a one-call step and reading."""

    def __init__(self) -> None:
        self.ocv_v = 1.25
        self.current_a = 0.0

    def step(self, current_a: float, dt_s: float) -> None:
        self.current_a = current_a
        self.ocv_v += current_a * dt_s * 1e-3

    def voltage_at(self, current_a: float) -> float:
        return self.ocv_v + 0.05 * current_a

    @property
    def terminal_voltage_v(self) -> float:
        return self.voltage_at(self.current_a)


def bits(x: float | None) -> object:
    return None if x is None else struct.pack("<d", x)


def make_bus(soc: float) -> tuple[VirtualClock, SimChadecheBus]:
    clock = VirtualClock()
    boards = {
        # A small cell: a discharge drives it past empty (a fault to report) in minutes.
        0: SimBoard(NiMHCell(capacity_ah=0.01, soc=soc)),
        2: SimBoard(PlainCell()),
    }
    return clock, SimChadecheBus(clock, boards)


def cell_state(board: SimBoard) -> tuple[object, ...]:
    cell = board.cell
    if isinstance(cell, NiMHCell):
        return (
            bits(cell.soc),
            bits(cell.temperature_c),
            bits(cell.charge_ah),
            bits(cell.current_a),
            bits(cell.reversal_ah),
            cell.fault,
        )
    assert isinstance(cell, PlainCell)
    return (bits(cell.ocv_v), bits(cell.current_a))


def bus_state(bus: SimChadecheBus) -> tuple[object, ...]:
    return (
        list(bus.history),
        {
            a: (b.transfers, b.hot_switches, b.dac_a, b.dac_b, b.charging, b._last_t)
            for a, b in bus.boards.items()
        },
        {a: cell_state(b) for a, b in bus.boards.items()},
        bus._lock.locked(),
    )


def outcome(call: Any, *args: Any) -> tuple[str, object]:
    try:
        return ("ok", call(*args))
    except Exception as exc:  # the same error on both paths
        return (type(exc).__name__, str(exc))


class Messages(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def run(bus: SimChadecheBus, clock: VirtualClock, ops: list[tuple[Any, ...]]) -> list[object]:
    """The ops on ``bus``; what each answered and the bus after it, and the log."""
    handler = Messages()
    logger = logging.getLogger("supervisor.devices.chadeche.sim")
    logger.addHandler(handler)
    try:
        results: list[object] = []
        for o in ops:
            kind = o[0]
            if kind == "wait":
                clock.advance(o[1])
            elif kind == "adc":
                # The plain bus gets an equal read in another bytes object: not the
                # driver's ``ADC_READ``, so ``advance`` then ``handle``.
                plain = bus.boards[0]._step_then_voltage_v is None
                data = bytes(bytearray(ADC_READ)) if plain else ADC_READ
                answer = outcome(bus.transfer, o[1], Chip.ADC, data)
                sim = bus.boards.get(o[1])
                if sim is not None and answer[0] == "ok":
                    # The reply is the codec's for the board's ADC input now.
                    assert answer[1] == encode_adc_reply(sim.adc_code())
                results.append(answer)
            elif kind == "dac":
                data = dac_transfer(DacChannel.A, o[2])
                results.append(outcome(bus.transfer, o[1], Chip.DAC, data))
            elif kind == "latch":
                results.append(outcome(bus.transfer, o[1], Chip.LATCH, encode_latch(o[2])))
            elif kind == "thermometer":
                results.append(outcome(bus.cell_temperature_c, o[1]))
            elif kind == "gain":
                bus.boards[o[1]].adc_gain, bus.boards[o[1]].adc_offset_v = o[2], o[3]
            else:
                bus.fault = DeviceIOError("bus", "cable pulled") if o[1] else None
            results.append(bus_state(bus))
    finally:
        logger.removeHandler(handler)
    return [*results, handler.messages]


op = st.one_of(
    st.tuples(st.just("wait"), st.sampled_from([0.0, 0.5, 1.0, 2.5, 30.0])),
    st.tuples(st.just("adc"), st.sampled_from([0, 2, 3])),
    st.tuples(st.just("dac"), st.sampled_from([0, 2]), st.integers(0, 4000)),
    st.tuples(st.just("latch"), st.sampled_from([0, 2]), st.booleans()),
    st.tuples(st.just("thermometer"), st.sampled_from([0, 2, 3])),
    st.tuples(st.just("gain"), st.sampled_from([0, 2]), st.floats(0.5, 4.0), st.floats(-1.0, 1.0)),
    st.tuples(st.just("fault"), st.booleans()),
)


@settings(max_examples=200, deadline=None)
@given(st.floats(0.0, 1.05), st.lists(op, max_size=60))
def test_the_one_call_adc_read_is_advance_then_handle(
    soc: float, ops: list[tuple[Any, ...]]
) -> None:
    fused_clock, fused = make_bus(soc)
    plain_clock, plain = make_bus(soc)
    for board in plain.boards.values():
        board._step_then_voltage_v = None  # stepped by ``advance``, read by ``voltage_at``
    assert run(fused, fused_clock, ops) == run(plain, plain_clock, ops)


def test_a_cell_driven_past_empty_by_polls_is_reported_once_at_the_same_time() -> None:
    ops: list[tuple[Any, ...]] = [("dac", 0, 4000), ("adc", 0)]  # 0.4 A out of 10 mAh
    ops += [("wait", 1.0), ("adc", 0), ("thermometer", 0)] * 200
    fused_clock, fused = make_bus(0.2)
    plain_clock, plain = make_bus(0.2)
    for board in plain.boards.values():
        board._step_then_voltage_v = None
    seen = run(fused, fused_clock, ops)
    assert seen == run(plain, plain_clock, ops)
    messages = seen[-1]
    assert isinstance(messages, list) and len(messages) == 1
    assert "reversal" in messages[0] and "t=" in messages[0]


def test_the_lock_is_given_back_when_a_transfer_or_a_reading_raises() -> None:
    clock, bus = make_bus(0.5)
    bus.fault = DeviceIOError("bus", "cable pulled")
    with pytest.raises(DeviceIOError):
        bus.transfer(0, Chip.ADC, ADC_READ)
    assert not bus._lock.locked()
    bus.fault = None
    bus.boards[0].adc_gain = math.nan  # a NaN ADC input: the codec refuses it
    clock.advance(1.0)
    with pytest.raises(ValueError, match="NaN"):
        bus.transfer(0, Chip.ADC, ADC_READ)
    assert not bus._lock.locked()
    bus.close()
    with pytest.raises(DeviceIOError, match="closed"):
        bus.transfer(0, Chip.ADC, ADC_READ)
    assert not bus._lock.locked()
    assert bus.cell_temperature_c(0) == bus.boards[0].temperature_c
    assert not bus._lock.locked()


def test_every_codes_span_holds_exactly_the_voltages_the_codec_gives_it() -> None:
    previous_high = -math.inf
    for code in range(ADC_MAX_CODE + 1):
        low, high = adc_code_span_v(code)
        assert low == math.nextafter(previous_high, math.inf) or code == 0
        assert low <= high
        for v in (low, high):
            if math.isfinite(v):
                assert voltage_to_adc_code(v) == code
        if math.isfinite(low):
            assert voltage_to_adc_code(math.nextafter(low, -math.inf)) == code - 1
        if math.isfinite(high):
            assert voltage_to_adc_code(math.nextafter(high, math.inf)) == code + 1
        previous_high = high
    assert adc_code_span_v(0)[0] == -math.inf and adc_code_span_v(ADC_MAX_CODE)[1] == math.inf
    with pytest.raises(ValueError):
        adc_code_span_v(ADC_MAX_CODE + 1)


@settings(max_examples=500, deadline=None)
@given(
    st.one_of(
        st.floats(-1.0, 5.0),
        # Right at a rounding edge, give or take a few floats.
        st.tuples(st.integers(0, ADC_MAX_CODE), st.integers(-4, 4)).map(
            lambda ku: _ulps_from((ku[0] + 0.5) * 0.001, ku[1])
        ),
    )
)
def test_a_voltage_lies_in_the_span_of_its_code(voltage_v: float) -> None:
    low, high = adc_code_span_v(voltage_to_adc_code(voltage_v))
    assert low <= voltage_v <= high


def _ulps_from(v: float, n: int) -> float:
    for _ in range(abs(n)):
        v = math.nextafter(v, math.inf if n > 0 else -math.inf)
    return v
