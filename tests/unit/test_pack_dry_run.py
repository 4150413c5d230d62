"""The seed 002 pack can be dry-run (issue 32, finding 4).

A 4S Li-ion pack dry-runs at any capacity ``supervisor dry-run`` allows: the simulated EA
unit enforces the rating it reports (a computed rating of 1565.9999999999998 W, reported
``1566.00 W``, refused the driver's ``POW 1566``: ``-222 Data out of range``, and the run
ended ``Held: voltage input BAD (comm failure)`` from 9 Ah on). A dry run on an I/O map's
channel runs that channel's own plant (its supply, pack and sensors), and so does the
Recipes screen's preview of a recipe for that channel. All on the virtual clock.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest

from supervisor.app import preview
from supervisor.app.bench import build_bench
from supervisor.app.dryrun import dry_run, implied_simulation
from supervisor.chains.states import State
from supervisor.cli.main import main
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigError
from supervisor.devices.ea import EaSimulator
from supervisor.devices.registry import load_bench
from supervisor.hmi.recipes_api import RecipesApi, RecipesConfig
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


def provenance_in(results: Path) -> dict[str, Any]:
    """The provenance.json of the only test folder under ``results``."""
    (folder,) = (p for p in results.iterdir() if p.is_dir())
    data: dict[str, Any] = json.loads((folder / "provenance.json").read_text(encoding="utf-8"))
    return data


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


# --- a channel of an I/O map, on its own plant ------------------------------------------------
CH4_CHARGE = """recipe: ch4-charge
steps:
  - {id: charge, charge: 5 A, duration: 10 min}
