"""ADAM-5000/TCP point catalog: the one place for module facts (slots, module kinds, points).

Module channel counts and point names are decided here, once: the driver, the simulator,
the codec's address checks (:mod:`supervisor.devices.adam.protocol`) and the I/O map checks
(:mod:`supervisor.devices.adam.config`) all read this catalog. Plain data, no imports of its
siblings: the codec and the I/O map model both build on it. Facts come from devices.md
("ADAM-5000/TCP"); the uncertain ones are marked UNVERIFIED.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final, Literal

from supervisor.core.driver import PointInfo

SLOTS: Final = range(8)
"""ADAM-5000/TCP has 8 slots (0..7); the 5000L/TCP only 4 (0..3)."""

Family = Literal["analog", "thermocouple", "relay"]


@dataclass(frozen=True, slots=True)
class ModuleKind:
    """What one I/O module type offers."""

    kind: str
    points: int
    family: Family
    range_code: int | None = None
    """Input range code (shared with ADAM-4017/4018), for documentation and checks."""
    unit: str = ""


MODULE_KINDS: Final[Mapping[str, ModuleKind]] = MappingProxyType(
    {
        # 8 differential inputs, range 0x08 = ±10 V [V].
        "5017": ModuleKind("5017", 8, "analog", 0x08, "V"),
        # 7 thermocouple inputs, range 0x10 = type T, −100…+400 °C [V].
        "5018": ModuleKind("5018", 7, "thermocouple", 0x10, "degC"),
        # Relay counts UNVERIFIED (devices.md [U]): 5060 6 relays (2 form A + 4 form C),
        # 5069 8 power relays.
        "5060": ModuleKind("5060", 6, "relay"),
        "5069": ModuleKind("5069", 8, "relay"),
    }
)

MIN_POLL_PERIOD_5017_S: Final = 0.1
"""UNVERIFIED (devices.md [U]): the 5017 converts about 10 samples/s in total; polling
faster only re-reads old values and loads the unit. A slot may still be read faster on
purpose (its own ``poll_period_s``): for a level such as the e-stop sense (seed 002 §1.5),
re-reading is what we want, so that the supervisor sees a change as soon as the module has
converted it, not up to a whole slow poll period later."""


def slot_points(slot: int, kind: str) -> list[PointInfo]:
    """The points of the module ``kind`` in ``slot``: ``slot{n}.ai{k}`` (5017, V),
    ``slot{n}.tc{k}`` (5018, degC), ``slot{n}.do{k}`` and its read-back ``slot{n}.do{k}_fb``
    (relays)."""
    spec = MODULE_KINDS[kind]
    out: list[PointInfo] = []
    for ch in range(spec.points):
        where = f"slot {slot} ({kind}) channel {ch}"
        if spec.family == "analog":
            out.append(PointInfo(f"slot{slot}.ai{ch}", "in", "float", "V", where))
        elif spec.family == "thermocouple":
            desc = f"{where}, type T thermocouple"
            out.append(PointInfo(f"slot{slot}.tc{ch}", "in", "float", "degC", desc))
        else:
            out.append(PointInfo(f"slot{slot}.do{ch}", "out", "bool", "", f"{where} relay"))
            out.append(
                PointInfo(f"slot{slot}.do{ch}_fb", "in", "bool", "", f"{where} relay read back")
            )
    return out


def catalog(modules: Mapping[int, str]) -> dict[str, PointInfo]:
    """Every point of a unit with ``modules`` (slot → module kind), in slot order."""
    return {p.name: p for slot in sorted(modules) for p in slot_points(slot, modules[slot])}
