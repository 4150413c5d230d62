"""ADAM-5000/TCP: the I/O map entry, and the point catalog (the one place for module facts).

Module channel counts and point names are decided here, once: the driver, the simulator,
the codec's address checks and ``supervisor check`` all read this catalog. Facts come from
``shared/reference/devices.md`` ("ADAM-5000/TCP"); the uncertain ones are marked UNVERIFIED.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final, Literal

from pydantic import Field, field_validator

from supervisor.config.models import NetworkDevice, Strict
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
faster only re-reads old values and loads the unit."""


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


class AdamModuleConfig(Strict):
    kind: Literal["5017", "5018", "5060", "5069"]
    raw_format: Literal["offset", "twos"] = "offset"


class AdamDevice(NetworkDevice):
    """ADAM-5000/TCP over Modbus TCP (seed 002 §1.1): modules by slot."""

    driver: Literal["adam5000tcp"]
    port: int = Field(502, ge=1, le=65535)
    unit_id: int = Field(1, ge=0, le=255)
    modules: dict[int, AdamModuleConfig] = Field(min_length=1)

    @field_validator("modules")
    @classmethod
    def _slots(cls, v: dict[int, AdamModuleConfig]) -> dict[int, AdamModuleConfig]:
        for slot in v:
            if slot not in SLOTS:
                raise ValueError(f"slot {slot} does not exist (ADAM-5000/TCP slots are 0..7)")
        return v

    def points(self) -> Mapping[str, PointInfo]:
        return catalog({slot: m.kind for slot, m in self.modules.items()})
