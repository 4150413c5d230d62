"""Step behaviours: what each kind of step asks for and when it is done by itself.

One class per step kind or family, chosen once per step when a program is loaded
(``behaviours_for``), so the scan never switches on a kind name. Each answers:

- ``setpoint(step_time_s, voltage_v)``: the current it asks for now (A, + charges, BDF);
- ``cv_target_v``: the constant-voltage target it asks of the source (V, 0: none);
- ``done(step_time_s)``: why it ended by itself ("" while it goes on): the end of a
  pulse train, a profile, a sleep (ADR 0004: after the conditions, before the duration);
- ``limits(step_time_s)``: limits of its own on top of the recipe's (a profile row's);
- ``enter(voltage_v, current_a)`` / ``scan(step_time_s, voltage_v, current_a)``: work at
  activation and every running scan (the pulse's DC internal resistance);
- ``entry``: for an instant step, what it does in the scan it is entered (ADR 0004).

Readings are None when their tag is not GOOD.

What the running chain's fast paths may skip is *derived* from each class, never a flag a
new kind must remember to set (issue 29: a constant-resistance step that inherited "my
setpoint is a constant" drove 0 A in the dry run): a behaviour is asked for its limits,
scan work and end when its class overrides those methods, and its setpoint is taken as a
constant only when the class that defines ``setpoint`` says so (``setpoint_reads``). A
class that says nothing gets the plain path. The kinds themselves are registered in
``supervisor.chains.kinds``.
"""

from __future__ import annotations

from bisect import bisect_right
from typing import Any, ClassVar

from supervisor.chains.program import Action, ActionKind, CompiledStep, ProfilePoint

EPS_S = 1e-9  # a time reached up to float noise counts as reached
# A power step divides by the voltage: below this the cell is as good as shorted or
# disconnected and the step asks for nothing rather than a huge current.
MIN_POWER_VOLTAGE_V = 0.05

# (variable, (low, high), unit) as the recipe-limit check reads it.
LimitCheck = tuple[str, tuple[float | None, float | None], str]

READINGS = frozenset({"voltage", "current", "temperature"})
"""The channel readings a behaviour's ``scan`` and ``limits`` may look at in the values."""


def overrides(cls: type[StepBehaviour], method: str) -> bool:
    """Whether ``cls`` answers ``method`` otherwise than a rest step (the base class)."""
    return getattr(cls, method) is not getattr(StepBehaviour, method)


def declared(cls: type[StepBehaviour], name: str, methods: tuple[str, ...]) -> Any:
    """The class attribute ``name`` of ``cls`` when it was set by a class at or below every
    class that defines one of ``methods`` (a declaration about code it sees); None
    otherwise. A subclass that overrides ``setpoint`` and inherits ``setpoint_reads``
    from above has said nothing about its own setpoint."""
    mro = cls.__mro__
    at = next((k for k, c in enumerate(mro) if name in vars(c)), None)
    if at is None:
        return None
    for method in methods:
        defined = next((k for k, c in enumerate(mro) if method in vars(c)), None)
        if defined is not None and defined < at:
            return None
    return vars(mro[at])[name]


