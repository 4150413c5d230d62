"""Engineering units as OPC UA clients read them (Part 8 §5.6.3, ``EUInformation``): the
UNECE Recommendation 20 common code of a tag's unit, packed into an Int32 ``UnitId``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Final

from asyncua import ua

UNECE_NAMESPACE: Final = "http://www.opcfoundation.org/UA/units/un/cefact"

# Tag unit → (UNECE common code, description). The project's base units first
# (supervisor/core/units.py), then the prefixed ones an I/O map may use.
UNECE_CODES: Final[Mapping[str, tuple[str, str]]] = {
    "V": ("VLT", "volt"),
    "A": ("AMP", "ampere"),
    "degC": ("CEL", "degree Celsius"),
    "°C": ("CEL", "degree Celsius"),
    "Ah": ("AMH", "ampere hour"),
    "Wh": ("WHR", "watt hour"),
    "s": ("SEC", "second"),
    "W": ("WTT", "watt"),
    "ohm": ("OHM", "ohm"),
    "Ω": ("OHM", "ohm"),
    "1": ("C62", "one"),
    "%": ("P1", "percent"),
    "mV": ("2Z", "millivolt"),
    "kV": ("KVT", "kilovolt"),
    "mA": ("4K", "milliampere"),
    "ms": ("C26", "millisecond"),
    "min": ("MIN", "minute"),
    "h": ("HUR", "hour"),
    "kW": ("KWT", "kilowatt"),
    "kWh": ("KWH", "kilowatt hour"),
    "K": ("KEL", "kelvin"),
    "Hz": ("HTZ", "hertz"),
}

NO_UNIT_ID: Final = -1
"""Part 8: UnitId -1 when the unit has no UNECE code."""


def unit_id(code: str) -> int:
    """The UnitId of a UNECE common code: its ASCII letters packed into an Int32, first
    letter highest (Part 8 §5.6.3): ``VLT`` → 5655636."""
    uid = 0
    for c in code:
        uid = (uid << 8) | ord(c)
    return uid


def eu_information(unit: str) -> ua.EUInformation:
    """The ``EngineeringUnits`` property value of a tag in ``unit``."""
    known = UNECE_CODES.get(unit)
    shown = "°C" if unit == "degC" else unit
    if known is None:
        return ua.EUInformation(
            NamespaceUri=UNECE_NAMESPACE,
            UnitId=NO_UNIT_ID,
            DisplayName=ua.LocalizedText(shown),
            Description=ua.LocalizedText(shown),
        )
    code, description = known
    return ua.EUInformation(
        NamespaceUri=UNECE_NAMESPACE,
        UnitId=unit_id(code),
        DisplayName=ua.LocalizedText(shown),
        Description=ua.LocalizedText(description),
    )
