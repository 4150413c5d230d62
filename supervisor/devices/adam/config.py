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

from pydantic import Field, field_validator, model_validator

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
faster only re-reads old values and loads the unit. A slot may still be read faster on
purpose (its own ``poll_period_s``): for a level such as the e-stop sense (seed 002 §1.5),
re-reading is what we want, so that the supervisor sees a change as soon as the module has
converted it, not up to a whole slow poll period later."""

HOST_WATCHDOG_POLL_RATIO: Final = 3.0
"""``host_watchdog_s`` must be at least this many (fastest) poll periods: every poll is the
keep-alive, it must come well within the unit's timeout (as for the EA's watchdog)."""


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
    poll_period_s: float | None = Field(
        None,
        gt=0,
        le=10,
        description="read this slot this often (default: the device's poll_period_s); a"
        " safety input (the e-stop sense) at the scan rate, thermocouples slower",
    )


class AdamDevice(NetworkDevice):
    """ADAM-5000/TCP over Modbus TCP (seed 002 §1.1): modules by slot."""

    driver: Literal["adam5000tcp"]
    port: int = Field(502, ge=1, le=65535)
    unit_id: int = Field(1, ge=0, le=255)
    modules: dict[int, AdamModuleConfig] = Field(min_length=1)
    host_watchdog_s: float | None = Field(
        None,
        gt=0,
        description="arm the unit's host (communication) watchdog: with no request for this"
        " long it switches every relay off (the contactor opens when the supervisor dies);"
        " null: not armed",
    )

    @field_validator("modules")
    @classmethod
    def _slots(cls, v: dict[int, AdamModuleConfig]) -> dict[int, AdamModuleConfig]:
        for slot in v:
            if slot not in SLOTS:
                raise ValueError(f"slot {slot} does not exist (ADAM-5000/TCP slots are 0..7)")
        return v

    def slot_period_s(self, slot: int) -> float:
        """How often ``slot`` is read."""
        own = self.modules[slot].poll_period_s
        return self.poll_period_s if own is None else own

    @property
    def fastest_period_s(self) -> float:
        """The driver's own poll period: its fastest slot's."""
        return min(self.slot_period_s(slot) for slot in self.modules)

    @model_validator(mode="after")
    def _periods(self) -> AdamDevice:
        for slot in self.modules:
            if self.slot_period_s(slot) >= self.stale_after_s:
                raise ValueError(
                    f"slot {slot} is read every {self.slot_period_s(slot):g} s, not faster than"
                    f" stale_after_s ({self.stale_after_s:g} s): its values would read stale"
                )
        if self.host_watchdog_s is not None:
            # Imported here: the codec imports this catalog.
            from supervisor.devices.adam.protocol import host_watchdog_counts

            host_watchdog_counts(self.host_watchdog_s)  # ValueError names what is wrong
            fastest = self.fastest_period_s
            if self.host_watchdog_s < HOST_WATCHDOG_POLL_RATIO * fastest - 1e-9:
                raise ValueError(
                    f"host_watchdog_s ({self.host_watchdog_s:g}) must be at least"
                    f" {HOST_WATCHDOG_POLL_RATIO:g} x the fastest poll period ({fastest:g} s)"
                    " so the keep-alive beats the unit's timeout"
                )
        return self

    def points(self) -> Mapping[str, PointInfo]:
        return catalog({slot: m.kind for slot, m in self.modules.items()})
