"""BMS over CAN: the I/O map entry, and the point catalog (the one place for its points).

Frame identifiers, periods and the current sign (the unverified facts) are in
:mod:`supervisor.devices.bms.protocol`, next to the DBC that describes the frames.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Final, Literal

from pydantic import Field, model_validator

from supervisor.config.models import LOOPBACK_HOSTS, DeviceConfig
from supervisor.core.driver import PointInfo

POINTS: Final[Mapping[str, PointInfo]] = MappingProxyType(
    {
        p.name: p
        for p in (
            PointInfo("pack_voltage", "in", "float", "V", "pack voltage (0x1B0)"),
            PointInfo("min_cell_voltage", "in", "float", "V", "lowest cell voltage (0x1B0)"),
            PointInfo("max_cell_voltage", "in", "float", "V", "highest cell voltage (0x1B0)"),
            PointInfo("pack_current", "in", "float", "A", "pack current, + charges (0x2B0)"),
            PointInfo("min_temp", "in", "float", "degC", "lowest temperature (0x3B0)"),
            PointInfo("max_temp", "in", "float", "degC", "highest temperature (0x3B0)"),
            PointInfo("avg_temp", "in", "float", "degC", "average temperature (0x3B0)"),
            PointInfo("frames_unknown", "in", "int", "", "frames with an id not in the DBC"),
            PointInfo("frames_bad", "in", "int", "", "frames that could not be decoded"),
            # Unit "1" (BDF's dimensionless, as "Cycle Count / 1"): a channel's result file
            # records it by default with the measurements of its BMS.
            PointInfo("faults", "in", "int", "1", "fault bits (driver.FAULT_BITS), 0: none"),
        )
    }
)


class BmsDevice(DeviceConfig):
    """BMS over CAN (seed 002 §2.1): frames 0x1B0, 0x2B0, 0x3B0 decoded with the DBC."""

    driver: Literal["bms-can"]
    interface: Literal["socketcand", "socketcan", "virtual"] = "socketcand"
    channel: str = "can0"
    host: str = "127.0.0.1"
    port: int = Field(29536, ge=1, le=65535)
    poll_period_s: float = Field(0.05, gt=0)
    stale_factor: float = Field(3.0, ge=1.0, description="a value is stale after k x period")
    stale_after_s: float = Field(3.0, gt=0)
    allow_extra_bytes: bool = Field(
        True,
        description="decode frames longer than the DBC says (padded to 8 bytes by the"
        " controller), extra bytes ignored; false refuses them",
    )
    sim: bool = False

    @property
    def simulated(self) -> bool:
        return self.sim

    @model_validator(mode="after")
    def _sim_on_loopback(self) -> BmsDevice:
        if self.sim and self.interface == "socketcand" and self.host not in LOOPBACK_HOSTS:
            raise ValueError(f"a simulated BMS serves on loopback only; host {self.host!r}")
        if self.sim and self.interface == "socketcan":
            raise ValueError("a simulated BMS uses interface socketcand or virtual")
        return self

    def points(self) -> Mapping[str, PointInfo]:
        return POINTS
