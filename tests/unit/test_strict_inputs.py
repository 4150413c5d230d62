"""Strict inputs (issue 9): what a user can get wrong is refused with one clear message —
a YAML boolean is not a number, numbers are finite, signs and ranges make sense, a step
asks only what the channel can do — and never answered with a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.app import build_bench
from supervisor.chains.compiler import Target, compile_recipe
from supervisor.cli.main import build_parser, main
from supervisor.config.recipe import load_recipe_text
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigErrors
from supervisor.core.units import UnitError, parse_quantity
from supervisor.devices.registry import load_bench
from supervisor.tags import TagSpec
from supervisor.tags.spec import clipped_repr, shown

ROOT = Path(__file__).resolve().parents[2]
RECIPE = str(ROOT / "recipes" / "nimh-ds2710.yaml")

# A Chadèche board's channel (sim.yaml ch0) on the bench's 0.1 s scan.
BOARD = Target(
    channel="ch0",
    current_limits_a=(-0.4, 0.4),
    voltage_limits_v=(0.8, 1.9),
    scan_period_s=0.1,
)


def refusals(text: str, target: Target | None = None) -> list[str]:
    with pytest.raises(ConfigErrors) as info:
        recipe, pos = load_recipe_text(text, "r.yaml")
        compile_recipe(recipe, pos, "r.yaml", target)
    return [e.location_message() for e in info.value.errors]


# --- supervisor dry-run arguments ------------------------------------------------------------
@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--period-s", "0"], "argument --period-s: expected a number from 0.001 to 10 s, got '0'"),
        (["--period-s", "-1"], "argument --period-s: expected a number from 0.001 to 10 s"),
        (["--period-s", "nan"], "argument --period-s: expected a finite number, got 'nan'"),
        (["--period-s", "1e-6"], "argument --period-s: expected a number from 0.001 to 10 s"),
        (["--soc", "2"], "argument --soc: expected a number from 0 to 1, got '2'"),
        (["--soc", "-0.5"], "argument --soc: expected a number from 0 to 1, got '-0.5'"),
        (["--soc", "5"], "argument --soc: expected a number from 0 to 1, got '5'"),
        (
            ["--capacity-ah", "0"],
            "argument --capacity-ah: expected a number from 0.001",
        ),
        (
            ["--capacity-ah", "-2"],
            "argument --capacity-ah: expected a number from 0.001",
        ),
        (["--cells", "0"], "argument --cells: expected from 1 to 1000 cells in series, got '0'"),
        (["--cells", "٣"], "argument --cells: expected a whole number of cells, got '٣'"),
        (["--start", "abc"], "argument --start: expected a time of day HH:MM"),
        (["--start", "7pm"], "argument --start: expected a time of day HH:MM"),
        (["--start", "12"], "argument --start: expected a time of day HH:MM"),
        (["--start", "25:99"], "argument --start: expected a time of day HH:MM"),
        (["--results", "/dev/null/x"], "argument --results: '/dev/null/x': /dev/null is not a"),
        (["--max-hours", "nan"], "argument --max-hours: expected a finite number, got 'nan'"),
        (["--max-hours", "-1"], "argument --max-hours: expected a number more than 0"),
        (["--max-hours", "1e999"], "argument --max-hours: expected a finite number"),
    ],
    ids=lambda x: " ".join(x) if isinstance(x, list) else "",
)
def test_a_bad_dry_run_argument_is_one_line_naming_the_option_with_exit_2(
    args: list[str], words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["dry-run", RECIPE, *args]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    (line,) = err.splitlines()
    assert line.startswith("supervisor dry-run: ")
    assert words in line
    assert "Traceback" not in err and ".py" not in err


def test_good_dry_run_arguments_are_read_as_given() -> None:
    args = build_parser().parse_args(
        ["dry-run", RECIPE, "--start", "7:05", "--soc", "0", "--period-s", "0.5", "--cells", "4"]
    )
    assert (args.start, args.soc, args.period_s, args.cells) == ("07:05", 0.0, 0.5, 4)


# --- tag writes: strict coercion ---------------------------------------------------------------
FLOAT = TagSpec("lab.setpoint_a", dtype="float")
BOOL = TagSpec("lab.enable", dtype="bool")
INT = TagSpec("lab.count", dtype="int")
STR = TagSpec("lab.mode", dtype="str")


@pytest.mark.parametrize(
    ("spec", "value", "words"),
    [
        (FLOAT, True, "lab.setpoint_a: expected a number, got true"),
        (FLOAT, None, "lab.setpoint_a: expected a number, got null"),
        (FLOAT, [0.1], "lab.setpoint_a: expected a number, got a list of 1"),
        (FLOAT, float("nan"), "lab.setpoint_a: expected a finite number, got NaN"),
        (FLOAT, float("inf"), "lab.setpoint_a: expected a finite number, got Infinity"),
        (
            FLOAT,
            10**400,
            "lab.setpoint_a: expected a finite number, got an integer of about 401 digits",
        ),
        (BOOL, 2, "lab.enable: expected a boolean, got 2"),
        (BOOL, [0], "lab.enable: expected a boolean, got a list of 1"),
        (BOOL, 1, "lab.enable: expected a boolean, got 1"),
        (BOOL, "maybe", "lab.enable: expected a boolean, got 'maybe'"),
        (INT, True, "lab.count: expected an integer, got true"),
        (INT, 2.5, "lab.count: expected an integer, got 2.5"),
        (INT, float("nan"), "lab.count: expected an integer, got NaN"),
        (STR, 3, "lab.mode: expected a text, got 3"),
        (STR, {"a": 1}, "lab.mode: expected a text, got an object"),
    ],
)
def test_a_tag_write_of_the_wrong_kind_is_refused_naming_tag_and_value(
    spec: TagSpec, value: object, words: str
) -> None:
    with pytest.raises((TypeError, ValueError)) as info:
        spec.coerce(value)
    assert str(info.value) == words
    assert "NoneType" not in str(info.value)


@pytest.mark.parametrize(
    ("spec", "value", "expected"),
    [
        (FLOAT, 1, 1.0),
        (FLOAT, 0.25, 0.25),
        (BOOL, True, True),
        (BOOL, "off", False),
        (INT, 3.0, 3),
        (STR, "manual", "manual"),
    ],
)
def test_a_tag_write_of_the_right_kind_is_taken(
    spec: TagSpec, value: object, expected: object
) -> None:
    got = spec.coerce(value)
    assert got == expected and type(got) is type(expected)


def test_a_value_in_a_message_is_never_thousands_of_digits_nor_python_words() -> None:
    assert shown(10**5000) == "an integer of about 5001 digits"  # str() of it would raise
    assert clipped_repr(10**5000) == "an integer of about 5001 digits"
    assert shown(None) == "null" and shown(False) == "false"
    assert len(clipped_repr("x" * 10_000)) < 50


# --- recipes: signs, finite numbers, underflow -------------------------------------------------
@pytest.mark.parametrize(
    ("text", "words"),
    [
        (
            "recipe: r\nlogging: {period: -1 s}\nsteps:\n  - {id: a, rest: 1 h}\n",
            "r.yaml:2:19: logging.period: a logging period must be greater than zero",
        ),
        (
            "recipe: r\nlogging: {period: 120 s, delta_v: 0 V}\nsteps:\n  - {id: a, rest: 1 h}\n",
            "r.yaml:2:35: logging.delta_v: a logging delta must be greater than zero",
        ),
        (
            "recipe: r\ngroups: [{id: g, steps: [a], duration: -1 h}]\nsteps:\n"
            "  - {id: a, rest: 1 h}\n",
            "groups[0].duration: '-1 h': a duration cannot be negative",
        ),
        (
            "recipe: r\nlimits: {voltage: [1 V, 2 V], delay: -2 s}\n"
            "steps:\n  - {id: a, rest: 1 h}\n",
            "limits.delay: '-2 s': a trip delay cannot be negative",
        ),
        (
            "recipe: r\nsteps:\n  - {id: a, rest: 1 h, supervision: {max_time: 0 s}}\n",
            "supervision.max_time: a supervision time must be greater than zero",
        ),
        (
            "recipe: r\nsteps:\n  - {id: p, pulse: {current: 1 A, on_time: -1 s, off_time: 1 s}}\n",
            "pulse.on_time: a pulse's on_time must be greater than zero",
        ),
        (
            "recipe: r\nsteps:\n  - {id: p, pulse: {current: 1 A, on_time: 1 s, off_time: -1 s}}\n",
            "pulse.off_time: '-1 s': a pulse's off_time cannot be negative",
        ),
        (
            "recipe: r\nparameters: {i: 1e-400 A}\nsteps:\n  - {id: a, rest: 1 h}\n",
            "parameters: parameter i: '1e-400 A' is too small to be told from zero",
        ),
        (
            "recipe: r\nsteps:\n  - {id: a, charge: .nan, duration: 1 h}\n",
            "steps[0].charge: expected a quantity, not an infinite or NaN number",
        ),
        (
            "recipe: r\nsteps:\n  - {id: p, pulse: {current: 1 A, on_time: 1 s, off_time: 1 s,"
            " count: true}}\n",
            "pulse.count: Input should be a valid integer (received true)",
        ),
        (
            "recipe: r\nsteps:\n  - {id: a, rest: 1 h, end: 1}\n",
            "steps[0].end: Input should be a valid boolean (received 1)",
        ),
    ],
    ids=[
        "log-period",
        "log-delta",
        "group-duration",
        "limits-delay",
        "max-time",
        "pulse-on",
        "pulse-off",
        "underflow-parameter",
        "nan-current",
        "bool-count",
        "int-as-bool",
    ],
)
def test_a_nonsense_value_in_a_recipe_is_refused_at_its_place(text: str, words: str) -> None:
    got = refusals(text)
    assert any(words in e for e in got), got


def test_zero_written_as_zero_is_not_an_underflow() -> None:
    text = "recipe: r\nsteps:\n  - {id: a, discharge: 0.000e-400 A, duration: 1 h}\n"
    recipe, pos = load_recipe_text(text, "r.yaml")
    assert compile_recipe(recipe, pos, "r.yaml").steps[0].current_a == 0.0


@pytest.mark.parametrize("value", ["1e-400V", "1e-400 V", "0.5e-330 V"])
def test_a_start_parameter_that_underflows_to_zero_is_refused(
    value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # The command line's parameters, like the recipe's own (issue 9 leftover: 1e-400 V was 0).
    assert main(["dry-run", RECIPE, "--param", f"v_min={value}"]) == 2
    err = capsys.readouterr().err
    assert f"parameter v_min: {value!r} is too small to be told from zero" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("text", ["٣ s", "３ V", "1.٩ V", "𝟏 s", "२० mA"])
def test_a_quantity_in_other_digits_than_ascii_is_not_a_quantity(text: str) -> None:
    # float() reads every Unicode digit: '٣ s' was 3 s (found by the mutation corpus).
    with pytest.raises(UnitError, match="is not a number with a unit"):
        parse_quantity(text)


def test_a_start_parameter_of_zero_is_zero() -> None:
    recipe, pos = load_recipe_text(
        "recipe: r\nparameters: {v: 1 V}\nsteps:\n  - {id: a, rest: 1 h}\n", "r.yaml"
    )
    assert compile_recipe(recipe, pos, "r.yaml", overrides={"v": "0e-400 V"}).parameters["v"] == 0


def test_a_pair_of_limits_from_yaml_is_still_read() -> None:
    text = "recipe: r\nlimits: {voltage: [1 V, 1.8 V]}\nsteps:\n  - {id: a, rest: 1 h}\n"
    recipe, pos = load_recipe_text(text, "r.yaml")
    assert compile_recipe(recipe, pos, "r.yaml").limits.voltage_v == (1.0, 1.8)


# --- what the channel can do: power, pulses ------------------------------------------------
def test_a_power_the_channel_cannot_reach_is_refused_even_with_a_0_v_low_limit() -> None:
    # With a low voltage limit at 0 V there is no P / V_low bound; P <= I_max · V_high is.
    target = Target(channel="ch0", current_limits_a=(-0.4, 0.4), voltage_limits_v=(0.0, 2.0))
    text = (
        "recipe: r\nsteps:\n"
        "  - {id: p, power: 1000 W, duration: 1 h}\n"
        "  - {id: q, power: -1 W, duration: 1 h}\n"
        "  - {id: ok, power: 0.5 W, duration: 1 h}\n"
    )
    assert refusals(text, target) == [
        "r.yaml:3:20: step 'p' asks 1000 W; channel ch0 reaches at most 0.8 W charging"
        " (0.4 A at its 2 V high limit)",
        "r.yaml:4:20: step 'q' asks -1 W; channel ch0 reaches at most 0.8 W discharging"
        " (-0.4 A at its 2 V high limit)",
    ]


def test_a_power_step_on_the_sim_benchs_board_is_refused_before_start(tmp_path: Path) -> None:
    recipe = tmp_path / "p.yaml"
    recipe.write_text("recipe: p\nsteps:\n  - {id: p, power: 1000 W, duration: 10 min}\n")
    assert main(["dry-run", str(recipe)]) == 2


def test_a_pulse_shorter_than_the_scan_period_is_refused() -> None:
    text = (
        "recipe: r\nsteps:\n"
        "  - id: p\n"
        "    pulse: {current: 100 mA, on_time: 1 ms, off_time: 50 ms, count: 10}\n"
        "  - id: q\n"
        "    pulse: {current: 100 mA, on_time: 0.1 s, off_time: 0 s}\n"
    )
    assert refusals(text, BOARD) == [
        "r.yaml:4:39: step 'p' pulse on_time 0.001 s is shorter than channel ch0's scan"
        " period (0.1 s): the current changes once per scan; make it at least 0.1 s",
        "r.yaml:4:55: step 'p' pulse off_time 0.05 s is shorter than channel ch0's scan"
        " period (0.1 s): the current changes once per scan; make it at least 0.1 s",
    ]


async def test_the_bench_target_carries_its_scan_period() -> None:
    bench = build_bench(load_bench(ROOT / "io_maps" / "sim.yaml"), VirtualClock(), in_process=True)
    try:
        assert bench.target("ch0").scan_period_s == bench.cfg.scan.period_s
    finally:
        await bench.shutdown()
