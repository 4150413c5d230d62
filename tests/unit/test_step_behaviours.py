"""Step behaviours on their own: setpoints, CV targets, "done?", pulse resistance. No bench."""

from __future__ import annotations

from typing import Any

import pytest

from supervisor.chains.behaviours import (
    ConstantCurrent,
    ConstantPower,
    ConstantVoltage,
    End,
    EndCycle,
    Goto,
    Profile,
    Pulse,
    Rest,
    Sleep,
    SleepUntil,
)
from supervisor.chains.compiler import WITH_CV
from supervisor.chains.kinds import KINDS, behaviour_for
from supervisor.chains.program import Action, ActionKind, CompiledStep, ProfilePoint


def step(kind: str, **kw: Any) -> CompiledStep:
    return CompiledStep(index=0, id="s", kind=kind, **kw)


def test_every_step_kind_a_recipe_may_use_has_a_behaviour() -> None:
    assert set(KINDS) == set(WITH_CV)


@pytest.mark.parametrize(
    ("kind", "cls"),
    [
        ("rest", Rest),
        ("sleep", Sleep),
        ("sleep_until", SleepUntil),
        ("charge", ConstantCurrent),
        ("discharge", ConstantCurrent),
        ("cv", ConstantVoltage),
        ("cccv", ConstantVoltage),
        ("power", ConstantPower),
        ("pulse", Pulse),
        ("profile", Profile),
        ("goto", Goto),
        ("end_cycle", EndCycle),
        ("end", End),
    ],
)
def test_a_step_gets_the_behaviour_of_its_kind(kind: str, cls: type) -> None:
    assert type(behaviour_for(step(kind))) is cls


def test_a_step_of_unknown_kind_is_refused_at_load() -> None:
    with pytest.raises(ValueError, match="no behaviour for step kind 'teleport'"):
        behaviour_for(step("teleport"))


@pytest.mark.parametrize(
    ("s", "label"),
    [
        (step("rest"), "REST"),
        (step("charge", current_a=0.3), "CC_CHG"),
        (step("discharge", current_a=-0.2), "CC_DCH"),
        (step("cccv", current_a=2.0, voltage_v=4.2), "CCCV_CHG"),
        (step("power", power_w=-5.0), "CP_DCH"),
        (step("profile"), "PROFILE"),
    ],
    ids=lambda x: x if isinstance(x, str) else x.kind,
)
def test_the_bdf_step_type_is_fixed_when_the_behaviour_is_chosen(
    s: CompiledStep, label: str
) -> None:
    assert behaviour_for(s).step_type == label


# --- rest, sleep ----------------------------------------------------------------------
def test_a_rest_asks_for_nothing_and_ends_only_by_its_duration_or_conditions() -> None:
    b = behaviour_for(step("rest", duration_s=60.0))
    assert b.setpoint(10.0, 1.3) == 0.0
    assert b.cv_target_v == 0.0
    assert b.done(1e6) == ""
    assert b.entry is None


def test_a_sleep_asks_for_nothing_and_is_done_after_its_time() -> None:
    b = behaviour_for(step("sleep", sleep_s=30.0))
    assert b.setpoint(10.0, 1.3) == 0.0
    assert b.done(29.9) == ""
    assert b.done(30.0) == "sleep done"


# --- constant current, constant voltage, constant power -----------------------------------
def test_a_cc_step_asks_for_its_current_whatever_the_time_or_voltage() -> None:
    b = behaviour_for(step("discharge", current_a=-0.2))
    assert [b.setpoint(t, v) for t, v in [(0.0, 1.3), (3600.0, None)]] == [-0.2, -0.2]
    assert b.cv_target_v == 0.0
    assert b.done(1e6) == ""
    assert b.progress_current_a == -0.2  # progress against the rated capacity


@pytest.mark.parametrize("kind", ["cv", "cccv"])
def test_a_cv_step_asks_for_its_current_limit_and_its_voltage_target(kind: str) -> None:
    b = behaviour_for(step(kind, current_a=2.0, voltage_v=4.2))
    assert b.setpoint(100.0, 4.19) == 2.0
    assert b.cv_target_v == 4.2
    assert b.progress_current_a is None  # the current tapers: no ETA at a fixed current


def test_a_cv_step_without_a_voltage_asks_for_no_target() -> None:
    assert behaviour_for(step("cv", current_a=1.0)).cv_target_v == 0.0


def test_a_power_step_asks_for_power_over_voltage() -> None:
    b = behaviour_for(step("power", power_w=-2.0))
    assert b.setpoint(0.0, 4.0) == pytest.approx(-0.5)
    assert b.setpoint(0.0, 2.0) == pytest.approx(-1.0)


@pytest.mark.parametrize("voltage_v", [None, 0.05, 0.0, -1.0], ids=str)
def test_a_power_step_asks_for_nothing_without_a_usable_voltage(voltage_v: float | None) -> None:
    assert behaviour_for(step("power", power_w=-2.0)).setpoint(0.0, voltage_v) == 0.0


# --- pulse ------------------------------------------------------------------------------
def pulses(count: int = 3) -> Pulse:
    b = behaviour_for(
        step("pulse", current_a=0.2, pulse_on_s=10.0, pulse_off_s=20.0, pulse_count=count)
    )
    assert isinstance(b, Pulse)
    return b


