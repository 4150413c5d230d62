"""A recipe's parameters do something (issue 26, finding 6a): ``capacity-test``'s
``i_discharge`` sets its discharge current; a setpoint may name a parameter; a parameter
that nothing reads is a located warning of ``supervisor check`` (not a refusal: a recipe
imported from a Chadèche sequence declares the seed's -m -M -c -C whether its rows read them
or not), and no shipped recipe has one."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from supervisor.chains.compiler import compile_recipe
from supervisor.chains.program import Program
from supervisor.cli.main import main
from supervisor.config.recipe import load_recipe, load_recipe_text
from supervisor.core.errors import ConfigErrors
from supervisor.testing.recipes import bench_tags

ROOT = Path(__file__).resolve().parents[2]
RECIPES = sorted((ROOT / "recipes").glob("*.yaml"))


def compiled(path: Path, **overrides: str) -> Program:
    """Against the tags of the bench the shipped recipes are written for (the pack's
    recipes name the BMS's)."""
    recipe, pos = load_recipe(path)
    return compile_recipe(recipe, pos, str(path), bench_tags(), overrides=overrides)


def text_program(text: str, **overrides: str) -> Program:
    recipe, pos = load_recipe_text(text, "r.yaml")
    return compile_recipe(recipe, pos, "r.yaml", overrides=overrides)


def discharge_a(program: Program) -> float:
    (step,) = [s for s in program.steps if s.id == "discharge"]
    return step.current_a


def test_the_capacity_test_discharges_at_its_i_discharge_parameter() -> None:
    path = ROOT / "recipes" / "capacity-test.yaml"
    assert discharge_a(compiled(path)) == pytest.approx(-0.4)  # 0.2 C of 2000 mAh
    assert discharge_a(compiled(path, i_discharge="0.1C")) == pytest.approx(-0.2)
    assert discharge_a(compiled(path, i_discharge="250 mA")) == pytest.approx(-0.25)


def test_a_dry_run_of_the_capacity_test_at_0_1_c_takes_longer_than_at_0_2_c(
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = str(ROOT / "recipes" / "capacity-test.yaml")

    def predicted_h(*extra: str) -> float:
        assert main(["dry-run", path, *extra]) == 0
        m = re.search(r"predicted duration: \S+ \(([\d.]+) h\)", capsys.readouterr().out)
        assert m
        return float(m[1])

    assert predicted_h("--param", "i_discharge=0.1C") > predicted_h() + 2.0


@pytest.mark.parametrize("path", RECIPES, ids=[p.name for p in RECIPES])
def test_every_shipped_recipe_reads_every_parameter_it_declares(path: Path) -> None:
    assert [w.location_message() for w in compiled(path).warnings] == []


def test_a_parameter_nothing_reads_is_a_located_warning_of_check(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "r.yaml"
    path.write_text(
        "recipe: r\nparameters:\n  i_d: 0.2 A\n  v_end: 1.0 V\nsteps:\n"
        "  - id: d\n    discharge: 200 mA\n    until: [{voltage <= v_end: next}]\n",
        encoding="utf-8",
    )
    assert main(["check", str(path)]) == 0
    out, err = capsys.readouterr()
    assert out == f"{path}: OK\n"
    assert err == (
        f"warning: {path}:3:3: parameter 'i_d' is declared but nothing reads it (a condition,"
        " a setpoint such as 'discharge: i_d', or initial_charge): giving it changes nothing;"
        " use it or remove it\n"
    )


def test_a_setpoint_may_name_a_parameter_of_its_kind() -> None:
    text = (
        "recipe: r\ncapacity: 2 Ah\nparameters: {i_c: 0.5 C, v_c: 1.45 V}\nsteps:\n"
        "  - {id: c, charge: i_c, duration: 1 h}\n"
        "  - {id: cv, cccv: {current: i_c, voltage: v_c}, duration: 1 h}\n"
    )
    p = text_program(text)
    assert [s.current_a for s in p.steps] == [pytest.approx(1.0), pytest.approx(1.0)]
    assert p.steps[1].voltage_v == pytest.approx(1.45)
    assert p.warnings == ()
    assert text_program(text, v_c="1.5 V").steps[1].voltage_v == pytest.approx(1.5)


@pytest.mark.parametrize(
    ("setpoint", "message"),
    [
        ("i_dis", "r.yaml:5:16: unknown parameter 'i_dis' (did you mean 'i_d'?); this recipe has"),
        ("v_end", "parameter 'v_end' is a voltage, not a current"),
    ],
)
def test_a_setpoint_naming_a_wrong_parameter_is_refused_at_its_line(
    setpoint: str, message: str
) -> None:
    text = (
        "recipe: r\nparameters: {i_d: 0.2 A, v_end: 1.0 V}\nsteps:\n  - id: d\n"
        f"    discharge: {setpoint}\n    until: [{{voltage <= v_end: next}}]\n"
    )
    with pytest.raises(ConfigErrors) as info:
        text_program(text)
    assert any(message in e.location_message() for e in info.value.errors), info.value.errors
