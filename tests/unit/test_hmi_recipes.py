"""The Recipes screen's parts (supervisor/hmi/recipes_api.py) without a server: a text is
refused with exactly what ``supervisor check`` says of the same file, names never make a
path outside the recipes folder, a save replaces a recipe whole or not at all, and a dry
run's trace stays within its points whatever the length of the run."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from supervisor.app.bench import build_bench
from supervisor.chains.compiler import Target
from supervisor.cli.main import main
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigErrors
from supervisor.core.records import Record
from supervisor.devices.registry import load_bench
from supervisor.hmi.recipes_api import (
    MAX_TRACE_POINTS,
    RecipesApi,
    RecipesConfig,
    Trace,
    check_recipe_text,
    error_json,
    valid_name,
)
from supervisor.testing.recipes import bench_tags

ROOT = Path(__file__).resolve().parents[2]
BAD = sorted((ROOT / "tests" / "data" / "bad_recipes").glob("*.yaml"))
GOOD = sorted((ROOT / "recipes").glob("*.yaml"))


def check_output(path: Path, capsys: pytest.CaptureFixture[str]) -> list[str]:
    """What ``supervisor check PATH`` prints on stderr, one line each."""
    capsys.readouterr()
    main(["check", str(path)])
    return capsys.readouterr().err.splitlines()


@pytest.mark.parametrize("path", BAD, ids=lambda p: p.name)
def test_a_broken_text_is_refused_with_the_lines_supervisor_check_prints(
    path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    expected = check_output(path, capsys)
    assert expected, f"{path.name}: supervisor check found nothing wrong"
    with pytest.raises(ConfigErrors) as refused:
        check_recipe_text(path.read_text(encoding="utf-8"), str(path))
    errors = [error_json(e) for e in refused.value.errors]
    assert [e["text"] for e in errors] == expected
    for e in errors:  # the parts the screen shows at the line
        assert e["text"] == f"{path}:{e['line']}:{e['column']}: {e['message']}"


@pytest.fixture(scope="module")
def sim_bench_tags() -> Target:
    """What the screens validate a recipe against without a channel on the simulated
    bench: its tags (a recipe may name ``bms.cell_max``), as ``RecipesApi`` does."""
    return bench_tags()


@pytest.mark.parametrize("path", GOOD, ids=lambda p: p.name)
def test_every_shipped_recipe_validates(path: Path, sim_bench_tags: Target) -> None:
    checked = check_recipe_text(path.read_text(encoding="utf-8"), str(path), sim_bench_tags)
    answer = checked.as_json()
    assert answer["ok"] is True and answer["steps"] == len(checked.program.steps) > 0


def test_validation_names_the_parameters_as_written_and_in_si() -> None:
    text = (ROOT / "recipes" / "nimh-25h-slow-cycle.yaml").read_text(encoding="utf-8")
    answer = check_recipe_text(text, "recipes/nimh-25h-slow-cycle.yaml").as_json()
    assert answer["parameters"] == [
        {"name": "v_end", "value": "1.0 V", "si": 1.0},
        {"name": "dv_stop", "value": "3 mV", "si": pytest.approx(0.003)},
    ]
    assert (answer["recipe"], answer["steps"], answer["cycles"]) == ("nimh-25h-slow-cycle", 4, 1)


@pytest.mark.parametrize(
    "name",
    ["nimh-25h-slow-cycle", "capacity_test", "v1.2", "A"],
)
def test_a_plain_name_is_a_recipe_name(name: str) -> None:
    assert valid_name(name)


@pytest.mark.parametrize(
    "name",
    ["", "..", "../etc/passwd", "a/b", "a\\b", ".hidden", "a..b", "/abs", "x" * 81, "é", "a b"],
)
def test_a_name_that_could_leave_the_folder_or_hide_is_refused(name: str) -> None:
    assert not valid_name(name)


def api(tmp_path: Path) -> RecipesApi:
    return RecipesApi(RecipesConfig(tmp_path / "recipes"))


def test_a_save_without_overwrite_never_replaces_an_existing_recipe(tmp_path: Path) -> None:
    a = api(tmp_path)
    target = tmp_path / "recipes" / "r.yaml"
    assert a._write(target, "recipe: one\n", overwrite=False) is True
    with pytest.raises(FileExistsError):
        a._write(target, "recipe: two\n", overwrite=False)
    assert target.read_text(encoding="utf-8") == "recipe: one\n"
    assert [p.name for p in target.parent.iterdir()] == ["r.yaml"]  # no temporary left


def test_a_save_with_overwrite_replaces_the_recipe_whole(tmp_path: Path) -> None:
    a = api(tmp_path)
    target = tmp_path / "recipes" / "r.yaml"
    a._write(target, "recipe: one\n", overwrite=False)
    assert a._write(target, "recipe: two\n", overwrite=True) is False  # it existed
    assert target.read_text(encoding="utf-8") == "recipe: two\n"
    assert [p.name for p in target.parent.iterdir()] == ["r.yaml"]


def record(t_s: float) -> Record:
    return Record(
        t=t_s,
        wall=t_s,
        test_time_s=t_s,
        step_time_s=t_s,
        cycle_time_s=t_s,
        cycle=1,
        step_count=1,
        step_index=0,
        step_id="c",
        step_type="charge",
        voltage_v=1.2 + t_s * 1e-6,
        current_a=0.2,
        power_w=0.24,
        temperature_c=25.0,
        charge_ah=0.0,
        charged_ah=0.0,
        discharged_ah=0.0,
        charged_wh=0.0,
        discharged_wh=0.0,
        cycle_charged_ah=0.0,
        cycle_discharged_ah=0.0,
        cycle_charged_wh=0.0,
        cycle_discharged_wh=0.0,
        setpoint_a=0.2,
        step_remaining_s=None,
        reason="period",
    )


@pytest.mark.parametrize("n", [1, 2, 1999, 2000, 2001, 4001, 87_000])
def test_a_trace_keeps_at_most_its_points_from_the_first_record_to_the_last(n: int) -> None:
    trace = Trace()
    for k in range(n):
        trace(record(float(k)))
    out = trace.as_json()
    t = out["t_s"]
    assert len(t) == min(n, len(t)) <= MAX_TRACE_POINTS
    assert t[0] == 0.0 and t[-1] == float(n - 1)
    assert t == sorted(set(t))
    assert len(out["voltage_v"]) == len(out["current_a"]) == len(t)
    assert out["records"] == n
    if n >= MAX_TRACE_POINTS:
        assert len(t) > MAX_TRACE_POINTS // 4  # spread over the run, not a few points
        gaps = [b - a for a, b in itertools.pairwise(t[:-1])]
        assert max(gaps) == min(gaps)  # evenly (the last point may come sooner)
    else:
        assert len(t) == n


def test_without_a_channel_a_recipe_is_checked_against_the_benchs_tags(
    tmp_path: Path, sim_bench_tags: Target
) -> None:
    # Validate and save name no channel: the seed 002 pack's capacity test (conditions on
    # bms.cell_max, bms.cell_min, bms.temp_max) was refused "unknown name" on a bench that
    # has those tags (issue 32).
    bench = build_bench(load_bench(ROOT / "io_maps" / "sim.yaml"), VirtualClock(), simulate=False)
    a = RecipesApi(RecipesConfig(tmp_path, target_of=bench.target, channels=bench.runners))
    target = a._target({})
    assert target is not None and target.channel is None and target.current_limits_a is None
    assert target.tags == sim_bench_tags.tags
    path = ROOT / "recipes" / "pack4s-cccv-capacity.yaml"
    check_recipe_text(path.read_text(encoding="utf-8"), str(path), target)
    assert api(tmp_path)._target({}) is None  # no bench: nothing known of its tags
