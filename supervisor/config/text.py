"""Text files as users hand them to us: bytes → text, and tables of cells with positions.

One decoder for every file an engineer writes or exports: YAML I/O maps and recipes, Chadèche
sequence and parameter files (seed 000 §III.D), calibration readings (§III.F), load profiles
(seed 002 §2.3).

* :func:`decode_yaml`: UTF-8 only, with or without a BOM (YAML files are shared between
  machines and editors; one encoding keeps them byte-comparable).
* :func:`decode_text`: UTF-8 with or without a BOM, else CP1252 (Windows-1252: what Excel and
  Notepad write on a French Windows, where the seed's files come from).
* Both refuse a UTF-16 byte order mark (Notepad's "Unicode") instead of reading garbage, keep
  the line ends as they are (CRLF, CR or LF; :attr:`DecodedText.newline_style` says which)
  and raise a :class:`~supervisor.core.errors.ConfigError` naming the file, and the line and
  column of the bad byte, for every refusal.

:func:`read_table` splits a decoded file into rows of cells with the ``csv`` module, in one
fixed layout per file (:class:`Layout`), keeping the 1-based line and column of each cell.
"""

from __future__ import annotations

import codecs
import csv
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from supervisor.config.limits import TooLarge
from supervisor.core.errors import ConfigError

__all__ = [
    "Cell",
    "DecodedText",
    "Layout",
    "Row",
    "decode_text",
    "decode_yaml",
    "line_col",
    "read_table",
]

_BREAK = re.compile(r"\r\n|\r|\n")
# YAML 1.1 §5.4 line breaks, as PyYAML's reader counts them (it also breaks on NEL, LS, PS).
_YAML_BREAK = re.compile(r"\r\n|[\r\n\x85\u2028\u2029]")
# A multi-byte UTF-8 character (RFC 3629 well-formed sequences): in a file that is not UTF-8
# all through, the sign that it mixes encodings (CP1252 text rarely holds such a pair:
# an accented capital followed by a symbol).
_UTF8_SEQUENCE = re.compile(
    rb"[\xc2-\xdf][\x80-\xbf]|\xe0[\xa0-\xbf][\x80-\xbf]|[\xe1-\xec\xee\xef][\x80-\xbf]{2}"
    rb"|\xed[\x80-\x9f][\x80-\xbf]|\xf0[\x90-\xbf][\x80-\xbf]{2}|[\xf1-\xf3][\x80-\xbf]{3}"
    rb"|\xf4[\x80-\x8f][\x80-\xbf]{2}"
)
_UTF16_BOMS = (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)  # also the start of a UTF-32 BOM
# A number in a table cell as the C library's strtod reads it, in ASCII digits; inf and nan
# included (refused by name where they make no sense).
_CELL_NUMBER = re.compile(
    r"^[-+]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?|inf|infinity|nan)$",
    re.IGNORECASE,
)


@dataclass(frozen=True)
class DecodedText:
    """A file's text (without its BOM, line ends as they were) and how it was encoded."""

    text: str
    encoding: str
    """``"UTF-8"``, ``"UTF-8 with BOM"`` or ``"CP1252"``."""

    @property
    def bom(self) -> bool:
        return self.encoding == "UTF-8 with BOM"

    @property
    def newline_style(self) -> str:
        """``"LF"``, ``"CRLF"``, ``"CR"``, a mix such as ``"CRLF+LF"``, or ``"one line"``."""
        crlf = self.text.count("\r\n")
        cr = self.text.count("\r") - crlf
        lf = self.text.count("\n") - crlf
        kinds = [name for name, n in (("CRLF", crlf), ("LF", lf), ("CR", cr)) if n]
        return "+".join(kinds) if kinds else "one line"

    @property
    def newline(self) -> str:
        """The line end to write added lines with: the file's own (LF for one line)."""
        return newline_of(self.text)

    def lines(self) -> list[str]:
        """The lines, split at CRLF, CR or LF (a final line break leaves one empty line)."""
        return _BREAK.split(self.text)

    def encode(self, text: str) -> bytes:
        """``text`` (e.g. an edited version of this one) in this file's encoding and BOM."""
        if self.encoding == "CP1252":
            return text.encode("cp1252")
        return (codecs.BOM_UTF8 if self.bom else b"") + text.encode("utf-8")


def newline_of(text: str) -> str:
    """The line end ``text`` uses: CRLF if it has one, else CR if it has one, else LF."""
    if "\r\n" in text:
        return "\r\n"
    return "\r" if "\r" in text else "\n"


