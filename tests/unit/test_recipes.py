"""Recipes: shipped files compile; broken ones get one clear file:line:col message."""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.chains.compiler import CC_ONLY, Target, compile_recipe
from supervisor.cli.main import main
from supervisor.config.recipe import load_recipe, load_recipe_text
from supervisor.core.errors import ConfigErrors
from supervisor.devices.chadeche.config import NO_CV_REASON

ROOT = Path(__file__).resolve().parents[2]
BAD = ROOT / "tests" / "data" / "bad_recipes"


@pytest.mark.parametrize("path", sorted((ROOT / "recipes").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_recipe_loads_and_compiles(path: Path) -> None:
    recipe, pos = load_recipe(path)
    program = compile_recipe(recipe, pos, str(path))
    assert program.steps


CASES = [
    ("bad_yaml.yaml", 4, 5, "YAML syntax error"),
    ("unknown_step_kind.yaml", 4, 5, "unknown key 'chrage'"),
    ("goto_missing_step.yaml", 4, 22, "goto to a missing step 'rset'"),
    ("unit_mismatch.yaml", 7, 17, "cannot compare a voltage with a current"),
    ("loop_without_exit.yaml", 4, 19, "loop with no exit and no duration: b → c → b"),
    ("negative_duration.yaml", 5, 15, "a duration cannot be negative"),
    ("unknown_parameter.yaml", 8, 20, "unknown name 'v_mx'; did you mean 'v_max'?"),
    ("step_never_ends.yaml", 3, 13, "never ends"),
    ("unknown_action.yaml", 7, 27, "unknown action 'jump!'"),
    ("c_rate_without_capacity.yaml", 3, 21, "a C-rate needs the rated capacity"),
    ("two_kinds_in_one_step.yaml", 3, 5, "(has: charge, discharge)"),
]


@pytest.mark.parametrize(("name", "line", "col", "words"), CASES, ids=[c[0] for c in CASES])
def test_a_broken_recipe_is_refused_with_file_line_and_column(
    name: str, line: int, col: int, words: str
) -> None:
    with pytest.raises(ConfigErrors) as info:
        recipe, pos = load_recipe(BAD / name)
        compile_recipe(recipe, pos, str(BAD / name))
    first = info.value.errors[0]
    assert (first.file, first.line, first.col) == (str(BAD / name), line, col)
    assert words in first.message


def test_every_broken_recipe_has_a_case() -> None:
    assert {p.name for p in BAD.glob("*.yaml")} == {c[0] for c in CASES}


@pytest.mark.parametrize("name", [c[0] for c in CASES])
def test_check_exits_2_on_each_broken_recipe_without_traceback(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check", str(BAD / name)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.startswith(f"{BAD / name}:")


def test_cv_on_a_chadeche_channel_is_refused_before_start_with_the_reason() -> None:
    recipe, pos = load_recipe(ROOT / "recipes" / "liion-cccv-cycle.yaml")
    # The reason is the source's own (the Chadèche package states it; the bench hands it on).
    target = Target(channel="ch0", capabilities=CC_ONLY, no_cv_reason=NO_CV_REASON, capacity_ah=2.0)
    with pytest.raises(ConfigErrors) as info:
        compile_recipe(recipe, pos, "liion.yaml", target)
    assert "cannot run on channel ch0: a Chadèche board drives a constant current only" in str(
        info.value
    )


def test_a_step_beyond_the_channel_current_limit_is_refused() -> None:
    recipe, pos = load_recipe_text(
        "recipe: r\nsteps:\n  - {id: a, charge: 500 mA, duration: 1 h}\n", "r.yaml"
    )
    with pytest.raises(ConfigErrors, match=r"r.yaml:3:13: step 'a' asks 0.5 A"):
        compile_recipe(recipe, pos, "r.yaml", Target(channel="ch0", current_limits_a=(-0.4, 0.4)))


def test_parameters_follow_default_then_file_then_start_command_precedence() -> None:
    text = "recipe: r\nparameters: {v_max: 1.75 V}\nsteps:\n  - {id: a, rest: 1 s}\n"
    recipe, pos = load_recipe_text(text, "r.yaml")
    assert compile_recipe(recipe, pos, "r.yaml").parameters["v_max"] == 1.75
    prog = compile_recipe(recipe, pos, "r.yaml", overrides={"v_max": "1.8 V"})
    assert prog.parameters["v_max"] == pytest.approx(1.8)
    with pytest.raises(ConfigErrors, match="unknown parameter 'v_mx'"):
        compile_recipe(recipe, pos, "r.yaml", overrides={"v_mx": "1.8 V"})
    with pytest.raises(ConfigErrors, match="is a current; the recipe declares a voltage"):
        compile_recipe(recipe, pos, "r.yaml", overrides={"v_max": "1 A"})


def test_c_rates_resolve_against_the_recipe_capacity() -> None:
    text = "recipe: r\ncapacity: 2 Ah\nsteps:\n  - {id: a, discharge: 0.5 C, duration: 1 h}\n"
    recipe, pos = load_recipe_text(text, "r.yaml")
    assert compile_recipe(recipe, pos, "r.yaml").steps[0].current_a == pytest.approx(-1.0)


def test_every_chadeche_action_has_an_equivalent() -> None:
    text = """
recipe: r
steps:
  - id: a
    charge: 100 mA
    duration: 1 h
    until:
      - voltage >= 1.7 V: next          # S
      - voltage >= 1.8 V: next_cycle    # C
      - voltage >= 1.9 V: b             # N (goto)
      - charge >= 1 Ah: "20:00"         # HH:MM
      - charge >= 2 Ah: "+01:30"        # +HH:MM
      - true: end
  - {id: b, rest: 1 s}
"""
    recipe, pos = load_recipe_text(text, "r.yaml")
    acts = [str(t.action) for t in compile_recipe(recipe, pos, "r.yaml").steps[0].transitions]
    assert acts == ["next", "next_cycle", "goto b", "sleep until 20:00", "sleep 5400 s", "end"]
