"""V against Ah per half-cycle, read back from a BDF result file (issue 33 finding 10).

A small file written by hand, whose curves are counted by hand below: a half is the rows
of a cycle going one way (the step's type, else the current's sign), rests excluded; Ah
counts from the half's start, from the recorded cycle capacity or, without those columns,
from the current's integral. Curves are decimated to a bound, extremes kept.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.publish.curves import (
    cycle_capacities,
    decimate,
    direction,
    half_curves,
)
from supervisor.publish.results import BDF_COLUMNS, CYCLES_SUFFIX

# test time, V, I, cycle, step type, cycle charged Ah, cycle discharged Ah
ROWS = [
    (0, 1.25, 0, 1, "CC_CHG", 0, 0),  # the charge step's first row: Ah 0 at the OCV
    (10, 1.30, 0.36, 1, "CC_CHG", 0.001, 0),
    (20, 1.40, 0.36, 1, "CV_CHG", 0.002, 0),  # a step change, the same half
    (30, 1.38, 0, 1, "REST", 0.002, 0),  # in no half
    (40, 1.20, -0.72, 1, "CC_DCH", 0.002, 0.002),
    (50, 1.10, -0.72, 1, "CC_DCH", 0.002, 0.004),
    (60, 1.31, 0.36, 2, "CC_CHG", 0.001, 0),  # cycle 2 counts from 0 again
    (70, 1.39, 0.36, 2, "CC_CHG", 0.002, 0),
    (80, 1.21, -0.36, 2, "PULSE", 0.002, 0.001),  # no charge/discharge type: the sign
    (90, 1.33, 0.36, 2, "PULSE", 0.003, 0.001),  # back to charge: a second charge half
    (100, 1.15, -0.36, 3, "CC_DCH", 0, 0.001),
]


def bdf(tmp_path: Path, recorded: bool = True) -> Path:
    header = list(BDF_COLUMNS)
    lines = [",".join(header)]
    for t, v, i, cycle, kind, chg, dch in ROWS:
        row = dict.fromkeys(header, "")
        row |= {"Test Time / s": f"{t:.3f}", "Voltage / V": f"{v}", "Current / A": f"{i}"}
        row |= {"Cycle Count / 1": str(cycle), "Step Type": kind}
        if recorded:
            row["Cycle Charging Capacity / Ah"] = f"{chg}"
            row["Cycle Discharging Capacity / Ah"] = f"{dch}"
        lines.append(",".join(row[h] for h in header))
    lines.append("110.000,1.1")  # the last row cut short by a power cut: skipped
    path = tmp_path / "t.bdf.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def table(halves: list) -> list[tuple]:
    return [(h.cycle, h.half, h.index, h.ah, h.v) for h in halves]


def test_halves_split_where_the_direction_changes_with_ah_from_the_recorded_charge(
    tmp_path: Path,
) -> None:
    got = table(half_curves(bdf(tmp_path), [1, 2]))
    assert got == [
        (1, "charge", 1, [0.0, 0.001, 0.002], [1.25, 1.30, 1.40]),
        (1, "discharge", 1, [0.002, 0.004], [1.20, 1.10]),
        (2, "charge", 1, [0.001, 0.002], [1.31, 1.39]),
        (2, "discharge", 1, [0.001], [1.21]),
        # from the cycle's charge before it (0.002): 0.001 since this half began
        (2, "charge", 2, [0.001], [1.33]),
    ]


def test_without_capacity_columns_ah_is_the_currents_integral(tmp_path: Path) -> None:
    got = {(h.cycle, h.half, h.index): h.ah for h in half_curves(bdf(tmp_path, False), [1])}
    # By hand: (0 + 0.36) / 2 A for 10 s is 0.0005 Ah, then 0.36 A for 10 s 0.001 Ah more;
    # the discharge: 0.72 A for 10 s from its first row, 0.002 Ah.
    assert got[(1, "charge", 1)] == pytest.approx([0.0, 0.0005, 0.0015])
    assert got[(1, "discharge", 1)] == pytest.approx([0.0, 0.002])


def test_only_the_cycles_asked_for_are_read(tmp_path: Path) -> None:
    got = half_curves(bdf(tmp_path), [3])
    assert table(got) == [(3, "discharge", 1, [0.001], [1.15])]
    assert half_curves(bdf(tmp_path), [7]) == []


def test_a_file_without_voltage_or_current_gives_no_curve(tmp_path: Path) -> None:
    path = tmp_path / "x.bdf.csv"
    path.write_text("Test Time / s,Cycle Count / 1\n0,1\n", encoding="utf-8")
    assert half_curves(path, [1]) == []


@pytest.mark.parametrize(
    ("step_type", "current_a", "half"),
    [
        ("CC_CHG", 0.0, "charge"),
        ("CCCV_CHG", -0.001, "charge"),  # the step says, not a noisy reading
        ("CC_DCH", 0.0, "discharge"),
        ("REST", 0.5, None),
        ("PULSE", 0.5, "charge"),
        ("PULSE", -0.5, "discharge"),
        ("PULSE", 0.0, None),
        ("", None, None),
    ],
)
def test_a_rows_half_is_its_steps_else_its_currents(
    step_type: str, current_a: float | None, half: str | None
) -> None:
    assert direction(step_type, current_a) == half


def test_a_long_half_is_decimated_to_the_bound_keeping_its_ends_and_extremes(
    tmp_path: Path,
) -> None:
    header = ",".join(BDF_COLUMNS)
    n = 20_000
    cols = {name: k for k, name in enumerate(BDF_COLUMNS)}
    lines = [header]
    for k in range(n):
        row = [""] * len(BDF_COLUMNS)
        v = 1.2 + k / n * 0.2 + (0.5 if k == 12_345 else 0.0)  # one spike
        row[cols["Test Time / s"]], row[cols["Voltage / V"]] = str(k), str(v)
        row[cols["Current / A"]], row[cols["Cycle Count / 1"]] = "0.36", "1"
        row[cols["Step Type"]] = "CC_CHG"
        row[cols["Cycle Charging Capacity / Ah"]] = str(k * 1e-4)
        lines.append(",".join(row))
    path = tmp_path / "long.bdf.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    (half,) = half_curves(path, [1], max_points=500)
    assert half.rows == n and len(half.ah) <= 500
    assert half.ah[0] == 0.0 and half.ah[-1] == pytest.approx((n - 1) * 1e-4)
    assert max(half.v) == pytest.approx(1.2 + 12_345 / n * 0.2 + 0.5)  # the spike kept


@given(
    ys=st.lists(st.floats(-10, 10, allow_nan=False), min_size=0, max_size=400),
    limit=st.integers(4, 100),
)
def test_decimation_keeps_order_ends_and_extremes_within_the_bound(
    ys: list[float], limit: int
) -> None:
    xs = [float(k) for k in range(len(ys))]
    dx, dy = decimate(xs, ys, limit)
    assert len(dx) <= limit
    assert dx == sorted(dx) and all(ys[int(x)] == y for x, y in zip(dx, dy, strict=True))
    if ys:
        assert dx[0] == 0 and dx[-1] == len(ys) - 1
        assert min(dy) == min(ys) and max(dy) == max(ys)
    if len(ys) <= limit:
        assert dy == ys


def test_capacity_per_cycle_is_the_finished_cycles_that_discharged(tmp_path: Path) -> None:
    rows = [
        {"cycle": 1, "complete": True, "discharge_capacity_ah": 0.9, "charge_capacity_ah": 1},
        {"cycle": 2, "complete": True, "discharge_capacity_ah": 0.0, "charge_capacity_ah": 1},
        {"cycle": 3, "complete": False, "discharge_capacity_ah": 0.5, "charge_capacity_ah": 1},
    ]
    (tmp_path / f"t{CYCLES_SUFFIX}").write_text(
        "".join(json.dumps(r) + "\n" for r in rows), encoding="utf-8"
    )
    summary = {"cycles": [{"cycle": 4, "complete": False}]}  # under way
    caps, seen = cycle_capacities(tmp_path, summary)
    assert [(c.cycle, c.discharge_ah) for c in caps] == [(1, 0.9)]
    assert seen == 4
