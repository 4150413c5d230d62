"""The chain's smaller collaborators: condition values, progress/ETA, logging rules."""

from __future__ import annotations

import math

import pytest

from supervisor.chains.compiler import Target, compile_recipe
from supervisor.chains.conditions import ConditionValues
from supervisor.chains.port import ChannelPort
from supervisor.chains.program import Program
from supervisor.chains.progress import Progress
from supervisor.chains.run import RunState
from supervisor.chains.sampling import LogRules, build_record
from supervisor.channels import Channel, ChannelLimits, Mode
from supervisor.config.recipe import load_recipe_text
from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality, Reason
from supervisor.core.units import Dim
from supervisor.tags import TagDB, TagSpec


def program(text: str, tags: dict[str, Dim] | None = None) -> Program:
    recipe, pos = load_recipe_text(text)
    return compile_recipe(recipe, pos, "<recipe>", Target(tags=tags or {}))


def bench(
    text: str = "recipe: r\nsteps:\n  - {id: a, rest: 1 h}\n",
) -> tuple[TagDB, Channel, ChannelPort, Program]:
    db = TagDB()
    db.add(TagSpec("amb.t", unit="degC"))
    ch = Channel("ch0", db, ChannelLimits((-0.4, 0.4), (0.8, 1.9)), capacity_ah=2.0)
    prog = program(text, {"amb.t": Dim.TEMPERATURE})
    return db, ch, ChannelPort.from_tags(db, "ch0", Mode.AUTO.value), prog


# --- condition values ----------------------------------------------------------------------
def test_dv_dt_needs_a_ten_second_span_and_looks_back_one_minute() -> None:
    db, _, port, prog = bench()
    c = ConditionValues(port, db, prog)
    c.observe(0.0, 1.30)
    c.observe(5.0, 1.31)
    assert c.dv_dt() is None  # 5 s: too short to tell a slope from noise
    c.observe(10.0, 1.32)
    assert c.dv_dt() == pytest.approx(0.002)
    for t in range(11, 100):
        c.observe(float(t), 1.32 + 0.001 * (t - 10))
    # Only the last 60 s count: a slope of 1 mV/s.
    assert c.dv_dt() == pytest.approx(0.001)


def test_the_peak_and_delta_peak_start_again_with_each_step() -> None:
    db, ch, port, prog = bench()
    c = ConditionValues(port, db, prog)
    for v in (1.40, 1.45, 1.43):
        c.observe(0.0, v)
    db.update(ch.voltage, 1.43)
    vals = c.values(0.0, RunState())
    assert vals["peak_voltage"] == 1.45
    assert vals["delta_peak"] == pytest.approx(0.02)  # −ΔV from the step's peak
    c.restart()
    vals = c.values(0.0, RunState())
    assert vals["peak_voltage"] is None and vals["delta_peak"] is None and c.dv_dt() is None


def test_a_reading_that_is_not_good_is_unknown_to_the_conditions() -> None:
    db, ch, port, prog = bench()
    db.update(ch.voltage, 1.3, Quality.BAD, Reason.STALE)
    db.update(ch.current, 0.1)
    vals = ConditionValues(port, db, prog).values(0.0, RunState())
    assert vals["voltage"] is None
    assert vals["current"] == 0.1


def test_times_charge_and_step_counters_are_relative_to_their_starts() -> None:
    db, ch, port, prog = bench(
        "recipe: r\ninitial_charge: 100 mAh\nsteps:\n  - {id: a, rest: 1 h}\n"
    )
    db.update(ch.charge_ah, 0.5)
    db.update(ch.energy_wh, 2.0)
    run = RunState(t_test0=10.0, t_cycle0=20.0, t_step0=30.0, q0_ah=0.2, step_q0=0.4, step_e0=1.5)
    run.cycle = 2
    vals = ConditionValues(port, db, prog).values(100.0, run)
    assert vals["test_time"] == 90.0 and vals["cycle_time"] == 80.0 and vals["step_time"] == 70.0
    assert vals["charge"] == pytest.approx(0.1 + 0.5 - 0.2)
    assert vals["step_charge"] == pytest.approx(0.1)
    assert vals["step_energy"] == pytest.approx(0.5)
    assert vals["cycle"] == 2.0


def test_bench_tags_the_program_reads_are_looked_up_by_their_full_name() -> None:
    db, _, port, prog = bench(
        "recipe: r\nsteps:\n  - {id: a, rest: 1 h, until: [{amb.t > 30 degC: next}]}\n"
    )
    c = ConditionValues(port, db, prog)
    assert c.values(0.0, RunState())["amb.t"] is None  # not read yet: unknown
    db.update(db["amb.t"], 31.0)
    assert c.values(0.0, RunState())["amb.t"] == 31.0


