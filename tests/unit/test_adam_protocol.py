"""ADAM-5000/TCP codecs: golden addresses and raw values, burn-out, round trips; golden
frames of the pymodbus minor we pin (bit and word order), Modbus exception answers."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymodbus.constants import ExcCodes
from pymodbus.pdu.bit_message import ReadCoilsResponse, WriteSingleCoilRequest
from pymodbus.pdu.register_message import ReadHoldingRegistersResponse

from supervisor.core.errors import SupervisorError
from supervisor.devices.adam.protocol import (
    ANALOG_READ_FUNCTION,
    MODULE_KINDS,
    OFFSET_BINARY_SPAN,
    TC_OPEN_WIRE_RAW,
    AdamModule,
    analog_register,
    coil_address,
    coil_slot_channel,
    is_burnout,
    lsb,
    raw_to_value,
    register_slot_channel,
    value_to_raw,
)
from supervisor.fieldbus.modbus import EXCEPTION_MEANINGS, ModbusExceptionAnswer

ANALOG_KINDS = ("5017", "5018")
FORMATS = ("offset", "twos")


# --- register map --------------------------------------------------------------------
@pytest.mark.parametrize(
    ("slot", "ch", "register"), [(0, 0, 0), (0, 7, 7), (1, 0, 8), (2, 3, 19), (7, 7, 63)]
)
def test_analog_register_golden(slot: int, ch: int, register: int) -> None:
    assert analog_register(slot, ch) == register
    assert register_slot_channel(register) == (slot, ch)


@pytest.mark.parametrize(
    ("slot", "ch", "coil"), [(0, 0, 0), (0, 5, 5), (3, 0, 48), (3, 5, 53), (7, 15, 127)]
)
def test_coil_address_golden(slot: int, ch: int, coil: int) -> None:
    assert coil_address(slot, ch) == coil
    assert coil_slot_channel(coil) == (slot, ch)


@pytest.mark.parametrize(("slot", "ch"), [(-1, 0), (8, 0), (0, 8), (0, -1), (True, 0)])
def test_analog_register_rejects_bad_slot_or_channel(slot: int, ch: int) -> None:
    with pytest.raises(ValueError):
        analog_register(slot, ch)


@pytest.mark.parametrize(("slot", "ch"), [(8, 0), (0, 16), (0, -1)])
def test_coil_address_rejects_bad_slot_or_channel(slot: int, ch: int) -> None:
    with pytest.raises(ValueError):
        coil_address(slot, ch)


def test_analog_read_function_is_holding_registers() -> None:
    assert ANALOG_READ_FUNCTION == 3


def test_module_kinds() -> None:
    assert {k: m.points for k, m in MODULE_KINDS.items()} == {
        "5017": 8,
        "5018": 7,
        "5060": 6,
        "5069": 8,
    }
    assert MODULE_KINDS["5017"].range_code == 0x08
    assert MODULE_KINDS["5018"].range_code == 0x10


def test_adam_module_validation() -> None:
    assert AdamModule("5018").raw_format == "offset"
    assert AdamModule("5017", "twos").spec.unit == "V"
    with pytest.raises(ValueError):
        AdamModule("5051")
    with pytest.raises(ValueError):
        AdamModule("5017", "bcd")


# --- golden raw values ---------------------------------------------------------------
@pytest.mark.parametrize(
    ("raw", "kind", "fmt", "value"),
    [
        # offset binary: 0x0000 = −FS, 0xFFFF = +FS
        (0x0000, "5017", "offset", -10.0),
        (0xFFFF, "5017", "offset", 10.0),
        (0x8000, "5017", "offset", 10.0 / 65535),  # half a step above 0 V
        (0x0000, "5018", "offset", -100.0),
        (0xFFFF, "5018", "offset", 400.0),
        (0x3333, "5018", "offset", 0.0),
        # two's complement: +FS 0x7FFF, −FS 0x8000
        (0x7FFF, "5017", "twos", 10.0),
        (0x8000, "5017", "twos", -10.0),
        (0x0000, "5017", "twos", 0.0),
        (0xC000, "5017", "twos", -5.0),
        (0x7FFF, "5018", "twos", 400.0),
        (0xE000, "5018", "twos", -100.0),
        (0x0000, "5018", "twos", 0.0),
    ],
)
def test_raw_to_value_golden(raw: int, kind: str, fmt: str, value: float) -> None:
    assert raw_to_value(raw, kind, fmt) == pytest.approx(value, abs=1e-9)


@pytest.mark.parametrize(
    ("value", "kind", "fmt", "raw"),
    [
        (-10.0, "5017", "offset", 0x0000),
        (10.0, "5017", "offset", 0xFFFF),
        (5.0, "5017", "offset", 0xBFFF),
        (25.0, "5018", "offset", 0x4000),
        (0.0, "5018", "offset", 0x3333),
        (10.0, "5017", "twos", 0x7FFF),
        (-10.0, "5017", "twos", 0x8000),
        (5.0, "5017", "twos", 0x4000),
        (-5.0, "5017", "twos", 0xC000),
        (400.0, "5018", "twos", 0x7FFF),
        (-100.0, "5018", "twos", 0xE000),
        (25.0, "5018", "twos", 0x0800),
        # clamped to the module range
        (12.0, "5017", "offset", 0xFFFF),
        (-12.0, "5017", "twos", 0x8000),
        (-150.0, "5018", "twos", 0xE000),
        (500.0, "5018", "offset", 0xFFFF),
    ],
)
def test_value_to_raw_golden(value: float, kind: str, fmt: str, raw: int) -> None:
    assert value_to_raw(value, kind, fmt) == raw


def test_codecs_reject_bad_arguments() -> None:
    with pytest.raises(ValueError):
        raw_to_value(0x10000, "5017")
    with pytest.raises(ValueError):
        raw_to_value(-1, "5017")
    with pytest.raises(ValueError):
        raw_to_value(0, "5060")
    with pytest.raises(ValueError):
        raw_to_value(0, "5017", "bcd")
    with pytest.raises(ValueError):
        value_to_raw(math.nan, "5017")


# --- burn-out ------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("raw", "fmt", "burnt"),
    [
        (0xFFFF, "offset", True),  # over-range / open wire
        (0x0000, "offset", True),  # −100 °C: range end
        (0x4000, "offset", False),  # 25 °C
        (0x3333, "offset", False),  # 0 °C
        (0xFFFF, "twos", True),  # open-wire code of the ASCII protocol
        (0x7FFF, "twos", True),  # +FS
        (0x8000, "twos", True),  # −FS
        (0x0800, "twos", False),  # 25 °C
        (0xE000, "twos", False),  # −100 °C
        (0x0000, "twos", False),  # 0 °C (also the ASCII under-range code: not flagged)
    ],
)
def test_is_burnout(raw: int, fmt: str, burnt: bool) -> None:
    assert is_burnout(raw, fmt) is burnt


def test_simulated_open_wire_code_is_burnout_in_both_formats() -> None:
    for fmt in FORMATS:
        assert is_burnout(TC_OPEN_WIRE_RAW, fmt)


# --- properties ----------------------------------------------------------------------
@given(
    kind=st.sampled_from(ANALOG_KINDS),
    fmt=st.sampled_from(FORMATS),
    fraction=st.floats(min_value=0.0, max_value=1.0),
)
def test_round_trip_within_one_lsb(kind: str, fmt: str, fraction: float) -> None:
    lo, hi = OFFSET_BINARY_SPAN[kind]
    value = lo + (hi - lo) * fraction
    back = raw_to_value(value_to_raw(value, kind, fmt), kind, fmt)
    assert abs(back - value) <= lsb(kind, fmt) + 1e-9


@given(
    raw=st.integers(min_value=0, max_value=0xFFFF),
    kind=st.sampled_from(ANALOG_KINDS),
    fmt=st.sampled_from(FORMATS),
)
def test_any_raw_decodes_to_a_finite_number(raw: int, kind: str, fmt: str) -> None:
    value = raw_to_value(raw, kind, fmt)
    assert math.isfinite(value)
    assert isinstance(is_burnout(raw, fmt), bool)


@given(
    value=st.floats(allow_nan=False),
    kind=st.sampled_from(ANALOG_KINDS),
    fmt=st.sampled_from(FORMATS),
)
def test_any_value_encodes_to_16_bits(value: float, kind: str, fmt: str) -> None:
    assert 0 <= value_to_raw(value, kind, fmt) <= 0xFFFF


@given(raw=st.integers(min_value=0, max_value=0xFFFF), fmt=st.sampled_from(FORMATS))
def test_raw_to_value_then_back_is_identity_inside_range(raw: int, fmt: str) -> None:
    value = raw_to_value(raw, "5017", fmt)
    assert value_to_raw(value, "5017", fmt) == raw


# --- pymodbus's bit and word order (STYLE.md: pinned minor; it changed between minors) --------
def test_pymodbus_packs_coils_lsb_first() -> None:
    """FC01 answer: coil ``address + 0`` is bit 0 of the first data byte (Modbus §6.1)."""
    bits = [True, False, True, False, False, False, False, False, True]
    assert ReadCoilsResponse(bits=bits).encode() == bytes([0x02, 0x05, 0x01])
    back = ReadCoilsResponse()
    back.decode(bytes([0x02, 0x05, 0x01]))
    assert back.bits[:9] == bits


def test_pymodbus_sends_registers_big_endian() -> None:
    """FC03/FC04 answer: byte count, then each register high byte first (Modbus §4.2)."""
    answer = ReadHoldingRegistersResponse(registers=[0x1234, 0xFFFF])
    assert answer.encode() == bytes([0x04, 0x12, 0x34, 0xFF, 0xFF])


def test_pymodbus_single_coil_on_is_ff00() -> None:
    """FC05: relay 2 of slot 3 is coil 50; ON is 0xFF00 (Modbus §6.5)."""
    request = WriteSingleCoilRequest(address=coil_address(3, 2), bits=[True])
    assert request.encode() == bytes([0x00, 0x32, 0xFF, 0x00])


# --- Modbus exception answers --------------------------------------------------------------
def test_exception_codes_are_pymodbus_codes() -> None:
    assert set(EXCEPTION_MEANINGS) == {int(c) for c in ExcCodes}
    for code in ExcCodes:
        if code == 0x0A:  # pymodbus spells it GATEWAY_PATH_UNAVIABLE
            assert EXCEPTION_MEANINGS[code] == "gateway path unavailable"
        else:
            assert EXCEPTION_MEANINGS[code] == code.name.lower().replace("_", " ")


def test_exception_answer_message_and_request() -> None:
    answer = ModbusExceptionAnswer(0x04)
    assert (answer.code, str(answer)) == (0x04, "Modbus exception 0x04 (device failure)")
    named = answer.about("slot1 FC03 @8x7")
    assert (named.code, named.what) == (0x04, "slot1 FC03 @8x7")
    assert str(named) == "slot1 FC03 @8x7: Modbus exception 0x04 (device failure)"
    assert str(ModbusExceptionAnswer(0x42)) == "Modbus exception 0x42 (unknown code)"
    # Slot-local data, never a comm failure that PolledDriver would catch.
    assert not isinstance(answer, SupervisorError)
