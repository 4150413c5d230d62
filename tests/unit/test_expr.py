"""The recipe condition language: parsing, units, dimensions, three-valued evaluation."""

from __future__ import annotations

import itertools
import math
import pickle
import re
from pathlib import Path
from typing import Any

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from supervisor.chains import expr as expr_module
from supervisor.chains.expr import (
    MAX_DEPTH,
    MAX_NESTING,
    Expr,
    ExprError,
    Signature,
    compile_condition,
    compile_expr,
)
from supervisor.core.units import Dim

NAMES: dict[str, Dim] = {
    "voltage": Dim.VOLTAGE,
    "v_max": Dim.VOLTAGE,
    "v_min": Dim.VOLTAGE,
    "current": Dim.CURRENT,
    "charge": Dim.CHARGE,
    "q_min": Dim.CHARGE,
    "q_max": Dim.CHARGE,
    "temperature": Dim.TEMPERATURE,
    "step_time": Dim.TIME,
    "delta_peak": Dim.VOLTAGE,
    "dv_dt": Dim.VOLTAGE_RATE,
    "power": Dim.POWER,
    "energy": Dim.ENERGY,
    "adam.slot1.tc0": Dim.TEMPERATURE,
    "ch1.voltage": Dim.VOLTAGE,
    "bms.ok": Dim.BOOL,
    "cycle": Dim.NONE,
}
SIG = Signature(NAMES, capacity_ah=2.0)
SIG_NO_CAPACITY = Signature(NAMES)

# A channel in the middle of a charge: nothing has ended yet.
CHARGING: dict[str, float | bool | None] = {
    "voltage": 4.10,
    "v_max": 4.20,
    "v_min": 3.00,
    "current": 1.0,
    "charge": 0.8,
    "q_min": 0.1,
    "q_max": 2.0,
    "temperature": 30.0,
    "step_time": 120.0,
    "delta_peak": 0.0005,
    "dv_dt": 0.001 / 60 * 5,
    "power": 4.1,
    "energy": 3.0,
    "adam.slot1.tc0": 25.0,
    "ch1.voltage": 4.1,
    "bms.ok": True,
    "cycle": 3.0,
}


def cond(text: str, sig: Signature = SIG) -> Expr:
    return compile_condition(text, sig)


def ev(text: str, sig: Signature = SIG, **changes: float | bool | None) -> float | bool | None:
    values = dict(CHARGING)
    values.update({k.replace("__", "."): v for k, v in changes.items()})
    return compile_expr(text, sig).evaluate(values)


def error_of(text: str, sig: Signature = SIG, *, condition: bool = True) -> ExprError:
    with pytest.raises(ExprError) as info:
        (compile_condition if condition else compile_expr)(text, sig)
    return info.value


# --------------------------------------------------------------------------- golden


@pytest.mark.parametrize(
    ("text", "changes", "expected"),
    [
        ("voltage >= v_max", {}, False),
        ("voltage >= v_max", {"voltage": 4.2}, True),
        ("voltage >= v_max", {"voltage": 4.2001}, True),
        ("charge <= q_min", {}, False),
        ("charge <= q_min", {"charge": 0.1}, True),
        ("current < 0.05 C", {}, False),  # 0.05 C of 2 Ah = 0.1 A
        ("current < 0.05 C", {"current": 0.099}, True),
        ("temperature > 45 degC and step_time > 4 min", {}, False),
        ("temperature > 45 degC and step_time > 4 min", {"temperature": 46.0}, False),
        (
            "temperature > 45 degC and step_time > 4 min",
            {"temperature": 46.0, "step_time": 241.0},
            True,
        ),
        ("delta_peak >= 2 mV", {}, False),
        ("delta_peak >= 2 mV", {"delta_peak": 0.002}, True),
        ("abs(dv_dt) < 1 mV/min", {}, False),
        ("abs(dv_dt) < 1 mV/min", {"dv_dt": -0.5e-3 / 60}, True),
        ("adam.slot1.tc0 > 60 degC", {}, False),
        ("adam.slot1.tc0 > 60 degC", {"adam__slot1__tc0": 60.5}, True),
        ("not bms.ok", {}, False),
        ("not bms.ok", {"bms__ok": False}, True),
        ("ch1.voltage < v_min", {"ch1__voltage": 2.9}, True),
        ("cycle >= 3", {}, True),
        ("cycle == 4", {}, False),
        ("voltage != v_max", {}, True),
    ],
)
def test_the_example_conditions_evaluate_to_the_expected_truth(
    text: str, changes: dict[str, float | bool], expected: bool
) -> None:
    values = {**CHARGING, **{k.replace("__", "."): v for k, v in changes.items()}}
    e = cond(text)
    assert e.dim is Dim.BOOL
    assert e.text == text
    assert e.evaluate(values) is expected