"""


async def test_a_dry_run_on_an_io_map_channel_runs_that_channels_plant(tmp_path: Path) -> None:
    # 5 A is beyond the built-in NiMH board (±0.4 A): only ch4's EA supply and pack run it.
    res = await dry_run(
        write(tmp_path, CH4_CHARGE), io_map=load_bench(SIM_MAP), channel="ch4", results_dir=tmp_path
    )
    assert res.state is State.COMPLETE, res.end_reason
    (cycle,) = res.summary["cycles"]
    assert cycle["charge_capacity_ah"] == pytest.approx(5.0 * 10 / 60, rel=0.02)
    provenance = provenance_in(tmp_path)
    assert provenance["channel"] == "ch4"
    assert provenance["io_map"]["file"] == str(SIM_MAP)
    assert provenance["io_map"]["channel"]["source_device"]["driver"] == "ea-psb"


async def test_a_dry_run_on_a_board_channel_runs_that_boards_cell(tmp_path: Path) -> None:
    recipe = "recipe: ch2-discharge\nsteps:\n  - {id: d, discharge: 0.2 A, duration: 30 min}\n"
    res = await dry_run(
        write(tmp_path, recipe), io_map=load_bench(SIM_MAP), channel="ch2", capacity_ah=0.8
    )
    assert res.state is State.COMPLETE, res.end_reason
    (cycle,) = res.summary["cycles"]
    assert cycle["discharge_capacity_ah"] == pytest.approx(0.1, rel=0.02)


async def test_a_real_bench_map_is_dry_run_with_every_device_simulated(tmp_path: Path) -> None:
    # io_maps/bench-adam-ea.yaml has no simulated device: its ADAM, EA and BMS are simulated
    # in process on its own wiring (its `simulation:` section), nothing is reached.
    cfg = load_bench(ROOT / "io_maps" / "bench-adam-ea.yaml")
    (channel,) = cfg.channels
    recipe = "recipe: charge\nsteps:\n  - {id: charge, charge: 10 A, duration: 10 min}\n"
    res = await dry_run(write(tmp_path, recipe), io_map=cfg)
    assert res.state is State.COMPLETE, res.end_reason
    (cycle,) = res.summary["cycles"]
    assert cycle["charge_capacity_ah"] == pytest.approx(10.0 * 10 / 60, rel=0.02)
    assert channel.name == "ch0"


async def test_a_channel_the_map_does_not_have_is_refused_naming_those_it_has(
    tmp_path: Path,
) -> None:
    with pytest.raises(ConfigError, match=r"no channel 'ch9' in the I/O map \(it has ch0, ch1"):
        await dry_run(write(tmp_path, CH4_CHARGE), io_map=load_bench(SIM_MAP), channel="ch9")


async def test_the_preview_of_a_ch4_recipe_runs_on_ch4s_plant(tmp_path: Path) -> None:
    # The Recipes screen's preview (the child's job, run here in process): before issue 32
    # it ran every recipe on the built-in NiMH board and refused this one ("channel ch0
    # allows [-0.4, 0.4] A").
    cfg = load_bench(SIM_MAP)
    job = {
        "file": str(tmp_path / "ch4-charge.yaml"),
        "text": CH4_CHARGE,
        "params": {},
        "capacity_ah": 10.0,
        "max_hours": 1.0,
        "timeout_s": 600.0,
        "channel": "ch4",
        "io_map": cfg.source_file,
        "io_map_sha256": cfg.source_sha256,
    }
    answer = await preview._run(job)
    assert "errors" not in answer, answer
    assert answer["summary"]["state"] == "Complete"
    assert max(answer["trace"]["current_a"]) == pytest.approx(5.0, abs=0.05)


async def test_the_preview_refuses_an_io_map_changed_since_the_supervisor_loaded_it(
    tmp_path: Path,
) -> None:
    job = {
        "file": str(tmp_path / "ch4-charge.yaml"),
        "text": CH4_CHARGE,
        "params": {},
        "capacity_ah": None,
        "max_hours": 1.0,
        "timeout_s": 600.0,
        "channel": "ch4",
        "io_map": str(SIM_MAP),
        "io_map_sha256": "0" * 64,
    }
    answer = await preview._run(job)
    (error,) = answer["errors"]
    assert "the I/O map changed since the supervisor loaded it" in error["message"]


def test_the_cli_dry_runs_a_channel_of_an_io_map(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = write(tmp_path, CH4_CHARGE)
    code = main(["dry-run", str(recipe), "--io-map", str(SIM_MAP), "--channel", "ch4"])
    out = capsys.readouterr().out
    assert code == 0, out
    charged = re.search(r"cycle 1: charged ([0-9.]+) mAh", out)
    assert charged is not None and float(charged[1]) == pytest.approx(833.3, rel=0.02)
    assert "end: Complete" in out


def test_the_cli_refuses_a_model_with_an_io_map(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = write(tmp_path, CH4_CHARGE)
    code = main(["dry-run", str(recipe), "--io-map", str(SIM_MAP), "--model", "nimh-aa"])
    assert code == 2
    assert "--io-map runs the map's plant" in capsys.readouterr().err


def test_a_real_bench_maps_channel_implies_its_sensor_wiring_and_pack() -> None:
    cfg = load_bench(ROOT / "io_maps" / "bench-adam-ea.yaml")
    assert implied_simulation(cfg, "ch0") == {
        "lem_current": {"device": "adam", "point": "slot0.ai0"},
        "lem_volts_per_amp": pytest.approx(4 / 300),
        "estop_sense": {"device": "adam", "point": "slot0.ai2"},
        "contactor": {"device": "adam", "point": "slot3.do0"},
        "thermocouples": [{"device": "adam", "point": "slot1.tc0"}],
        # 58 V at most: 13 cells of 4.2 V; the channel's 50 Ah.
        "pack": {"model": "liion-pack", "cells_series": 13, "capacity_ah": 50.0},
    }


async def test_the_recipes_screens_dry_run_hands_the_channel_to_the_preview(
    tmp_path: Path,
) -> None:
    asked: list[tuple[float | None, str | None]] = []

    async def runner(
        file: str,
        text: str,
        params: Mapping[str, str],
        capacity_ah: float | None,
        max_hours: float,
        timeout_s: float,
        channel: str | None = None,
    ) -> Mapping[str, Any]:
        asked.append((capacity_ah, channel))
        return {"errors": [{"message": "stop here", "file": file, "line": 1, "col": 1}]}

    bench = build_bench(load_bench(SIM_MAP), VirtualClock(), simulate=False)
    api = RecipesApi(RecipesConfig(tmp_path, runner, bench.target, bench.runners))
    await api._dry_run(runner, "r.yaml", CH4_CHARGE, {}, bench.target("ch4"), 1.0)
    await api._dry_run(runner, "r.yaml", CH4_CHARGE, {}, None, 1.0)
    assert asked == [(10.0, "ch4"), (None, None)]


def test_the_cli_asks_for_the_channel_of_a_map_with_several(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = write(tmp_path, CH4_CHARGE)
    assert main(["dry-run", str(recipe), "--io-map", str(SIM_MAP)]) == 2
    err = capsys.readouterr().err
    assert f"{SIM_MAP}: name the channel to dry-run (the I/O map has ch0, ch1, ch2, ch3," in err
