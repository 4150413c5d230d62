"""A load profile's header line: which column is the time, the current, a window's bound.

Seed 002's profiles come from spreadsheets and from the Tk HMI's own log (figures 21 and
26: ``Time,Voltage,Current,Temperature,BMS Faults,Cell Voltage,Cell Temperature``), so a
column is found by its name, never by its place (issue 32: ``Time,Voltage,Current`` read
the voltage as the current). Names are compared without case, accents, ``_``/``-``/blank
differences, and with their unit in parentheses or brackets (``Courant (A)``,
``Time [ms]``) or as a suffix (``current_a``, ``t_s``). A name not known here is refused
naming the column: a column silently dropped or misread drives the wrong current.

What a name may be (:func:`column_of`):

- the time: ``t``, ``time``, ``temps``, ``timestamp``, … in s (default), ms, min or h;
- the current, the one setpoint a profile drives: ``i``, ``current``, ``courant``, in A
  (default) or mA;
- a window bound: ``V min``, ``v_max``, ``Courant Max``, ``t_min`` (``t`` with a bound is
  the temperature, as in a recipe's rows), or both in one cell: ``Tension Min/Max``,
  ``v_min/v_max``;
- a bare ``V``/``Voltage``/``Tension`` or ``T``/``Temperature``: a window when its cells
  hold ``min/max`` pairs (``t;I;V`` then ``0;2;12/16.8``), else a value recorded by the
  run that wrote the file (the seed's log): not a setpoint, read past with a notice;
- the seed's other recorded columns (``BMS Faults``, ``Cell Voltage``, ``Cell
  Temperature``) and a column without a name: read past with a notice.
"""

from __future__ import annotations

import re
import unicodedata
from dataclasses import dataclass
from typing import Final, Literal

__all__ = ["KNOWN_COLUMNS", "Column", "ColumnError", "column_of"]

Role = Literal["time", "current", "bound", "pair", "bare", "ignored"]

KNOWN_COLUMNS: Final = (
    "Time (s|ms|min|h), Current (A|mA), and optionally V/I/T min and max"
    " (e.g. 'V min (V)', 'Courant Max', 't_max', or one 'Tension Min/Max' cell)"
)

_TIME_NAMES: Final = frozenset(
    {"t", "time", "temps", "timestamp", "time stamp", "test time", "elapsed", "horodatage"}
)
_QUANTITY: Final = {
    "i": 1,
    "current": 1,
    "courant": 1,
    "v": 0,
    "u": 0,
    "voltage": 0,
    "tension": 0,
    "t": 2,  # with a bound: the temperature (a recipe row's t_min/t_max)
    "temp": 2,
    "temperature": 2,
}
"""A window's quantity: its index in ``PROFILE_WINDOWS`` (V, I, T)."""
_RECORDED: Final = frozenset(
    {
        "bms faults",
        "faults",
        "defauts bms",
        "defauts",
        "cell voltage",
        "cell temperature",
        "cell temp",
        "tension cellule",
        "temperature cellule",
    }
)
_SCALES: Final = {
    "time": {"": 1.0, "s": 1.0, "sec": 1.0, "ms": 1e-3, "min": 60.0, "h": 3600.0},
    0: {"": 1.0, "v": 1.0, "mv": 1e-3},
    1: {"": 1.0, "a": 1.0, "ma": 1e-3},
    2: {"": 1.0, "c": 1.0, "°c": 1.0, "degc": 1.0, "deg c": 1.0},
}
_UNIT_NAMES: Final = {"time": "s, ms, min, h", 0: "V, mV", 1: "A, mA", 2: "°C"}
# Units written as a suffix (``t_s``, ``current_a``); never ``min`` (``t_min`` is a bound).
_SUFFIX_UNITS: Final = frozenset({"s", "ms", "h", "a", "ma", "v", "mv", "c", "degc"})
_UNIT_IN_BRACKETS: Final = re.compile(r"^(.*?)\s*[(\[]([^)\]]*)[)\]]\s*$")
_BOUND: Final = re.compile(r"^(.*?)\s*(min|max)$")


