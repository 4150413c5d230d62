"""Load profiles in CSV (seed 002 §2.3), read for a recipe's ``profile: {file: ...}``."""

from __future__ import annotations

import math
import re
from pathlib import Path

from supervisor.chains.program import ProfilePoint
from supervisor.config.limits import MAX_PROFILE_CSV_BYTES, MAX_PROFILE_ROWS, read_limited
from supervisor.config.recipe import profile_window_problem
from supervisor.config.text import Layout, Row, decode_text, read_table
from supervisor.core.errors import ConfigError

__all__ = ["read_profile_csv"]

_LIMITS = 6  # V min/max, I min/max, T min/max after the current
_COLUMNS = "time, current, v_min, v_max, i_min, i_max, t_min, t_max"
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


def _point(row: Row, layout: Layout, path: Path, *, header: bool) -> ProfilePoint | None:
    """One row as a point; None for a header line or a row of empty cells."""
    if not any(cell.text for cell in row.cells):
        return None
    first = row.cells[0]
    t = layout.number(first.text)
    if t is None:
        if header:
            return None
        raise ConfigError(f"time {first.text!r} is not a number", path, row.line, first.col)
    if not math.isfinite(t):
        # A NaN time compares false with everything: it would slip past the ordering check.
        raise ConfigError(f"time {first.text!r} is not a finite number", path, row.line, first.col)
    values = _limits(row, layout, path)
    if not values or values[0] is None:
        col = row.cells[1].col if len(row.cells) > 1 else row.end_col
        raise ConfigError("each row needs a current after the time", path, row.line, col)
    values += [None] * (1 + _LIMITS - len(values))
    return ProfilePoint(t, values[0], *values[1 : 1 + _LIMITS])


def read_profile_csv(path: Path) -> tuple[ProfilePoint, ...]:
    """A load profile (seed 002 §2.3): time, current, then optional V/I/T min/max columns.

    Accepts ``,`` ``;`` or tab separators (with ``;`` or tab a ``,`` is a decimal comma:
    :func:`supervisor.config.text.read_table`), a header line, UTF-8 or CP1252, and
    ``min/max`` pairs written in one cell as ``3.0/4.2``. Errors name file, line and column.
    """
    try:
        raw = read_limited(path, MAX_PROFILE_CSV_BYTES, "a load profile")
    except OSError as exc:
        raise ConfigError(f"cannot read profile: {exc.strerror or exc}", path) from None
    decoded = decode_text(raw, path)
    if not decoded.text:
        raise ConfigError("profile is empty", path, 1, 1)
    # One more row than the limit: the header line.
    layout, rows = read_table(decoded, path, max_rows=MAX_PROFILE_ROWS + 1, what="a load profile")
    out: list[ProfilePoint] = []
    last_t = -1.0
    for k, row in enumerate(rows):
        point = _point(row, layout, path, header=k == 0)
        if point is None:
            continue
        if point.t_s <= last_t:
            raise ConfigError(
                f"time {point.t_s:g} s does not increase", path, row.line, row.cells[0].col
            )
        last_t = point.t_s
        out.append(point)
    if not out:
        raise ConfigError("profile has no rows", path, 1, 1)
    return tuple(out)
