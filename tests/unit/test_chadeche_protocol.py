"""Chadèche SPI codecs: golden words, round trips, and decoding that never crashes."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.core.errors import ProtocolError
from supervisor.devices.chadeche.config import MAX_CURRENT_A
from supervisor.devices.chadeche.protocol import (
    ADC_MAX_CODE,
    CHIP_SELECT_GPIO,
    DAC_MAX_CODE,
    DIP_SWITCHES,
    MAX_CURRENT_CODE,
    Calibration,
    Chip,
    DacChannel,
    DacWord,
    adc_code_to_voltage_v,
    address_lines,
    current_to_dac_code,
    current_to_dac_command,
    dac_code_to_current_a,
    dac_transfer,
    dac_word_from_bytes,
    dac_word_to_bytes,
    decode_adc_reply,
    decode_dac_word,
    decode_latch,
    dip_switch_text,
    encode_adc_reply,
    encode_dac_word,
    encode_latch,
    voltage_to_adc_code,
)

calibrations = st.builds(
    Calibration,
    current_slope=st.floats(0.8, 1.2),
    current_offset_ma=st.floats(-2.0, 2.0),
    voltage_slope=st.floats(0.9, 1.1),
    voltage_offset_v=st.floats(-0.01, 0.01),
)


# --- DAC words ----------------------------------------------------------------------------
def test_dac_word_channel_a_gain_1_active_code_3000_is_0x3bb8() -> None:
    assert encode_dac_word(DacChannel.A, 3000) == 0x3BB8
    assert dac_transfer(DacChannel.A, 3000) == b"\x3b\xb8"


def test_dac_word_channel_b_full_scale_is_0xbfff() -> None:
    assert encode_dac_word(DacChannel.B, 4095) == 0xBFFF


def test_dac_word_flags_map_to_bits_14_13_12() -> None:
    assert encode_dac_word(DacChannel.A, 0, buffered=True, gain_1x=False, active=False) == 0x4000
    assert encode_dac_word(DacChannel.A, 0, gain_1x=False, active=False) == 0x0000
    assert encode_dac_word(DacChannel.A, 0, active=False) == 0x2000
    assert encode_dac_word(DacChannel.A, 0, gain_1x=False) == 0x1000


def test_dac_word_decodes_golden_value() -> None:
    assert decode_dac_word(0x3BB8) == DacWord(DacChannel.A, 3000, False, True, True)
    assert decode_dac_word(0xC001) == DacWord(DacChannel.B, 1, True, False, False)


def test_dac_code_out_of_range_is_refused() -> None:
    with pytest.raises(ValueError):
        encode_dac_word(DacChannel.A, 4096)
    with pytest.raises(ValueError):
        encode_dac_word(DacChannel.A, -1)


@given(st.integers(0, 0xFFFF))
def test_every_16_bit_dac_word_round_trips(word: int) -> None:
    w = decode_dac_word(word)
    again = encode_dac_word(
        w.channel, w.code, buffered=w.buffered, gain_1x=w.gain_1x, active=w.active
    )
    assert again == word
    assert dac_word_from_bytes(dac_word_to_bytes(word)) == word


@given(st.binary(max_size=6))
def test_random_bytes_never_crash_dac_decoding(data: bytes) -> None:
    try:
        word = dac_word_from_bytes(data)
    except ProtocolError as exc:
        assert len(data) != 2
        assert exc.raw == data
    else:
        assert decode_dac_word(word).code <= DAC_MAX_CODE


# --- ADC replies --------------------------------------------------------------------------
def test_adc_golden_bytes_decode() -> None:
    assert decode_adc_reply(b"\x17\x70") == 3000
    # Sample clocks, null bit and the LSB-first trailing bit are ignored.
    assert decode_adc_reply(b"\xf7\x71") == 3000
    assert decode_adc_reply(b"\x1f\xfe") == 4095
    assert decode_adc_reply(b"\x00\x00") == 0
    assert decode_adc_reply(b"\xff\xff") == 4095


def test_adc_reply_encodes_like_an_mcp3201() -> None:
    assert encode_adc_reply(3000) == b"\x17\x70"
    assert encode_adc_reply(0x0002) == b"\x00\x05"  # B1 repeated as the 16th bit


@given(st.integers(0, ADC_MAX_CODE))
def test_every_adc_code_round_trips(code: int) -> None:
    assert decode_adc_reply(encode_adc_reply(code)) == code


@given(st.binary(max_size=6))
def test_random_bytes_never_crash_adc_decoding(data: bytes) -> None:
    try:
        code = decode_adc_reply(data)
    except ProtocolError:
        assert len(data) != 2
    else:
        assert 0 <= code <= ADC_MAX_CODE


def test_voltage_to_adc_code_clamps_to_the_converter_range() -> None:
    assert voltage_to_adc_code(-0.5) == 0
    assert voltage_to_adc_code(1.2345) == 1234 or voltage_to_adc_code(1.2345) == 1235
    assert voltage_to_adc_code(9.0) == ADC_MAX_CODE
    assert voltage_to_adc_code(math.inf) == ADC_MAX_CODE


# --- latch, addresses ---------------------------------------------------------------------
def test_latch_byte_decodes_back_to_the_same_direction() -> None:
    assert decode_latch(encode_latch(True)) is True
    assert decode_latch(encode_latch(False)) is False
    # Every bit carries the level, whichever one the flip-flop samples.
    assert encode_latch(True) in (b"\x00", b"\xff")
    assert encode_latch(True) != encode_latch(False)


@given(st.binary(min_size=1, max_size=4))
def test_random_bytes_never_crash_latch_decoding(data: bytes) -> None:
    assert isinstance(decode_latch(data), bool)


def test_empty_latch_transfer_is_a_protocol_error() -> None:
    with pytest.raises(ProtocolError):
        decode_latch(b"")


def test_address_lines_are_a0_bit_0_and_a1_bit_1() -> None:
    assert [address_lines(a) for a in range(4)] == [
        (False, False),
        (True, False),
        (False, True),
        (True, True),
    ]
    with pytest.raises(ValueError):
        address_lines(4)


def test_dip_switch_table_matches_seed_table_1() -> None:
    assert dip_switch_text(0) == "SW1 OFF, SW2 ON, SW3 OFF, SW4 ON"
    assert dip_switch_text(3) == "SW1 ON, SW2 OFF, SW3 ON, SW4 OFF"
    for address, (sw1, sw2, sw3, sw4) in DIP_SWITCHES.items():
        a0, a1 = address_lines(address)
        # Each pair picks A or /A: SW1/SW2 for A0, SW3/SW4 for A1, never both.
        assert (sw1, sw2) == (a0, not a0)
        assert (sw3, sw4) == (a1, not a1)


def test_chip_selects_are_gpio_3_6_5() -> None:
    assert (Chip.DAC.gpio, Chip.ADC.gpio, Chip.LATCH.gpio) == (3, 6, 5)
    assert set(CHIP_SELECT_GPIO) == set(Chip)


# --- current and voltage scaling ----------------------------------------------------------
def test_one_dac_step_is_a_tenth_of_a_milliamp() -> None:
    assert current_to_dac_code(0.3) == 3000
    assert current_to_dac_code(0.0001) == 1
    assert dac_code_to_current_a(3000) == pytest.approx(0.3)


def test_dac_code_is_for_the_magnitude_only() -> None:
    assert current_to_dac_code(-0.25) == current_to_dac_code(0.25) == 2500


def test_current_above_400_ma_is_clamped_and_flagged() -> None:
    assert current_to_dac_command(0.5) == (MAX_CURRENT_CODE, True)
    assert current_to_dac_command(MAX_CURRENT_A) == (MAX_CURRENT_CODE, False)
    # A calibration that asks for more than 400 mA of command is clamped too.
    assert current_to_dac_command(0.4, Calibration(current_slope=1.05)).clamped


def test_negative_command_near_zero_becomes_code_0_without_flag() -> None:
    assert current_to_dac_command(0.0, Calibration(current_offset_ma=-0.5)) == (0, False)


def test_non_finite_current_is_refused() -> None:
    with pytest.raises(ValueError):
        current_to_dac_code(math.nan)


def test_current_calibration_follows_the_seed_fit() -> None:
    # §III.F.1: setpoint = a·measured + b, so the command for 200 mA true is a·200 + b.
    cal = Calibration(current_slope=0.9823, current_offset_ma=0.8)
    assert current_to_dac_code(0.2, cal) == round((0.9823 * 200 + 0.8) * 10)
    assert dac_code_to_current_a(current_to_dac_code(0.2, cal), cal) == pytest.approx(
        0.2, abs=0.00006
    )


@given(st.floats(0.0, MAX_CURRENT_A * 0.95), calibrations)
def test_current_round_trips_within_half_a_step(current_a: float, cal: Calibration) -> None:
    code, clamped = current_to_dac_command(current_a, cal)
    back = dac_code_to_current_a(code, cal)
    if clamped:
        assert back <= current_a
    elif code > 0:
        assert back == pytest.approx(current_a, abs=0.05e-3 / cal.current_slope + 1e-12)


def test_voltage_calibration_follows_the_seed_fit() -> None:
    # §III.F.2: V_voltmeter = s·V_adc + o.
    cal = Calibration(voltage_slope=1.0065, voltage_offset_v=0.0003)
    assert adc_code_to_voltage_v(1250, cal) == pytest.approx(1.0065 * 1.25 + 0.0003)
    assert adc_code_to_voltage_v(1250) == pytest.approx(1.25)


def test_calibration_refuses_non_positive_slopes_and_nan() -> None:
    with pytest.raises(ValueError):
        Calibration(current_slope=0.0)
    with pytest.raises(ValueError):
        Calibration(voltage_offset_v=math.nan)