def test_a_compiled_expression_reports_the_names_it_reads() -> None:
    e = cond("temperature > 45 degC and step_time > 4 min or not bms.ok")
    assert e.names == frozenset({"temperature", "step_time", "bms.ok"})
    assert cond("current < 0.05 C").names == frozenset({"current"})
    assert compile_expr("4.2 V", SIG).names == frozenset()


def test_an_expression_has_the_dimension_of_its_result() -> None:
    assert compile_expr("v_max - 50 mV", SIG).dim is Dim.VOLTAGE
    assert compile_expr("cycle + 1", SIG).dim is Dim.NONE
    assert compile_expr("voltage >= v_max", SIG).dim is Dim.BOOL


def test_a_compiled_expression_is_reusable_with_new_values_each_scan() -> None:
    e = cond("voltage >= v_max")
    results = [e.evaluate({"voltage": v, "v_max": 4.2}) for v in (4.0, 4.1, 4.2, 4.3)]
    assert results == [False, False, True, True]


# --------------------------------------------------------------------------- precedence


def kleene_and(a: bool | None, b: bool | None) -> bool | None:
    if a is False or b is False:
        return False
    return None if a is None or b is None else True


def kleene_or(a: bool | None, b: bool | None) -> bool | None:
    if a is True or b is True:
        return True
    return None if a is None or b is None else False


def kleene_not(a: bool | None) -> bool | None:
    return None if a is None else not a


BOOL_SIG = Signature({"a": Dim.BOOL, "b": Dim.BOOL, "c": Dim.BOOL, "x": Dim.NONE})
TRI = (True, False, None)


def test_not_binds_tighter_than_and_which_binds_tighter_than_or() -> None:
    e = compile_condition("not a and b or c", BOOL_SIG)
    for a, b, c in itertools.product(TRI, repeat=3):
        expected = kleene_or(kleene_and(kleene_not(a), b), c)
        assert e.evaluate({"a": a, "b": b, "c": c}) is expected, (a, b, c)


def test_and_binds_tighter_than_or_on_either_side() -> None:
    e1 = compile_condition("a or b and c", BOOL_SIG)
    e2 = compile_condition("a and b or c", BOOL_SIG)
    for a, b, c in itertools.product(TRI, repeat=3):
        values = {"a": a, "b": b, "c": c}
        assert e1.evaluate(values) is kleene_or(a, kleene_and(b, c))
        assert e2.evaluate(values) is kleene_or(kleene_and(a, b), c)


def test_parentheses_override_precedence() -> None:
    e = compile_condition("not (a and (b or c))", BOOL_SIG)
    for a, b, c in itertools.product(TRI, repeat=3):
        expected = kleene_not(kleene_and(a, kleene_or(b, c)))
        assert e.evaluate({"a": a, "b": b, "c": c}) is expected


def test_not_applies_to_a_whole_comparison() -> None:
    assert ev("not voltage > v_max") is True
    assert ev("not voltage > v_max", voltage=4.3) is False


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("1 + 2 * 3", 7.0),
        ("(1 + 2) * 3", 9.0),
        ("10 - 4 - 3", 3.0),
        ("12 / 3 / 2", 2.0),
        ("-2 * 3", -6.0),
        ("- -2", 2.0),
        ("2 * -3", -6.0),
        ("+4 - 1", 3.0),
        ("1 + 8 / 4 * 2 - 1", 4.0),
        ("min(3, 1, 2) + max(1, 5) * abs(-2)", 11.0),
        ("cycle * 2 + 1", 7.0),
    ],
)
def test_arithmetic_follows_the_usual_precedence_and_left_associativity(
    text: str, expected: float
) -> None:
    assert ev(text) == expected


def test_arithmetic_binds_tighter_than_comparison_and_comparison_tighter_than_and() -> None:
    assert ev("voltage + 150 mV >= v_max and cycle * 2 == 6") is True
    assert ev("v_max - voltage < 50 mV or cycle > 10") is False


# --------------------------------------------------------------------------- units