class StepBehaviour:
    """A step that asks for no current and ends by its duration or conditions (rest)."""

    cv_target_v: float = 0.0
    # The current against which progress is measured (a CC step: charge moved over the
    # rated capacity, seed 001's progress bar); None for steps without one.
    progress_current_a: float | None = None
    entry: Action | None = None
    # What the behaviour needs, said by the class that defines the method concerned (see
    # ``declared``; not said: the plain path).
    setpoint_reads: ClassVar[frozenset[str] | None] = frozenset()
    """What ``setpoint`` depends on: ``step_time``, ``voltage``; empty: a constant, asked
    once at load (a rest step's 0 A)."""
    reads: ClassVar[frozenset[str] | None] = frozenset()
    """The readings (``READINGS``) ``scan`` and ``limits`` look at."""
    # Derived for each class (``__init_subclass__``), for the running scan (issue 13: one
    # call fewer each for the many steps that answer as a rest step does): whether it must
    # ask ``limits``, ``scan``, ``done``, whether the setpoint must be asked every scan,
    # and the readings the values must hold for this behaviour.
    has_limits: ClassVar[bool] = False
    has_scan: ClassVar[bool] = False
    has_done: ClassVar[bool] = False
    setpoint_varies: ClassVar[bool] = False
    readings: ClassVar[frozenset[str]] = frozenset()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.has_limits = overrides(cls, "limits")
        cls.has_scan = overrides(cls, "scan")
        cls.has_done = overrides(cls, "done")
        cls.setpoint_varies = declared(cls, "setpoint_reads", ("setpoint",)) != frozenset()
        reads = declared(cls, "reads", ("scan", "limits"))
        if cls.has_scan or cls.has_limits:
            cls.readings = READINGS if reads is None else frozenset(reads)
        else:
            cls.readings = frozenset()

    def __init__(self, step: CompiledStep) -> None:
        self.step = step
        self.step_type = step.step_type  # BDF label, fixed for the step

    def setpoint(self, step_time_s: float, voltage_v: float | None) -> float:
        return 0.0

    def done(self, step_time_s: float) -> str:
        return ""

    def limits(self, step_time_s: float) -> tuple[LimitCheck, ...]:
        return ()

    def enter(self, voltage_v: float | None, current_a: float | None) -> None:
        """The step is activated (again): forget what the last activation measured."""

    def scan(
        self, step_time_s: float, voltage_v: float | None, current_a: float | None
    ) -> float | None:
        """Per-scan work while running; returns a DC internal resistance (ohm) when one
        was just measured."""
        return None


class Rest(StepBehaviour):
    """Rest / OCV: no current, ends by its duration or conditions."""


class Sleep(StepBehaviour):
    """Chadèche's timed sleep (``+HH:MM`` as a step): no current for ``sleep_s``."""

    def done(self, step_time_s: float) -> str:
        s = self.step.sleep_s
        return "sleep done" if s is not None and step_time_s >= s - EPS_S else ""


class ConstantCurrent(StepBehaviour):
    """CC charge or discharge at the step's current."""

    setpoint_reads = frozenset()

    def __init__(self, step: CompiledStep) -> None:
        super().__init__(step)
        self.progress_current_a = step.current_a

    def setpoint(self, step_time_s: float, voltage_v: float | None) -> float:
        return self.step.current_a


class ConstantVoltage(StepBehaviour):
    """CV with a current limit, or CC-CV as one step: the source regulates the voltage,
    the chain asks for the current (limit) and the CV target."""

    setpoint_reads = frozenset()

    def __init__(self, step: CompiledStep) -> None:
        super().__init__(step)
        if step.voltage_v is not None:
            self.cv_target_v = step.voltage_v

    def setpoint(self, step_time_s: float, voltage_v: float | None) -> float:
        return self.step.current_a


class ConstantPower(StepBehaviour):
    """CP regulated in software: I = P / V from the last GOOD voltage."""

    setpoint_reads = frozenset({"voltage"})

    def setpoint(self, step_time_s: float, voltage_v: float | None) -> float:
        p = self.step.power_w
        if p is None or voltage_v is None or voltage_v <= MIN_POWER_VOLTAGE_V:
            return 0.0
        return p / voltage_v


