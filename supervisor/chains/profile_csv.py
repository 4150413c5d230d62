"""Load profiles in CSV (seed 002 §2.3), read for a recipe's ``profile: {file: ...}``,
``supervisor import profile`` and the Recipes screen's profile upload.

With a header line, columns are found by name (:mod:`supervisor.chains.profile_columns`);
without one, by place: time, current, then the V/I/T windows. Times written as Unix
timestamps (the seed's Tk HMI writes ``time.time()``: figures 21 and 26) are made relative
to the first row, with a notice: read as seconds from the step's start, a 0.5 s profile
ran for 55 years (issue 32).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Final

from supervisor.chains.profile_columns import KNOWN_COLUMNS, Column, ColumnError, column_of
from supervisor.chains.program import ProfilePoint
from supervisor.config.limits import MAX_PROFILE_CSV_BYTES, MAX_PROFILE_ROWS, read_limited
from supervisor.config.recipe import PROFILE_WINDOWS, profile_window_problem
from supervisor.config.text import Cell, Layout, Row, decode_text, read_table
from supervisor.core.errors import ConfigError

__all__ = [
    "UNIX_TIME_MIN_S",
    "ProfileTable",
    "parse_profile_csv",
    "read_profile_csv",
    "read_profile_table",
]

log = logging.getLogger(__name__)

UNIX_TIME_MIN_S: Final = 1e9
"""A first time at least this (2001-09-09 as a Unix time; 31 years as a duration) is a
Unix timestamp: no profile step lasts decades, and every log of this century is above."""

_LIMITS = 6  # V min/max, I min/max, T min/max after the current
_COLUMNS = "time, current, v_min, v_max, i_min, i_max, t_min, t_max"
_KNOWN = KNOWN_COLUMNS
# A number with a non-zero digit before its exponent: ``1e-400`` is not zero, it underflows
# (as core.units refuses it in a recipe).
_NONZERO_MANTISSA = re.compile(r"^[-+]?0*[.,]?0*[1-9]")


def _number(text: str, layout: Layout, path: Path, line: int, col: int) -> float | None:
    value = layout.number(text) if text else None
    if text and value is None:
        raise ConfigError(f"{text!r} is not a number", path, line, col)
    if value is not None and not math.isfinite(value):
        raise ConfigError(f"{text!r} is not a finite number", path, line, col)
    if value == 0.0 and _NONZERO_MANTISSA.match(text):
        raise ConfigError(
            f"{text!r} is too small to be told from zero: write 0 or a larger value",
            path,
            line,
            col,
        )
    return value


def _limits(row: Row, layout: Layout, path: Path) -> list[float | None]:
    """Current and the optional limits: a pair in two cells or one ``min/max`` cell."""
    values: list[float | None] = []
    cols: list[int] = []
    for k, cell in enumerate(row.cells[1:]):
        parts = cell.text.split("/")
        # ``1/2/3`` spilled into the next window, ``1/2`` as the current into v_min.
        if len(parts) > 2 or (k == 0 and len(parts) > 1):
            what = "the current is one number" if k == 0 else "a min/max cell holds two numbers"
            raise ConfigError(f"{cell.text!r}: {what}", path, row.line, cell.col)
        for part in parts:
            values.append(_number(part.strip(), layout, path, row.line, cell.col))
            cols.append(cell.col)
    if len(values) > 1 + _LIMITS:
        # A column after t_max was dropped without a word (issue 28).
        raise ConfigError(
            f"this row has {1 + len(values)} columns; a load profile has at most"
            f" {2 + _LIMITS}: {_COLUMNS}",
            path,
            row.line,
            cols[1 + _LIMITS],
        )
    last = row.cells[-1].text
    if layout.delimiter == "," and len(values) % 2 == 0 and last and "/" not in last:
        # Time and current, then whole windows: a window with one bound gives the other
        # an empty cell. A row ending in a lone bound is what decimal commas make of a
        # row with ``,`` as the separator (``0,0,5`` read as 0 s, 0 A and v_min 5 V;
        # issue 28).
        raise ConfigError(
            f"this row has {1 + len(values)} values with ',' as the separator: a window"
            " lacks its other bound. If the file has decimal commas, separate the cells"
            " with ';' (or write decimal points); a window with one bound gives the other"
            " an empty cell (e.g. '0,1.5,3.0,')",
            path,
            row.line,
            row.cells[0].col,
        )
    # Each V/I/T window low then high, as in a recipe's own rows (at the window's cell).
    for k in range(_LIMITS // 2):
        pair = values[1 + 2 * k : 3 + 2 * k]
        problem = profile_window_problem(k, *pair) if len(pair) == 2 else None
        if problem:
            raise ConfigError(problem, path, row.line, cols[1 + 2 * k])
    return values


def _point(row: Row, layout: Layout, path: Path) -> ProfilePoint | None:
    """One row read by place (no header line); None for a row of empty cells."""
    if not any(cell.text for cell in row.cells):
        return None
    first = row.cells[0]
    t = _time(first, layout, path, row.line)
    values = _limits(row, layout, path)
    if not values or values[0] is None:
        col = row.cells[1].col if len(row.cells) > 1 else row.end_col
        raise ConfigError("each row needs a current after the time", path, row.line, col)
    values += [None] * (1 + _LIMITS - len(values))
    return ProfilePoint(t, values[0], *values[1 : 1 + _LIMITS])


def _time(cell: Cell, layout: Layout, path: Path, line: int) -> float:
    t = layout.number(cell.text)
    if t is None:
        raise ConfigError(f"time {cell.text!r} is not a number", path, line, cell.col)
    if not math.isfinite(t):
        # A NaN time compares false with everything: it would slip past the ordering check.
        raise ConfigError(f"time {cell.text!r} is not a finite number", path, line, cell.col)
    return t


# --- columns by name (a header line) --------------------------------------------------------
@dataclass(frozen=True)
class _Header:
    columns: tuple[Column, ...]
    notices: tuple[str, ...]
    by_place: bool
    """The names are those of the places (time, current, then windows in order, no unit
    to convert): the rows are read by place, as without a header, so a row may go on
    past the names (``t,i`` then ``0,0.5,2.5,4.2``, as before names were read)."""


def _named_by_place(columns: Sequence[Column]) -> bool:
    if [c.role for c in columns[:2]] != ["time", "current"] or any(c.scale != 1.0 for c in columns):
        return False
    window, half = 0, 0  # the next window expected, and which end of it
    for c in columns[2:]:
        if c.role == "pair" and half == 0 and c.window == window:
            window += 1
        elif c.role == "bound" and c.window == window and c.high == (half == 1):
            window, half = (window + 1, 0) if half else (window, 1)
        else:
            return False
    return True


def _column(cell: Cell, path: Path, line: int) -> Column:
    try:
        return column_of(cell.text)
    except ColumnError as exc:
        raise ConfigError(str(exc), path, line, cell.col) from None


def _settle_bare(column: Column, k: int, body: Sequence[Row]) -> Column:
    """A bare V or T column: a window when its first value is a ``min/max`` pair, else a
    value recorded by the run that wrote the file (figure 21's ``Voltage``)."""
    for row in body:
        if k < len(row.cells) and row.cells[k].text:
            if "/" in row.cells[k].text:
                return Column("pair", column.window, scale=column.scale, name=column.name)
            return Column("ignored", name=column.name)
    return Column("ignored", name=column.name)


def _slot(column: Column) -> str:
    """What a column fills, to find two columns filling one thing."""
    if column.role in ("time", "current"):
        return column.role
    if column.role == "pair":
        return f"w{column.window}"
    return f"w{column.window}{'hi' if column.high else 'lo'}"


def _check_slots(columns: Sequence[Column], header: Row, path: Path) -> None:
    seen: dict[str, str] = {}
    for column, cell in zip(columns, header.cells, strict=True):
        if column.role == "ignored":
            continue
        slot = _slot(column)
        clash = [s for s in (slot, slot[:2] if column.role == "bound" else "") if s in seen]
        clash += [s for s in seen if column.role == "pair" and s.startswith(slot)]
        if clash:
            raise ConfigError(
                f"column {cell.text!r} gives what column {seen[clash[0]]!r} gives already",
                path,
                header.line,
                cell.col,
            )
        seen[slot] = cell.text
    for needed in ("time", "current"):
        if needed not in seen:
            raise ConfigError(
                f"the header names no {needed} column: a load profile has {_KNOWN}",
                path,
                header.line,
                header.cells[0].col,
            )


def _header(header: Row, body: Sequence[Row], path: Path) -> _Header:
    columns = [_column(cell, path, header.line) for cell in header.cells]
    columns = [_settle_bare(c, k, body) if c.role == "bare" else c for k, c in enumerate(columns)]
    _check_slots(columns, header, path)
    ignored = [c.name for c in columns if c.role == "ignored" and c.name]
    notices = []
    if ignored:
        names = ", ".join(repr(n) for n in ignored)
        notices.append(
            f"column{'s' if len(ignored) > 1 else ''} {names} not used: values a run recorded,"
            " not setpoints (a profile drives the current, within its V/I/T windows)"
        )
    return _Header(tuple(columns), tuple(notices), _named_by_place(columns))


def _cell_values(
    column: Column, cell: Cell, layout: Layout, path: Path, line: int
) -> list[float | None]:
    """The numbers of one cell (two for a ``min/max`` pair), scaled to s, A, V, °C."""
    if column.role == "time":
        return [_scaled(_time(cell, layout, path, line), column.scale)]
    parts = cell.text.split("/") if cell.text else []
    expected = 2 if column.role == "pair" else 1
    if cell.text and len(parts) != expected:
        what = "a min/max cell holds two numbers: low/high" if expected == 2 else "one number"
        raise ConfigError(
            f"{cell.text!r}: column {column.name!r} takes {what}", path, line, cell.col
        )
    values = [_number(part.strip(), layout, path, line, cell.col) for part in parts]
    if not values:
        return [None] * expected
    return [_scaled(v, column.scale) if v is not None else None for v in values]


def _scaled(value: float, scale: float) -> float:
    """``value`` in the base unit: divided for a sub-unit (``700 mA`` is 0.7 A, where
    ``700 * 1e-3`` is 0.7000000000000001)."""
    return value / round(1 / scale) if scale < 1 else value * scale


def _named_point(row: Row, header: _Header, layout: Layout, path: Path) -> ProfilePoint | None:
    """One row read by the header's names; None for a row of empty cells."""
    if not any(cell.text for cell in row.cells):
        return None
    columns = header.columns
    # Empty cells past the names are a spreadsheet's trailing separators.
    extra = [k for k in range(len(columns), len(row.cells)) if row.cells[k].text]
    if extra:
        raise ConfigError(
            f"this row has a value in column {extra[0] + 1}; the header names"
            f" {len(columns)} columns",
            path,
            row.line,
            row.cells[extra[0]].col,
        )
    fields: dict[str, float | None] = {}
    cols: dict[str, int] = {}
    for column, cell in zip(columns, row.cells, strict=False):
        if column.role == "ignored":
            continue
        values = _cell_values(column, cell, layout, path, row.line)
        for key, value in zip(_keys(column), values, strict=True):
            fields[key], cols[key] = value, cell.col
    return _point_of(fields, cols, row, header, path)


def _keys(column: Column) -> tuple[str, ...]:
    if column.role in ("time", "current"):
        return (column.role,)
    low, high, _ = PROFILE_WINDOWS[column.window]
    if column.role == "pair":
        return (low, high)
    return (high if column.high else low,)


def _point_of(
    fields: dict[str, float | None], cols: dict[str, int], row: Row, header: _Header, path: Path
) -> ProfilePoint:
    t, current = fields.pop("time", None), fields.pop("current", None)
    if t is None:
        raise ConfigError("each row needs a time", path, row.line, row.end_col)
    if current is None:
        k = next(k for k, c in enumerate(header.columns) if c.role == "current")
        col = row.cells[k].col if k < len(row.cells) else row.end_col
        raise ConfigError("each row needs a current", path, row.line, col)
    for k, (low, high, _) in enumerate(PROFILE_WINDOWS):
        problem = profile_window_problem(k, fields.get(low), fields.get(high))
        if problem:
            # At the window's low cell, as a row read by place is refused.
            raise ConfigError(problem, path, row.line, cols[low])
    return ProfilePoint(t, current, **fields)


# --- the table --------------------------------------------------------------------------------
@dataclass(frozen=True)
class ProfileTable:
    """A load profile as read: its points (times from the step start) and what the reader
    did that the operator should know (columns not used, absolute times made relative)."""

    points: tuple[ProfilePoint, ...]
    notices: tuple[str, ...] = ()
    unix_start_s: float | None = None
    """The first row's Unix time when the file's times were Unix timestamps."""


def _absolute_to_relative(
    points: tuple[ProfilePoint, ...],
) -> tuple[tuple[ProfilePoint, ...], str | None]:
    """Times from the first row when they are Unix timestamps, with the notice saying so
    (rounded to the microsecond: a timestamp's float has about that resolution)."""
    t0 = points[0].t_s
    if t0 < UNIX_TIME_MIN_S:
        return points, None
    moved = tuple(replace(p, t_s=round(p.t_s - t0, 6)) for p in points)
    when = datetime.fromtimestamp(t0, UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]
    notice = (
        f"times are Unix timestamps (the first row at {when} UTC): made relative to the"
        f" first row; the profile lasts {moved[-1].t_s:g} s"
    )
    return moved, notice


def _ordered(points: Sequence[tuple[ProfilePoint, Row]], path: Path) -> None:
    last_t = -math.inf
    for point, row in points:
        if point.t_s <= last_t:
            raise ConfigError(
                f"time {point.t_s:g} s does not increase", path, row.line, row.cells[0].col
            )
        last_t = point.t_s


def parse_profile_csv(raw: bytes, path: str | Path) -> ProfileTable:
    """A load profile's bytes (``path`` names it in errors), as :func:`read_profile_table`."""
    path = Path(path)
    decoded = decode_text(raw, path)
    if not decoded.text:
        raise ConfigError("profile is empty", path, 1, 1)
    # One more row than the limit: the header line.
    layout, rows = read_table(decoded, path, max_rows=MAX_PROFILE_ROWS + 1, what="a load profile")
    header: _Header | None = None
    if rows and layout.number(rows[0].cells[0].text) is None:
        header = _header(rows[0], rows[1:], path)
        rows = rows[1:]
    read: list[tuple[ProfilePoint, Row]] = []
    named = header if header is not None and not header.by_place else None
    for row in rows:
        point = _named_point(row, named, layout, path) if named else _point(row, layout, path)
        if point is not None:
            read.append((point, row))
    if not read:
        raise ConfigError("profile has no rows", path, 1, 1)
    _ordered(read, path)
    points, moved = _absolute_to_relative(tuple(p for p, _ in read))
    notices = (*(header.notices if header else ()), *([moved] if moved else []))
    return ProfileTable(points, notices, read[0][0].t_s if moved else None)


def read_profile_table(path: Path) -> ProfileTable:
    """A load profile (seed 002 §2.3) with what the reader noticed.

    Columns by their header's names (:mod:`supervisor.chains.profile_columns`), else by
    place: time, current, then optional V/I/T min/max. Accepts ``,`` ``;`` or tab
    separators (with ``;`` or tab a ``,`` is a decimal comma:
    :func:`supervisor.config.text.read_table`), UTF-8 or CP1252, and ``min/max`` pairs
    written in one cell as ``3.0/4.2``. Unix timestamps are made relative to the first
    row. Errors name file, line and column.
    """
    try:
        raw = read_limited(path, MAX_PROFILE_CSV_BYTES, "a load profile")
    except OSError as exc:
        raise ConfigError(f"cannot read profile: {exc.strerror or exc}", path) from None
    return parse_profile_csv(raw, path)


def read_profile_csv(path: Path) -> tuple[ProfilePoint, ...]:
    """The points of :func:`read_profile_table` (a recipe's ``profile: {file: ...}``); its
    notices are logged."""
    table = read_profile_table(path)
    for notice in table.notices:
        log.info("profile %s: %s", path, notice)
    return table.points
