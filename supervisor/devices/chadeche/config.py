"""Chadèche boards: the I/O map entry, and the point catalog (the one place for board facts).

The board rating and addresses are decided here, once: the driver and the codec, the
simulator, ``supervisor check`` and the sequence-file importer all read them from here.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar, Final, Literal

from pydantic import Field

from supervisor.config.models import DeviceConfig, SimCell, SourcePoints, SourceSpec, Strict
from supervisor.core.driver import PointInfo

MAX_CURRENT_A: Final = 0.400
"""Board maximum, either direction (seed §II.C.4: 4.096 V DAC across the 10 Ω foot resistor;
"ne pouvant dépasser 400 mA", §III.D.1)."""
BOARD_ADDRESSES: Final = range(4)
"""DIP-switch addresses of the boards on one bus (seed table 1)."""
NO_CV_REASON: Final = "a Chadèche board drives a constant current only (no voltage regulation)"


def board_points(address: int) -> list[PointInfo]:
    """The points of board ``address``: ``b{n}.voltage``, ``.current``, ``.charging`` (in),
    ``.current_set``, ``.led_duty`` (out)."""
    p = f"b{address}."
    a = address
    return [
        PointInfo(p + "voltage", "in", "float", "V", f"board {a} cell voltage"),
        PointInfo(p + "current", "in", "float", "A", f"board {a} commanded current, + charge"),
        PointInfo(p + "charging", "in", "bool", "", f"board {a} relay in charge"),
        PointInfo(p + "current_set", "out", "float", "A", f"board {a} current, + charge"),
        PointInfo(p + "led_duty", "out", "float", "", f"board {a} LED duty 0..1"),
    ]


SIM_ONLY_MARK: Final = "SIMULATION ONLY"
"""In the description of a point that only a simulated device has."""


def sim_board_points(address: int) -> list[PointInfo]:
    """The simulation-only points of board ``address``: ``b{n}.temperature`` (in, degC).

    A Chadèche board has no temperature sensor (seed §II.B: it measures the cell voltage
    only). A simulated board offers its cell model's temperature (supervisor/sim/battery.py)
    so that dry runs and the simulated bench can exercise temperature and dT terminations
    and the over-temperature limits; map it as a channel's ``temperature_tag``. Only a
    ``backend: sim`` device lists it, so ``supervisor check`` refuses an I/O map that maps
    it on real boards (there, glue a sensor read by another device to the cell)."""
    return [
        PointInfo(
            f"b{address}.temperature",
            "in",
            "float",
            "degC",
            f"board {address} simulated cell temperature ({SIM_ONLY_MARK}: no board sensor)",
        )
    ]


def source_points(board: int | None) -> SourcePoints:
    p = f"b{board}."
    return SourcePoints(voltage=p + "voltage", current=p + "current", current_set=p + "current_set")


class ChadecheCalibration(Strict):
    """The seed's ``-1 -2 -s -o`` (seed 000 §III.F)."""

    current_slope: float = Field(1.0, gt=0, description="-1: DAC mA per wanted mA")
    current_offset_ma: float = Field(0.0, description="-2: DAC offset in mA")
    voltage_slope: float = Field(1.0, gt=0, description="-s: true V per ADC V")
    voltage_offset_v: float = Field(0.0, description="-o: offset in V")


class ChadecheBoard(Strict):
    address: int = Field(
        ge=BOARD_ADDRESSES[0],
        le=BOARD_ADDRESSES[-1],
        description="DIP switch address 0..3 (seed table 1)",
    )
    calibration: ChadecheCalibration = ChadecheCalibration()
    sim: SimCell = SimCell()


class SpiConfig(Strict):
    bus: int = Field(0, ge=0)
    device: int = Field(0, ge=0)
    max_speed_hz: int = Field(500_000, gt=0, le=20_000_000)


class ChadecheDevice(DeviceConfig):
    driver: Literal["chadeche"]
    source_noun: ClassVar[str | None] = "a Chadèche board"
    backend: Literal["sim", "spidev"] = "sim"
    poll_period_s: float = Field(0.1, gt=0)
    stale_after_s: float = Field(1.0, gt=0)
    spi: SpiConfig = SpiConfig()
    lock_dir: str | None = None
    boards: list[ChadecheBoard] = Field(min_length=1, max_length=len(BOARD_ADDRESSES))

    @property
    def simulated(self) -> bool:
        return self.backend == "sim"

    def points(self) -> Mapping[str, PointInfo]:
        points = {p.name: p for b in self.boards for p in board_points(b.address)}
        if self.simulated:
            points.update((p.name, p) for b in self.boards for p in sim_board_points(b.address))
        return points

    def channel_source(self) -> SourceSpec:
        return SourceSpec(
            noun=self.source_noun or "",
            title="Chadèche device",
            addresses=BOARD_ADDRESSES,
            boards=tuple(b.address for b in self.boards),
            max_current_a=MAX_CURRENT_A,
            regulates_voltage=False,
            no_cv_reason=NO_CV_REASON,
            points=source_points,
        )

    def problems(self) -> list[tuple[tuple[str | int, ...], str]]:
        out: list[tuple[tuple[str | int, ...], str]] = []
        seen: dict[int, int] = {}
        for i, b in enumerate(self.boards):
            if b.address in seen:
                out.append(
                    (
                        ("boards", i, "address"),
                        f"board address {b.address} is already used by boards[{seen[b.address]}]",
                    )
                )
            seen.setdefault(b.address, i)
        return out
