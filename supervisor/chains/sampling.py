"""When a result sample is taken (logging rules), and what it holds (a ``Record``).

Logging rules as the cyclers have them (reference/semantics.md): every Δt, ΔV or ΔI,
per step or for the whole recipe, and always at a step change and at the end.
"""

from __future__ import annotations

import math

from supervisor.chains.port import ChannelPort
from supervisor.chains.program import CompiledStep, Program
from supervisor.chains.run import RunState
from supervisor.core.clock import Clock
from supervisor.core.records import Record

EPS_S = 1e-9


class LogRules:
    """Each step's logging rule, its own settings falling back to the recipe's."""

    def __init__(self, program: Program) -> None:
        base = program.log
        self._rules = tuple(
            (
                s.log.period_s if s.log.period_s is not None else base.period_s,
                s.log.delta_v if s.log.delta_v is not None else base.delta_v,
                s.log.delta_i if s.log.delta_i is not None else base.delta_i,
            )
            for s in program.steps
        )
        # Per step, for the running chain's steady scan (``ChainRunner.run``): the time
        # since the last record from which a record may be due, so that ``reason`` is asked
        # only then. With a period only, the right-hand side of ``reason``'s period test
        # (the period less float noise, the same float every scan): due exactly when that
        # test says so. With a ΔV or ΔI rule, -inf: asked every scan (the readings tell).
        # Without any rule, +inf: ``reason`` never finds one anyway.
        self.may_be_due_s: tuple[float, ...] = tuple(
            -math.inf
            if dv is not None or di is not None
            else math.inf
            if period is None
            else period - EPS_S
            for period, dv, di in self._rules
        )

    def reason(
        self, step_index: int, now: float, run: RunState, v: float | None, i: float | None
    ) -> str:
        """Why a sample is due now ("" when none is)."""
        period, dv, di = self._rules[step_index]
        if period is not None and now - run.last_rec_t >= period - EPS_S:
            return "period"
        # ΔV / ΔI: has the reading moved by the rule's delta since the last record? (Asked
        # every running scan: no call.)
        if dv is not None and v is not None:
            last = run.last_rec_v
            if last is not None and abs(v - last) >= dv:
                return "delta_v"
        if di is not None and i is not None:
            last = run.last_rec_i
            if last is not None and abs(i - last) >= di:
                return "delta_i"
        return ""


def build_record(
    port: ChannelPort,
    clock: Clock,
    now: float,
    run: RunState,
    step: CompiledStep,
    step_type: str,
    charge_ah: float,
    setpoint_a: float,
    reason: str,
) -> Record:
    """The channel as it is now, with the test's times and counters (BDF scopes)."""
    v, i = port.voltage, port.current
    p, t = port.power, port.temperature
    test0, cycle0 = run.test0, run.cycle0
    charged_ah = port.charged_ah.as_float()
    discharged_ah = port.discharged_ah.as_float()
    charged_wh = port.charged_wh.as_float()
    discharged_wh = port.discharged_wh.as_float()
    st = now - run.t_step0
    aux = port.record
    return Record(
        t=now,
        wall=clock.to_wall(now),
        test_time_s=now - run.t_test0,
        step_time_s=st,
        cycle_time_s=now - run.t_cycle0,
        cycle=run.cycle,
        step_count=run.step_count,
        step_index=step.index,
        step_id=step.id,
        step_type=step_type,
        voltage_v=v.as_float() if v.good else None,
        current_a=i.as_float() if i.good else None,
        power_w=p.as_float() if p.good else None,
        temperature_c=t.as_float() if t.good else None,
        charge_ah=charge_ah,
        charged_ah=charged_ah - test0.get("charged_ah", 0.0),
        discharged_ah=discharged_ah - test0.get("discharged_ah", 0.0),
        charged_wh=charged_wh - test0.get("charged_wh", 0.0),
        discharged_wh=discharged_wh - test0.get("discharged_wh", 0.0),
        cycle_charged_ah=charged_ah - cycle0.get("charged_ah", 0.0),
        cycle_discharged_ah=discharged_ah - cycle0.get("discharged_ah", 0.0),
        cycle_charged_wh=charged_wh - cycle0.get("charged_wh", 0.0),
        cycle_discharged_wh=discharged_wh - cycle0.get("discharged_wh", 0.0),
        setpoint_a=setpoint_a,
        step_remaining_s=(step.duration_s - st) if step.duration_s is not None else None,
        reason=reason,
        current_cmd_a=port.current_cmd.as_float(),
        last_voltage_v=v.as_float(),
        # Read in the scan of V and I; raw values (formatted on the row writer's thread).
        aux=tuple([t.value if t.good else None for t in aux]) if aux else (),
    )
