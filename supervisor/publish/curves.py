"""Voltage against charge per half-cycle, and capacity per cycle, read back from a test's
result files (issue 33 finding 10: tests compared on the Tests screen).

A *half* is a run of rows of one cycle going one way: ``charge`` (a charge step, or
current into the cell: BDF's convention, positive current charges) or ``discharge``. Rests
(no current, a rest step) belong to no half and do not end one: a charge, a rest, more
charge is one charge half. A half ends where the current's direction changes, or at the
end of its cycle; a cycle that goes back the other way has a second half of that kind
(``index`` 2). Ah is counted from the start of the half, positive both ways (as the BDF's
capacity columns are): from the recorded cycle capacity (``Cycle Charging Capacity / Ah``,
``Cycle Discharging Capacity / Ah``) less its value before the half, or, for a file without
those columns, from the integral of the current over test time (trapezoids).

A curve has at most ``max_points`` points (min-max decimation: each bucket of rows keeps
its lowest and highest voltage in order, so a spike or a knee survives). Only the rows of
the cycles asked for are kept, and the reading stops after the last of them (a result
file's cycles only grow, also after a resume).
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Final

from supervisor.publish.results import CYCLES_SUFFIX, read_jsonl

log = logging.getLogger(__name__)

__all__ = [
    "MAX_POINTS_PER_CURVE",
    "CycleCapacity",
    "HalfCurve",
    "cycle_capacities",
    "cycle_numbers",
    "decimate",
    "direction",
    "half_curves",
]

MAX_POINTS_PER_CURVE: Final = 2000
"""What a browser draws at once without a wait, for up to a dozen curves overlaid."""

CURRENT_DEADBAND_A: Final = 1e-6
"""A current this small is a rest (the BDF writes 6 significant digits, a rest 0)."""

_T, _V, _I, _CYCLE, _STEP_TYPE = (
    "Test Time / s",
    "Voltage / V",
    "Current / A",
    "Cycle Count / 1",
    "Step Type",
)
_CYCLE_AH = {
    "charge": "Cycle Charging Capacity / Ah",
    "discharge": "Cycle Discharging Capacity / Ah",
}


@dataclass
class HalfCurve:
    """One half of one cycle: voltage (V) against the charge since the half began (Ah)."""

    cycle: int
    half: str  # "charge" | "discharge"
    index: int = 1  # the first, second, … half of that kind in its cycle
    ah: list[float] = field(default_factory=list)
    v: list[float] = field(default_factory=list)
    rows: int = 0  # the file's rows in it, before decimation

    def as_dict(self) -> dict[str, Any]:
        return {
            "cycle": self.cycle,
            "half": self.half,
            "index": self.index,
            "rows": self.rows,
            "ah": self.ah,
            "v": self.v,
        }


def _float(cell: str) -> float | None:
    try:
        x = float(cell)
    except ValueError:
        return None
    return x if x == x and abs(x) != float("inf") else None  # no NaN, no infinity


@lru_cache(maxsize=256)
def _step_half(step_type: str) -> str | None:
    """The half a step's type names ("" for a rest, None when it names none)."""
    kind = step_type.upper()
    if "DCH" in kind or "DISCHARGE" in kind:
        return "discharge"
    if "CHG" in kind or "CHARGE" in kind:
        return "charge"
    return "" if "REST" in kind else None


def direction(step_type: str, current_a: float | None) -> str | None:
    """Which half a row belongs to: the step's type when it says, else the current's sign
    (a pulse or a custom step), None for a rest."""
    named = _step_half(step_type)
    if named is not None:
        return named or None
    if current_a is None or abs(current_a) <= CURRENT_DEADBAND_A:
        return None
    return "charge" if current_a > 0 else "discharge"


