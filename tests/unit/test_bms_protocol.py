"""BMS CAN frames: DBC golden values (seed 002 annex IV, reference/devices.md) and fuzzing."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.core.errors import ProtocolError
from supervisor.devices.bms.protocol import (
    BMS_CURRENT_SIGN,
    FRAME_IDS,
    PACK_CURRENT_ID,
    PACK_TEMPERATURES_ID,
    PACK_VOLTAGES_ID,
    PERIODS_MS,
    BmsValues,
    UnknownFrameError,
    decode,
    encode,
    encode_values,
    implausible,
    load_database,
    period_s,
)


def test_the_dbc_declares_the_three_bms_frames_with_their_lengths() -> None:
    db = load_database()
    lengths = {m.frame_id: m.length for m in db.messages}
    assert lengths == {0x1B0: 8, 0x2B0: 4, 0x3B0: 6}
    assert FRAME_IDS == (PACK_VOLTAGES_ID, PACK_CURRENT_ID, PACK_TEMPERATURES_ID)
    assert (PACK_VOLTAGES_ID, PACK_CURRENT_ID, PACK_TEMPERATURES_ID) == (0x1B0, 0x2B0, 0x3B0)


def test_periods_are_1000_100_1000_ms() -> None:
    assert dict(PERIODS_MS) == {0x1B0: 1000, 0x2B0: 100, 0x3B0: 1000}
    assert period_s(0x2B0) == pytest.approx(0.1)


def test_a_12_8_v_pack_encodes_as_00_00_32_00() -> None:
    data = encode("PackVoltages", {"PackVoltage": 12.8, "MinCellVoltage": 0, "MaxCellVoltage": 0})
    assert data[:4] == bytes.fromhex("00003200")
    assert decode(0x1B0, data)["PackVoltage"] == pytest.approx(12.8)


def test_the_seed_sample_voltage_frame_decodes_to_12800_16_v_at_the_stated_scale() -> None:
    values = decode(0x1B0, bytes.fromhex("00C350A0030005F0"))
    assert values["PackVoltage"] == pytest.approx(12_800.16)
    assert values["MinCellVoltage"] == pytest.approx(0.768)
    assert values["MaxCellVoltage"] == pytest.approx(1.52)


def test_pack_current_is_a_big_endian_ieee_float32() -> None:
    assert decode(0x2B0, bytes.fromhex("42C80000")) == {"PackCurrent": 100.0}
    assert decode(0x2B0, bytes.fromhex("BFC00000")) == {"PackCurrent": -1.5}
    assert encode(0x2B0, {"PackCurrent": -1.5}) == bytes.fromhex("BFC00000")


def test_temperatures_are_signed_tenths_of_a_degree() -> None:
    # First six bytes of the seed's sample 0x3B0 frame, then a negative one.
    assert decode(0x3B0, bytes.fromhex("006400320019")) == pytest.approx(
        {"MinTemp": 10.0, "MaxTemp": 5.0, "AvgTemp": 2.5}
    )
    assert decode(0x3B0, bytes.fromhex("FF9C0000FFFF")) == pytest.approx(
        {"MinTemp": -10.0, "MaxTemp": 0.0, "AvgTemp": -0.1}
    )


@pytest.mark.parametrize(
    ("frame_id", "data"),
    [(0x1B0, "00003200"), (0x2B0, "42C800"), (0x3B0, ""), (0x3B0, "0064003200")],
)
def test_a_short_frame_is_a_protocol_error_keeping_the_raw_bytes(frame_id: int, data: str) -> None:
    raw = bytes.fromhex(data)
    with pytest.raises(ProtocolError) as info:
        decode(frame_id, raw)
    assert info.value.raw == raw
    assert not isinstance(info.value, UnknownFrameError)


def test_a_frame_padded_to_8_bytes_decodes_unless_extra_bytes_are_refused() -> None:
    # The seed's sample current frame: 8 bytes where the DBC says 4 (a controller pads).
    padded = bytes.fromhex("0000006400000000")
    value = decode(0x2B0, padded)["PackCurrent"]
    assert value == pytest.approx(1.4e-43, rel=0.01)  # 0x64 as float32 bits: a denormal
    with pytest.raises(ProtocolError) as info:
        decode(0x2B0, padded, allow_extra_bytes=False)
    assert info.value.raw == padded


ANNEX_IV = {  # seed 002 annex IV, verbatim: 8 bytes each
    PACK_VOLTAGES_ID: "00 C3 50 A0 03 00 05 F0",
    PACK_CURRENT_ID: "00 00 00 64 00 00 00 00",
    PACK_TEMPERATURES_ID: "00 64 00 32 00 19 00 00",
}


def test_the_annex_iv_frames_decode_as_the_seeds_code_does_and_are_implausible() -> None:
    decoded = {i: decode(i, bytes.fromhex(h)) for i, h in ANNEX_IV.items()}
    assert decoded[PACK_VOLTAGES_ID] == pytest.approx(
        {"PackVoltage": 12800.16, "MinCellVoltage": 0.768, "MaxCellVoltage": 1.52}
    )
    assert decoded[PACK_TEMPERATURES_ID] == pytest.approx(
        {"MinTemp": 10.0, "MaxTemp": 5.0, "AvgTemp": 2.5}
    )
    why = {i: implausible(i, v) for i, v in decoded.items()}
    assert set(why[PACK_VOLTAGES_ID]) == {"PackVoltage"}  # the cells are 0.768 and 1.52 V
    assert "outside [0, 1000]" in why[PACK_VOLTAGES_ID]["PackVoltage"]
    assert "subnormal" in why[PACK_CURRENT_ID]["PackCurrent"]
    assert set(why[PACK_TEMPERATURES_ID]) == {"MinTemp", "MaxTemp", "AvgTemp"}
    assert "MinTemp 10 degC > MaxTemp 5 degC" in why[PACK_TEMPERATURES_ID]["MinTemp"]


def test_a_plausible_pack_breaks_no_rule() -> None:
    frames = encode_values(
        BmsValues(14.8, 3.69, 3.71, -5.0, min_temp_c=-1.5, max_temp_c=24.0, avg_temp_c=-0.7)
    )
    assert all(implausible(i, decode(i, data)) == {} for i, data in frames.items())
    assert implausible(PACK_CURRENT_ID, {"PackCurrent": 0.0}) == {}  # zero is no subnormal


@pytest.mark.parametrize(
    ("frame_id", "signals", "broken"),
    [
        (
            PACK_VOLTAGES_ID,
            {"PackVoltage": 14.8, "MinCellVoltage": 3.8, "MaxCellVoltage": 3.7},
            {"MinCellVoltage", "MaxCellVoltage"},
        ),
        (
            PACK_VOLTAGES_ID,
            {"PackVoltage": 14.8, "MinCellVoltage": 3.7, "MaxCellVoltage": 5.2},
            {"MaxCellVoltage"},
        ),
        (PACK_CURRENT_ID, {"PackCurrent": -1500.0}, {"PackCurrent"}),
        (PACK_TEMPERATURES_ID, {"MinTemp": 20.0, "MaxTemp": 25.0, "AvgTemp": 26.0}, {"AvgTemp"}),
        (PACK_TEMPERATURES_ID, {"MinTemp": -41.0, "MaxTemp": 25.0, "AvgTemp": 20.0}, {"MinTemp"}),
    ],
)
def test_each_plausibility_rule_names_the_signals_that_break_it(
    frame_id: int, signals: dict[str, float], broken: set[str]
) -> None:
    assert set(implausible(frame_id, signals)) == broken


@pytest.mark.parametrize("bits", ["7FC00000", "7F800000", "FF800000"])
def test_a_non_finite_current_is_a_protocol_error(bits: str) -> None:
    with pytest.raises(ProtocolError):
        decode(0x2B0, bytes.fromhex(bits))


def test_an_unknown_id_is_an_unknown_frame_error() -> None:
    with pytest.raises(UnknownFrameError) as info:
        decode(0x123, b"\x01\x02")
    assert info.value.raw == b"\x01\x02"
    # Identifiers the DBC knows only as standard frames are not found through masking.
    with pytest.raises(UnknownFrameError):
        decode(0x800001B0, bytes(8))


def test_encode_rejects_unknown_messages_and_values_out_of_the_dbc_range() -> None:
    with pytest.raises(ValueError):
        encode("NoSuchMessage", {})
    with pytest.raises(ValueError):
        encode(0x123, {})
    with pytest.raises(ValueError):
        encode(0x3B0, {"MinTemp": 5000.0, "MaxTemp": 0.0, "AvgTemp": 0.0})
    with pytest.raises(ValueError):
        encode(0x3B0, {"MinTemp": 1.0})


def test_current_sign_is_plus_or_minus_one() -> None:
    assert BMS_CURRENT_SIGN in (+1, -1)


def test_encode_values_round_trips_through_decode_with_the_current_sign() -> None:
    values = BmsValues(
        pack_voltage_v=13.2,
        min_cell_v=3.28,
        max_cell_v=3.31,
        pack_current_a=-2.5,
        min_temp_c=-5.3,
        max_temp_c=31.2,
        avg_temp_c=24.0,
    )
    frames = encode_values(values)
    assert set(frames) == set(FRAME_IDS)
    assert decode(0x1B0, frames[0x1B0]) == pytest.approx(
        {"PackVoltage": 13.2, "MinCellVoltage": 3.28, "MaxCellVoltage": 3.31}
    )
    assert decode(0x2B0, frames[0x2B0])["PackCurrent"] * BMS_CURRENT_SIGN == -2.5
    assert decode(0x3B0, frames[0x3B0]) == pytest.approx(
        {"MinTemp": -5.3, "MaxTemp": 31.2, "AvgTemp": 24.0}
    )


@given(
    frame_id=st.one_of(st.sampled_from(FRAME_IDS), st.integers(-(2**32), 2**32)),
    data=st.binary(max_size=72),
    allow_extra=st.booleans(),
)
def test_any_id_and_bytes_give_finite_values_or_a_protocol_error(
    frame_id: int, data: bytes, allow_extra: bool
) -> None:
    try:
        values = decode(frame_id, data, allow_extra_bytes=allow_extra)
    except ProtocolError as exc:
        assert exc.raw == data
        return
    assert frame_id in FRAME_IDS
    assert all(isinstance(v, float) and math.isfinite(v) for v in values.values())


@given(
    voltage=st.integers(0, 1_000_000),
    cells=st.tuples(st.integers(0, 5000), st.integers(0, 5000)),
    temps=st.tuples(*(st.integers(-400, 1250) for _ in range(3))),
    # Within the DBC's (plausibility) range: encode refuses values outside it.
    current=st.floats(-1000, 1000, width=32),
)
def test_every_in_range_value_round_trips(
    voltage: int,
    cells: tuple[int, int],
    temps: tuple[int, int, int],
    current: float,
) -> None:
    signals = {
        "PackVoltage": voltage * 0.001,
        "MinCellVoltage": cells[0] * 0.001,
        "MaxCellVoltage": cells[1] * 0.001,
    }
    assert decode(0x1B0, encode(0x1B0, signals)) == pytest.approx(signals)
    assert decode(0x2B0, encode(0x2B0, {"PackCurrent": current})) == {"PackCurrent": current}
    t = {"MinTemp": temps[0] * 0.1, "MaxTemp": temps[1] * 0.1, "AvgTemp": temps[2] * 0.1}
    assert decode(0x3B0, encode(0x3B0, t)) == pytest.approx(t)
