"""A parameter may not take the name of a measurement, a counter, a function or a word of
the expressions (issue 28, finding 4): ``parameters: {voltage: 5 V}`` replaced the measured
voltage in every condition, so ``until: voltage <= 1.1 V`` never fired on a discharge."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from supervisor.chains.compiler import (
    CHANNEL_VARIABLES,
    RESERVED_NAMES,
    Target,
    compile_recipe,
    reserved_names_text,
)
from supervisor.chains.expr import FUNCTIONS, KEYWORDS
from supervisor.config.recipe import load_recipe_text
from supervisor.core.errors import ConfigErrors
from supervisor.core.units import Dim

ROOT = Path(__file__).resolve().parents[2]

SHADOWING = """\
recipe: shadow
capacity: 2 Ah
parameters: {voltage: 5 V}
steps:
  - id: discharge
    discharge: 1 A
    until:
      - voltage <= 1.1 V: end
"""


def refusals(text: str, target: Target | None = None) -> list[str]:
    recipe, pos = load_recipe_text(text, "r.yaml")
    with pytest.raises(ConfigErrors) as exc:
        compile_recipe(recipe, pos, "r.yaml", target)
    return [e.location_message() for e in exc.value.errors]


def test_check_refuses_a_parameter_named_voltage_at_its_key_listing_the_reserved_names(
    tmp_path: Path,
) -> None:
    path = tmp_path / "shadow.yaml"
    path.write_text(SHADOWING, encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "supervisor.cli.main", "check", str(path)],
        capture_output=True,
        text=True,
        check=False,
        cwd=ROOT,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert f"{path}:3:14: parameter 'voltage' takes the name of a measurement" in proc.stderr
    assert "Reserved names: measurements: voltage, current" in proc.stderr


@pytest.mark.parametrize(
    ("name", "value", "kind"),
    [
        ("current", "1 A", "measurement"),
        ("temperature", "20 degC", "measurement"),
        ("dv_dt", "0 V/s", "measurement"),
        ("cycle", "3", "counter"),
        ("step_charge", "1 Ah", "counter"),
        ("test_time", "1 h", "counter"),
        ("abs", "2 V", "function"),
        ("max", "1 V", "function"),
        ("min", "1 V", "function"),
    ],
)
def test_a_parameter_named_like_a_measurement_counter_or_function_is_refused(
    name: str, value: str, kind: str
) -> None:
    text = (
        f"recipe: r\nparameters:\n  {name}: {value}\nsteps:\n"
        "  - {id: a, rest: 1 s, until: [{'voltage > 1 V': end}]}\n"
    )
    (message,) = refusals(text)
    assert message.startswith(f"r.yaml:3:3: parameter {name!r} takes the name of a {kind}")
    assert reserved_names_text() in message


def test_a_parameter_named_like_a_dotless_bench_tag_is_refused() -> None:
    text = "recipe: r\nparameters: {door: 1}\nsteps:\n  - {id: a, rest: 1 s}\n"
    (message,) = refusals(text, Target(tags={"door": Dim.BOOL}))
    assert "parameter 'door' takes the name of a bench tag" in message


def test_the_reserved_names_are_exactly_what_expressions_read_besides_parameters() -> None:
    # One table for the refusal and its message: every channel variable the conditions
    # read, every function and every word of the expressions, nothing else.
    reserved = {n for names in RESERVED_NAMES.values() for n in names}
    assert reserved == set(CHANNEL_VARIABLES) | set(FUNCTIONS) | set(KEYWORDS)
    for name in reserved:
        assert name in reserved_names_text()


def test_a_parameter_with_a_free_name_is_still_read_by_the_conditions() -> None:
    text = SHADOWING.replace("{voltage: 5 V}", "{v_end: 1.1 V}").replace("1.1 V: end", "v_end: end")
    recipe, pos = load_recipe_text(text, "r.yaml")
    program = compile_recipe(recipe, pos, "r.yaml")
    assert program.parameters == {"v_end": pytest.approx(1.1)}


ACTION_WORD_STEP = """\
recipe: shadowed-step
capacity: 2 Ah
steps:
  - id: charge
    charge: 1 A
    until:
      - voltage >= 1.5 V: end
      - step_time >= 1 h: goto end
  - {id: end, rest: 1 min}
"""


def test_a_bare_action_word_that_is_also_a_step_id_is_the_action_and_is_warned_where_written() -> (
    None
):
    # The mutation corpus found it (issue 28's round): a step 'hold' and [true: hold] held
    # the chain; nimh-ds2710.yaml ships a step 'end'. The bare word stays the action.
    recipe, pos = load_recipe_text(ACTION_WORD_STEP, "r.yaml")
    program = compile_recipe(recipe, pos, "r.yaml")
    (warning,) = [w.location_message() for w in program.warnings]
    assert warning == (
        "r.yaml:7:27: 'end' is the action end, not the step 'end': write 'goto end' to go"
        " to the step"
    )
    first, second = program.steps[0].transitions
    assert first.action.kind.value == "end"  # the action, as before
    assert second.action.target_id == "end"  # goto names the step