@pytest.mark.parametrize(
    ("literal", "dim", "value"),
    [
        ("4.2 V", Dim.VOLTAGE, 4.2),
        ("4.2V", Dim.VOLTAGE, 4.2),
        ("300 mA", Dim.CURRENT, 0.3),
        ("300mA", Dim.CURRENT, 0.3),
        ("20 min", Dim.TIME, 1200.0),
        ("20min", Dim.TIME, 1200.0),
        ("1.5 h", Dim.TIME, 5400.0),
        ("1.5h", Dim.TIME, 5400.0),
        ("250 ms", Dim.TIME, 0.25),
        ("45 degC", Dim.TEMPERATURE, 45.0),
        ("45degC", Dim.TEMPERATURE, 45.0),
        ("45 °C", Dim.TEMPERATURE, 45.0),
        ("1300 mAh", Dim.CHARGE, 1.3),
        ("1300mAh", Dim.CHARGE, 1.3),
        ("2 Ah", Dim.CHARGE, 2.0),
        ("2 mV", Dim.VOLTAGE, 0.002),
        ("1 mV/min", Dim.VOLTAGE_RATE, 0.001 / 60),
        ("1mV/min", Dim.VOLTAGE_RATE, 0.001 / 60),
        ("2 V/s", Dim.VOLTAGE_RATE, 2.0),
        ("5 Wh", Dim.ENERGY, 5.0),
        ("10 W", Dim.POWER, 10.0),
        ("50 mohm", Dim.RESISTANCE, 0.05),
        ("50 mΩ", Dim.RESISTANCE, 0.05),
        ("10 uA", Dim.CURRENT, 10e-6),
        ("10 µA", Dim.CURRENT, 10e-6),
        ("1e3 mV", Dim.VOLTAGE, 1.0),
        (".5 V", Dim.VOLTAGE, 0.5),
        ("3", Dim.NONE, 3.0),
    ],
)
def test_a_number_takes_a_unit_with_or_without_a_space(
    literal: str, dim: Dim, value: float
) -> None:
    e = compile_expr(literal, SIG)
    assert e.dim is dim
    assert e.evaluate({}) == pytest.approx(value)


def test_the_longest_unit_wins_but_only_up_to_a_word_boundary() -> None:
    sig = Signature({"s_count": Dim.NONE, "step_time": Dim.TIME})
    assert compile_expr("1 mAh", sig).dim is Dim.CHARGE  # not mA followed by h
    assert compile_expr("1 V/s", sig).dim is Dim.VOLTAGE_RATE
    # 'V/s' followed by '_count' is not the unit V/s: it is 1 V divided by s_count
    assert compile_expr("1 V/s_count", sig).dim is Dim.VOLTAGE
    assert compile_expr("1 V/step_time", sig).dim is Dim.VOLTAGE_RATE


def test_a_c_rate_literal_is_resolved_to_amperes_with_the_rated_capacity() -> None:
    e = compile_expr("0.5 C", SIG)
    assert e.dim is Dim.CURRENT
    assert e.evaluate({}) == pytest.approx(1.0)  # 0.5 × 2 Ah
    assert compile_expr("0.05C", Signature({}, capacity_ah=1.3)).evaluate({}) == pytest.approx(
        0.065
    )
    assert ev("current < 0.05 C", current=0.09) is True
    assert ev("current < 0.05 C", current=0.11) is False


def test_a_c_rate_literal_without_a_rated_capacity_is_an_error_pointing_at_the_literal() -> None:
    err = error_of("current < 0.05 C", SIG_NO_CAPACITY)
    assert err.message == (
        "'0.05 C' is a C-rate: a rated capacity is needed to turn it into a current "
        "(capacity_ah is not set)"
    )
    assert (err.offset, err.length) == (10, 6)


def test_an_unknown_unit_is_an_error_suggesting_close_units() -> None:
    err = error_of("voltage >= 4 volts")
    assert err.message == "unknown unit 'volts' in '4 volts'; did you mean 'V'?"
    assert (err.offset, err.length) == (13, 5)
    assert (
        error_of("current < 300 MA").message == "unknown unit 'MA' in '300 MA'; did you mean 'mA'?"
    )
    err = error_of("step_time > 4 mn")
    assert err.message == "unknown unit 'mn' in '4 mn'; did you mean 'min', 'mΩ' or 'ms'?"
    assert (err.offset, err.length) == (14, 2)
    err = error_of("step_time > 4 xyz")
    assert err.message.startswith("unknown unit 'xyz' in '4 xyz' (known units: A, Ah, As, C, ")
    err = error_of("temperature > 45 °F")
    assert err.message == "unknown unit '°F' in '45 °F'; did you mean '°C'?"
    assert (err.offset, err.length) == (17, 2)


# --------------------------------------------------------------------------- dimensions


