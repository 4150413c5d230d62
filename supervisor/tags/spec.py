"""Immutable description of a tag: type, unit, range, scaling, access, alarms, history."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum

from supervisor.core.driver import DType, Value


class Access(IntEnum):
    """Who may write a tag (ordered: a higher level may do what a lower one may)."""

    READ_ONLY = 0
    OPERATOR = 1
    ENGINEER = 2


@dataclass(frozen=True, slots=True)
class Scaling:
    """Linear raw → engineering units: ``eu = a·raw + b`` (also where calibration lands)."""

    a: float = 1.0
    b: float = 0.0

    def __post_init__(self) -> None:
        if self.a == 0 or not math.isfinite(self.a) or not math.isfinite(self.b):
            raise ValueError("scaling slope must be finite and non-zero (zero span)")

    def to_eu(self, raw: float) -> float:
        return self.a * raw + self.b

    def to_raw(self, eu: float) -> float:
        return (eu - self.b) / self.a

    @classmethod
    def from_spans(cls, raw: tuple[float, float], eu: tuple[float, float]) -> Scaling:
        """Two-point scaling, e.g. raw ±4 V ↔ eu ±300 A."""
        span = raw[1] - raw[0]
        if span == 0:
            raise ValueError("raw span is zero")
        a = (eu[1] - eu[0]) / span
        return cls(a=a, b=eu[0] - a * raw[0])


@dataclass(frozen=True, slots=True)
class AlarmLimits:
    """HH/H/L/LL limits with deadband and on-delay (evaluated by the safety layer)."""

    hh: float | None = None
    h: float | None = None
    l: float | None = None  # noqa: E741 - ISA-18.2 name
    ll: float | None = None
    deadband: float = 0.0
    delay_s: float = 0.0


@dataclass(frozen=True, slots=True)
class HistorySettings:
    """When a change is worth storing: absolute deadband and minimum interval."""

    enabled: bool = True
    deadband: float = 0.0
    min_interval_s: float = 0.0


@dataclass(frozen=True, slots=True)
class TagSpec:
    name: str
    dtype: DType = "float"
    unit: str = ""
    description: str = ""
    range: tuple[float, float] | None = None
    access: Access = Access.READ_ONLY
    scaling: Scaling | None = None
    retain: bool = False
    stale_after_s: float | None = None
    alarms: AlarmLimits | None = None
    history: HistorySettings = field(default_factory=HistorySettings)
    initial: Value | None = None
    choices: tuple[str, ...] | None = None  # allowed values of a str tag

    def coerce(self, value: Value) -> Value:
        """Convert a value to this tag's type; raises ValueError/TypeError if it cannot."""
        if self.dtype == "float":
            if isinstance(value, str):
                raise TypeError(f"{self.name}: expected a number, got {value!r}")
            return float(value)
        if self.dtype == "int":
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(f"{self.name}: expected an integer, got {value!r}")
            if isinstance(value, str):
                raise TypeError(f"{self.name}: expected an integer, got {value!r}")
            return int(value)
        if self.dtype == "bool":
            if isinstance(value, str):
                low = value.strip().lower()
                if low in ("1", "true", "on", "yes"):
                    return True
                if low in ("0", "false", "off", "no"):
                    return False
                raise ValueError(f"{self.name}: expected a boolean, got {value!r}")
            return bool(value)
        return str(value)
