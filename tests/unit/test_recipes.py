"""Recipes: shipped files compile; broken ones get one clear file:line:col message."""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.app import build_bench
from supervisor.chains.compiler import CC_ONLY, Target, compile_recipe
from supervisor.cli.main import main
from supervisor.config.recipe import load_recipe, load_recipe_text
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigErrors
from supervisor.devices.chadeche.config import NO_CV_REASON
from supervisor.devices.registry import load_bench
from supervisor.testing.recipes import bench_tags

ROOT = Path(__file__).resolve().parents[2]
BAD = ROOT / "tests" / "data" / "bad_recipes"


@pytest.mark.parametrize("path", sorted((ROOT / "recipes").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_recipe_loads_and_compiles(path: Path) -> None:
    recipe, pos = load_recipe(path)
    # Against the tags of the bench they are written for (the pack's recipes name the BMS's).
    program = compile_recipe(recipe, pos, str(path), bench_tags())
    assert program.steps


CASES = [
    ("bad_yaml.yaml", 4, 5, "YAML syntax error"),
    ("unknown_step_kind.yaml", 4, 5, "unknown key 'chrage'"),
    ("goto_missing_step.yaml", 4, 22, "goto to a missing step 'rset'"),
    ("unit_mismatch.yaml", 7, 17, "cannot compare a voltage with a current"),
    ("loop_without_exit.yaml", 4, 19, "loop with no exit and no duration: b → c → b"),
    # Zero-time loops (issue 9, ADR 0011): steps that can all end in the scan they start.
    ("zero_rest_loop.yaml", 4, 24, "loop that lets no time pass: settle → again → settle"),
    ("zero_sleep_loop.yaml", 3, 22, "loop that lets no time pass: nap → again → nap; "),
    ("until_true_at_once.yaml", 6, 9, "spin → spin; each of its steps can end in the scan"),
    ("zero_group_loop.yaml", 3, 42, "work → again → work; each of its steps can end in"),
    ("goto_chain_into_zero_step.yaml", 4, 22, "hop1 → hop2 → idle → back → hop1; "),
    ("zero_cycle_body.yaml", 4, 24, "settle → (next cycle) → settle; each of its steps"),
    ("negative_duration.yaml", 5, 15, "a duration cannot be negative"),
    ("unknown_parameter.yaml", 8, 20, "unknown name 'v_mx'; did you mean 'v_max'?"),
    ("step_never_ends.yaml", 3, 13, "never ends"),
    ("unknown_action.yaml", 7, 27, "unknown action 'jump!'"),
    ("c_rate_without_capacity.yaml", 3, 21, "a C-rate needs the rated capacity"),
    ("two_kinds_in_one_step.yaml", 3, 5, "(has: charge, discharge)"),
    # Accepted although invalid (issue 9): strict types, signs, finite numbers, ASCII.
    ("boolean_as_number.yaml", 2, 9, "cycles: Input should be a valid integer (received true)"),
    ("boolean_as_quantity.yaml", 2, 11, "capacity: expected a quantity"),
    ("negative_rest.yaml", 4, 11, "a duration cannot be negative"),
    ("zero_logging_period.yaml", 3, 11, "a logging period must be greater than zero"),
    ("infinite_profile_current.yaml", 7, 28, "current: Input should be a finite number"),
    ("nan_profile_time.yaml", 4, 21, "nan_profile_time.csv:3:1: time 'nan' is not a finite"),
    ("underflow_current.yaml", 3, 24, "'1e-400 A' is too small to be told from zero"),
    ("unicode_digit_time.yaml", 4, 26, "sleep_until needs a time of day HH:MM"),
    # Input limits (issue 9, README: Input limits).
    ("too_many_cycles.yaml", 2, 9, "cycles: 2,000,000 is too many; a recipe may run at most"),
    ("too_many_groups.yaml", 1006, 5, "too many groups: 1,001; a recipe may have at most 1,000"),
    ("initial_charge_too_large.yaml", 2, 17, "initial_charge 1e+300 Ah is too large"),
    # Found by the mutation corpus (tests/mutation.py): float() and \d take any Unicode
    # digit, so '٣ s' was 3 s, '+٠١:0٠' a one-hour sleep and '６0' in a profile 60 s.
    ("unicode_digit_quantity.yaml", 3, 19, "'٣ s' is not a number with a unit"),
    ("unicode_digit_sleep_action.yaml", 6, 26, "unknown action '+٠١:0٠'"),
    ("unicode_digit_profile_time.yaml", 4, 21, "unicode_digit_profile_time.csv:3:1: time '６0'"),
    # ... and a profile row's window written high first (v_min above v_max) was taken.
    ("inverted_profile_window.yaml", 7, 11, "v_min 4.2 V is not below v_max 2.8 V"),
    (
        "inverted_profile_window_csv.yaml",
        4,
        21,
        "inverted_profile_window.csv:3:9: v_min 4.2 V is not below v_max 2.8 V",
    ),
    # ... a group's `until: [{}]` was a traceback, and a negative capacity turned a 0.5 C
    # charge into a discharge.
    ("group_until_not_a_pair.yaml", 6, 7, "each 'until' entry is one 'condition: action' pair"),
    ("negative_capacity.yaml", 2, 11, "a rated capacity must be greater than zero"),
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


# --- a recipe must fit the channel's hard limits (refused before start) ------------------
# ch4 of io_maps/sim.yaml: a four-cell Li-ion pack on the EA supply.
PACK = Target(
    channel="ch4",
    capacity_ah=10.0,
    current_limits_a=(-20.0, 20.0),
    voltage_limits_v=(12.0, 16.8),
    temperature_limits_c=(None, 55.0),
)
LIION = ROOT / "recipes" / "liion-cccv-cycle.yaml"


def refusals(text: str, target: Target = PACK, file: str = "r.yaml") -> list[str]:
    """Every refusal of ``text`` on ``target``, as file:line:col: message."""
    recipe, pos = load_recipe_text(text, file)
    with pytest.raises(ConfigErrors) as info:
        compile_recipe(recipe, pos, file, target)
    return [e.location_message() for e in info.value.errors]


async def test_a_one_cell_recipe_is_refused_on_the_pack_channel_of_the_sim_bench() -> None:
    bench = build_bench(load_bench(ROOT / "io_maps" / "sim.yaml"), VirtualClock(), in_process=True)
    try:
        with pytest.raises(ConfigErrors) as info:
            bench.load_recipe("ch4", LIION)
        assert [e.location_message() for e in info.value.errors] == [
            f"{LIION}:14:13: recipe limits voltage [2.8, 4.3] V lie outside channel ch4's"
            " hard limits voltage_v [12, 16.8] V (a recipe for another cell or cell count?)",
            f"{LIION}:20:37: step 'charge' asks 4.2 V; channel ch4 allows [12, 16.8] V"
            " (a recipe for another cell or cell count?)",
        ]
        assert bench.runners["ch4"].program is None  # nothing loaded
    finally:
        await bench.shutdown()


def test_check_without_a_channel_still_accepts_the_one_cell_recipe(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["check", str(LIION)]) == 0
    assert "liion-cccv-cycle.yaml: OK" in capsys.readouterr().out


def test_a_recipe_voltage_window_reaching_beyond_the_channel_is_refused_without_the_hint() -> None:
    text = "recipe: r\nlimits:\n  voltage: [11.5 V, 16.8 V]\nsteps:\n  - {id: a, rest: 1 s}\n"
    assert refusals(text) == [
        "r.yaml:3:13: recipe limits voltage [11.5, 16.8] V reach beyond channel ch4's"
        " hard limits voltage_v [12, 16.8] V"
    ]


def test_recipe_current_and_temperature_windows_must_lie_within_the_channel() -> None:
    text = (
        "recipe: r\ncapacity: 10 Ah\nlimits:\n"
        "  current: [-3 C, 1 C]\n"
        "  temperature: [null, 60 degC]\n"
        "steps:\n  - {id: a, rest: 1 s}\n"
    )
    assert refusals(text) == [
        "r.yaml:4:13: recipe limits current [-30, 10] A reach beyond channel ch4's"
        " hard limits current_a [-20, 20] A",
        "r.yaml:5:23: recipe limits temperature [null, 60] degC reach beyond channel ch4's"
        " hard limits temperature_c [null, 55] degC",
    ]


def test_a_cv_voltage_outside_the_channel_is_refused_at_the_value() -> None:
    text = (
        "recipe: r\nsteps:\n"
        "  - {id: hold, cv: {voltage: 17 V, current_limit: 1 A}, duration: 1 h}\n"
    )
    assert refusals(text) == ["r.yaml:3:30: step 'hold' asks 17 V; channel ch4 allows [12, 16.8] V"]


def test_c_rates_and_nested_currents_are_checked_and_named_as_written() -> None:
    text = (
        "recipe: r\ncapacity: 10 Ah\nsteps:\n"
        "  - {id: fast, cccv: {current: 3 C, voltage: 16.4 V}, duration: 1 h}\n"
        "  - {id: hold, cv: {voltage: 16.4 V, current_limit: 25 A}, duration: 1 h}\n"
        "  - id: dcir\n"
        "    pulse: {current: -2.5 C, on_time: 10 s, off_time: 10 s}\n"
    )
    assert refusals(text) == [
        "r.yaml:4:32: step 'fast' asks 30 A (3 C of 10 Ah); channel ch4 allows [-20, 20] A",
        "r.yaml:5:53: step 'hold' asks 25 A; channel ch4 allows [-20, 20] A",
        "r.yaml:7:22: step 'dcir' asks -25 A (-2.5 C of 10 Ah); channel ch4 allows [-20, 20] A",
    ]


def test_a_power_step_is_refused_when_its_current_at_the_low_voltage_limit_is_too_high() -> None:
    text = (
        "recipe: r\nsteps:\n"
        "  - {id: ok, power: 200 W, duration: 1 h}\n"
        "  - {id: heavy, power: -300 W, duration: 1 h}\n"
    )
    assert refusals(text) == [
        "r.yaml:4:24: step 'heavy' asks -300 W: up to -25 A at the 12 V low limit;"
        " channel ch4 allows [-20, 20] A"
    ]


def test_profile_row_currents_and_voltage_windows_must_fit_the_channel() -> None:
    text = (
        "recipe: r\nsteps:\n"
        "  - id: p\n"
        "    profile:\n"
        "      rows:\n"
        "        - {t: 0, current: 5, v_min: 12.5, v_max: 16.5}\n"
        "        - {t: 60, current: -25, v_min: 3.0}\n"
        "        - {t: 120, current: 0}\n"
    )
    assert refusals(text) == [
        "r.yaml:7:28: step 'p' profile row 2 asks -25 A; channel ch4 allows [-20, 20] A",
        "r.yaml:7:40: step 'p' profile row 2: v_min 3 V is outside channel ch4's voltage"
        " limits [12, 16.8] V (a recipe for another cell or cell count?)",
    ]


def test_a_profile_csv_row_beyond_the_channel_is_refused_at_the_file_naming_the_row(
    tmp_path: Path,
) -> None:
    (tmp_path / "load.csv").write_text("t;I;V\n0;2;12/16.8\n60;30;12/16.8\n120;0\n")
    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nsteps:\n  - {id: p, profile: {file: load.csv}}\n")
    assert refusals(recipe.read_text(), file=str(recipe)) == [
        f"{recipe}:3:29: step 'p' profile load.csv row 2 asks 30 A; channel ch4 allows [-20, 20] A"
    ]


def test_parameter_defaults_in_conditions_are_left_to_the_operator() -> None:
    # v_max is a cell's 4.2 V, but conditions compare measurements: nothing to refuse.
    text = (
        "recipe: r\nparameters: {v_max: 4.2 V}\nsteps:\n"
        "  - id: a\n    charge: 2 A\n    duration: 1 h\n"
        "    until:\n      - voltage >= v_max: next\n"
    )
    recipe, pos = load_recipe_text(text, "r.yaml")
    assert compile_recipe(recipe, pos, "r.yaml", PACK).steps[0].current_a == 2.0


def test_a_recipe_within_the_pack_channel_is_accepted() -> None:
    text = (
        "recipe: pack\ncapacity: 10 Ah\nlimits:\n"
        "  voltage: [12 V, 16.8 V]\n  current: [-1 C, 1 C]\n  temperature: [0 degC, 55 degC]\n"
        "steps:\n"
        "  - {id: c, cccv: {current: 0.5 C, voltage: 16.4 V}, duration: 3 h}\n"
        "  - {id: d, discharge: 2 C, duration: 1 h}\n"
        "  - {id: p, power: -240 W, duration: 1 h}\n"
    )
    recipe, pos = load_recipe_text(text, "r.yaml")
    program = compile_recipe(recipe, pos, "r.yaml", PACK)
    assert [s.current_a for s in program.steps[:2]] == [5.0, -20.0]


@pytest.mark.parametrize("channel", ["ch0", "ch1", "ch3"])  # ch2 allows 0.2 A only
async def test_the_case_study_recipe_still_loads_on_every_chadeche_channel_of_the_sim_bench(
    channel: str, tmp_path: Path
) -> None:
    bench = build_bench(load_bench(ROOT / "io_maps" / "sim.yaml"), VirtualClock(), in_process=True)
    try:
        runner = bench.load_recipe(
            channel, ROOT / "recipes" / "nimh-ds2710.yaml", results_dir=tmp_path
        )
        assert runner.program is not None
    finally:
        await bench.shutdown()


def test_recipe_limits_carry_a_trip_delay() -> None:
    recipe, pos = load_recipe_text(
        "recipe: r\nlimits: {voltage: [1 V, 1.8 V], delay: 2 s}\nsteps:\n  - {id: a, rest: 1 h}\n",
        "r.yaml",
    )
    program = compile_recipe(recipe, pos, "r.yaml")
    assert program.limits.delay_s == 2.0
    with pytest.raises(ConfigErrors, match=r"r\.yaml:2:40: limits\.delay: .2 V. is a voltage"):
        text = (
            "recipe: r\nlimits: {voltage: [1 V, 1.8 V], delay: 2 V}\n"
            "steps:\n  - {id: a, rest: 1 h}\n"
        )
        bad, pos = load_recipe_text(text, "r.yaml")
        compile_recipe(bad, pos, "r.yaml")
