"""Dry runs whose predictions stay physical (issue 9, "wrong physics in dry runs").

The cell model runs out (its voltage collapses at empty, reversal trips the channel's low
hard limit), turns past full into a voltage peak, a -ΔV and a steep temperature rise, and
its temperature reaches the channel: -ΔV, temperature terminations and temperature limits
can be dry-run, and the shipped NiMH fast-charge recipe ends by -ΔV.
"""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from supervisor.app.dryrun import DryRunResult, dry_run
from supervisor.chains.states import State

ROOT = Path(__file__).resolve().parents[2]
FAST_CHARGE = ROOT / "recipes" / "nimh-fast-charge-dv.yaml"
DELTA_V_CAUSE = "until #1: delta_peak >= dv_stop and step_time > blanking"
pytestmark = pytest.mark.integration


def write(tmp_path: Path, text: str, name: str = "r.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def step_times(res: DryRunResult) -> dict[str, float]:
    """Test time at which each step (last) started."""
    return {
        e["step"]: float(e["test_time_s"])
        for e in res.summary["timeline"]
        if e["kind"] == "step" and e["text"].startswith("starting step")
    }


def temperatures(results: Path) -> list[float]:
    (bdf,) = results.rglob("*.bdf.csv")
    rows = csv.DictReader(bdf.read_text(encoding="utf-8").splitlines())
    return [float(r["Temperature T1 / degC"]) for r in rows if r["Temperature T1 / degC"]]


# --- running out -------------------------------------------------------------------------
async def test_a_30_h_discharge_without_a_stop_ends_when_the_cell_is_empty(
    tmp_path: Path,
) -> None:
    # The issue: 11 986 mAh from a 2 000 mAh cell at 0.388 V after 30 h.
    path = write(
        tmp_path,
        "recipe: r\nchemistry: nimh\ncapacity: 2000 mAh\nsteps:\n"
        "  - {id: discharge, discharge: 400 mA, duration: 30 h}\n",
    )
    res = await dry_run(path, soc=0.9)
    assert res.state is State.HELD
    assert "hard limit 0.2 V" in res.end_reason
    (cycle,) = res.summary["cycles"]
    # What the cell held (0.9 × 2 Ah), not 400 mA × 30 h.
    assert cycle["discharge_capacity_ah"] == pytest.approx(1.8, rel=0.01)
    assert res.simulated_s == pytest.approx(1.8 / 0.4 * 3600, rel=0.01)


# --- past full ---------------------------------------------------------------------------
async def test_a_half_c_charge_of_a_small_cell_ends_on_a_5_mv_delta_peak(tmp_path: Path) -> None:
    # The issue: 0.8 Ah at 400 mA from 20 % for 8 h put 3 200 mAh in, 1 mV of drop, and no
    # cell temperature in the dry run.
    path = write(
        tmp_path,
        "recipe: r\nchemistry: nimh\ncapacity: 800 mAh\nlogging: {period: 60 s}\nsteps:\n"
        "  - id: charge\n    charge: 400 mA\n    duration: 8 h\n"
        "    until:\n      - delta_peak >= 5 mV: next\n"
        "  - {id: rest, rest: 1 min}\n",
    )
    res = await dry_run(path, soc=0.2, results_dir=tmp_path / "results")
    assert res.state is State.COMPLETE
    assert res.step_sequence[1] == ("rest", "until #1: delta_peak >= 5 mV")
    (cycle,) = res.summary["cycles"]
    input_from_empty = 0.2 + cycle["charge_capacity_ah"] / 0.8
    assert 1.0 <= input_from_empty <= 1.2
    temps = temperatures(tmp_path / "results")
    assert temps[0] == pytest.approx(25.0, abs=0.5)
    assert max(temps) - temps[0] > 10.0  # the steep rise of overcharge, seen by the channel


async def test_a_recipe_temperature_limit_halts_an_overcharge_in_the_dry_run(
    tmp_path: Path,
) -> None:
    path = write(
        tmp_path,
        "recipe: r\nchemistry: nimh\ncapacity: 800 mAh\n"
        "limits: {temperature: [null, 35 degC]}\nsteps:\n"
        "  - {id: charge, charge: 400 mA, duration: 4 h}\n",
    )
    res = await dry_run(path, soc=0.9)
    assert res.state is State.HELD
    assert "temperature" in res.end_reason and "35 degC" in res.end_reason
    assert res.simulated_s < 3600.0


# --- the shipped fast-charge recipe ------------------------------------------------------
@pytest.mark.parametrize(
    ("c_rate", "capacity"),
    [("0.5 C", "800 mAh"), ("1 C", "400 mAh")],  # 400 mA at most on a Chadèche board
)
async def test_the_fast_charge_recipe_ends_by_minus_delta_v_after_100_to_120_percent(
    tmp_path: Path, c_rate: str, capacity: str
) -> None:
    text = FAST_CHARGE.read_text(encoding="utf-8")
    assert "charge: 0.5 C\n" in text and "capacity: 800 mAh\n" in text
    text = text.replace("charge: 0.5 C\n", f"charge: {c_rate}\n")
    text = text.replace("capacity: 800 mAh\n", f"capacity: {capacity}\n")
    res = await dry_run(write(tmp_path, text), soc=0.0)
    ids = [s for s, _ in res.step_sequence]
    assert ids == ["precharge", "fast", "topoff", "done"]
    assert dict(res.step_sequence)["topoff"] == DELTA_V_CAUSE
    assert res.state is State.COMPLETE
    t = step_times(res)
    rate = float(c_rate.split()[0])
    fast_input = rate * (t["topoff"] - t["fast"]) / 3600.0  # in capacities, from empty
    assert 1.0 <= fast_input <= 1.2


async def test_the_shipped_fast_charge_recipe_ends_by_minus_delta_v_as_it_is() -> None:
    res = await dry_run(FAST_CHARGE, soc=0.0)
    assert ("topoff", DELTA_V_CAUSE) in res.step_sequence
    assert res.state is State.COMPLETE


async def test_a_0_05_c_charge_does_not_falsely_end_by_minus_delta_v(tmp_path: Path) -> None:
    # Below about 0.1 C -ΔV is unreliable: the recipe's -ΔV must not fire, neither in the
    # first minutes nor later; its safety timer ends the charge.
    text = FAST_CHARGE.read_text(encoding="utf-8").replace("charge: 0.5 C\n", "charge: 0.05 C\n")
    res = await dry_run(write(tmp_path, text), soc=0.0)
    assert [s for s, _ in res.step_sequence] == ["precharge", "fast", "timer_expired"]
    assert res.step_sequence[2][1] == "duration elapsed"
    t = step_times(res)
    assert t["timer_expired"] - t["fast"] == pytest.approx(3 * 3600.0, abs=2.0)
    assert all("delta_peak" not in cause for _, cause in res.step_sequence)