@pytest.mark.parametrize(
    ("text", "dim", "value"),
    [
        ("voltage / step_time", Dim.VOLTAGE_RATE, 4.1 / 120),
        ("current * step_time", Dim.CHARGE, 1.0 * 120 / 3600),  # A·s → Ah
        ("step_time * current", Dim.CHARGE, 1.0 * 120 / 3600),
        ("2 A * 30 min", Dim.CHARGE, 1.0),
        ("voltage * current", Dim.POWER, 4.1),
        ("power * step_time", Dim.ENERGY, 4.1 * 120 / 3600),  # W·s → Wh
        ("10 W * 360 s", Dim.ENERGY, 1.0),
        ("voltage / current", Dim.RESISTANCE, 4.1),
        ("charge / q_max", Dim.NONE, 0.4),
        ("voltage * 2", Dim.VOLTAGE, 8.2),
        ("2 * voltage", Dim.VOLTAGE, 8.2),
        ("voltage / 2", Dim.VOLTAGE, 2.05),
        ("1 Ah / 1 h", Dim.CURRENT, 1.0),
        ("1 Wh / 1 W", Dim.TIME, 3600.0),
        ("dv_dt * 1 min", Dim.VOLTAGE, 0.001 / 60 * 5 * 60),
        ("temperature - adam.slot1.tc0", Dim.TEMPERATURE, 5.0),
        ("-temperature", Dim.TEMPERATURE, -30.0),
        ("max(temperature, adam.slot1.tc0)", Dim.TEMPERATURE, 30.0),
        ("abs(adam.slot1.tc0 - temperature)", Dim.TEMPERATURE, 5.0),
    ],
)
def test_products_and_quotients_follow_the_dimension_algebra_in_base_units(
    text: str, dim: Dim, value: float
) -> None:
    e = compile_expr(text, SIG)
    assert e.dim is dim
    result = e.evaluate(CHARGING)
    assert isinstance(result, float)
    assert result == pytest.approx(value)


@pytest.mark.parametrize(
    "text",
    [
        "dv_dt < 0",
        "current > 0",
        "0 <= current",
        "voltage + 0 >= v_max",
        "voltage - 0 >= v_max",
        "temperature > 0",
        "temperature > -20 degC",
        "min(current, 0) < 0",
        "current > -0",
        "current > (0)",
        "current >= 0.0",
    ],
)
def test_the_literal_zero_goes_with_any_dimension(text: str) -> None:
    assert cond(text).dim is Dim.BOOL


def test_the_literal_zero_does_not_pass_for_a_condition() -> None:
    err = error_of("bms.ok == 0")
    assert err.message == "cannot compare a boolean with a plain number (bms.ok == 0)"
    assert (err.offset, err.length) == (7, 2)