def line_col(text: str, index: int, *, yaml: bool = False) -> tuple[int, int]:
    """1-based line and column of ``text[index]`` (a character that is not a line break).

    Lines end at CRLF, CR or LF; with ``yaml`` also at NEL, LS and PS, and a BOM takes no
    column, which is how PyYAML counts (so positions agree with its own error marks).
    """
    parts = (_YAML_BREAK if yaml else _BREAK).split(text[:index])
    last = parts[-1]
    col = len(last) + 1 - (last.count("\ufeff") if yaml else 0)
    return len(parts), col


def _refuse_utf16(data: bytes, file: str | Path, must_be: str) -> None:
    if data.startswith(_UTF16_BOMS):
        raise ConfigError(
            f"file is encoded as UTF-16 (it has a UTF-16 byte order mark); the file must be "
            f"{must_be}",
            file,
            1,
            1,
        )


def _bad_byte(data: bytes, exc: UnicodeDecodeError, codec: str, *, yaml: bool) -> tuple[int, int]:
    """Line and column of the byte ``exc`` stopped at: everything before it decodes."""
    prefix = data[: exc.start].decode(codec)
    return line_col(prefix, len(prefix), yaml=yaml)


def decode_yaml(data: bytes, file: str | Path) -> DecodedText:
    """A YAML file's bytes: UTF-8, with or without a BOM; anything else is refused.

    Positions count lines like PyYAML does (:func:`line_col` with ``yaml=True``).
    """
    _refuse_utf16(data, file, "UTF-8")
    bom = data.startswith(codecs.BOM_UTF8)
    body = data[len(codecs.BOM_UTF8) :] if bom else data
    try:
        return DecodedText(body.decode("utf-8"), "UTF-8 with BOM" if bom else "UTF-8")
    except UnicodeDecodeError as exc:
        line, col = _bad_byte(body, exc, "utf-8", yaml=True)
        raise ConfigError(
            f"invalid UTF-8 byte 0x{body[exc.start]:02x} at line {line}, column {col}: "
            "the file must be UTF-8 encoded",
            file,
            line,
            col,
        ) from None


def decode_text(data: bytes, file: str | Path) -> DecodedText:
    """A text file's bytes: UTF-8 (BOM allowed), else CP1252 (what Excel writes on Windows).

    A file with a UTF-8 BOM must be UTF-8 all through, and so must one holding any UTF-8
    character (a file that mixes both is refused where its first non-UTF-8 byte is, not read
    as mojibake). CP1252 leaves five bytes undefined
    (0x81, 0x8D, 0x8F, 0x90, 0x9D): a file holding one is neither, and refused where it is.
    """
    _refuse_utf16(data, file, "UTF-8 or CP1252 (Windows-1252)")
    if data.startswith(codecs.BOM_UTF8):
        body = data[len(codecs.BOM_UTF8) :]
        try:
            return DecodedText(body.decode("utf-8"), "UTF-8 with BOM")
        except UnicodeDecodeError as exc:
            line, col = _bad_byte(body, exc, "utf-8", yaml=False)
            raise ConfigError(
                f"invalid UTF-8 byte 0x{body[exc.start]:02x} in a file with a UTF-8 BOM",
                file,
                line,
                col,
            ) from None
    try:
        return DecodedText(data.decode("utf-8"), "UTF-8")
    except UnicodeDecodeError as exc:
        not_utf8 = exc
    utf8 = _UTF8_SEQUENCE.search(data)
    if utf8 is not None:
        # Read as CP1252, the UTF-8 part turns to mojibake ("Repos" with an accent shown
        # as "RÃ©pos") and nobody is told: a file edited in two editors is refused instead.
        line, col = _bad_byte(data, not_utf8, "utf-8", yaml=False)
        head = data[: utf8.start()].decode("cp1252", errors="replace")
        u_line, u_col = line_col(head, len(head))
        shown = utf8[0].decode("utf-8")
        raise ConfigError(
            f"the file mixes encodings: byte 0x{data[not_utf8.start]:02x} is not UTF-8, but"
            f" line {u_line}, column {u_col} is UTF-8 ({shown!r}); read as CP1252 it would"
            " show as mojibake. Save the whole file in one encoding (UTF-8, or CP1252 /"
            " Windows-1252)",
            file,
            line,
            col,
        )
    try:
        return DecodedText(data.decode("cp1252"), "CP1252")
    except UnicodeDecodeError as exc:
        line, col = _bad_byte(data, exc, "cp1252", yaml=False)
        raise ConfigError(
            f"byte 0x{data[exc.start]:02x} is neither UTF-8 nor CP1252 (Windows-1252) text",
            file,
            line,
            col,
        ) from None


