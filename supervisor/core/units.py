"""Quantities with units, as engineers write them in recipes: ``4.2 V``, ``300 mA``, ``20 min``.

Internally every value is in one base unit per dimension: V, A, s, Ah, Wh, W, degC,
ohm, V/s. A C-rate (``0.5 C``) is a current relative to the rated capacity and is
resolved to amperes only when a capacity is known.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from enum import StrEnum


class Dim(StrEnum):
    NONE = "dimensionless"
    VOLTAGE = "voltage"
    CURRENT = "current"
    TIME = "time"
    CHARGE = "charge"
    ENERGY = "energy"
    POWER = "power"
    TEMPERATURE = "temperature"
    RESISTANCE = "resistance"
    VOLTAGE_RATE = "voltage rate"
    C_RATE = "C-rate"
    BOOL = "boolean"


# unit symbol → (dimension, factor to the base unit)
UNITS: dict[str, tuple[Dim, float]] = {
    "V": (Dim.VOLTAGE, 1.0),
    "mV": (Dim.VOLTAGE, 1e-3),
    "kV": (Dim.VOLTAGE, 1e3),
    "A": (Dim.CURRENT, 1.0),
    "mA": (Dim.CURRENT, 1e-3),
    "uA": (Dim.CURRENT, 1e-6),
    "s": (Dim.TIME, 1.0),
    "ms": (Dim.TIME, 1e-3),
    "min": (Dim.TIME, 60.0),
    "h": (Dim.TIME, 3600.0),
    "d": (Dim.TIME, 86400.0),
    "Ah": (Dim.CHARGE, 1.0),
    "mAh": (Dim.CHARGE, 1e-3),
    "As": (Dim.CHARGE, 1 / 3600),
    "C": (Dim.C_RATE, 1.0),
    "Wh": (Dim.ENERGY, 1.0),
    "mWh": (Dim.ENERGY, 1e-3),
    "kWh": (Dim.ENERGY, 1e3),
    "W": (Dim.POWER, 1.0),
    "mW": (Dim.POWER, 1e-3),
    "kW": (Dim.POWER, 1e3),
    "degC": (Dim.TEMPERATURE, 1.0),
    "°C": (Dim.TEMPERATURE, 1.0),
    "ohm": (Dim.RESISTANCE, 1.0),
    "mohm": (Dim.RESISTANCE, 1e-3),
    "Ω": (Dim.RESISTANCE, 1.0),
    "mΩ": (Dim.RESISTANCE, 1e-3),
    "V/s": (Dim.VOLTAGE_RATE, 1.0),
    "mV/s": (Dim.VOLTAGE_RATE, 1e-3),
    "mV/min": (Dim.VOLTAGE_RATE, 1e-3 / 60),
    "V/h": (Dim.VOLTAGE_RATE, 1 / 3600),
}

BASE_UNIT: dict[Dim, str] = {
    Dim.NONE: "",
    Dim.VOLTAGE: "V",
    Dim.CURRENT: "A",
    Dim.TIME: "s",
    Dim.CHARGE: "Ah",
    Dim.ENERGY: "Wh",
    Dim.POWER: "W",
    Dim.TEMPERATURE: "degC",
    Dim.RESISTANCE: "ohm",
    Dim.VOLTAGE_RATE: "V/s",
    Dim.C_RATE: "C",
    Dim.BOOL: "",
}

# ASCII digits only: ``\d`` (and ``float()``) take any Unicode digit, so ``٣ s`` or ``３ V``
# would be read as 3 (issue 9; the mutation corpus, tests/mutation.py, found it).
_QUANTITY = re.compile(
    r"^\s*(?P<num>[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?)\s*(?P<unit>[A-Za-zΩ°µ/]+)?\s*$"
)
# A number with a non-zero digit before its exponent: ``1e-400`` is not zero, it underflows.
_NONZERO_MANTISSA = re.compile(r"^[-+]?0*\.?0*[1-9]")


class UnitError(ValueError):
    """A quantity that does not parse or has the wrong dimension."""


@dataclass(frozen=True, slots=True)
class Quantity:
    value: float  # in the dimension's base unit
    dim: Dim

    def __str__(self) -> str:
        return f"{self.value:g} {BASE_UNIT[self.dim]}".strip()

    def to_current_a(self, capacity_ah: float | None) -> float:
        """A current or a C-rate as amperes."""
        if self.dim is Dim.CURRENT:
            return self.value
        if self.dim is Dim.C_RATE:
            if capacity_ah is None:
                raise UnitError(f"{self}: a C-rate needs the rated capacity (capacity_ah)")
            return self.value * capacity_ah
        raise UnitError(f"{self} is a {self.dim}, not a current")


def parse_quantity(
    text: str | float | int, expect: Dim | tuple[Dim, ...] | None = None
) -> Quantity:
    """Parse ``"4.2 V"``, ``"300 mA"``, ``"0.5 C"``; a bare number is dimensionless.

    ``expect`` restricts the accepted dimensions; a bare number is accepted for one
    expected dimension and taken in its base unit only if that is ``Dim.NONE``.
    """
    if isinstance(text, bool):
        raise UnitError(f"expected a quantity, got {text!r}")
    if isinstance(text, int | float):
        q = Quantity(float(text), Dim.NONE)
    else:
        m = _QUANTITY.match(text.replace("µ", "u"))
        if not m:
            raise UnitError(f"{text!r} is not a number with a unit (e.g. '4.2 V', '300 mA')")
        unit = m.group("unit")
        num = float(m.group("num"))
        if num == 0.0 and _NONZERO_MANTISSA.match(m.group("num")):
            # A command-line parameter (--param x=1e-400V) as much as a recipe's value.
            raise UnitError(
                f"{text!r} is too small to be told from zero: write 0 or a larger value"
            )
        if unit is None:
            q = Quantity(num, Dim.NONE)
        else:
            if unit not in UNITS:
                known = ", ".join(sorted(UNITS, key=str.lower))
                raise UnitError(f"unknown unit {unit!r} in {text!r} (known: {known})")
            dim, factor = UNITS[unit]
            q = Quantity(num * factor, dim)
    if not math.isfinite(q.value):
        raise UnitError(f"{text!r} is not finite")
    if expect is not None:
        dims = (expect,) if isinstance(expect, Dim) else expect
        if q.dim not in dims:
            want = " or ".join(f"a {d} (e.g. {_example(d)})" for d in dims)
            if q.dim is Dim.NONE:
                raise UnitError(f"{text!r} needs a unit: expected {want}")
            raise UnitError(f"{text!r} is a {q.dim}; expected {want}")
    return q


def _example(d: Dim) -> str:
    return {
        Dim.VOLTAGE: "4.2 V",
        Dim.CURRENT: "300 mA",
        Dim.TIME: "20 min",
        Dim.CHARGE: "1300 mAh",
        Dim.ENERGY: "5 Wh",
        Dim.POWER: "10 W",
        Dim.TEMPERATURE: "45 degC",
        Dim.RESISTANCE: "50 mohm",
        Dim.VOLTAGE_RATE: "1 mV/min",
        Dim.C_RATE: "0.5 C",
        Dim.NONE: "3",
        Dim.BOOL: "true",
    }[d]