def test_booleans_compare_only_for_equality() -> None:
    assert ev("bms.ok == true") is True
    assert ev("bms.ok != true", bms__ok=False) is True
    err = error_of("bms.ok > false")
    assert err.message == "conditions can only be compared with '==' or '!=' (bms.ok > false)"
    assert (err.offset, err.length) == (7, 1)


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("text", "offset", "length", "message"),
    [
        (
            "voltage >= 300 mA",
            8,
            2,
            "cannot compare a voltage with a current (voltage >= 300 mA)",
        ),
        (
            "voltage >= 4.2",
            8,
            2,
            "cannot compare a voltage with a plain number (voltage >= 4.2); "
            "give the number a unit, e.g. '4.2 V'",
        ),
        (
            "voltage + current > 1 V",
            8,
            1,
            "cannot add a voltage and a current (voltage + current)",
        ),
        (
            "v_max - 50 mA < voltage",
            6,
            1,
            "cannot subtract a current from a voltage (v_max - 50 mA)",
        ),
        (
            "voltage * voltage > 1 V",
            8,
            1,
            "cannot multiply a voltage by a voltage (voltage * voltage)",
        ),
        (
            "voltage * current * voltage > 1 W",
            18,
            1,
            "cannot multiply a power by a voltage (voltage * current * voltage)",
        ),
        (
            "2 / voltage > 1",
            2,
            1,
            "cannot divide a plain number by a voltage (2 / voltage)",
        ),
        (
            "current / voltage > 1",
            8,
            1,
            "cannot divide a current by a voltage (current / voltage)",
        ),
        (
            "temperature + adam.slot1.tc0 > 90 degC",
            12,
            1,
            "a temperature can only be compared or subtracted, not added "
            "(temperature + adam.slot1.tc0)",
        ),
        (
            "2 * temperature > 90 degC",
            2,
            1,
            "a temperature can only be compared or subtracted, not multiplied (2 * temperature)",
        ),
        (
            "temperature / 2 > 20 degC",
            12,
            1,
            "a temperature can only be compared or subtracted, not divided (temperature / 2)",
        ),
        (
            "v_min < voltage < v_max",
            16,
            1,
            "comparisons cannot be chained; write 'v_min < voltage and voltage < v_max'",
        ),
        ("voltage >= v_max && bms.ok", 17, 2, "use 'and' instead of '&&'"),
        ("voltage >= v_max & bms.ok", 17, 1, "use 'and' instead of '&'"),
        ("voltage >= v_max || bms.ok", 17, 2, "use 'or' instead of '||'"),
        ("voltage >= v_max | bms.ok", 17, 1, "use 'or' instead of '|'"),
        ("!bms.ok", 0, 1, "use 'not' instead of '!'"),
        ("cycle = 3", 6, 1, "use '==' to test equality, not '='"),
        ("voltage => v_max", 8, 2, "use '>=' instead of '=>'"),
        ("voltage =< v_max", 8, 2, "use '<=' instead of '=<'"),
        ("voltage <> v_max", 8, 2, "use '!=' instead of '<>'"),
        ("cycle ** 2 > 4", 6, 2, "there is no power operator '**'; multiply explicitly"),
        ("cycle ^ 2 > 4", 6, 1, "there is no power operator '^'; multiply explicitly"),
        (
            "voltage and bms.ok",
            0,
            7,
            "'and' needs a condition on each side, but 'voltage' is a voltage",
        ),
        (
            "bms.ok or current",
            10,
            7,
            "'or' needs a condition on each side, but 'current' is a current",
        ),
        ("not voltage", 4, 7, "'not' needs a condition, but 'voltage' is a voltage"),
        ("bms.ok + 1 > 0", 0, 6, "'+' needs numbers, but 'bms.ok' is a condition"),
        ("-bms.ok", 0, 1, "'-' needs a number, but 'bms.ok' is a condition (use 'not')"),
        (
            "voltge >= v_max",
            0,
            6,
            "unknown name 'voltge'; did you mean 'voltage' or 'ch1.voltage'?",
        ),
        (
            "slot1.tc0 > 60 degC",
            0,
            9,
            "unknown name 'slot1.tc0'; did you mean 'adam.slot1.tc0'?",
        ),
        ("voltage > v_max AND bms.ok", 16, 3, "write 'and' in lower case"),
        ("TRUE", 0, 4, "unknown name 'TRUE'; write 'true' in lower case"),
        ("abs > 1", 0, 3, "'abs' is a function; write abs(...)"),
        ("sqrt(cycle) > 1", 0, 4, "unknown function 'sqrt'; available functions: abs, min, max"),
        ("abs(voltage, current) > 1 V", 0, 21, "abs() takes exactly one argument, got 2"),
        ("min(voltage) > 1 V", 0, 12, "min() needs at least two arguments, got 1"),
        (
            "max(voltage, current) > 1 V",
            13,
            7,
            "max() arguments must have the same dimension: "
            "'voltage' is a voltage but 'current' is a current",
        ),
        ("abs(bms.ok) > 0", 4, 6, "abs() needs numbers, but 'bms.ok' is a condition"),
        ("", 0, 1, "empty expression"),
        ("   ", 0, 1, "empty expression"),
        (
            "voltage >=",
            10,
            1,
            "the expression ends too early; expected a number, a name or '('",
        ),
        ("voltage >= * 2", 11, 1, "expected a number, a name or '(', found '*'"),
        ("(voltage >= v_max", 0, 1, "'(' is never closed"),
        ("max(voltage, v_max", 3, 1, "'(' is never closed"),
        ("voltage >= v_max)", 16, 1, "unmatched ')'"),
        (
            "voltage v_max",
            8,
            5,
            "expected an operator or the end of the expression, found 'v_max'",
        ),
        ("2 voltage > 1 V", 2, 7, "missing operator between '2' and 'voltage'"),
        ("voltage > 4 V v_max", 14, 5, "missing operator between '4 V' and 'v_max'"),
        ("(voltage v_max)", 9, 5, "expected ')', found 'v_max'"),
        ("min(voltage v_max)", 12, 5, "expected ',' or ')', found 'v_max'"),
        ("voltage # comment", 8, 1, "unexpected character '#'"),
        ("voltage > 'x'", 10, 1, 'unexpected character "\'"'),
        ("bms. > 1", 3, 1, "a name cannot end with '.' (bms.)"),
        ("cycle > 1e999", 8, 5, "number '1e999' is too large"),
        (
            "voltage < not bms.ok",
            10,
            3,
            "'not' applies to a whole condition here; put it in parentheses: (not ...)",
        ),
    ],
)
def test_each_error_has_its_message_and_points_at_the_fault(
    text: str, offset: int, length: int, message: str
) -> None:
    err = error_of(text)
    assert err.message == message
    assert str(err) == message
    assert (err.offset, err.length) == (offset, length)
    assert err.text == text


def test_a_voltage_compared_with_a_current_is_an_error_pointing_at_the_operator() -> None:
    err = error_of("voltage >= 300 mA")
    assert err.message == "cannot compare a voltage with a current (voltage >= 300 mA)"
    assert err.text[err.offset : err.offset + err.length] == ">="
    assert err.caret() == "voltage >= 300 mA\n        ^^"


def test_a_value_that_is_not_boolean_is_not_a_condition() -> None:
    err = error_of("voltage + 1 V")
    assert err.message == (
        "'voltage + 1 V' is a voltage, not a condition (compare it, e.g. 'voltage + 1 V >= 1 V')"
    )
    assert (err.offset, err.length) == (0, 13)
    err = error_of("  cycle ")
    assert (
        err.message == "'cycle' is a plain number, not a condition (compare it, e.g. 'cycle >= 1')"
    )
    assert (err.offset, err.length) == (2, 5)
    # compile_expr accepts the same text
    assert compile_expr("voltage + 1 V", SIG).dim is Dim.VOLTAGE