# --------------------------------------------------------------------------------------------
# Tables


@dataclass(frozen=True)
class Layout:
    """How a file's cells are separated: one fixed ``csv`` dialect for the whole file.

    ``delimiter`` is a tab, ``;``, ``,`` or ``" "`` (runs of blanks). With a tab or ``;`` a
    ``,`` in a number is a decimal comma (what spreadsheets write in French locales).
    """

    delimiter: str

    @property
    def decimal_comma(self) -> bool:
        return self.delimiter in ("\t", ";")

    def number(self, text: str) -> float | None:
        """The number a cell holds, or None; ``inf``/``nan`` are numbers here (the caller
        refuses them by name). ASCII digits only, no ``_``: ``float()`` alone would read
        ``６0`` as 60 and ``1_000`` as 1000 (issue 9)."""
        t = text.strip()
        if self.decimal_comma:
            t = t.replace(",", ".")
        if not _CELL_NUMBER.match(t):
            return None
        return float(t)


@dataclass(frozen=True)
class Cell:
    text: str
    """The cell without its surrounding blanks."""
    col: int
    """1-based column of its first non-blank character (of where it starts when empty)."""


@dataclass(frozen=True)
class Row:
    line: int
    """1-based line in the file."""
    cells: tuple[Cell, ...]
    end_col: int
    """The column just after the last non-blank character: where a missing cell would be."""


# Precedence, not counting: "0;1,5" is a French decimal comma, not three cells.
_DELIMITERS = ("\t", ";", ",")


def _layout(lines: Sequence[str], blanks: bool) -> Layout:
    """The first of tab, ``;``, ``,`` that the rows use, else blanks (or ``;``: one cell).

    The first line is left out when there are others: it may be a header, and column titles
    hold any punctuation ("Consigne, mA"). ``csv.Sniffer`` is not used: it wants the same
    number of delimiters on (nearly) every line, and gives up on a profile whose last row
    only has time and current, on a blank line written as CRLF, and on a file with one bad
    row, which must be reported at its column instead.
    """
    sample = lines[1:] or lines
    for delimiter in _DELIMITERS:
        if any(delimiter in line for line in sample):
            return Layout(delimiter)
    return Layout(" " if blanks else ";")


def _cells(raw: Sequence[str], delimiter: str) -> tuple[Cell, ...]:
    cells: list[Cell] = []
    start = 1
    for part in raw:
        lead = len(part) - len(part.lstrip())
        if part.strip() or delimiter != " ":  # a run of blanks is one separator
            cells.append(Cell(part.strip(), start + lead))
        start += len(part) + 1
    return tuple(cells)


def read_table(
    decoded: DecodedText,
    file: str | Path,
    *,
    blanks: bool = False,
    comments: bool = False,
    max_rows: int | None = None,
    what: str = "a table",
) -> tuple[Layout, list[Row]]:
    """The rows of a delimited text file, in the file's :class:`Layout`.

    Blank lines are skipped, and lines starting with ``#`` when ``comments``. Blanks
    separate cells only with ``blanks`` and when no line after the first has a tab, ``;`` or
    ``,``. Quotes are ordinary characters (``csv.QUOTE_NONE``): tables of numbers have none,
    and so every cell keeps its exact column. More than ``max_rows`` rows (the header
    line included) is refused at the first row over, before any cell is split
    (``supervisor.config.limits``; ``what`` names the file in the message).
    """
    numbered = [
        (ln, line.rstrip())
        for ln, line in enumerate(decoded.lines(), start=1)
        if line.strip() and not (comments and line.lstrip().startswith("#"))
    ]
    if max_rows is not None and len(numbered) > max_rows:
        raise TooLarge(
            f"too many rows: {len(numbered):,}; {what} may have at most {max_rows:,}"
            " (README: Input limits)",
            file,
            numbered[max_rows][0],
            1,
        )
    layout = _layout([line for _, line in numbered], blanks)
    reader = csv.reader(
        (line for _, line in numbered), delimiter=layout.delimiter, quoting=csv.QUOTE_NONE
    )
    rows: list[Row] = []
    for ln, line in numbered:
        try:
            raw = next(reader)
        except csv.Error as exc:  # e.g. a line longer than csv.field_size_limit()
            raise ConfigError(f"cannot read this line: {exc}", file, ln, 1) from None
        rows.append(Row(ln, _cells(raw, layout.delimiter), len(line) + 1))
    return layout, rows
