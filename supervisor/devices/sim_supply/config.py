"""An ideal bidirectional supply acting directly on the simulated pack (dry runs)."""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import ClassVar, Final, Literal

from pydantic import Field

from supervisor.config.models import DeviceConfig, SourcePoints, SourceSpec
from supervisor.core.driver import PointInfo

POINTS: Final[Mapping[str, PointInfo]] = MappingProxyType(
    {
        p.name: p
        for p in (
            PointInfo("voltage", "in", "float", "V"),
            PointInfo("current", "in", "float", "A", "+ charges the battery"),
            PointInfo("power", "in", "float", "W"),
            PointInfo("output_on", "in", "bool"),
            PointInfo("output", "out", "bool"),
            PointInfo("current_set", "out", "float", "A"),
            PointInfo("voltage_set", "out", "float", "V"),
        )
    }
)
SOURCE_POINTS: Final = SourcePoints("voltage", "current", "current_set", "output", "voltage_set")


class SimSupplyDevice(DeviceConfig):
    """An ideal bidirectional supply acting directly on the simulated pack (dry runs)."""

    driver: Literal["sim-supply"]
    source_noun: ClassVar[str | None] = "an EA supply"
    poll_period_s: float = Field(0.1, gt=0)
    stale_after_s: float = Field(1.0, gt=0)

    @property
    def simulated(self) -> bool:
        return True

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