def test_an_unknown_name_lists_the_closest_known_names() -> None:
    err = error_of("q_mx < charge")
    assert err.message == "unknown name 'q_mx'; did you mean 'q_max', 'v_max' or 'q_min'?"
    err = error_of("zzz > 1")
    assert err.message.startswith("unknown name 'zzz'; known names: adam.slot1.tc0, bms.ok, ")
    err = error_of("voltage > 1 V", Signature({}))
    assert err.message == "unknown name 'voltage'; no names are available here"


def test_deep_nesting_is_an_error_not_a_crash() -> None:
    text = "(" * (MAX_NESTING + 10) + "cycle > 1" + ")" * (MAX_NESTING + 10)
    err = error_of(text)
    assert err.message == f"expression is nested too deeply (more than {MAX_NESTING} levels)"
    assert err.offset == MAX_NESTING
    err = error_of("not " * (MAX_NESTING + 1) + "bms.ok")
    assert err.message.startswith("expression is nested too deeply")
    assert (
        compile_condition("not " * MAX_NESTING + "bms.ok", SIG).evaluate({"bms.ok": True}) is True
    )


def test_a_very_long_chain_is_an_error_not_a_crash() -> None:
    err = error_of(" + ".join(["cycle"] * (MAX_DEPTH + 5)) + " > 0")
    assert err.message == f"expression is too long (more than {MAX_DEPTH} levels)"
    assert err.offset == 0
    # a long chain of 'and' is flat and fine
    e = cond(" and ".join(["bms.ok"] * 500))
    assert e.evaluate({"bms.ok": True}) is True


def test_an_expr_error_survives_pickling_with_its_position() -> None:
    err = error_of("voltage >= 300 mA")
    copy = pickle.loads(pickle.dumps(err))
    assert (copy.message, copy.offset, copy.length, copy.text) == (
        err.message,
        err.offset,
        err.length,
        err.text,
    )


def test_the_module_never_uses_eval_exec_compile_or_the_ast_module() -> None:
    source = Path(expr_module.__file__).read_text(encoding="utf-8")
    assert not re.search(r"(?<![\w.])(eval|exec|compile)\(", source)
    assert not re.search(r"^\s*(import ast|from ast )", source, re.MULTILINE)


# --------------------------------------------------------------------------- three-valued


def test_an_unknown_value_makes_a_comparison_unknown() -> None:
    e = cond("voltage >= v_max")
    assert e.evaluate({"voltage": None, "v_max": 4.2}) is None
    assert e.evaluate({"voltage": 4.3, "v_max": None}) is None
    assert cond("voltage >= 4.2 V").evaluate({"voltage": None}) is None
    assert cond("4.2 V <= voltage").evaluate({"voltage": None}) is None


def test_a_missing_value_counts_as_unknown() -> None:
    assert cond("voltage >= v_max").evaluate({}) is None
    assert cond("not bms.ok").evaluate({}) is None


def test_an_unknown_value_makes_arithmetic_and_functions_unknown() -> None:
    for text in (
        "voltage + 1 V",
        "voltage - v_max",
        "voltage * 2",
        "voltage / current",
        "-voltage",
        "abs(voltage)",
        "min(voltage, v_max)",
        "max(v_max, voltage)",
    ):
        assert ev(text, voltage=None) is None, text


def test_false_and_unknown_is_false_and_true_or_unknown_is_true() -> None:
    assert ev("voltage > v_max and current > 1 A", current=None) is False
    assert ev("current > 1 A and voltage > v_max", current=None) is False
    assert ev("voltage < v_max or current > 1 A", current=None) is True
    assert ev("current > 1 A or voltage < v_max", current=None) is True
    assert ev("voltage < v_max and current > 1 A", current=None) is None
    assert ev("voltage > v_max or current > 1 A", current=None) is None
    assert ev("not (current > 1 A)", current=None) is None


def test_and_or_and_not_follow_kleene_logic_for_every_combination() -> None:
    e_and = compile_condition("a and b", BOOL_SIG)
    e_or = compile_condition("a or b", BOOL_SIG)
    e_and3 = compile_condition("a and b and c", BOOL_SIG)
    e_or3 = compile_condition("a or b or c", BOOL_SIG)
    e_not = compile_condition("not a", BOOL_SIG)
    for a, b, c in itertools.product(TRI, repeat=3):
        values = {"a": a, "b": b, "c": c}
        assert e_and.evaluate(values) is kleene_and(a, b)
        assert e_or.evaluate(values) is kleene_or(a, b)
        assert e_and3.evaluate(values) is kleene_and(kleene_and(a, b), c)
        assert e_or3.evaluate(values) is kleene_or(kleene_or(a, b), c)
        assert e_not.evaluate(values) is kleene_not(a)


