"""Text files: bytes → text with the encoding they were written in, and tables of cells.

What an engineer hands the supervisor is UTF-8 from an editor or CP1252 from Excel on a French
Windows (seed 000 §III.D), with LF, CRLF or CR line ends; YAML must be UTF-8. Every refusal
names the file, and the line and column of the bad byte."""

from __future__ import annotations

import codecs
import csv
import math
from collections.abc import Callable

import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.config.text import (
    Cell,
    DecodedText,
    Layout,
    decode_text,
    decode_yaml,
    line_col,
    read_table,
)
from supervisor.core.errors import ConfigError

FILE = "bench/file.txt"


Decode = Callable[[bytes, str], DecodedText]


def refusal(decode: Decode, data: bytes) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        decode(data, FILE)
    return info.value


# --------------------------------------------------------------------------------------------
# Encodings


@pytest.mark.parametrize("decode", [decode_text, decode_yaml], ids=["text", "yaml"])
def test_utf8_is_read_as_utf8(decode: Decode) -> None:
    got = decode("bench: \u00e9t\u00e9\n".encode(), FILE)
    assert got == DecodedText("bench: été\n", "UTF-8")
    assert not got.bom


@pytest.mark.parametrize("decode", [decode_text, decode_yaml], ids=["text", "yaml"])
def test_a_utf8_bom_is_removed_and_remembered(decode: Decode) -> None:
    got = decode(codecs.BOM_UTF8 + "été\n".encode(), FILE)
    assert got.text == "été\n"
    assert got.encoding == "UTF-8 with BOM"
    assert got.bom


def test_a_cp1252_accent_from_excel_is_read_as_that_accent() -> None:
    got = decode_text(b"Mesur\xe9 (mA);R\xe9veil \xe0 20 heures\x80\n", FILE)
    assert got == DecodedText("Mesuré (mA);Réveil à 20 heures€\n", "CP1252")


def test_a_yaml_file_must_be_utf8_a_cp1252_accent_is_refused_where_it_is() -> None:
    error = refusal(decode_yaml, b"bench: t\ndevices: {}\n# caf\xe9\n")
    assert (error.file, error.line, error.col) == (FILE, 3, 6)
    assert error.message == (
        "invalid UTF-8 byte 0xe9 at line 3, column 6: the file must be UTF-8 encoded"
    )


def test_the_column_of_a_bad_byte_counts_characters_not_bytes() -> None:
    # "  été caf" is 9 characters but 11 bytes: the bad byte is character 10 of line 3.
    error = refusal(decode_yaml, b"a:\n  b: 1\n  " + "été caf".encode() + b"\xe9\n")
    assert (error.line, error.col) == (3, 10)


@pytest.mark.parametrize("byte", [0x81, 0x8D, 0x8F, 0x90, 0x9D], ids=lambda b: f"0x{b:02X}")
def test_a_byte_cp1252_leaves_undefined_is_refused_at_its_line_and_column(byte: int) -> None:
    error = refusal(decode_text, b"t;I\r\n0;0,5\r\n10;1" + bytes([byte]) + b"\r\n")
    assert (error.file, error.line, error.col) == (FILE, 3, 5)
    assert error.message == f"byte 0x{byte:02x} is neither UTF-8 nor CP1252 (Windows-1252) text"


def test_a_file_with_a_utf8_bom_must_be_utf8_all_through() -> None:
    error = refusal(decode_text, codecs.BOM_UTF8 + b"one\ntwo\nthr\xe9e\n")
    assert (error.line, error.col) == (3, 4)
    assert error.message == "invalid UTF-8 byte 0xe9 in a file with a UTF-8 BOM"


@pytest.mark.parametrize(
    "bom", [codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE, codecs.BOM_UTF32_LE], ids=["le", "be", "32"]
)
def test_a_utf16_bom_is_refused_for_yaml_naming_the_encoding(bom: bytes) -> None:
    error = refusal(decode_yaml, bom + "a: 1\n".encode("utf-16-le"))
    assert (error.file, error.line, error.col) == (FILE, 1, 1)
    assert error.message == (
        "file is encoded as UTF-16 (it has a UTF-16 byte order mark); the file must be UTF-8"
    )


def test_a_utf16_bom_is_refused_for_text_files_too_instead_of_reading_garbage() -> None:
    error = refusal(decode_text, codecs.BOM_UTF16_LE + "0;1\n".encode("utf-16-le"))
    assert (error.line, error.col) == (1, 1)
    assert "UTF-16" in error.message
    assert "must be UTF-8 or CP1252" in error.message


def test_the_text_keeps_the_bytes_it_was_given_encode_gives_them_back() -> None:
    for data in (b"a\r\nb\n", codecs.BOM_UTF8 + "é\r".encode(), b"caf\xe9\r\n"):
        decoded = decode_text(data, FILE)
        assert decoded.encode(decoded.text) == data


# --------------------------------------------------------------------------------------------
# Line ends


@pytest.mark.parametrize(
    ("data", "style", "newline"),
    [
        (b"a\r\nb\r\n", "CRLF", "\r\n"),
        (b"a\nb\n", "LF", "\n"),
        (b"a\rb\r", "CR", "\r"),
        (b"a\r\nb\n", "CRLF+LF", "\r\n"),
        (b"a", "one line", "\n"),
    ],
    ids=["crlf", "lf", "cr", "mixed", "one-line"],
)
def test_crlf_cr_and_lf_line_ends_are_all_lines_and_the_file_says_which_it_uses(
    data: bytes, style: str, newline: str
) -> None:
    decoded = decode_text(data, FILE)
    assert decoded.newline_style == style
    assert decoded.newline == newline
    assert decoded.lines()[:2] == (["a", "b"] if data != b"a" else ["a"])
    assert decoded.text == data.decode()  # line ends are kept as they were


