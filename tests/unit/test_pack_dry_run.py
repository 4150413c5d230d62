"""The seed 002 pack can be dry-run (issue 32, finding 4).

A 4S Li-ion pack dry-runs at any capacity ``supervisor dry-run`` allows: the simulated EA
unit enforces the rating it reports (a computed rating of 1565.9999999999998 W, reported
``1566.00 W``, refused the driver's ``POW 1566``: ``-222 Data out of range``, and the run
ended ``Held: voltage input BAD (comm failure)`` from 9 Ah on). A dry run on an I/O map's
channel runs that channel's own plant (its supply, pack and sensors), and so does the
Recipes screen's preview of a recipe for that channel. All on the virtual clock.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.app.dryrun import dry_run
from supervisor.chains.states import State
from supervisor.core.clock import VirtualClock
from supervisor.devices.ea import EaSimulator
from supervisor.sim.battery import make_model
from supervisor.sim.plant import BenchPlant

ROOT = Path(__file__).resolve().parents[2]
SIM_MAP = ROOT / "io_maps" / "sim.yaml"

PACK_4S_CHARGE = """recipe: pack-4s-charge
chemistry: liion
limits:
  voltage: [11.2 V, 17.2 V]
steps:
  - id: charge
    cccv: {current: 0.5 C, voltage: 16.8 V}
    duration: 10 min
"""


def write(tmp_path: Path, text: str, name: str = "r.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def unit(nominal_w: float) -> EaSimulator:
    plant = BenchPlant(VirtualClock(), make_model("liion-pack", cells_series=4, capacity_ah=10.0))
    return EaSimulator(plant, nominal_w=nominal_w)


def test_the_simulated_unit_accepts_a_setting_at_the_rating_it_reports() -> None:
    ea = unit(nominal_w=17.4 * 90)  # 1565.9999999999998 W
    reported = ea.handle_line(b"SYST:NOM:POW?\n")
    assert reported == "1566.00 W"
    ea.handle_line(b"SYST:LOCK ON\n")
    ea.handle_line(b"POW 1566.0000; SINK:POW 1566.0000\n")
    assert ea.handle_line(b"SYST:ERR?\n") == '0,"No error"'
    assert ea.handle_line(b"POW?\n") == "1566.00 W"


def test_a_setting_above_the_reported_rating_is_still_refused() -> None:
    ea = unit(nominal_w=1500.0)
    ea.handle_line(b"SYST:LOCK ON\n")
    ea.handle_line(b"POW 1500.01\n")
    assert ea.handle_line(b"SYST:ERR?\n") == '-222,"Data out of range"'


@pytest.mark.parametrize("capacity_ah", [8.0, 9.0, 10.0, 37.5, 1000.0])
async def test_a_4s_pack_charges_in_a_dry_run_at_any_capacity(
    tmp_path: Path, capacity_ah: float
) -> None:
    res = await dry_run(
        write(tmp_path, PACK_4S_CHARGE),
        model="liion-pack",
        cells=4,
        capacity_ah=capacity_ah,
    )
    assert (res.state, res.end_reason) == (
        State.COMPLETE,
        "complete after step charge of cycle 1: duration elapsed; end of steps; cycle 1 of 1 done",
    )
    (cycle,) = res.summary["cycles"]
    # 10 min at 0.5 C: at most C/12 went in (less once the CV phase tapers the current).
    assert capacity_ah / 24 < cycle["charge_capacity_ah"] <= capacity_ah / 12 * 1.01
