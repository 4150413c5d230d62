"""Immutable description of a tag: type, unit, range, scaling, access, alarms, history."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Final

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

    def coerce(self, value: object) -> Value:
        """Convert a value written by a person or client to this tag's type, strictly.

        A boolean is not a number, a number is not a boolean, numbers are finite, and a
        text is only a text (a bool tag also takes ``"true"``/``"false"``, ``"on"``/``"off"``,
        ``"1"``/``"0"``, as typed on a command line). Raises ``TypeError``/``ValueError``
        whose message names the tag and shows what was received as JSON writes it.
        """
        if self.dtype == "float":
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise TypeError(f"{self.name}: expected a number, got {shown(value)}")
            number = finite_float(value)
            if number is None:
                raise ValueError(f"{self.name}: expected a finite number, got {shown(value)}")
            return number
        if self.dtype == "int":
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise TypeError(f"{self.name}: expected an integer, got {shown(value)}")
            if isinstance(value, float) and not (math.isfinite(value) and value.is_integer()):
                raise ValueError(f"{self.name}: expected an integer, got {shown(value)}")
            return int(value)
        if self.dtype == "bool":
            if isinstance(value, bool):
                return value
            if isinstance(value, str):
                low = value.strip().lower()
                if low in ("1", "true", "on", "yes"):
                    return True
                if low in ("0", "false", "off", "no"):
                    return False
            raise ValueError(f"{self.name}: expected a boolean, got {shown(value)}")
        if not isinstance(value, str):
            raise TypeError(f"{self.name}: expected a text, got {shown(value)}")
        return value


SHOWN_MAX_CHARS: Final = 40
"""How much of a received value a message repeats."""


def finite_float(value: int | float) -> float | None:
    """``float(value)`` when that is a finite number, else None (NaN, ±inf, or an integer
    too large for a float, which ``float()`` answers with ``OverflowError``)."""
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def clipped_repr(value: object) -> str:
    """``repr(value)``, but a long text or list clipped and a huge integer by its size
    (``repr`` of 5000 digits raises ``ValueError``; of 400 it floods the message)."""
    if isinstance(value, int) and not isinstance(value, bool):
        return shown(value)
    text = repr(value) if not isinstance(value, str) else repr(value[: SHOWN_MAX_CHARS + 1])
    return text if len(text) <= SHOWN_MAX_CHARS + 2 else text[:SHOWN_MAX_CHARS] + "…"


def shown(value: object) -> str:
    """A received value as a message shows it: as JSON writes it (``true``, ``null``, a
    list or object by its kind), a long text or number clipped — never Python's words
    (``None``, ``'NoneType'``) nor thousands of digits."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        digits = value.bit_length() * 0.30103  # log10(2): the size without str() of it all
        if digits > SHOWN_MAX_CHARS:
            return f"an integer of about {int(digits) + 1} digits"
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        if math.isinf(value):
            return "Infinity" if value > 0 else "-Infinity"
        return repr(value)
    if isinstance(value, str):
        text = value if len(value) <= SHOWN_MAX_CHARS else value[:SHOWN_MAX_CHARS] + "…"
        return repr(text)
    if isinstance(value, list | tuple):
        return f"a list of {len(value)}" if value else "an empty list"
    if isinstance(value, dict):
        return "an object"
    return f"a {type(value).__name__}"
