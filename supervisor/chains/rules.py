"""A running step's rules: what can hold the chain or end the step in a scan, in the order a
scan asks (ADR 0004, S7-GRAPH): the recipe's limits (and the step's own) with their
on-delay, the step's supervision, its interlock, its until conditions then its groups',
its own end, its duration, its groups' time limits.

One description, used by both of the chain's ways through a running scan (issue 29, 2): the
plain scan (``ChainRunner._running``) and the steady one (``ChainRunner.run``), which
differ only in what they know before asking (no fault, no command, no sleep pending).
The rules decide; the chain acts on what they answer (an alarm, an action).

``fast`` (``ChainRunner._fast``): ask a behaviour only what its class answers otherwise
than a rest step (derived in ``StepBehaviour.__init_subclass__``); False only in the tests
that check it against asking everything.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from supervisor.chains.behaviours import EPS_S, LimitCheck, StepBehaviour
from supervisor.chains.conditions import Values
from supervisor.chains.program import Action, ActionKind, CompiledStep, Program
from supervisor.chains.run import RunState
from supervisor.core.delay import OnDelay

NEXT = Action(ActionKind.NEXT)

Hit = tuple[Action, str]
"""An action to take and its cause, as the step's events name it."""
NOTHING: Hit | None = None


class StepRules:
    """The rules of a loaded program's steps, and the one state they keep between scans:
    the on-delay of the limits."""

    def __init__(self, program: Program) -> None:
        self.program = program
        lim = program.limits
        self.delay = OnDelay(lim.delay_s)
        # Whether the on-delay was last told of a violation (else telling it of none
        # changes nothing and is left out).
        self.timing = False
        # Only the limits with a bound: one without either never finds a violation.
        self.checks: tuple[LimitCheck, ...] = tuple(
            check
            for check in (
                ("voltage", lim.voltage_v, "V"),
                ("current", lim.current_a, "A"),
                ("temperature", lim.temperature_c, "degC"),
            )
            if check[1] != (None, None)
        )
        # ``x < lo or x > hi`` with a missing bound infinite is ``violation``'s answer for
        # every float x (NaN included: no comparison with it holds): a quick first look.
        self.bounds = tuple(
            (name, -math.inf if lo is None else lo, math.inf if hi is None else hi)
            for name, (lo, hi), _ in self.checks
        )

    @property
    def readings(self) -> frozenset[str]:
        """The readings the recipe's limits look at."""
        return frozenset(name for name, _, _ in self.checks)

    def hold(
        self,
        now: float,
        r: RunState,
        step: CompiledStep,
        behaviour: StepBehaviour,
        step_time_s: float,
        values: Values,
        armed: bool,
        fast: bool,
    ) -> str:
        """Why the chain must hold with a latched alarm ("" while nothing says so):

        - the recipe's limits and the step's own (a profile row's), armed once the power
          path is closed (the battery is what they are about), once a violation has lasted
          the on-delay;
        - S7-GRAPH supervision, halting the chain until acknowledged: the step's time
          limit (once per activation: an acknowledged one does not fire again), then its
          error condition.
        """
        why = ""
        if not armed:
            pass
        elif behaviour.has_limits or not fast:
            why = self.violation(values, step, behaviour.limits(step_time_s))
        else:
            for name, lo, hi in self.bounds:
                x = values[name]  # a reading: always in the values
                if isinstance(x, float) and (x < lo or x > hi):
                    why = self.violation(values, step, ())
                    break
        if why or self.timing:
            self.timing = bool(why)
            if self.delay.update(bool(why), now):
                return why
        if (
            step.max_time_s is not None
            and r.max_time_acked != r.step_count
            and step_time_s > step.max_time_s
        ):
            return f"supervision: step {step.id} exceeded {step.max_time_s:g} s"
        if step.error is not None and step.error.evaluate(values) is True:
            return f"supervision: {step.error.text}"
        return ""

    def violation(self, values: Values, step: CompiledStep, own: tuple[LimitCheck, ...]) -> str:
        """The first limit ``values`` cross, described ("" when none)."""
        for name, (lo, hi), unit in (*self.checks, *own) if own else self.checks:
            x = values.get(name)
            if not isinstance(x, float):
                continue
            if lo is not None and x < lo:
                return f"limit: {name} {x:.4g} {unit} below {lo:g} {unit} in step {step.id}"
            if hi is not None and x > hi:
                return f"limit: {name} {x:.4g} {unit} above {hi:g} {unit} in step {step.id}"
        return ""

    @staticmethod
    def interlock(step: CompiledStep, values: Values) -> str:
        """Why the step's outputs are held safe ("" while its interlock holds): they clear
        by themselves, and the transitions are still evaluated."""
        if step.interlock is None or step.interlock.evaluate(values) is True:
            return ""
        return f"interlock: {step.interlock.text}"

    def next(
        self,
        now: float,
        r: RunState,
        step: CompiledStep,
        behaviour: StepBehaviour,
        step_time_s: float,
        values: Values,
        fast: bool,
    ) -> tuple[Hit | None, float | None]:
        """What ends the step now, if anything, and a DC internal resistance the
        behaviour's scan work measured (None: none), in their order:

        - the first until condition that is true: the step's, then its groups';
        - the behaviour's scan work (a pulse's resistance), then its end of its own (ADR
          0004: after the conditions, before the duration);
        - the step's duration, its groups' time limits (which leave the group: on to the
          step after its last one).
        """
        for tr in step.transitions:
            try:  # ``tr.condition.evaluate(values)``, without the method call
                hit = tr.condition.fn(values)
            except ArithmeticError:
                hit = None
            if hit is True:
                return (tr.action, f"until #{tr.index}: {tr.text}"), None
        groups = step.groups
        if groups:
            group_hit = self._group_until(groups, values)
            if group_hit is not None:
                return group_hit, None
        resistance = None
        if behaviour.has_scan or not fast:
            v, i = values["voltage"], values["current"]
            resistance = behaviour.scan(
                step_time_s,
                v if isinstance(v, float) else None,
                i if isinstance(i, float) else None,
            )
        if behaviour.has_done or not fast:
            done = behaviour.done(step_time_s)
            if done:
                return (NEXT, done), resistance
        if step.duration_s is not None and step_time_s >= step.duration_s - EPS_S:
            return (NEXT, "duration elapsed"), resistance
        for g in groups:
            grp = self.program.groups[g]
            t0 = r.group_t0.get(g)
            if grp.duration_s is not None and t0 is not None and now - t0 >= grp.duration_s:
                goto = Action(ActionKind.GOTO, max(grp.steps) + 1)
                return (goto, f"group {grp.id} duration elapsed"), resistance
        return NOTHING, resistance

    def _group_until(self, groups: Sequence[int], values: Values) -> Hit | None:
        """The first until condition of the step's groups that is true (None: none)."""
        for g in groups:
            grp = self.program.groups[g]
            for tr in grp.transitions:
                if tr.condition.evaluate(values) is True:
                    return tr.action, f"group {grp.id} until #{tr.index}: {tr.text}"
        return None
