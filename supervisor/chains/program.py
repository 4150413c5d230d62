"""A compiled recipe: what the step-chain engine executes (no YAML, no strings to parse)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

from supervisor.chains.expr import Expr
from supervisor.core.errors import ConfigError


class ActionKind(StrEnum):
    NEXT = "next"
    NEXT_CYCLE = "next_cycle"
    END = "end"
    GOTO = "goto"
    SLEEP_UNTIL = "sleep_until"
    SLEEP = "sleep"
    HOLD = "hold"


@dataclass(frozen=True, slots=True)
class Action:
    kind: ActionKind
    target: int | None = None  # step index for GOTO
    target_id: str | None = None
    hhmm: tuple[int, int] | None = None  # SLEEP_UNTIL
    seconds: float | None = None  # SLEEP

    def __str__(self) -> str:
        if self.kind is ActionKind.GOTO:
            return f"goto {self.target_id}"
        if self.kind is ActionKind.SLEEP_UNTIL and self.hhmm:
            return f"sleep until {self.hhmm[0]:02d}:{self.hhmm[1]:02d}"
        if self.kind is ActionKind.SLEEP:
            return f"sleep {self.seconds:g} s"
        return self.kind.value


@dataclass(frozen=True, slots=True)
class Transition:
    index: int  # 1-based position in the step's (or group's) until list
    text: str
    condition: Expr
    action: Action


@dataclass(frozen=True, slots=True)
class ProfilePoint:
    t_s: float
    current_a: float
    v_min: float | None = None
    v_max: float | None = None
    i_min: float | None = None
    i_max: float | None = None
    t_min: float | None = None
    t_max: float | None = None


@dataclass(frozen=True, slots=True)
class LogRule:
    period_s: float | None = None
    delta_v: float | None = None
    delta_i: float | None = None


@dataclass(frozen=True)
class CompiledStep:
    index: int
    id: str
    kind: str
    comment: str = ""
    # Setpoints (A, + charges; V; W).
    current_a: float = 0.0
    voltage_v: float | None = None
    power_w: float | None = None
    pulse_on_s: float = 0.0
    pulse_off_s: float = 0.0
    pulse_count: int = 0
    profile: tuple[ProfilePoint, ...] = ()
    profile_repeat: int = 1
    sleep_s: float | None = None
    sleep_until: tuple[int, int] | None = None
    goto: int | None = None
    # Ending and guarding.
    duration_s: float | None = None
    transitions: tuple[Transition, ...] = ()
    advance: Action | None = None
    interlock: Expr | None = None
    max_time_s: float | None = None
    error: Expr | None = None
    log: LogRule = field(default_factory=LogRule)
    groups: tuple[int, ...] = ()

    # What a kind is (instant, its BDF label) is said once, in ``supervisor.chains.kinds``.
    # Imported here, not at the top: the registry holds the behaviours, which hold steps.
    @property
    def instant(self) -> bool:
        """Takes no time: goto, end of cycle, end."""
        from supervisor.chains.kinds import kind_of

        return kind_of(self.kind).instant

    @property
    def step_type(self) -> str:
        """BDF step type label."""
        from supervisor.chains.kinds import kind_of

        return kind_of(self.kind).step_type(self)


@dataclass(frozen=True)
class CompiledGroup:
    index: int
    id: str
    steps: frozenset[int]
    duration_s: float | None
    transitions: tuple[Transition, ...]


@dataclass(frozen=True)
class Limits:
    voltage_v: tuple[float | None, float | None] = (None, None)
    current_a: tuple[float | None, float | None] = (None, None)
    temperature_c: tuple[float | None, float | None] = (None, None)
    delay_s: float = 0.0  # a crossing holds only once it has lasted this long


@dataclass(frozen=True)
class Program:
    name: str
    file: str
    steps: tuple[CompiledStep, ...]
    groups: tuple[CompiledGroup, ...]
    cycles: int
    limits: Limits
    parameters: dict[str, float]
    capacity_ah: float | None
    initial_charge_ah: float
    log: LogRule
    description: str = ""
    # What compiled but is likely a mistake, located (a parameter nothing reads):
    # ``supervisor check`` prints them.
    warnings: tuple[ConfigError, ...] = ()