def test_a_pulse_train_alternates_its_current_and_rest() -> None:
    b = pulses()
    on = [t for t in range(90) if b.setpoint(float(t), 1.3) != 0.0]
    assert on == [*range(0, 10), *range(30, 40), *range(60, 70)]
    assert b.setpoint(5.0, None) == 0.2


def test_a_pulse_train_is_done_after_its_count_of_periods() -> None:
    b = pulses(3)
    assert b.done(89.0) == ""
    assert b.done(90.0) == "pulses done"


def test_a_pulse_without_a_period_never_pulses_nor_ends_by_itself() -> None:
    b = behaviour_for(step("pulse", current_a=0.2, pulse_count=3))
    assert b.setpoint(0.0, 1.3) == 0.0
    assert b.done(1e6) == ""


def drive(b: Pulse, seconds: int, r_ohm: float = 0.05, ocv_v: float = 1.30) -> list[float]:
    """Feed the pulse a cell with internal resistance ``r_ohm``; return what it measured."""
    measured = []
    b.enter(ocv_v, 0.0)
    for t in range(seconds):
        amps = b.setpoint(float(t), ocv_v)
        res = b.scan(float(t), ocv_v + r_ohm * amps, amps)
        if res is not None:
            measured.append(res)
    return measured


def test_each_pulse_measures_the_dc_internal_resistance_dv_over_di() -> None:
    # R = ΔV/ΔI between the last reading at rest before the pulse and the last under current.
    assert drive(pulses(3), 95) == pytest.approx([0.05, 0.05, 0.05])


def test_the_resistance_is_measured_once_per_pulse_when_the_pulse_ends() -> None:
    b = pulses(3)
    b.enter(1.30, 0.0)
    assert all(b.scan(float(t), 1.31, 0.2) is None for t in range(10))  # under current
    assert b.scan(10.0, 1.30, 0.0) == pytest.approx(0.05)  # first reading at rest
    assert all(b.scan(float(t), 1.30, 0.0) is None for t in range(11, 30))


def test_no_resistance_without_readings() -> None:
    b = pulses(1)
    b.enter(None, None)
    assert [b.scan(float(t), None, None) for t in range(30)] == [None] * 30


def test_entering_the_step_again_forgets_the_last_activation() -> None:
    b = pulses(1)
    drive(b, 5)  # cut off in the middle of a pulse
    b.enter(None, None)  # re-entered with no reading at rest
    assert [b.scan(float(t), 1.31, 0.2) for t in range(10)] == [None] * 10
    assert b.scan(10.0, 1.30, 0.0) is None  # no reference before this pulse: no figure


# --- profile ----------------------------------------------------------------------------
ROWS = (
    ProfilePoint(0.0, 0.1, v_min=0.5, v_max=2.0),
    ProfilePoint(60.0, -0.1, i_min=-1.0, i_max=1.0),
    ProfilePoint(120.0, 0.2, v_max=1.0, t_max=60.0),
    ProfilePoint(180.0, 0.0),
)


def profile(repeat: int = 1) -> Profile:
    b = behaviour_for(step("profile", profile=ROWS, profile_repeat=repeat))
    assert isinstance(b, Profile)
    return b


def test_a_profile_asks_for_the_current_of_the_row_in_force() -> None:
    b = profile()
    assert [b.setpoint(t, None) for t in (0.0, 59.0, 60.0, 150.0, 180.0)] == [
        0.1,
        0.1,
        -0.1,
        0.2,
        0.1,  # the last row's time is the period: the profile starts again
    ]


def test_a_profile_is_done_after_its_repeats() -> None:
    b = profile(repeat=2)
    assert b.done(359.0) == ""
    assert b.done(360.0) == "profile done"


def test_a_profile_row_brings_its_own_limits() -> None:
    b = profile()
    assert b.limits(130.0) == (
        ("voltage", (None, 1.0), "V"),
        ("current", (None, None), "A"),
        ("temperature", (None, 60.0), "degC"),
    )


def test_an_empty_profile_asks_for_nothing_and_brings_no_limits() -> None:
    b = behaviour_for(step("profile"))
    assert b.setpoint(10.0, 1.3) == 0.0
    assert b.limits(10.0) == ()
    assert b.done(1e6) == ""


# --- instant steps ----------------------------------------------------------------------
def test_instant_steps_say_what_they_do_in_the_scan_they_are_entered() -> None:
    assert behaviour_for(step("goto", goto=3)).entry == Action(ActionKind.GOTO, 3)
    assert behaviour_for(step("end_cycle")).entry == Action(ActionKind.NEXT_CYCLE)
    assert behaviour_for(step("end")).entry == Action(ActionKind.END)
    assert behaviour_for(step("sleep_until", sleep_until=(20, 0))).entry == Action(
        ActionKind.SLEEP_UNTIL, hhmm=(20, 0)
    )


@pytest.mark.parametrize("kind", ["goto", "end_cycle", "end", "sleep_until"])
def test_instant_steps_ask_for_no_current(kind: str) -> None:
    assert behaviour_for(step(kind)).setpoint(0.0, 1.3) == 0.0