def test_a_boolean_signal_given_as_a_number_counts_by_its_truth() -> None:
    e = cond("not bms.ok")
    assert e.evaluate({"bms.ok": 1.0}) is False
    assert e.evaluate({"bms.ok": 0.0}) is True
    assert cond("bms.ok and bms.ok").evaluate({"bms.ok": 1.0}) is True


def test_division_by_zero_is_unknown() -> None:
    assert ev("voltage / current", current=0.0) is None
    assert ev("voltage / current > 1 ohm", current=0.0) is None
    assert ev("cycle / 0") is None
    assert compile_expr("1 / 0", SIG).evaluate({}) is None  # folded at compile time


def test_constants_are_folded_but_keep_their_meaning() -> None:
    e = compile_expr("2 * 60 s + 1 min", SIG)
    assert e.dim is Dim.TIME
    assert e.names == frozenset()
    assert e.evaluate({}) == 180.0
    assert cond("true or false").evaluate({}) is True
    assert cond("1 V < 2 V and not false").evaluate({}) is True


# --------------------------------------------------------------------------- properties

FUZZ_FRAGMENTS = [
    "voltage",
    "v_max",
    "current",
    "step_time",
    "temperature",
    "bms.ok",
    "cycle",
    "adam.slot1.tc0",
    "unknown",
    " and ",
    " or ",
    "not ",
    "true",
    "false",
    "abs(",
    "min(",
    "max(",
    "(",
    ")",
    ",",
    " ",
    "+",
    "-",
    "*",
    "/",
    "<",
    "<=",
    ">",
    ">=",
    "==",
    "!=",
    "=",
    "!",
    "&&",
    "||",
    ".",
    "0",
    "1",
    "4.2",
    "1e3",
    "1e999",
    " V",
    "mV",
    "mA",
    " C",
    " min",
    " degC",
    "°",
    "µA",
    "mV/min",
    "/s",
    "h",
    "#",
    "\n",
]


def _compiles_or_raises_expr_error(text: str, sig: Signature) -> None:
    try:
        e = compile_expr(text, sig)
    except ExprError as err:
        assert err.length >= 1
        assert 0 <= err.offset <= len(text)
        assert err.message
        return
    assert e.dim in Dim
    assert e.names <= set(sig.names)
    for values in ({}, dict.fromkeys(sig.names), CHARGING, dict.fromkeys(sig.names, 0.0)):
        result = e.evaluate(values)
        assert result is None or isinstance(result, bool | float | int)
    if e.dim is Dim.BOOL:
        compile_condition(text, sig)


@settings(max_examples=400, deadline=None, database=None)
@given(st.text(max_size=40))
@example("((((((((((((((")
@example("min(,)")
@example("1e999 V")
@example("voltage >= 4.2 V)")
def test_any_string_compiles_or_raises_expr_error(text: str) -> None:
    _compiles_or_raises_expr_error(text, SIG)
    _compiles_or_raises_expr_error(text, SIG_NO_CAPACITY)


@settings(max_examples=600, deadline=None, database=None)
@given(st.lists(st.sampled_from(FUZZ_FRAGMENTS), max_size=14).map("".join))
def test_any_string_of_expression_fragments_compiles_or_raises_expr_error(text: str) -> None:
    _compiles_or_raises_expr_error(text, SIG)
    _compiles_or_raises_expr_error(text, SIG_NO_CAPACITY)


# A random tree is printed with as few parentheses as precedence allows, compiled, and
# evaluated; a direct evaluation of the tree must give the same value.

ARITH_SIG = Signature({"x": Dim.NONE, "y": Dim.NONE, "z": Dim.NONE, "p": Dim.BOOL, "q": Dim.BOOL})
PREC = {"or": 1, "and": 2, "not": 3, "cmp": 4, "+": 5, "-": 5, "*": 6, "/": 6, "neg": 7}
ATOM = 8