# --- progress --------------------------------------------------------------------------
def test_progress_follows_the_estimated_duration_when_there_is_one() -> None:
    p = Progress(estimated_duration_s=1000.0)
    kw = {"complete": False, "step_current_a": None, "step_moved_ah": 0.0, "capacity_ah": 2.0}
    assert p.update(active=True, elapsed_s=250.0, **kw) == (0.25, 750.0)
    assert p.update(active=True, elapsed_s=2000.0, **kw) == (1.0, 0.0)


def test_a_cc_step_shows_progress_against_the_rated_capacity() -> None:
    # Seed 001's progress bar: 0.4 Ah of 2 Ah moved at 400 mA leaves 4 h.
    shown = Progress().update(
        active=True,
        complete=False,
        elapsed_s=0.0,
        step_current_a=-0.4,
        step_moved_ah=-0.4,
        capacity_ah=2.0,
    )
    assert shown == (pytest.approx(0.2), pytest.approx(4 * 3600))


def test_progress_is_left_alone_without_an_estimate_or_a_cc_step() -> None:
    shown = Progress().update(
        active=True,
        complete=False,
        elapsed_s=10.0,
        step_current_a=None,
        step_moved_ah=0.0,
        capacity_ah=2.0,
    )
    assert shown is None


def test_a_completed_test_shows_full_progress() -> None:
    shown = Progress().update(
        active=False,
        complete=True,
        elapsed_s=10.0,
        step_current_a=None,
        step_moved_ah=0.0,
        capacity_ah=None,
    )
    assert shown == (1.0, 0.0)


# --- logging rules and records ----------------------------------------------------------
def test_a_steps_logging_rule_overrides_the_recipes() -> None:
    prog = program(
        "recipe: r\nlogging: {period: 10 s, delta_v: 5 mV}\nsteps:\n"
        "  - {id: a, rest: 1 h}\n  - {id: b, rest: 1 h, log: {period: 1 s}}\n"
    )
    rules = LogRules(prog)
    run = RunState(last_rec_t=0.0, last_rec_v=1.300, last_rec_i=0.0)
    assert rules.reason(0, 5.0, run, 1.302, 0.0) == ""
    assert rules.reason(1, 5.0, run, 1.302, 0.0) == "period"
    assert rules.reason(0, 10.0, run, 1.302, 0.0) == "period"
    assert rules.reason(0, 5.0, run, 1.306, 0.0) == "delta_v"
    assert rules.reason(0, 5.0, run, None, 0.0) == ""  # an unknown voltage has not moved


def test_the_first_sample_of_a_periodic_rule_is_due_at_once() -> None:
    prog = program("recipe: r\nlogging: {period: 10 s}\nsteps:\n  - {id: a, rest: 1 h}\n")
    assert RunState().last_rec_t == -math.inf
    assert LogRules(prog).reason(0, 0.0, RunState(), None, None) == "period"


def test_a_record_holds_test_and_cycle_scoped_counters() -> None:
    db, ch, port, prog = bench("recipe: r\nsteps:\n  - {id: a, charge: 100 mA, duration: 1 h}\n")
    db.update(ch.voltage, 1.35)
    db.update(ch.current_cmd, 0.1)
    db.update(ch.charged_ah, 0.30)
    run = RunState(t_test0=0.0, t_cycle0=100.0, t_step0=200.0, step_count=3)
    run.test0 = {"charged_ah": 0.10, "discharged_ah": 0.0, "charged_wh": 0.0, "discharged_wh": 0.0}
    run.cycle0 = dict(run.test0, charged_ah=0.25)
    rec = build_record(
        port, VirtualClock(), 300.0, run, prog.steps[0], "CC_CHG", 0.2, 0.1, "period"
    )
    assert (rec.test_time_s, rec.cycle_time_s, rec.step_time_s) == (300.0, 200.0, 100.0)
    assert rec.step_remaining_s == 3500.0
    assert rec.charged_ah == pytest.approx(0.20) and rec.cycle_charged_ah == pytest.approx(0.05)
    assert rec.voltage_v == 1.35 and rec.current_a is None  # the current was never read
    assert (rec.current_cmd_a, rec.setpoint_a, rec.charge_ah) == (0.1, 0.1, 0.2)
    assert (rec.step_count, rec.step_id, rec.step_type, rec.reason) == (
        3,
        "a",
        "CC_CHG",
        "period",
    )
