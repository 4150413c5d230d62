"""The step kinds: one registry, read by the compiler, the engine, the program and the dry run.

A kind is its name, the behaviour that runs it (``supervisor.chains.behaviours``) and what
the rest of the system must know of it:

- ``instant``: it takes no time (goto, end of cycle, end): it acts in the scan it starts;
- ``needs_cv``: the source must regulate a voltage (a board that only sources a current
  cannot run it: the compiler's capabilities);
- ``ends_itself``: it ends without a duration or an until condition. Derived: an instant
  kind, or one whose behaviour has an end of its own (``done``); said only for an end the
  behaviour does not see (``sleep_until``'s wake-up, set by the engine);
- ``label``: its BDF step type (``CompiledStep.step_type``).

What the running chain may skip for a kind (its fast paths) is derived from its behaviour
class, not said here (``StepBehaviour.__init_subclass__``): a kind that says nothing runs
the plain way. A new kind is one behaviour class plus one ``register`` line below (and its
field in the recipe model, ``supervisor.config.recipe``); every registered kind enters the
fast-versus-plain equivalence test (``tests/unit/test_step_kinds_equivalence.py``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

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
    StepBehaviour,
)
from supervisor.chains.program import CompiledStep


@dataclass(frozen=True)
class StepKind:
    name: str
    behaviour: type[StepBehaviour]
    label: str | Callable[[CompiledStep], str] | None = None
    """The BDF step type: a text, or one computed from the step (a pulse's sign); None:
    the name in capitals."""
    instant: bool = False
    needs_cv: bool = False
    ends_itself: bool = False
    """An end the behaviour does not see; see ``ends_by_itself``."""

    @property
    def ends_by_itself(self) -> bool:
        """It ends without a duration or an until condition (else a step of it must have
        one: the compiler refuses a step that never ends)."""
        return self.ends_itself or self.instant or self.behaviour.has_done

    def step_type(self, step: CompiledStep) -> str:
        label = self.label
        if label is None:
            return self.name.upper()
        return label if isinstance(label, str) else label(step)


KINDS: dict[str, StepKind] = {}
"""Every step kind by name, in the order registered."""


def register(kind: StepKind) -> StepKind:
    if kind.name in KINDS:
        raise ValueError(f"step kind {kind.name!r} is registered already")
    KINDS[kind.name] = kind
    return kind


def kind_of(name: str) -> StepKind:
    try:
        return KINDS[name]
    except KeyError:
        raise ValueError(f"no behaviour for step kind {name!r}") from None


def kind_names(*, cv: bool = True) -> frozenset[str]:
    """The kinds a source can run: every one, or (``cv`` False) those that need no
    constant voltage."""
    return frozenset(k.name for k in KINDS.values() if cv or not k.needs_cv)


def behaviour_for(step: CompiledStep) -> StepBehaviour:
    try:
        kind = kind_of(step.kind)
    except ValueError as exc:
        raise ValueError(f"step {step.id!r}: {exc}") from None
    return kind.behaviour(step)


def behaviours_for(steps: Iterable[CompiledStep]) -> tuple[StepBehaviour, ...]:
    return tuple(behaviour_for(s) for s in steps)


def _sign(
    positive: str, negative: str, value: Callable[[CompiledStep], float]
) -> Callable[[CompiledStep], str]:
    return lambda step: positive if value(step) > 0 else negative


for _kind in (
    StepKind("rest", Rest, "REST"),
    StepKind("sleep", Sleep, "REST"),
    StepKind("sleep_until", SleepUntil, "REST", ends_itself=True),
    # The kind says it, even at 0 A.
    StepKind("charge", ConstantCurrent, "CC_CHG"),
    StepKind("discharge", ConstantCurrent, "CC_DCH"),
    StepKind("cv", ConstantVoltage, "CV_CHG", needs_cv=True),
    StepKind("cccv", ConstantVoltage, "CCCV_CHG", needs_cv=True),
    StepKind("power", ConstantPower, _sign("CP_CHG", "CP_DCH", lambda s: s.power_w or 0.0)),
    StepKind("pulse", Pulse, _sign("CC_CHG", "CC_DCH", lambda s: s.current_a)),
    StepKind("profile", Profile, "PROFILE"),
    StepKind("goto", Goto, instant=True),
    StepKind("end_cycle", EndCycle, instant=True),
    StepKind("end", End, instant=True),
):
    register(_kind)
