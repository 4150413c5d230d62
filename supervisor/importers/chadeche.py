"""Import a Chadèche sequence file (seed 000 §III.D) and its ``chadecheN.prm`` as a recipe.

The sequence file is tab separated, with a mandatory header line (the program ignores it,
so a file without one silently loses its first sequence) and eleven columns::

    ADR  C/D  mA  SD  TL  TH  LmAh  HmAh  TRUE  CTRLZ  COMMENT

Mapping (every row becomes one step, id ``s<ADR>``, in file order):

* ``C``/``D`` + ``mA`` → ``charge: N mA`` / ``discharge: N mA``; ``mA`` 0 → ``rest: true``
  (with 0 mA the letter only sets the relay); ``SD`` → ``duration: N s`` (0 → ``0 s``);
* the condition columns, in column order (the program evaluates them left to right and the
  first true non-``I`` one acts, which is what ``until`` does): TL ``voltage <= v_min``,
  TH ``voltage >= v_max``, LmAh ``charge <= q_min``, HmAh ``charge >= q_max``, TRUE
  ``true``; actions ``S`` → ``next``, ``C`` → ``next_cycle``, ``N`` → ``s<N>`` (a goto),
  ``HH:MM`` (sleep until then, then the next step), ``+HH:MM`` (sleep that long, then the
  next step); ``I`` entries are dropped;
* ``CTRLZ`` → ``advance:`` (``I`` → ``advance: false``, other actions mapped as above);
* ``COMMENT`` (without its ``#``) → ``comment:``; the source row is repeated as a YAML
  comment above its step, so nothing of the file is lost.

Instant rows (``simplify=True``, the default): a 0 mA row whose first acting condition is
TRUE ends at its first evaluation, whatever its SD says; it is written as the step kind
that means the same thing — ``goto: s<N>``, ``end_cycle: true``, ``sleep_until: "HH:MM"``
or ``sleep: N min`` — and a last row at 0 mA, SD 0, with no condition (the end of the
cycle) as ``end_cycle: true``. This is how ``recipes/nimh-ds2710.yaml`` writes the seed's
figure 10 by hand. ``simplify=False`` keeps every row a rest/charge/discharge step.

Parameters: program defaults < ``chadecheN.prm`` < ``overrides`` (the command line), like
the program itself (seed §III.D.4). ``-m -M -c -C -i`` become the recipe parameters
``v_min v_max q_min q_max q_init`` (``initial_charge: q_init``), ``-n`` the ``cycles``,
``-p`` the ``logging.period``. ``-1 -2 -s -o`` are the board's calibration (they belong in
the I/O map, not in a recipe): see :attr:`ImportResult.calibration_snippet`. ``-2`` is an
offset in mA: the seed's current fit is setpoint mA against measured mA (§III.F.1, its
example ``-2 0.0008`` comes from a 0–250 mA staircase), so it lands in
``current_offset_ma``; ``-o`` is in volts (``voltage_offset_v``).

Numbers are read as the C program reads them: ASCII digits only (``\\d`` and Python's
``int``/``float`` would take ``٣`` or ``３`` as 3, and ``1_000`` as 1000 where ``atof`` reads
1), whole numbers within a C ``int``, and every option within a physically plausible range
(:data:`OPTION_RANGES`): a value outside is refused with the reason, at its file:line:col.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from supervisor.chains.compiler import Target, compile_recipe
from supervisor.config.limits import (
    MAX_CYCLES,
    MAX_SEQUENCE_ROWS,
    MAX_TEXT_BYTES,
    TooLarge,
    read_limited,
)
from supervisor.config.recipe import ID_PATTERN, STEP_KINDS, load_recipe_text
from supervisor.config.text import DecodedText, decode_text
from supervisor.config.yamledit import yaml_comment, yaml_float, yaml_scalar
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.devices.chadeche.config import MAX_CURRENT_A
from supervisor.devices.chadeche.protocol import VREF_V

__all__ = [
    "COLUMNS",
    "C_INT_MAX",
    "DEFAULTS",
    "OPTION_RANGES",
    "ImportResult",
    "import_chadeche",
]

COLUMNS = ("ADR", "C/D", "mA", "SD", "TL", "TH", "LmAh", "HmAh", "TRUE", "CTRLZ", "COMMENT")
_MAX_MA = round(MAX_CURRENT_A * 1000)  # the board maximum (seed §III.D.1), in the file's mA

# Condition columns (index in COLUMNS) → the recipe condition.
CONDITIONS: tuple[tuple[int, str], ...] = (
    (4, "voltage <= v_min"),
    (5, "voltage >= v_max"),
    (6, "charge <= q_min"),
    (7, "charge >= q_max"),
    (8, "true"),
)


@dataclass(frozen=True)
class _Option:
    letter: str
    target: str  # recipe parameter name, or "cycles" / "logging.period"
    unit: str
    default: float
    source: str  # where the default comes from
    assumed: bool = False  # the seed does not state this default


# The options that are recipe matters, in the order they are written out.
OPTIONS: dict[str, _Option] = {
    "m": _Option("m", "v_min", "V", 1.0, "default, seed §IV (TL 1 V)"),
    "M": _Option("M", "v_max", "V", 1.75, "default, seed §IV (TH 1.75 V)"),
    "c": _Option("c", "q_min", "mAh", 100.0, "default, seed §IV (LmAh 100 mAh)"),
    "C": _Option("C", "q_max", "mAh", 1300.0, "default, seed §IV (HmAh 1300 mAh)"),
    "i": _Option(
        "i", "q_init", "mAh", 0.0, "assumed default: the program's CINIT, 0 mAh", assumed=True
    ),
    "n": _Option("n", "cycles", "", 1.0, "assumed default: one cycle", assumed=True),
    "p": _Option("p", "logging.period", "s", 120.0, "default, seed §III.E.2 (120 s)"),
}
DEFAULTS: dict[str, float] = {k: o.default for k, o in OPTIONS.items()}

# Calibration options (seed §III.D.6, §III.F) → the I/O map's board calibration keys.
CALIBRATION: dict[str, tuple[str, str]] = {
    "1": ("current_slope", "current slope, setpoint mA per measured mA"),
    "2": ("current_offset_ma", "current offset in mA"),
    "s": ("voltage_slope", "voltage slope, meter V per ADC V"),
    "o": ("voltage_offset_v", "voltage offset in V"),
}
_POSITIVE_CAL = {"1", "s"}

# Ignored in a parameter file (seed §III.D.6).
IGNORED_IN_PRM = {"a": "board address", "h": "help"}
# Options of the program that have no meaning in a recipe.
NOT_RECIPE = {
    "v": "verbose display",
    "t": "test mode",
    "f": "results file name",
    "g": "sequence file name",
    "l": "message language",
}
_FLAGS = {"v", "t", "h"}  # options without a value

# ASCII digits only: the C program reads ASCII; ``\d`` (and ``int()``) take any Unicode digit.
_INT = re.compile(r"^[0-9]+$")
_HHMM = re.compile(r"^([0-9]{1,2}):([0-9]{2})$")
_PLUS_HHMM = re.compile(r"^\+([0-9]{1,3}):([0-9]{2})$")
# A decimal number as ``atof`` reads it whole (no ``_``, no ``inf``/``nan``, no Unicode).
_DECIMAL = re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?$")

_ATOF_HINT = " (the Chadèche program's atof stops at the '_': write the digits alone)"

C_INT_MAX: Final = 2**31 - 1
"""The largest ADR, mA, SD or goto address: the program keeps these whole numbers in a C
``int`` (32 bits on the Raspberry Pi's ARM Linux). ASSUMED: the seed does not show the
program's source, only that they are whole numbers (§III.D.1)."""

MAX_THRESHOLD_V: Final = VREF_V
"""``-m``/``-M`` are compared with the cell voltage the board's ADC reads, 0 to its 4.096 V
reference (seed §II.C): a threshold above it is never reached by TH, always true for TL."""
MAX_CHARGE_MAH: Final = 100_000.0
"""``-c -C -i`` (mAh) at most 100 Ah: ten times a large NiMH D cell (10 Ah), and what a
0.4 A board moves in 250 h; a larger charge is a typing slip, not a cell."""
MIN_LOG_PERIOD_S: Final = 0.1
"""``-p`` at least the bench's default scan period (``ScanConfig.period_s``, 0.1 s): a result
line cannot come more often than a scan."""
MAX_LOG_PERIOD_S: Final = 86_400.0
"""``-p`` at most one day: a longer period records nothing in most tests."""
CAL_SLOPE_MIN: Final = 0.5
CAL_SLOPE_MAX: Final = 2.0
"""``-1``/``-s``: a calibration slope corrects a few per cent (seed §III.F: 0.9851, 1.0099,
1.0065); beyond a factor of two the fit or the wiring is wrong."""
MAX_CURRENT_OFFSET_MA: Final = MAX_CURRENT_A * 1000
"""``-2`` (mA) within the board's whole current range: a larger offset is no calibration."""
MAX_VOLTAGE_OFFSET_V: Final = VREF_V
"""``-o`` (V) within the ADC's whole range: a larger offset is no calibration."""


@dataclass(frozen=True)
class _Range:
    low: float
    high: float
    why: str
    low_included: bool = True


OPTION_RANGES: Final[dict[str, _Range]] = {
    "m": _Range(0.0, MAX_THRESHOLD_V, "the board's ADC reads 0 to 4.096 V", low_included=False),
    "M": _Range(0.0, MAX_THRESHOLD_V, "the board's ADC reads 0 to 4.096 V", low_included=False),
    "c": _Range(0.0, MAX_CHARGE_MAH, "a charge of a cell, at most 100 Ah"),
    "C": _Range(0.0, MAX_CHARGE_MAH, "a charge of a cell, at most 100 Ah"),
    "i": _Range(0.0, MAX_CHARGE_MAH, "a charge of a cell, at most 100 Ah"),
    "n": _Range(1.0, float(MAX_CYCLES), f"a recipe runs at most {MAX_CYCLES} cycles"),
    "p": _Range(MIN_LOG_PERIOD_S, MAX_LOG_PERIOD_S, "from one scan to one day"),
    "1": _Range(CAL_SLOPE_MIN, CAL_SLOPE_MAX, "a calibration slope corrects a few per cent"),
    "s": _Range(CAL_SLOPE_MIN, CAL_SLOPE_MAX, "a calibration slope corrects a few per cent"),
    "2": _Range(-MAX_CURRENT_OFFSET_MA, MAX_CURRENT_OFFSET_MA, "within the board's ±400 mA range"),
    "o": _Range(-MAX_VOLTAGE_OFFSET_V, MAX_VOLTAGE_OFFSET_V, "within the ADC's 4.096 V range"),
}
"""Where each option's value must lie (the unit is the option's: V, mAh, s, mA)."""


def _clip(text: str) -> str:
    """A cell as messages show it: a long run of digits by its length, not in full."""
    return text if len(text) <= 24 else f"{text[:12]}… ({len(text)} characters)"


def _digits_hint(text: str) -> str:
    """Why a number that looks like one to a person is not one here."""
    if any(ch.isdigit() and not ch.isascii() for ch in text):
        return " (ASCII digits 0-9 only: the Chadèche program reads no other digits)"
    return ""


def _whole(digits: str) -> int:
    """ASCII digits as an int, without their leading zeros: ``int()`` refuses more than
    4300 digits, and 5000 zeros before a 5 is the number 5 (issue 28)."""
    return int(digits.lstrip("0") or "0")


def _too_large(digits: str) -> bool:
    """ASCII digits beyond :data:`C_INT_MAX` (``int()`` is not asked for thousands)."""
    digits = digits.lstrip("0")
    return len(digits) > len(str(C_INT_MAX)) or (digits != "" and int(digits) > C_INT_MAX)


@dataclass(frozen=True)
class ImportResult:
    """What :func:`import_chadeche` produced."""

    yaml_text: str
    """A complete recipe file, with a comment header saying where it came from."""
    recipe: dict[str, Any]
    """The same recipe as plain data (what loading ``yaml_text`` gives)."""
    calibration: dict[str, float] | None
    """``-1 -2 -s -o`` as I/O-map calibration keys (only those given), or None."""
    calibration_snippet: str | None
    """YAML lines to paste under the board's ``calibration:`` in the I/O map."""
    warnings: list[str] = field(default_factory=list)


def _num(value: float) -> str:
    """A number for a quantity string: ``1``, ``1.75``, ``0.5``."""
    if float(value).is_integer() and abs(value) < 1e15:
        return str(int(value))
    return yaml_float(value)


# --------------------------------------------------------------------------------------------
# Reading


def _split_fields(line: str) -> list[tuple[str, int]]:
    """Tab-separated fields with the 1-based column where each starts (a tab is one column)."""
    out: list[tuple[str, int]] = []
    start = 0
    for part in line.split("\t"):
        out.append((part, start + 1))
        start += len(part) + 1
    return out


@dataclass(frozen=True)
class _Act:
    """One action cell: I, S, C, N (goto ADR), HH:MM, +HH:MM."""

    kind: str  # "I" "S" "C" "N" "HHMM" "PLUS"
    value: str  # normalised text (ADR number, "20:00", "+01:30")
    col: int

    def recipe_action(self) -> str:
        if self.kind == "S":
            return "next"
        if self.kind == "C":
            return "next_cycle"
        if self.kind == "N":
            return f"s{self.value}"
        return self.value


@dataclass
class _Row:
    line: int
    adr: int
    letter: str
    ma: int
    sd: int
    conditions: list[tuple[str, _Act]]  # (recipe condition, action), I included
    ctrlz: _Act
    comment: str
    cells: list[str]


def _parse_action(text: str, col: int) -> _Act | str:
    """An action cell, or an error message."""
    t = text.strip()
    up = t.upper()
    if up in ("I", "S", "C"):
        return _Act(up, up, col)
    if _INT.match(t):
        if _too_large(t):
            return f"goto address {_clip(t)} is too large: at most {C_INT_MAX} (a C int)"
        return _Act("N", str(_whole(t)), col)
    m = _HHMM.match(t)
    if m and int(m[1]) < 24 and int(m[2]) < 60:
        return _Act("HHMM", f"{int(m[1]):02d}:{m[2]}", col)
    m = _PLUS_HHMM.match(t)
    if m and int(m[2]) < 60:
        return _Act("PLUS", f"+{int(m[1]):02d}:{m[2]}", col)
    if not t:
        return "empty action: expected I, S, C, an ADR number, HH:MM or +HH:MM"
    if _digits_hint(t):
        return f"unknown action {_clip(t)!r}{_digits_hint(t)}"
    return (
        f"unknown action {_clip(t)!r}: expected I (ignore), S (next sequence), C (next cycle), "
        "an ADR number (goto), HH:MM (sleep until) or +HH:MM (sleep for)"
    )


def _read_text(path: Path, not_found: str) -> DecodedText:
    """The file's text: UTF-8 (BOM allowed), else CP1252, what Excel writes on Windows."""
    file = str(path)
    try:
        return decode_text(read_limited(path, MAX_TEXT_BYTES, "a Chadèche file"), file)
    except FileNotFoundError:
        raise ConfigErrors([ConfigError(not_found, file)]) from None
    except OSError as exc:
        raise ConfigErrors([ConfigError(f"cannot read: {exc.strerror or exc}", file)]) from None
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None


def _sequence_lines(decoded: DecodedText, file: str) -> list[str]:
    """The file's lines without the trailing empty ones; refused when there is none, or
    more than a sequence file may have."""
    lines = decoded.lines()
    while lines and not lines[-1].strip(" \t"):
        lines.pop()  # trailing empty lines (and a final line break)
    if not lines:
        raise ConfigErrors([ConfigError("file is empty: expected a header line", file, 1, 1)])
    if len(lines) > MAX_SEQUENCE_ROWS + 1:  # + the header line
        raise ConfigErrors(
            [
                TooLarge(
                    f"too many rows: {len(lines) - 1:,}; a sequence file may have at most"
                    f" {MAX_SEQUENCE_ROWS:,} (README: Input limits)",
                    file,
                    MAX_SEQUENCE_ROWS + 2,
                    1,
                )
            ]
        )
    return lines


@dataclass
class _SequenceReader:
    """One sequence file read row by row: every problem is collected (the caller raises
    them together, in file order) and a bad row is left out, so that the rows after it
    are still checked."""

    file: str
    errors: list[ConfigError] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    prev_adr: tuple[int, int] | None = None  # (adr, line)
    adrs: set[int] = field(default_factory=set)
    actions: list[tuple[int, str, _Act]] = field(default_factory=list)
    """(line, column title, action) of every action read, for the goto checks."""

    def err(self, line: int, col: int, msg: str) -> None:
        self.errors.append(ConfigError(msg, self.file, line, col))

    def header_is_missing(self, first: str) -> bool:
        """Check line 1, the column titles; True when it is a row instead (then it is
        checked as one: the program would lose it)."""
        header = first.rstrip(" \t")
        hfields = _split_fields(header)
        expected = "\t".join(COLUMNS)
        if _INT.match(hfields[0][0].strip()):
            self.err(
                1,
                1,
                "missing header line: the first line must be the column titles "
                f"({' '.join(COLUMNS)}); the Chadèche program ignores the first line, "
                "so this sequence would be lost",
            )
            return True
        if len(hfields) < len(COLUMNS):
            missing = " ".join(COLUMNS[len(hfields) :])
            self.err(
                1,
                len(header) + 1,
                f"short header: {len(hfields)} of {len(COLUMNS)} columns (missing {missing}); "
                f"expected {expected!r}",
            )
        elif len(hfields) > len(COLUMNS):
            self.err(
                1,
                hfields[len(COLUMNS)][1],
                f"header has {len(hfields)} columns, expected {len(COLUMNS)}: {expected!r}",
            )
        else:
            odd = [
                f"{got.strip()!r} for {want}"
                for (got, _), want in zip(hfields, COLUMNS, strict=True)
                if got.strip().upper() != want.upper()
            ]
            if odd:
                self.warnings.append(
                    f"{self.file}:1: unusual column titles ({', '.join(odd)}); read as usual"
                )
        return False

    def row(self, ln: int, raw: str) -> _Row | None:
        """One sequence row, or None when it has an error (each one reported)."""
        split = self._cells(ln, raw)
        if split is None:
            return None
        cells, cols = split
        # Every cell is checked, also after a bad one: all of a row's errors at once.
        adr = self._adr(ln, cells[0].strip(), cols[0])
        letter = self._letter(ln, cells[1].strip(), cols[1])
        ma = self._ma(ln, cells[2].strip(), cols[2])
        sd = self._sd(ln, cells[3].strip(), cols[3])
        acts = self._actions(ln, cells, cols)
        comment = cells[10].strip()
        if not comment.startswith("#"):
            self.err(ln, cols[10], f"comment {comment!r} must start with '#'")
            return None
        if adr is None or letter is None or ma is None or sd is None or acts is None:
            return None
        return _Row(
            line=ln,
            adr=adr,
            letter=letter,
            ma=ma,
            sd=sd,
            conditions=[(cond, acts[k - 4]) for k, cond in CONDITIONS],
            ctrlz=acts[5],
            comment=comment[1:].strip(),
            cells=[c.strip() for c in cells],
        )

    def _cells(self, ln: int, raw: str) -> tuple[list[str], list[int]] | None:
        """The row's eleven cells (the comment takes the tabs in it) and the column where
        each starts, or None when the row is empty or has too few or too many fields."""
        line = raw.rstrip(" \t")
        if not line.strip():
            self.err(
                ln, 1, "empty line among the sequences (the Chadèche program stops reading here)"
            )
            return None
        fields = _split_fields(line)
        n = len(COLUMNS)
        if len(fields) < n:
            last, last_col = fields[-1]
            if len(fields) > 1 and last.lstrip().startswith("#"):
                self.err(
                    ln,
                    last_col,
                    f"row has {len(fields)} fields, expected {n}: the comment is in the "
                    f"{COLUMNS[len(fields) - 1]} column, so a column before it is missing",
                )
            else:
                missing = " ".join(COLUMNS[len(fields) :])
                self.err(
                    ln,
                    len(line) + 1,
                    f"row has {len(fields)} fields, expected {n} (missing {missing})",
                )
            return None
        if len(fields) > n and not fields[n - 1][0].lstrip().startswith("#"):
            self.err(ln, fields[n][1], f"row has {len(fields)} fields, expected {n}")
            return None
        cells = [f for f, _ in fields[: n - 1]] + ["\t".join(f for f, _ in fields[n - 1 :])]
        return cells, [c for _, c in fields[:n]]

    def _adr(self, ln: int, text: str, col: int) -> int | None:
        if not _INT.match(text):
            self.err(ln, col, f"ADR {_clip(text)!r} is not a whole number{_digits_hint(text)}")
            return None
        if _too_large(text):
            self.err(ln, col, f"ADR {_clip(text)} is too large: at most {C_INT_MAX} (a C int)")
            return None
        adr = _whole(text)
        self.adrs.add(adr)  # a goto to it is not reported as well
        if self.prev_adr is not None and adr <= self.prev_adr[0]:
            self.err(
                ln,
                col,
                f"ADR {adr} does not increase (line {self.prev_adr[1]} has ADR"
                f" {self.prev_adr[0]}); addresses must always increase",
            )
            return None
        self.prev_adr = (adr, ln)
        return adr

    def _letter(self, ln: int, text: str, col: int) -> str | None:
        letter = text.upper()
        if letter not in ("C", "D"):
            self.err(ln, col, f"unknown C/D letter {text!r}: expected C (charge) or D (discharge)")
            return None
        return letter

    def _ma(self, ln: int, text: str, col: int) -> int | None:
        if not _INT.match(text):
            self.err(ln, col, f"mA {_clip(text)!r} is not a whole number of mA{_digits_hint(text)}")
            return None
        ma = _MAX_MA + 1 if _too_large(text) else _whole(text)
        if ma > _MAX_MA:
            shown = _clip(text) if _too_large(text) else str(ma)
            self.err(ln, col, f"{shown} mA is over the board's {_MAX_MA} mA maximum")
            return None
        return ma

    def _sd(self, ln: int, text: str, col: int) -> int | None:
        if not _INT.match(text):
            self.err(
                ln,
                col,
                f"SD {_clip(text)!r} is not a whole number of seconds{_digits_hint(text)}",
            )
            return None
        if _too_large(text):
            self.err(ln, col, f"SD {_clip(text)} is too large: at most {C_INT_MAX} s (a C int)")
            return None
        return _whole(text)

    def _actions(self, ln: int, cells: list[str], cols: list[int]) -> list[_Act] | None:
        """The six action cells (TL TH LmAh HmAh TRUE CTRLZ), or None when one is bad."""
        acts: list[_Act] = []
        for k in range(4, 10):
            parsed = _parse_action(cells[k], cols[k])
            if isinstance(parsed, str):
                self.err(ln, cols[k], f"{COLUMNS[k]}: {parsed}")
            else:
                acts.append(parsed)
                self.actions.append((ln, COLUMNS[k], parsed))
        return acts if len(acts) == 6 else None

    def check_actions(self) -> None:
        """Every goto to an ADR of the file (any row with a whole-number ADR counts, even
        one with other errors); a sleep-for, which the program did not implement, said."""
        for ln, name, act in self.actions:
            if act.kind == "N" and int(act.value) not in self.adrs:
                known = ", ".join(str(a) for a in sorted(self.adrs)[:30])
                self.err(
                    ln,
                    act.col,
                    f"{name}: goto to a missing ADR {act.value} (this file has: {known})",
                )
            if act.kind == "PLUS":
                self.warnings.append(
                    f"{self.file}:{ln}:{act.col}: {act.value} (sleep for) was not implemented in"
                    " the Chadèche program (seed §III.D.1); here it sleeps, then goes on"
                )


def _read_rows(path: Path) -> tuple[list[_Row], list[str], str]:
    """Parse the sequence file; raise ConfigErrors listing every problem."""
    reader = _SequenceReader(str(path))
    decoded = _read_text(path, "file not found")
    lines = _sequence_lines(decoded, reader.file)
    body = list(enumerate(lines, start=1))
    if not reader.header_is_missing(lines[0]):
        body = body[1:]  # else line 1 is a row too: check it
    if not body:
        reader.err(len(lines) + 1, 1, "no sequence rows after the header")
    rows = [row for ln, raw in body if (row := reader.row(ln, raw)) is not None]
    reader.check_actions()
    if reader.errors:
        reader.errors.sort(key=lambda e: (e.line or 0, e.col or 0))
        raise ConfigErrors(reader.errors)
    return rows, reader.warnings, f"{decoded.encoding}, {decoded.newline_style}"


# --------------------------------------------------------------------------------------------
# Parameters


@dataclass
class _Param:
    value: float
    source: str
    file: str | None = None
    """Where it was set (None: a default); an error about it is reported there."""
    line: int | None = None
    col: int | None = None

    def error(self, message: str, fallback: str) -> ConfigError:
        if self.file is None:
            return ConfigError(message, fallback)
        return ConfigError(message, self.file, self.line, self.col)


def _unit(letter: str) -> str:
    if letter in OPTIONS:
        return OPTIONS[letter].unit
    return {"2": "mA", "o": "V"}.get(letter, "")


def _in_range(letter: str, v: float, t: str) -> str | None:
    """None when ``v`` lies in :data:`OPTION_RANGES`, else why not."""
    r = OPTION_RANGES[letter]
    unit = f" {_unit(letter)}" if _unit(letter) else ""
    low_ok = v >= r.low if r.low_included else v > r.low
    if low_ok and v <= r.high:
        return None
    if r.low_included:
        span = f"from {_num(r.low)} to {_num(r.high)}{unit}"
    else:
        span = f"more than {_num(r.low)} and at most {_num(r.high)}{unit}"
    return f"-{letter} must be {span} ({r.why}), got {_clip(t)!r}"


def _convert(letter: str, raw: str) -> float | str:
    """The value of option ``letter``, or an error message."""
    t = raw.strip()
    if letter == "n":
        digits = t.lstrip("0")
        if not _INT.match(t) or not digits:
            return f"-n needs a whole number of cycles >= 1, got {_clip(t)!r}{_digits_hint(t)}"
        # More digits than the largest count: too many, without asking int() for thousands.
        cycles = math.inf if len(digits) > len(str(MAX_CYCLES)) else float(int(digits))
        return _in_range("n", cycles, t) or cycles
    if not _DECIMAL.match(t):
        # ``atof`` would read a prefix of it (``1_000`` as 1): refuse rather than guess.
        hint = _digits_hint(t) or (_ATOF_HINT if "_" in t else "")
        return f"-{letter} needs a number, got {_clip(t)!r}{hint}"
    v = float(t)
    if not math.isfinite(v):
        return f"-{letter} needs a finite number, got {_clip(t)!r}"
    if letter == "p" and v <= 0:
        return f"-p (logging period) must be > 0 s, got {t!r}"
    if letter in _POSITIVE_CAL and v <= 0:
        return f"-{letter} (a calibration slope) must be > 0, got {t!r}"
    return _in_range(letter, v, t) or v


def _check_together(params: dict[str, _Param], fallback: str) -> None:
    """Options that only make sense together: the low threshold below the high one."""
    errors: list[ConfigError] = []
    for lo, hi, what in (("m", "M", "voltage"), ("c", "C", "charge")):
        a, b = params[lo], params[hi]
        if a.value < b.value:
            continue
        unit = OPTIONS[lo].unit
        at = a if a.file is not None or b.file is None else b
        errors.append(
            at.error(
                f"-{lo} {_num(a.value)} {unit} ({a.source}) must be below -{hi}"
                f" {_num(b.value)} {unit} ({b.source}): the low {what} threshold"
                f" ({OPTIONS[lo].target}) is not below the high one ({OPTIONS[hi].target})",
                fallback,
            )
        )
    if errors:
        raise ConfigErrors(errors)


def _read_prm(
    path: Path,
    params: dict[str, _Param],
    calibration: dict[str, _Param],
    warnings: list[str],
) -> None:
    file = str(path)
    decoded = _read_text(path, "parameter file not found")
    errors: list[ConfigError] = []
    ignored: list[str] = []
    not_recipe: list[str] = []
    for ln, raw in enumerate(decoded.lines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        col = len(raw) - len(raw.lstrip()) + 1
        m = re.match(r"^-(.)(.*)$", line)
        if m is None:
            errors.append(
                ConfigError(f"expected an option such as '-m 1.1', got {line!r}", file, ln, col)
            )
            continue
        letter, value = m[1], m[2].strip()
        vcol = col + 2 + (len(m[2]) - len(m[2].lstrip()))
        if letter in IGNORED_IN_PRM:
            ignored.append(f"-{letter} ({IGNORED_IN_PRM[letter]}, line {ln})")
            continue
        if letter in NOT_RECIPE:
            not_recipe.append(f"-{letter} ({NOT_RECIPE[letter]}, line {ln})")
            continue
        if letter not in OPTIONS and letter not in CALIBRATION:
            errors.append(_unknown_prm_option(letter, file, ln, col))
            continue
        if not value:
            errors.append(ConfigError(f"-{letter} needs a value", file, ln, col))
            continue
        got = _convert(letter, value)
        if isinstance(got, str):
            errors.append(ConfigError(got, file, ln, vcol))
            continue
        target = params if letter in OPTIONS else calibration
        target[letter] = _Param(got, f"{path.name}:{ln}", file, ln, vcol)
    if errors:
        raise ConfigErrors(errors)
    if ignored:
        warnings.append(
            f"{file}: {', '.join(ignored)} ignored: a parameter file cannot set them "
            "(seed §III.D.6)"
        )
    if not_recipe:
        warnings.append(f"{file}: {', '.join(not_recipe)} ignored: not a recipe matter")


def _unknown_prm_option(letter: str, file: str, ln: int, col: int) -> ConfigError:
    known = " ".join(f"-{k}" for k in [*OPTIONS, *CALIBRATION])
    other = " ".join(f"-{k}" for k in [*IGNORED_IN_PRM, *NOT_RECIPE])
    return ConfigError(
        f"unknown option -{letter} (recipe and calibration options: {known}; ignored: {other})",
        file,
        ln,
        col,
    )


def _apply_overrides(
    overrides: Mapping[str, str | float | int],
    params: dict[str, _Param],
    calibration: dict[str, _Param],
    warnings: list[str],
) -> None:
    errors: list[ConfigError] = []
    skipped: list[str] = []
    for key, raw in overrides.items():
        letter = str(key)[1:] if str(key).startswith("-") else str(key)
        if letter in IGNORED_IN_PRM or letter in NOT_RECIPE:
            what = IGNORED_IN_PRM.get(letter) or NOT_RECIPE[letter]
            skipped.append(f"-{letter} ({what})")
            continue
        if letter not in OPTIONS and letter not in CALIBRATION:
            known = " ".join(f"-{k}" for k in [*OPTIONS, *CALIBRATION])
            errors.append(ConfigError(f"unknown option {key!r} (known: {known})", "<overrides>"))
            continue
        got = _convert(letter, str(raw))
        if isinstance(got, str):
            errors.append(ConfigError(got, "<overrides>"))
            continue
        (params if letter in OPTIONS else calibration)[letter] = _Param(
            got, "override", "<overrides>"
        )
    if errors:
        raise ConfigErrors(errors)
    if skipped:
        warnings.append(f"overrides: {', '.join(skipped)} ignored: not a recipe matter")


# --------------------------------------------------------------------------------------------
# Rows → steps


def _instant_step(row: _Row, last: bool) -> tuple[str, Any, str] | None:
    """(kind, value, why) when a 0 mA row ends at its first evaluation, else None."""
    if row.ma != 0:
        return None
    acting = [(cond, act) for cond, act in row.conditions if act.kind != "I"]
    if not acting:
        if last and row.sd == 0:
            return "end_cycle", True, "last row, 0 mA, SD 0, no condition: the end of the cycle"
        return None
    cond, act = acting[0]
    if cond != "true":
        return None
    why = "0 mA and TRUE acts first, so the row ends at once whatever SD says"
    if act.kind == "N":
        return "goto", f"s{act.value}", why
    if act.kind == "C":
        return "end_cycle", True, why
    if act.kind == "HHMM":
        return "sleep_until", act.value, why
    if act.kind == "PLUS":
        hh, mm = act.value[1:].split(":")
        return "sleep", f"{int(hh) * 60 + int(mm)} min", why
    return None  # TRUE → S: an empty step; keep it as written


def _step_kind(step: Mapping[str, Any]) -> str:
    return next(k for k in STEP_KINDS if k in step)


def _step(row: _Row, last: bool, simplify: bool) -> tuple[dict[str, Any], str | None]:
    step: dict[str, Any] = {"id": f"s{row.adr}"}
    if row.comment:
        step["comment"] = row.comment
    instant = _instant_step(row, last) if simplify else None
    if instant is not None:
        kind, value, why = instant
        step[kind] = value
    else:
        why = None
        if row.ma == 0:
            step["rest"] = True
        else:
            step["charge" if row.letter == "C" else "discharge"] = f"{row.ma} mA"
        step["duration"] = f"{row.sd} s"
        until = [{cond: act.recipe_action()} for cond, act in row.conditions if act.kind != "I"]
        if until:
            step["until"] = until
    step["advance"] = False if row.ctrlz.kind == "I" else row.ctrlz.recipe_action()
    return step, why


# --------------------------------------------------------------------------------------------
# Writing


def _recipe_name(path: Path, name: str | None) -> str:
    if name is not None:
        if not re.match(ID_PATTERN, name):
            raise ConfigError(
                f"--name {name!r}: a recipe name must match {ID_PATTERN}", "<command line>"
            )
        return name
    stem = re.sub(r"[^A-Za-z0-9_\-]+", "-", path.stem).strip("-") or "imported"
    if not re.match(r"^[A-Za-z_]", stem):
        stem = f"chadeche-{stem}"
    return stem


def _emit(
    recipe: dict[str, Any],
    header: list[str],
    param_notes: dict[str, str],
    step_notes: list[list[str]],
) -> tuple[str, list[tuple[int, int]], dict[int, str]]:
    """Recipe YAML text, per step the (first, last) line it spans, and the line of each
    option's value (line → option target: ``v_min``, ``cycles``, ``logging.period``)."""
    out: list[str] = [f"# {yaml_comment(h)}".rstrip() for h in header]
    option_lines: dict[int, str] = {}

    def put(text: str, note: str | None = None, target: str | None = None) -> None:
        out.append(f"{text:<24}  # {yaml_comment(note)}" if note else text)
        if target is not None:
            option_lines[len(out)] = target

    put(f"recipe: {yaml_scalar(recipe['recipe'])}")
    put(f"description: {yaml_scalar(recipe['description'])}")
    put("parameters:")
    for pname, value in recipe["parameters"].items():
        put(f"  {pname}: {yaml_scalar(value)}", param_notes.get(pname), pname)
    put(f"initial_charge: {recipe['initial_charge']}", target="q_init")
    put(f"cycles: {recipe['cycles']}", param_notes.get("cycles"), "cycles")
    put("logging:")
    put(
        f"  period: {yaml_scalar(recipe['logging']['period'])}",
        param_notes.get("logging.period"),
        "logging.period",
    )
    put("steps:")
    spans: list[tuple[int, int]] = []
    for step, notes in zip(recipe["steps"], step_notes, strict=True):
        for note in notes:
            put(f"  # {yaml_comment(note)}")
        first = len(out) + 1
        lead = "  - "
        for key, value in step.items():
            if key == "until":
                put(f"    {key}:")
                for item in value:
                    ((cond, act),) = item.items()
                    put(f"      - {yaml_scalar(cond, key=True)}: {yaml_scalar(act)}")
            else:
                put(f"{lead}{key}: {yaml_scalar(value)}")
            lead = "    "
        spans.append((first, len(out)))
    return "\n".join(out) + "\n", spans, option_lines


def _check_compiles(
    text: str,
    spans: list[tuple[int, int]],
    rows: list[_Row],
    source: str,
    options: Mapping[int, _Param],
) -> None:
    """Load and compile the produced recipe; a refusal is reported at the source row, or
    where the option it is about was set (``chadeche0.prm:5``)."""
    where = "<imported recipe>"
    try:
        recipe, pos = load_recipe_text(text, where)
        compile_recipe(recipe, pos, where, Target())
    except ConfigErrors as exc:
        mapped: list[ConfigError] = []
        for e in exc.errors:
            message = f"the imported recipe is refused: {e.message}"
            option = options.get(e.line) if e.line is not None else None
            if option is not None:
                mapped.append(option.error(message, source))
                continue
            line = None
            for (first, last), row in zip(spans, rows, strict=True):
                if e.line is not None and first <= e.line <= last:
                    line = row.line
            mapped.append(ConfigError(message, source, line, 1))
        raise ConfigErrors(mapped) from None


def _warn_instant_currents(rows: list[_Row], path: Path, warnings: list[str]) -> None:
    """A row with a current whose TRUE acts first: the current flows for one scan at most."""
    for r in rows:
        first = next(((c, a) for c, a in r.conditions if a.kind != "I"), None)
        if r.ma and first is not None and first[0] == "true":
            warnings.append(
                f"{path}:{r.line}: TRUE acts at once, so the {r.ma} mA of ADR {r.adr} "
                "flow for one scan at most"
            )


def _recipe_data(
    path: Path, name: str | None, params: dict[str, _Param], rows: list[_Row], simplify: bool
) -> tuple[dict[str, Any], dict[str, str], list[list[str]]]:
    """The recipe as plain data, the note beside each option's line (where its value came
    from) and the comment lines above each step (its source row, why it is instant)."""
    recipe_params: dict[str, str] = {}
    notes: dict[str, str] = {}
    for letter, opt in OPTIONS.items():
        p = params[letter]
        notes[opt.target] = f"-{letter}: {p.source}"
        if opt.target in ("cycles", "logging.period"):
            continue
        recipe_params[opt.target] = f"{_num(p.value)} {opt.unit}"
    recipe: dict[str, Any] = {
        "recipe": _recipe_name(path, name),
        "description": f"Imported from the Chadèche sequence file {path.name}",
        "parameters": recipe_params,
        "initial_charge": "q_init",
        "cycles": int(params["n"].value),
        "logging": {"period": f"{_num(params['p'].value)} s"},
    }
    steps: list[dict[str, Any]] = []
    step_notes: list[list[str]] = []
    for k, row in enumerate(rows):
        step, why = _step(row, k == len(rows) - 1, simplify)
        steps.append(step)
        note = [f"line {row.line}: " + "  ".join(row.cells)]
        if why:
            note.append(f"  → {_step_kind(step)}: {why}")
        step_notes.append(note)
    recipe["steps"] = steps
    return recipe, notes, step_notes


def _header(
    path: Path,
    prm_path: str | Path | None,
    about: str,
    rows: list[_Row],
    params: dict[str, _Param],
    overridden: bool,
) -> list[str]:
    """The recipe file's comment header: where it came from and what was assumed."""
    assumed = [
        f"-{o.letter} {_num(o.default)}{(' ' + o.unit) if o.unit else ''}"
        for o in OPTIONS.values()
        if o.assumed and params[o.letter].source == o.source
    ]
    header = [
        "Imported by supervisor.importers.chadeche from a Chadèche sequence file (seed 000",
        "§III.D); edit freely, the source is not read again.",
        f"source: {path} ({about}, {len(rows)} rows)",
        f"parameters: {prm_path if prm_path is not None else 'no .prm file'}"
        + (", with overrides" if overridden else ""),
        "Row ADR → step s<ADR>; TL TH LmAh HmAh TRUE → until (column order, first true acts);",
        "CTRLZ → advance; each source row is repeated above its step.",
    ]
    if assumed:
        header.append(f"Assumed defaults (the seed does not state them): {', '.join(assumed)}.")
    header.append("A sequence file has no safety limits: add `limits:` (voltage, temperature).")
    return header


def _calibration_out(
    calibration: dict[str, _Param],
) -> tuple[dict[str, float] | None, str | None]:
    """``-1 -2 -s -o`` as I/O-map calibration keys and the YAML lines to paste, or None."""
    if not calibration:
        return None, None
    cal: dict[str, float] = {}
    lines = ["# Chadèche board calibration (seed §III.F); paste under the board's calibration:"]
    for letter, (key, what) in CALIBRATION.items():
        if letter in calibration:
            cal[key] = calibration[letter].value
            source = calibration[letter].source
            lines.append(
                f"{key + ':':<19} {yaml_float(cal[key]):<8}  # -{letter}: {what} ({source})"
            )
    return cal, "\n".join(lines) + "\n"


def import_chadeche(
    config_path: str | Path,
    prm_path: str | Path | None = None,
    *,
    name: str | None = None,
    overrides: Mapping[str, str | float | int] | None = None,
    simplify: bool = True,
) -> ImportResult:
    """Translate a Chadèche sequence file (+ optional ``chadecheN.prm``) into a recipe.

    ``overrides`` are command-line options by letter (``{"-m": 1.1, "-i": 1300}``, the
    dash is optional); they win over the parameter file, which wins over the defaults.
    Raises ConfigErrors (every problem, each with file, line and column) for a broken file.
    """
    path = Path(config_path)
    rows, warnings, about = _read_rows(path)

    params = {k: _Param(o.default, o.source) for k, o in OPTIONS.items()}
    calibration: dict[str, _Param] = {}
    if prm_path is not None:
        _read_prm(Path(prm_path), params, calibration, warnings)
    if overrides:
        _apply_overrides(overrides, params, calibration, warnings)
    _check_together(params, str(prm_path if prm_path is not None else path))
    _warn_instant_currents(rows, path, warnings)

    recipe, notes, step_notes = _recipe_data(path, name, params, rows, simplify)
    header = _header(path, prm_path, about, rows, params, bool(overrides))
    text, spans, option_lines = _emit(recipe, header, notes, step_notes)
    by_target = {o.target: params[letter] for letter, o in OPTIONS.items()}
    options = {line: by_target[target] for line, target in option_lines.items()}
    _check_compiles(text, spans, rows, str(path), options)
    cal, snippet = _calibration_out(calibration)
    return ImportResult(text, recipe, cal, snippet, warnings)
