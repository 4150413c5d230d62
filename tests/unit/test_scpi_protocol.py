"""SCPI codecs (supervisor.fieldbus.scpi and the EA's): golden replies from devices.md and
seed 002 §2.2, and fuzzing (every parser returns a value or raises ProtocolError, never
anything else)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.core.errors import ProtocolError
from supervisor.devices.ea.protocol import (
    LockOwner,
    Measurement,
    format_meas_array,
    is_ea,
    model_matches,
    normalize_header,
    parse_command,
    parse_lock_owner,
    parse_meas_array,
)
from supervisor.fieldbus.scpi import (
    COMMAND_SEPARATOR,
    Command,
    Identity,
    LineFramer,
    ScpiError,
    bit_set,
    decode_line,
    encode_line,
    format_error,
    format_idn,
    format_number,
    format_setting,
    join_commands,
    parse_error,
    parse_idn,
    parse_number,
    parse_on_off,
    parse_register,
    split_commands,
    split_reply,
)

SEED_IDN = (
    "EA Elektro-Automatik GmbH & Co. KG, ELR 10200-50, 2775120003, "
    "V3.03 05.10.2022 V3.06 24.05.2023 V1.0.2.20"
)


# --- framing -----------------------------------------------------------------------------
def test_decode_line_strips_lf_and_crlf() -> None:
    assert decode_line(b"48.00 V\n") == "48.00 V"
    assert decode_line(b"48.00 V\r\n") == "48.00 V"
    assert decode_line(b"OFF") == "OFF"


def test_decode_line_refuses_binary_with_the_raw_bytes() -> None:
    with pytest.raises(ProtocolError) as info:
        decode_line(b"\x00\xff\n", "psu")
    assert info.value.raw == b"\x00\xff\n"
    assert info.value.device == "psu"


def test_encode_line_appends_lf_and_refuses_embedded_line_breaks() -> None:
    assert encode_line("*IDN?") == b"*IDN?\n"
    with pytest.raises(ValueError):
        encode_line("OUTP ON\nOUTP OFF")


def test_framer_cuts_a_stream_into_lines_across_chunks() -> None:
    framer = LineFramer()
    assert framer.feed(b"ON;REM") == []
    assert framer.feed(b'OTE\r\n0,"No error"\n1') == ["ON;REMOTE", '0,"No error"']
    assert framer.pending == b"1"


def test_framer_refuses_an_endless_line() -> None:
    framer = LineFramer()
    with pytest.raises(ProtocolError):
        framer.feed(b"x" * 10_000)


def test_commands_join_and_split_with_semicolons() -> None:
    line = join_commands(["CURR 2", "VOLT 16.8", "SINK:CURR 0"])
    assert line == COMMAND_SEPARATOR.join(["CURR 2", "VOLT 16.8", "SINK:CURR 0"])
    assert split_commands(line) == ["CURR 2", "VOLT 16.8", "SINK:CURR 0"]
    assert split_commands("OUTP?;;") == ["OUTP?"]
    with pytest.raises(ValueError):
        join_commands(["OUTP ON; OUTP OFF"])


def test_split_reply_needs_exactly_the_expected_count() -> None:
    assert split_reply("1.00 V, 2.00 A, 2.00 W;ON; REMOTE;0", 4) == [
        "1.00 V, 2.00 A, 2.00 W",
        "ON",
        "REMOTE",
        "0",
    ]
    with pytest.raises(ProtocolError):
        split_reply("ON;REMOTE", 3)
    with pytest.raises(ProtocolError):
        split_reply("ON;;0", 3)


# --- commands ---------------------------------------------------------------------------------
def test_parse_command_handles_queries_arguments_and_long_forms() -> None:
    assert parse_command("*IDN?") == Command("*IDN", True, None)
    assert parse_command("volt 12.00 V") == Command("VOLT", False, "12.00 V")
    assert parse_command("SINK:CURR:PROT?") == Command("SINK:CURR:PROT", True, None)
    assert parse_command("MEASure:ARRay?") == Command("MEAS:ARR", True, None)
    assert parse_command(":SYST:LOCK ON") == Command("SYST:LOCK", False, "ON")
    assert normalize_header("SYSTem:COMMunicate:MONitoring:TIMe") == "SYST:COMM:MON:TIM"
    with pytest.raises(ProtocolError):
        parse_command("12 V")


# --- numbers ----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("text", "unit", "value"),
    [
        ("48.00 V", "V", 48.0),
        ("-1.50 A", "A", -1.5),
        ("72.00 W", "W", 72.0),
        ("48", "V", 48.0),
        ("4.8E+01", None, 48.0),
        ("12.00V", "V", 12.0),
        ("+0.5 a", "A", 0.5),
    ],
)
def test_parse_number_reads_values_with_and_without_unit(
    text: str, unit: str | None, value: float
) -> None:
    assert parse_number(text, unit=unit) == value


@pytest.mark.parametrize("text", ["", "V", "48.00 A", "nan", "inf V", "9.91E37", "1,5 V", "1e999"])
def test_parse_number_refuses_wrong_unit_and_non_numbers(text: str) -> None:
    with pytest.raises(ProtocolError):
        parse_number(text, "psu", "V")


def test_format_number_is_fixed_point_and_refuses_nan() -> None:
    assert format_number(2.0) == "2.0000"
    assert format_number(-0.0) == "0.0000"
    assert format_setting("VOLT", 16.8) == "VOLT 16.8000"
    with pytest.raises(ValueError):
        format_number(float("nan"))


@given(st.floats(-1e6, 1e6, allow_nan=False))
def test_formatted_numbers_parse_back(value: float) -> None:
    assert parse_number(format_number(value)) == pytest.approx(value, abs=1e-4)


# --- replies ---------------------------------------------------------------------------------
def test_meas_array_golden_reply_from_devices_md() -> None:
    assert parse_meas_array("48.00 V, 1.50 A, 72.00 W") == Measurement(48.0, 1.5, 72.0)


def test_meas_array_keeps_sink_current_and_power_negative() -> None:
    m = parse_meas_array("15.08 V, -2.00 A, -30.16 W")
    assert m.current_a == -2.0
    assert m.power_w == -30.16


def test_meas_array_round_trips_through_the_simulator_format() -> None:
    m = Measurement(14.8, -2.5, -37.0)
    assert parse_meas_array(format_meas_array(m)) == m


@pytest.mark.parametrize(
    "text", ["48.00 V, 1.50 A", "48.00 V, 1.50 V, 72.00 W", "48.00 V; 1.50 A; 72.00 W", ""]
)
def test_meas_array_refuses_malformed_replies(text: str) -> None:
    with pytest.raises(ProtocolError):
        parse_meas_array(text)


def test_idn_golden_reply_from_seed_002() -> None:
    idn = parse_idn(SEED_IDN)
    assert idn == Identity(
        "EA Elektro-Automatik GmbH & Co. KG",
        "ELR 10200-50",
        "2775120003",
        "V3.03 05.10.2022 V3.06 24.05.2023 V1.0.2.20",
    )
    assert is_ea(idn)


def test_idn_tolerates_the_trailing_comma_seen_in_seed_002() -> None:
    assert parse_idn(SEED_IDN + ",") == parse_idn(SEED_IDN)
    assert parse_idn(format_idn(parse_idn(SEED_IDN))) == parse_idn(SEED_IDN)


def test_idn_of_another_manufacturer_parses_but_is_not_ea() -> None:
    assert not is_ea(parse_idn("Keysight Technologies,N5767A,MY123,A.01"))


@pytest.mark.parametrize("text", ["", "EA Elektro-Automatik", "EA, PSB 10060-60, 123", ", , , "])
def test_idn_refuses_incomplete_replies(text: str) -> None:
    with pytest.raises(ProtocolError):
        parse_idn(text)


def test_model_comparison_ignores_case_spacing_and_the_ea_prefix() -> None:
    assert model_matches("PSB 10060-60", "EA-PSB  10060-60")
    assert model_matches("elr 10200-50", "ELR 10200-50")
    assert not model_matches("PSB 10060-60", "ELR 10200-50")


def test_error_queue_golden_replies() -> None:
    assert parse_error('0,"No error"') == ScpiError(0, "No error")
    assert parse_error('-201,"Invalid while in local"') == ScpiError(-201, "Invalid while in local")
    assert parse_error("-222, Data out of range") == ScpiError(-222, "Data out of range")
    assert format_error(-222) == '-222,"Data out of range"'
    assert str(ScpiError(-100, "Command error")) == '-100,"Command error"'
    with pytest.raises(ProtocolError):
        parse_error("No error")


def test_status_registers_are_non_negative_integers() -> None:
    assert parse_register("0") == 0
    assert parse_register("+5") == 5
    assert bit_set(parse_register("3"), 1)
    for text in ("-1", "1.5", "0x10", "", "99999999999"):
        with pytest.raises(ProtocolError):
            parse_register(text)


def test_lock_owner_values() -> None:
    assert parse_lock_owner("REMOTE") is LockOwner.REMOTE
    assert parse_lock_owner("none") is LockOwner.NONE
    assert parse_lock_owner(" LOCAL ") is LockOwner.LOCAL
    with pytest.raises(ProtocolError):
        parse_lock_owner("USB")


def test_on_off_values() -> None:
    assert parse_on_off("ON") is True
    assert parse_on_off("off") is False
    assert parse_on_off("1") is True
    with pytest.raises(ProtocolError):
        parse_on_off("MAYBE")


# --- fuzzing: a value or ProtocolError, never another exception ---------------------------------
TEXT_PARSERS: list[Callable[[str], object]] = [
    parse_number,
    lambda t: parse_number(t, "psu", "A"),
    parse_meas_array,
    parse_idn,
    parse_error,
    parse_register,
    parse_lock_owner,
    parse_on_off,
    parse_command,
    lambda t: split_reply(t, 3),
]


@pytest.mark.parametrize("parser", TEXT_PARSERS)
@given(text=st.text(max_size=80))
def test_text_parsers_only_return_or_raise_protocol_error(
    parser: Callable[[str], object], text: str
) -> None:
    with contextlib.suppress(ProtocolError):
        parser(text)


@pytest.mark.parametrize("parser", TEXT_PARSERS)
@given(text=st.from_regex(r"[-+0-9.eE ,;:\"A-Z?*a-z]{0,40}", fullmatch=True))
def test_text_parsers_survive_reply_like_strings(
    parser: Callable[[str], object], text: str
) -> None:
    with contextlib.suppress(ProtocolError):
        parser(text)


@given(st.binary(max_size=200))
def test_decode_line_only_returns_text_or_raises_protocol_error(raw: bytes) -> None:
    try:
        text = decode_line(raw)
    except ProtocolError:
        return
    assert text.isascii()


@given(st.lists(st.binary(max_size=100), max_size=10))
def test_framer_only_returns_lines_or_raises_protocol_error(chunks: list[bytes]) -> None:
    framer = LineFramer()
    try:
        for chunk in chunks:
            for line in framer.feed(chunk):
                assert "\n" not in line
    except ProtocolError:
        pass