class Pulse(StepBehaviour):
    """A train of ``pulse_count`` pulses (``pulse_on_s`` at the current, ``pulse_off_s``
    at rest), measuring the DC internal resistance of each pulse."""

    setpoint_reads = frozenset({"step_time"})
    reads = frozenset({"voltage", "current"})

    def __init__(self, step: CompiledStep) -> None:
        super().__init__(step)
        self.period_s = step.pulse_on_s + step.pulse_off_s
        self._on: bool | None = None
        self._rest_vi: tuple[float, float] | None = None
        self._on_vi: tuple[float, float] | None = None
        self._start_vi: tuple[float, float] | None = None

    def setpoint(self, step_time_s: float, voltage_v: float | None) -> float:
        period = self.period_s
        if period > 0 and (step_time_s % period) < self.step.pulse_on_s:
            return self.step.current_a
        return 0.0

    def done(self, step_time_s: float) -> str:
        period = self.period_s
        if period > 0 and step_time_s >= period * self.step.pulse_count - EPS_S:
            return "pulses done"
        return ""

    def enter(self, voltage_v: float | None, current_a: float | None) -> None:
        # DCIR reference: the last reading before the step's first pulse.
        self._on, self._on_vi, self._start_vi = False, None, None
        self._rest_vi = (
            (voltage_v, current_a) if voltage_v is not None and current_a is not None else None
        )

    def scan(
        self, step_time_s: float, voltage_v: float | None, current_a: float | None
    ) -> float | None:
        """DC internal resistance: R = ΔV/ΔI between the last sample at rest before a pulse
        and the last sample under current at its end (the usual DCIR definition)."""
        period = self.period_s
        if period <= 0 or voltage_v is None or current_a is None:
            return None
        step = self.step
        on = (step_time_s % period) < step.pulse_on_s and step_time_s < period * step.pulse_count
        measured = None
        if on and self._on is False and self._rest_vi is not None:
            self._start_vi = self._rest_vi
        if not on and self._on is True and self._start_vi is not None and self._on_vi is not None:
            dv = self._on_vi[0] - self._start_vi[0]
            di = self._on_vi[1] - self._start_vi[1]
            if abs(di) > 1e-6:
                measured = dv / di
        if on:
            self._on_vi = (voltage_v, current_a)
        else:
            self._rest_vi = (voltage_v, current_a)
        self._on = on
        return measured


class Profile(StepBehaviour):
    """A drive-cycle profile (seed 002): rows of time and current, each with its own
    V/I/T window, repeated ``profile_repeat`` times."""

    setpoint_reads = frozenset({"step_time"})
    reads = READINGS

    def __init__(self, step: CompiledStep) -> None:
        super().__init__(step)
        self.rows = step.profile
        self.period_s = step.profile[-1].t_s if step.profile else 0.0
        # Row start times, strictly increasing (the recipe model and the CSV reader check).
        self._starts = [p.t_s for p in step.profile]

    def row(self, step_time_s: float) -> ProfilePoint | None:
        """The row in force at ``step_time_s`` (the last one started). A binary search: a
        profile may have 100 000 rows and this runs every scan (issue 9)."""
        total = self.period_s
        t = step_time_s % total if total > 0 else 0.0
        k = bisect_right(self._starts, t + EPS_S)
        return self.rows[k - 1] if k else None

    def setpoint(self, step_time_s: float, voltage_v: float | None) -> float:
        row = self.row(step_time_s)
        return row.current_a if row is not None else 0.0

    def done(self, step_time_s: float) -> str:
        if self.rows and step_time_s >= self.period_s * self.step.profile_repeat - EPS_S:
            return "profile done"
        return ""

    def limits(self, step_time_s: float) -> tuple[LimitCheck, ...]:
        row = self.row(step_time_s)
        if row is None:
            return ()
        return (
            ("voltage", (row.v_min, row.v_max), "V"),
            ("current", (row.i_min, row.i_max), "A"),
            ("temperature", (row.t_min, row.t_max), "degC"),
        )


class Goto(StepBehaviour):
    """An instant jump to another step."""

    def __init__(self, step: CompiledStep) -> None:
        super().__init__(step)
        if step.goto is not None:
            self.entry = Action(ActionKind.GOTO, step.goto)


class EndCycle(StepBehaviour):
    """An instant end of the cycle (the next one starts, or the test completes)."""

    entry = Action(ActionKind.NEXT_CYCLE)


class End(StepBehaviour):
    """An instant end of the test."""

    entry = Action(ActionKind.END)


class SleepUntil(StepBehaviour):
    """No current until the next local HH:MM (Chadèche's sleep action as a step); the
    wake-up time is set in the scan the step is entered."""

    def __init__(self, step: CompiledStep) -> None:
        super().__init__(step)
        if step.sleep_until is not None:
            self.entry = Action(ActionKind.SLEEP_UNTIL, hhmm=step.sleep_until)
