"""The seed 002 bench's sensor layout and its pack's recipes (issue 32, findings 8 and 10).

Finding 8: io_maps/bench-adam-ea.yaml ships the seed's layout — three current sensors
(LEM HAL 300-S, ±4 V ↔ ±300 A, the data sheet's scale, said in the map against the seed's
±800 A), three voltage board channels (1:10), ten type T thermocouples on the two 5018s,
the free points commented — and still passes ``supervisor check``.

Finding 10: the seed 002 pack's recipes — a 4S Li-ion CC-CV capacity test whose end
conditions come from the BMS's tags, and the §2.3 load profile — pass ``supervisor check``
with the seed 002 maps (a recipe naming bench tags is checked with the map that has
them), and a dry run of the capacity test on ch4's own plant (io_maps/sim.yaml: the EA
supply, the 4S 10 Ah pack, the BMS and the ADAM's sensors, all simulated) completes with
the pack's capacity. On the virtual clock.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

import pytest

from supervisor.app.dryrun import dry_run, format_report
from supervisor.chains.states import State
from supervisor.cli.main import check_files, main
from supervisor.config.models import LinearScaling, SpanScaling
from supervisor.devices.adam.config import AdamDevice
from supervisor.devices.registry import load_bench

ROOT = Path(__file__).resolve().parents[2]
SEED002_MAP = ROOT / "io_maps" / "bench-adam-ea.yaml"
SIM_MAP = ROOT / "io_maps" / "sim.yaml"
CAPACITY_TEST = ROOT / "recipes" / "pack4s-cccv-capacity.yaml"
PROFILE = ROOT / "recipes" / "seed002-profile.yaml"
PACK_CAPACITY_AH: Final = 10.0
CAPACITY_TOLERANCE: Final = 0.10
"""The capacity a dry run measures, within 10 % of the pack's rating: a 0.5 C discharge
that stops at 3.1 V a cell leaves a few percent of the charge in the pack."""


# --- finding 8: the layout ----------------------------------------------------------------
def test_the_seed_002_map_has_three_current_sensors_at_the_data_sheet_scale() -> None:
    cfg = load_bench(SEED002_MAP)
    currents = [t for t in cfg.tags if t.unit == "A" and t.device == "adam"]
    assert [t.point for t in currents] == ["slot0.ai0", "slot0.ai4", "slot0.ai5"]
    for t in currents:
        assert isinstance(t.scaling, SpanScaling)
        assert (t.scaling.raw, t.scaling.eu) == ((-4.0, 4.0), (-300.0, 300.0))
    text = SEED002_MAP.read_text(encoding="utf-8")
    assert "±800 A" in text and "data sheet's scale is ±4 V ↔ ±300 A" in text


def test_the_seed_002_map_has_three_voltage_board_channels() -> None:
    cfg = load_bench(SEED002_MAP)
    volts = [t for t in cfg.tags if t.unit == "V" and t.device == "adam"]
    assert [t.point for t in volts] == ["slot0.ai1", "slot0.ai6", "slot0.ai7"]
    for t in volts:
        assert isinstance(t.scaling, LinearScaling)
        assert (t.scaling.a, t.scaling.b) == (10.0, 0.0)


def test_the_seed_002_map_has_ten_thermocouples_and_comments_the_free_inputs() -> None:
    cfg = load_bench(SEED002_MAP)
    adam = cfg.devices["adam"]
    assert isinstance(adam, AdamDevice)
    assert {slot: m.kind for slot, m in adam.modules.items()} == {
        0: "5017",
        1: "5018",
        2: "5018",
        3: "5060",
    }
    tcs = [t.point for t in cfg.tags if t.unit == "degC" and t.device == "adam"]
    assert tcs == [*(f"slot1.tc{k}" for k in range(7)), "slot2.tc0", "slot2.tc1", "slot2.tc2"]
    text = SEED002_MAP.read_text(encoding="utf-8")
    for k in range(3, 7):
        assert f"# - {{name: tc{k + 8}.temp, device: adam, point: slot2.tc{k}" in text


def test_every_shipped_map_and_recipe_passes_check_together(
    capsys: pytest.CaptureFixture[str],
) -> None:
    files = sorted(str(p) for p in (ROOT / "io_maps").glob("*.yaml"))
    files += sorted(str(p) for p in (ROOT / "recipes").glob("*.yaml"))
    assert main(["check", *files]) == 0, capsys.readouterr().err


# --- finding 10: the recipes ----------------------------------------------------------------
@pytest.mark.parametrize("recipe", [CAPACITY_TEST, PROFILE], ids=lambda p: p.name)
@pytest.mark.parametrize("io_map", [SEED002_MAP, SIM_MAP], ids=lambda p: p.name)
def test_the_pack_recipes_pass_check_with_a_seed_002_map(io_map: Path, recipe: Path) -> None:
    (map_result, recipe_result) = check_files([io_map, recipe])
    assert map_result[0] == [] and recipe_result[0] == []
    assert recipe_result[1] == ()  # no warning: every parameter is read


def test_a_recipe_naming_bms_tags_is_refused_without_the_map_that_has_them() -> None:
    ((errors, _, _),) = check_files([CAPACITY_TEST])
    assert "unknown name 'bms.temp_max'" in errors[0].message


async def test_the_capacity_test_of_the_4s_10_ah_pack_completes_on_ch4_with_its_capacity(
    tmp_path: Path,
) -> None:
    res = await dry_run(CAPACITY_TEST, io_map=load_bench(SIM_MAP), channel="ch4")
    assert (res.state, res.end_reason) == (
        State.COMPLETE,
        "complete after step done of cycle 1: end step",
    )
    steps = [step for step, _ in res.step_sequence]
    assert steps == ["charge", "rest_full", "discharge", "rest_empty", "done"]
    (cycle,) = res.summary["cycles"]
    assert cycle["discharge_capacity_ah"] == pytest.approx(PACK_CAPACITY_AH, rel=CAPACITY_TOLERANCE)
    # The pack starts at 50 % charge: the first charge is a top-up, so its cycle gives back
    # twice what it took — no efficiency of the cell, and the report says why instead.
    assert cycle["coulombic_efficiency"] is None
    (line,) = [s for s in format_report(res) if s.startswith("  cycle 1:")]
    assert "coulombic efficiency" not in line and "it began partly charged" in line


async def test_the_seed_002_profile_runs_on_ch4_within_its_windows(tmp_path: Path) -> None:
    res = await dry_run(PROFILE, io_map=load_bench(SIM_MAP), channel="ch4")
    assert res.state is State.COMPLETE, res.end_reason
    (cycle,) = res.summary["cycles"]
    # 240 times figure 21's 1.25 s: 5 min at 0.7 A on average (0.5, 0.6, 0.7, 0.8, 0.9 A).
    assert cycle["charge_capacity_ah"] == pytest.approx(0.7 * 300 / 3600, rel=0.05)