class ColumnError(ValueError):
    """A header cell that names no column of a load profile (the message says why)."""


@dataclass(frozen=True)
class Column:
    """What one column of a profile holds."""

    role: Role
    window: int = -1
    """V, I or T (0, 1, 2: ``PROFILE_WINDOWS``) for a bound, a pair or a bare column."""
    high: bool = False
    """A bound: the window's high end."""
    scale: float = 1.0
    """Multiplies the cell's number into s, A, V or °C."""
    name: str = ""
    """The header cell as written."""


def _plain(text: str) -> str:
    """Lower case, no accents, ``_``/``-``/runs of blanks as one blank."""
    decomposed = unicodedata.normalize("NFKD", text)
    bare = "".join(c for c in decomposed if not unicodedata.combining(c))
    return re.sub(r"[\s_\-]+", " ", bare.lower()).strip()


def _split_unit(plain: str) -> tuple[str, str]:
    """``(name, unit)``: the unit in brackets at the end, or a known unit as last word."""
    m = _UNIT_IN_BRACKETS.match(plain)
    if m:
        return m.group(1).strip(), m.group(2).strip()
    words = plain.split(" ")
    if len(words) > 1 and words[-1] in _SUFFIX_UNITS:
        return " ".join(words[:-1]), words[-1]
    return plain, ""


def _bound(name: str) -> tuple[str, str]:
    """``(quantity, "min"|"max"|"")``: ``v min``, ``vmin``, ``min v`` and ``v`` alike
    (``max`` alone: no quantity, the right half of ``Tension Min/Max``)."""
    if name in ("min", "max"):
        return "", name
    m = _BOUND.match(name)
    if m and m.group(1):
        return m.group(1).strip(), m.group(2)
    m = re.match(r"^(min|max)\s+(.+)$", name)
    if m:
        return m.group(2).strip(), m.group(1)
    return name, ""


def _scale(key: str | int, unit: str, written: str) -> float:
    scales = _SCALES[key]
    if unit not in scales:
        raise ColumnError(f"column {written!r}: unit {unit!r} is not one of {_UNIT_NAMES[key]}")
    return scales[unit]


def _pair(name: str, unit: str, written: str) -> Column:
    """``Tension Min/Max``, ``v_min/v_max``, ``Vmin/Vmax``: one cell ``low/high``."""
    left, _, right = name.partition("/")
    (q_lo, lo), (q_hi, hi) = _bound(left.strip()), _bound(right.strip())
    window = _QUANTITY.get(q_lo)
    if window is None or (lo, hi) != ("min", "max") or q_hi not in ("", q_lo):
        raise _unknown(written)
    return Column("pair", window, scale=_scale(window, unit, written), name=written)


def _unknown(written: str) -> ColumnError:
    return ColumnError(
        f"column {written!r} is not a column of a load profile: a profile has {KNOWN_COLUMNS}"
    )


def column_of(written: str) -> Column:
    """The column a header cell names; ``ColumnError`` naming it when none."""
    plain = _plain(written)
    if not plain:
        return Column("ignored", name=written)
    name, unit = _split_unit(plain)
    if "/" in name:
        return _pair(name, unit, written)
    if name in _RECORDED:
        return Column("ignored", name=written)
    quantity, bound = _bound(name)
    if not bound and name in _TIME_NAMES:
        return Column("time", scale=_scale("time", unit, written), name=written)
    window = _QUANTITY.get(quantity)
    if window is None:
        raise _unknown(written)
    scale = _scale(window, unit, written)
    if bound:
        return Column("bound", window, high=bound == "max", scale=scale, name=written)
    if window == 1:
        return Column("current", 1, scale=scale, name=written)
    return Column("bare", window, scale=scale, name=written)
