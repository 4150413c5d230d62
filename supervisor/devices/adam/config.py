"""ADAM-5000/TCP: the I/O map entry (``supervisor check`` reads it).

Module facts are the point catalog's (:mod:`supervisor.devices.adam.catalog`), register facts
the codec's (:mod:`supervisor.devices.adam.protocol`); this model checks an I/O map against
both.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Final, Literal

from pydantic import Field, field_validator, model_validator

from supervisor.config.models import NetworkDevice, Strict
from supervisor.core.driver import PointInfo
from supervisor.devices.adam.catalog import SLOTS, catalog
from supervisor.devices.adam.protocol import host_watchdog_counts

HOST_WATCHDOG_POLL_RATIO: Final = 3.0
"""``host_watchdog_s`` must be at least this many (fastest) poll periods: every poll is the
keep-alive, it must come well within the unit's timeout (as for the EA's watchdog)."""


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