def test_a_bad_byte_after_crlf_and_cr_lines_is_on_the_line_an_editor_shows() -> None:
    error = refusal(decode_text, b"one\r\ntwo\rthree\n\x81")
    assert (error.line, error.col) == (4, 1)


def test_yaml_positions_count_line_breaks_like_pyyaml() -> None:
    # YAML 1.1 §5.4: NEL, LS and PS break lines too, and a BOM takes no column.
    text = "a\x85b\u2028c\r\n\ufeffd"
    assert line_col(text, len(text), yaml=True) == (4, 2)
    assert line_col(text, len(text)) == (2, 3)  # other files: CR, LF and CRLF only


# --------------------------------------------------------------------------------------------
# Tables


def table(text: str, **options: bool) -> tuple[Layout, list[list[tuple[str, int]]]]:
    layout, rows = read_table(decode_text(text.encode(), FILE), FILE, **options)
    return layout, [[(c.text, c.col) for c in row.cells] for row in rows]


@pytest.mark.parametrize("delimiter", [";", "\t"], ids=["semicolon", "tab"])
def test_with_semicolons_or_tabs_a_comma_is_a_decimal_comma(delimiter: str) -> None:
    layout, rows = table(f"0{delimiter}0,5\n10{delimiter}1,5\n")
    assert layout == Layout(delimiter)
    assert layout.decimal_comma
    assert rows[1] == [("10", 1), ("1,5", 4)]
    assert layout.number("1,5") == 1.5


@pytest.mark.parametrize(
    ("text", "value"),
    [
        (" 60 ", 60.0),
        ("+1.5", 1.5),
        (".5", 0.5),
        ("1e3", 1000.0),
        ("-2E-1", -0.2),
        ("inf", math.inf),
    ],
)
def test_a_cell_number_is_what_strtod_reads(text: str, value: float) -> None:
    assert Layout(",").number(text) == value


@pytest.mark.parametrize("text", ["６0", "٣", "1_000", "0x10", "1.5.2", "", "1e", "nan s"])
def test_a_cell_in_other_digits_or_python_syntax_is_not_a_number(text: str) -> None:
    # float() alone reads '６0' as 60 and '1_000' as 1000 (issue 9, the mutation corpus).
    assert Layout(",").number(text) is None


def test_with_commas_a_comma_separates_cells_and_a_point_is_the_decimal_point() -> None:
    layout, rows = table("0,0.5\n10,1.5\n")
    assert layout == Layout(",")
    assert not layout.decimal_comma
    assert rows == [[("0", 1), ("0.5", 3)], [("10", 1), ("1.5", 4)]]


def test_runs_of_blanks_separate_cells_only_where_the_caller_allows_it() -> None:
    layout, rows = table("0   0.1\n50  50.9\n", blanks=True)
    assert layout == Layout(" ")
    assert rows == [[("0", 1), ("0.1", 5)], [("50", 1), ("50.9", 5)]]
    layout, rows = table("0   0.1\n50  50.9\n")
    assert rows == [[("0   0.1", 1)], [("50  50.9", 1)]]


def test_the_header_line_does_not_choose_the_layout_its_titles_hold_any_punctuation() -> None:
    layout, rows = table("Consigne, mA  Mesure, mA\n0 0.1\n50 50.9\n", blanks=True)
    assert layout == Layout(" ")
    assert rows[0] == [("Consigne,", 1), ("mA", 11), ("Mesure,", 15), ("mA", 23)]
    layout, _ = table("t (s),I (A)\n0;0,5\n")
    assert layout == Layout(";")


def test_every_cell_keeps_its_line_and_the_column_of_its_first_non_blank() -> None:
    _, rows = read_table(decode_text(b"\n# note\nt; I\n\n 0 ;  0,5;\n", FILE), FILE)
    assert [(r.line, r.end_col) for r in rows] == [(2, 7), (3, 5), (5, 11)]
    assert rows[2].cells == (Cell("0", 2), Cell("0,5", 7), Cell("", 11))


def test_blank_lines_are_skipped_and_hash_lines_too_when_they_are_comments() -> None:
    _, rows = table("# readings\n\n0;1\n   \n2;3\n", comments=True)
    assert rows == [[("0", 1), ("1", 3)], [("2", 1), ("3", 3)]]


def test_quotes_are_ordinary_characters_so_columns_stay_exact() -> None:
    _, rows = table('"t";"I"\n0;"1"\n')
    assert rows == [[('"t"', 1), ('"I"', 5)], [("0", 1), ('"1"', 3)]]


def test_a_line_the_csv_module_cannot_read_is_refused_at_that_line() -> None:
    limit = csv.field_size_limit()
    with pytest.raises(ConfigError) as info:
        read_table(decode_text(b"0;1\n" + b"9" * (limit + 1) + b";2\n", FILE), FILE)
    assert (info.value.file, info.value.line, info.value.col) == (FILE, 2, 1)


@given(st.binary(max_size=64))
def test_any_bytes_decode_as_text_or_are_refused_with_a_position(data: bytes) -> None:
    for decode in (decode_text, decode_yaml):
        try:
            decoded = decode(data, FILE)
        except ConfigError as error:
            assert error.file == FILE
            assert error.line is not None and error.line >= 1
            assert error.col is not None and error.col >= 1
        else:
            assert decoded.encode(decoded.text) == data
