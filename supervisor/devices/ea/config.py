"""EA-PSB 10000: the I/O map entry, and the point catalog (the one place for its points).

The driver, the simulator and ``supervisor check`` read these points from here. Protocol
facts (SCPI headers, status bits, the unverified ones marked) are in
:mod:`supervisor.devices.ea.protocol`.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import ClassVar, Final, Literal

from pydantic import Field, model_validator

from supervisor.config.models import NetworkDevice, SourcePoints, SourceSpec
from supervisor.core.driver import PointInfo

WATCHDOG_POLL_RATIO: Final = 3.0
"""``watchdog_s`` must be at least this many poll periods: every poll is the keep-alive."""

POINTS: Final[Mapping[str, PointInfo]] = MappingProxyType(
    {
        p.name: p
        for p in (
            PointInfo("voltage", "in", "float", "V", "measured output voltage"),
            PointInfo("current", "in", "float", "A", "measured current, + charging, - discharging"),
            PointInfo("power", "in", "float", "W", "measured power, same sign as current"),
            PointInfo("output_on", "in", "bool", "", "DC output on (OUTP?)"),
            PointInfo("remote", "in", "bool", "", "remote control held (SYST:LOCK:OWN?)"),
            PointInfo("ques", "in", "int", "", "STAT:QUES:COND? (bit 0 OVP, 1 OCP, 2 OPP, 3 OT)"),
            PointInfo("error", "in", "str", "", "last non-zero SYST:ERR? entry, or ''"),
            PointInfo("output", "out", "bool", "", "DC output on/off"),
            PointInfo("current_set", "out", "float", "A", "+ charge, - discharge"),
            PointInfo("voltage_set", "out", "float", "V", "CV target while charging"),
        )
    }
)

SOURCE_POINTS: Final = SourcePoints(
    voltage="voltage",
    current="current",
    current_set="current_set",
    output="output",
    output_fb="output_on",
    voltage_set="voltage_set",
)


class EaDevice(NetworkDevice):
    """EA-PSB 10000 bidirectional supply over SCPI/TCP (seed 002 §2.2)."""

    driver: Literal["ea-psb"]
    source_noun: ClassVar[str | None] = "an EA supply"
    port: int = Field(5025, ge=1, le=65535)
    expected_model: str | None = Field(None, description="refuse any other model")
    watchdog_s: float = Field(2.0, gt=0, description="interface monitoring timeout")
    sim_model: str = "PSB 10060-60"
    sim_nominal_v: float = Field(60.0, gt=0)
    sim_nominal_a: float = Field(60.0, gt=0)
    sim_nominal_w: float = Field(1500.0, gt=0)

    @model_validator(mode="after")
    def _keepalive(self) -> EaDevice:
        if self.watchdog_s < WATCHDOG_POLL_RATIO * self.poll_period_s - 1e-9:
            raise ValueError(
                f"watchdog_s ({self.watchdog_s}) must be at least 3 x poll_period_s"
                f" ({self.poll_period_s}) so the keep-alive beats the supply's timeout"
            )
        return self

    def points(self) -> Mapping[str, PointInfo]:
        return POINTS

    def channel_source(self) -> SourceSpec:
        return SourceSpec(
            noun=self.source_noun or "",
            title="EA supply",
            regulates_voltage=True,
            owner_required=True,
            points=lambda board: SOURCE_POINTS,
        )