def decimate(
    xs: Sequence[float], ys: Sequence[float], max_points: int
) -> tuple[list[float], list[float]]:
    """At most ``max_points`` of the points, the first and the last kept: each bucket of
    consecutive points gives its lowest and its highest ``y``, in their order."""
    n = len(xs)
    if n <= max_points:
        return list(xs), list(ys)
    buckets = max(1, (max_points - 2) // 2)
    keep = {0, n - 1}
    inner = n - 2
    for b in range(buckets):
        lo, hi = 1 + b * inner // buckets, 1 + (b + 1) * inner // buckets
        if lo >= hi:
            continue
        part = range(lo, hi)
        keep.add(min(part, key=ys.__getitem__))
        keep.add(max(part, key=ys.__getitem__))
    idx = sorted(keep)
    return [xs[i] for i in idx], [ys[i] for i in idx]


class _Reader:
    """The halves of the wanted cycles, row by row (one pass over the file)."""

    def __init__(self, header: list[str]) -> None:
        col = {name: i for i, name in enumerate(header)}
        self.t, self.v, self.i = col[_T], col[_V], col[_I]
        self.cycle, self.step_type = col[_CYCLE], col.get(_STEP_TYPE)
        self.cycle_ah = {k: col.get(name) for k, name in _CYCLE_AH.items()}
        self.halves: list[HalfCurve] = []
        self._current: HalfCurve | None = None
        self._before: list[str] | None = None  # the cycle's row before this one
        self._base = 0.0  # the half's recorded Ah before it began
        self._prev: tuple[float, float] | None = None  # (t, current) of the half's last row
        self._row_cycle: int | None = None

    def _recorded_ah(self, row: list[str] | None, half: str) -> float | None:
        k = self.cycle_ah[half]
        return None if row is None or k is None or k >= len(row) else _float(row[k])

    def row(self, row: list[str], cycle: int) -> None:
        if cycle != self._row_cycle:
            self._row_cycle, self._current, self._before = cycle, None, None
        i = _float(row[self.i])
        kind = direction(row[self.step_type] if self.step_type is not None else "", i)
        if kind is not None:
            self._add(row, cycle, kind, i)
        self._before = row

    def _add(self, row: list[str], cycle: int, kind: str, i: float | None) -> None:
        t, v = _float(row[self.t]), _float(row[self.v])
        cur = self._current
        if cur is None or cur.half != kind:
            index = 1 + sum(1 for h in self.halves if h.cycle == cycle and h.half == kind)
            cur = self._current = HalfCurve(cycle, kind, index)
            self.halves.append(cur)
            self._base = self._recorded_ah(self._before, kind) or 0.0
            self._prev = None
        ah = self._recorded_ah(row, kind)
        if ah is not None:
            x = ah - self._base
        else:  # no recorded capacity: the current's integral, the half's own way
            sign = 1.0 if kind == "charge" else -1.0
            x = cur.ah[-1] if cur.ah else 0.0
            if self._prev is not None and t is not None and i is not None:
                t0, i0 = self._prev
                x += max(0.0, sign * (i0 + i) / 2) * (t - t0) / 3600.0
        if t is not None and i is not None:
            self._prev = (t, i)
        cur.rows += 1
        if v is not None:
            cur.ah.append(round(x, 9))
            cur.v.append(v)


def _rows(path: Path) -> Iterator[list[str]]:
    with path.open(encoding="utf-8", newline="") as f:
        yield from csv.reader(f)


def half_curves(
    path: Path, cycles: Collection[int], max_points: int = MAX_POINTS_PER_CURVE
) -> list[HalfCurve]:
    """The halves of ``cycles`` in the BDF file ``path``, in the file's order, each
    decimated to ``max_points``. A file without the needed columns gives none."""
    rows = _rows(path)
    header = next(rows, None)
    try:
        reader = _Reader(list(header or ()))
    except KeyError as exc:
        log.warning("curves: %s has no column %s", path, exc)
        return []
    last = max(cycles, default=0)
    wanted = set(cycles)
    for row in rows:
        if len(row) <= max(reader.t, reader.v, reader.i, reader.cycle):
            continue  # a row cut short (a power cut)
        try:
            cycle = int(row[reader.cycle])
        except ValueError:
            continue
        if cycle > last:
            break
        if cycle in wanted:
            reader.row(row, cycle)
    for h in reader.halves:
        h.ah, h.v = decimate(h.ah, h.v, max_points)
    return reader.halves


@dataclass(frozen=True)
class CycleCapacity:
    cycle: int
    discharge_ah: float
    charge_ah: float


def cycle_capacities(
    folder: Path, summary: dict[str, Any] | None
) -> tuple[list[CycleCapacity], int]:
    """The finished cycles of the test in ``folder`` that discharged (its cycles file, else
    its summary's cycles), and the highest cycle number it reached (finished or not)."""
    files = sorted(folder.glob(f"*{CYCLES_SUFFIX}"))
    rows: list[dict[str, Any]] = list(read_jsonl(files[0])) if files else []
    if not rows and summary is not None:
        rows = [c for c in summary.get("cycles", []) if isinstance(c, dict)]
    seen = 0
    out: dict[int, CycleCapacity] = {}
    for c in rows:
        try:
            n = int(c["cycle"])
            dch = float(c.get("discharge_capacity_ah") or 0.0)
            chg = float(c.get("charge_capacity_ah") or 0.0)
        except (KeyError, TypeError, ValueError):
            continue
        seen = max(seen, n)
        if c.get("complete") and dch > 0:
            out[n] = CycleCapacity(n, dch, chg)
    if summary is not None:  # a cycle under way is in the summary only
        for c in summary.get("cycles", []):
            if isinstance(c, dict) and isinstance(c.get("cycle"), int):
                seen = max(seen, c["cycle"])
    return [out[n] for n in sorted(out)], seen


def cycle_numbers(folder: Path, summary: dict[str, Any] | None) -> list[int]:
    """Every cycle number the test reached (for the curves' choice of cycles)."""
    _, seen = cycle_capacities(folder, summary)
    return list(range(1, seen + 1))