numbers = st.one_of(
    st.integers(0, 10**6).map(str),
    st.sampled_from(["0", "0.5", "3.25", "1e3", "2.5e-3", ".5", "7.", "1e-300", "1e300"]),
)
arith_leaves = st.one_of(
    numbers.map(lambda s: ("num", s)), st.sampled_from("xyz").map(lambda n: ("name", n))
)
arith_trees = st.recursive(
    arith_leaves,
    lambda child: st.one_of(
        st.tuples(st.just("neg"), child),
        st.tuples(st.just("bin"), st.sampled_from("+-*/"), child, child),
        st.tuples(st.just("abs"), child),
        st.tuples(st.sampled_from(["min", "max"]), st.lists(child, min_size=2, max_size=4)),
    ),
    max_leaves=16,
)
bool_leaves = st.one_of(
    st.tuples(
        st.just("cmp"),
        st.sampled_from(["<", "<=", ">", ">=", "==", "!="]),
        arith_trees,
        arith_trees,
    ),
    st.sampled_from("pq").map(lambda n: ("bname", n)),
    st.booleans().map(lambda b: ("bool", b)),
)
bool_trees = st.recursive(
    bool_leaves,
    lambda child: st.one_of(
        st.tuples(st.just("not"), child),
        st.tuples(st.sampled_from(["and", "or"]), child, child),
    ),
    max_leaves=6,
)
maybe_float = st.none() | st.floats(-1e6, 1e6, allow_nan=False)
maybe_bool = st.none() | st.booleans()


def prec(t: Any) -> int:
    kind = t[0]
    if kind == "bin":
        return PREC[t[1]]
    return PREC.get(kind, ATOM)


def show(t: Any, min_prec: int = 0) -> str:
    kind = t[0]
    if kind in ("num", "name", "bname"):
        s = t[1]
    elif kind == "bool":
        s = "true" if t[1] else "false"
    elif kind == "neg":
        s = "-" + show(t[1], PREC["neg"])
    elif kind == "bin":
        p = PREC[t[1]]
        s = f"{show(t[2], p)} {t[1]} {show(t[3], p + 1)}"
    elif kind == "abs":
        s = f"abs({show(t[1])})"
    elif kind in ("min", "max"):
        s = f"{kind}({', '.join(show(a) for a in t[1])})"
    elif kind == "cmp":
        s = f"{show(t[2], PREC['+'])} {t[1]} {show(t[3], PREC['+'])}"
    elif kind == "not":
        s = "not " + show(t[1], PREC["not"])
    else:  # and / or
        p = PREC[kind]
        s = f"{show(t[1], p)} {kind} {show(t[2], p + 1)}"
    return s if prec(t) >= min_prec else f"({s})"


CMP_REF = {
    "<": lambda a, b: a < b,
    "<=": lambda a, b: a <= b,
    ">": lambda a, b: a > b,
    ">=": lambda a, b: a >= b,
    "==": lambda a, b: a == b,
    "!=": lambda a, b: a != b,
}


def reference(t: Any, env: dict[str, Any]) -> Any:
    """A direct evaluation of the tree, three-valued, division by zero unknown."""
    kind = t[0]
    if kind == "num":
        return float(t[1])
    if kind in ("name", "bname"):
        return env[t[1]]
    if kind == "bool":
        return t[1]
    if kind == "neg":
        a = reference(t[1], env)
        return None if a is None else -a
    if kind == "abs":
        a = reference(t[1], env)
        return None if a is None else abs(a)
    if kind in ("min", "max"):
        args = [reference(a, env) for a in t[1]]
        if any(a is None for a in args):
            return None
        return min(args) if kind == "min" else max(args)
    if kind in ("bin", "cmp"):
        a, b = reference(t[2], env), reference(t[3], env)
        if a is None or b is None:
            return None
        op = t[1]
        if kind == "cmp":
            return CMP_REF[op](a, b)
        if op == "+":
            return a + b
        if op == "-":
            return a - b
        if op == "*":
            return a * b
        return None if b == 0 else a / b
    if kind == "not":
        return kleene_not(reference(t[1], env))
    a, b = reference(t[1], env), reference(t[2], env)
    return kleene_and(a, b) if kind == "and" else kleene_or(a, b)


def same(a: Any, b: Any) -> bool:
    if a is None or b is None or isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return bool(a == b)


@settings(max_examples=500, deadline=None, database=None)
@given(arith_trees, maybe_float, maybe_float, maybe_float)
def test_random_arithmetic_evaluates_like_a_direct_evaluation_of_its_tree(
    tree: Any, x: float | None, y: float | None, z: float | None
) -> None:
    text = show(tree)
    e = compile_expr(text, ARITH_SIG)
    env = {"x": x, "y": y, "z": z}
    assert e.dim is Dim.NONE
    got, want = e.evaluate(env), reference(tree, env)
    assert same(got, want), (text, env, got, want)


@settings(max_examples=400, deadline=None, database=None)
@given(bool_trees, maybe_float, maybe_float, maybe_float, maybe_bool, maybe_bool)
def test_random_conditions_evaluate_like_a_direct_three_valued_evaluation(
    tree: Any, x: float | None, y: float | None, z: float | None, p: bool | None, q: bool | None
) -> None:
    text = show(tree)
    e = compile_condition(text, ARITH_SIG)
    env = {"x": x, "y": y, "z": z, "p": p, "q": q}
    got, want = e.evaluate(env), reference(tree, env)
    assert same(got, want), (text, env, got, want)
