"""Validated models of a bench I/O map (``io_maps/*.yaml``).

Unknown keys are errors everywhere (``extra="forbid"``): a misspelt key silently
ignored is how a limit goes missing. Names carry units (``period_s``, ``current_a``).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    field_validator,
    model_validator,
)

NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*$"
TAG_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z0-9_]+)*$"


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ScanConfig(Strict):
    period_s: float = Field(0.1, ge=0.001, le=10.0, description="Scan period in seconds.")


class HmiConfig(Strict):
    host: str = Field("127.0.0.1", description="Address the HTTP API listens on.")
    port: int = Field(8080, ge=0, le=65535, description="0 picks a free port.")


# --- scaling, alarms, history ---------------------------------------------------------
class LinearScaling(Strict):
    """``eu = a·raw + b``."""

    a: float = 1.0
    b: float = 0.0

    @field_validator("a")
    @classmethod
    def _nonzero(cls, v: float) -> float:
        if v == 0:
            raise ValueError("scaling slope a is zero (zero span)")
        return v


class SpanScaling(Strict):
    """Two-point scaling: ``raw: [lo, hi]`` maps to ``eu: [lo, hi]`` (e.g. ±4 V ↔ ±300 A)."""

    raw: tuple[float, float]
    eu: tuple[float, float]

    @model_validator(mode="after")
    def _spans(self) -> SpanScaling:
        if self.raw[0] == self.raw[1]:
            raise ValueError("raw span is zero")
        if self.eu[0] == self.eu[1]:
            raise ValueError("engineering-unit span is zero")
        return self

    def linear(self) -> tuple[float, float]:
        a = (self.eu[1] - self.eu[0]) / (self.raw[1] - self.raw[0])
        return a, self.eu[0] - a * self.raw[0]


def _scaling_kind(v: Any) -> str:
    # Pick the form from its keys so an error names only the form the user meant.
    if isinstance(v, dict):
        return "span" if ("raw" in v or "eu" in v) else "linear"
    return "span" if isinstance(v, SpanScaling) else "linear"


Scaling = Annotated[
    Annotated[LinearScaling, Tag("linear")] | Annotated[SpanScaling, Tag("span")],
    Discriminator(_scaling_kind),
]


class AlarmConfig(Strict):
    hh: float | None = None
    h: float | None = None
    l: float | None = None  # noqa: E741 - ISA-18.2 name
    ll: float | None = None
    deadband: float = Field(0.0, ge=0)
    delay_s: float = Field(0.0, ge=0)


class HistoryConfig(Strict):
    enabled: bool = True
    deadband: float = Field(0.0, ge=0)
    min_interval_s: float = Field(0.0, ge=0)


class TagMapping(Strict):
    """A device point published as a tag, with optional scaling to engineering units."""

    name: str = Field(pattern=TAG_PATTERN)
    device: str
    point: str
    unit: str = ""
    description: str = ""
    scaling: Scaling | None = None
    range: tuple[float, float] | None = None
    stale_after_s: float | None = Field(None, gt=0)
    alarms: AlarmConfig | None = None
    history: HistoryConfig = HistoryConfig()
    retain: bool = False


# --- devices -----------------------------------------------------------------------------
class ChadecheCalibration(Strict):
    """The seed's ``-1 -2 -s -o`` (seed 000 §III.F)."""

    current_slope: float = Field(1.0, gt=0, description="-1: DAC mA per wanted mA")
    current_offset_ma: float = Field(0.0, description="-2: DAC offset in mA")
    voltage_slope: float = Field(1.0, gt=0, description="-s: true V per ADC V")
    voltage_offset_v: float = Field(0.0, description="-o: offset in V")


class SimCell(Strict):
    """Battery model behind a simulated board or supply."""

    model: Literal["nimh-aa", "liion-pack"] = "nimh-aa"
    capacity_ah: float = Field(2.0, gt=0)
    soc: float = Field(0.5, ge=0, le=1)
    temperature_c: float = 25.0
    cells_series: int | None = Field(None, ge=1, description="Li-ion pack only")


class ChadecheBoard(Strict):
    address: int = Field(ge=0, le=3, description="DIP switch address 0..3 (seed table 1)")
    calibration: ChadecheCalibration = ChadecheCalibration()
    sim: SimCell = SimCell()


class SpiConfig(Strict):
    bus: int = Field(0, ge=0)
    device: int = Field(0, ge=0)
    max_speed_hz: int = Field(500_000, gt=0, le=20_000_000)


class ChadecheDevice(Strict):
    driver: Literal["chadeche"]
    backend: Literal["sim", "spidev"] = "sim"
    poll_period_s: float = Field(0.1, gt=0)
    stale_after_s: float = Field(1.0, gt=0)
    spi: SpiConfig = SpiConfig()
    lock_dir: str | None = None
    boards: list[ChadecheBoard] = Field(min_length=1, max_length=4)

    def point_names(self) -> set[str]:
        out: set[str] = set()
        for b in self.boards:
            n = b.address
            out |= {f"b{n}.voltage", f"b{n}.current", f"b{n}.charging"}
            out |= {f"b{n}.current_set", f"b{n}.led_duty"}
        return out

    def output_points(self) -> set[str]:
        return {p for p in self.point_names() if p.endswith(("_set", "led_duty"))}


Device = Annotated[ChadecheDevice, Field(discriminator="driver")]


# --- channels ----------------------------------------------------------------------------
class ChadecheSource(Strict):
    device: str
    board: int = Field(ge=0, le=3)


class ChannelLimits(Strict):
    """Hard limits: setpoints are clamped to them, crossings trip the channel."""

    current_a: tuple[float, float] = Field(description="[max discharge (<=0), max charge (>=0)]")
    voltage_v: tuple[float, float]
    temperature_c: tuple[float | None, float | None] = (None, None)

    @model_validator(mode="after")
    def _ordered(self) -> ChannelLimits:
        lo, hi = self.current_a
        if lo > 0 or hi < 0:
            raise ValueError("current_a must be [discharge limit <= 0, charge limit >= 0]")
        if self.voltage_v[0] >= self.voltage_v[1]:
            raise ValueError("voltage_v must be [low, high] with low < high")
        tlo, thi = self.temperature_c
        if tlo is not None and thi is not None and tlo >= thi:
            raise ValueError("temperature_c must be [low, high] with low < high")
        return self


class ChannelConfig(Strict):
    name: str = Field(pattern=NAME_PATTERN)
    description: str = ""
    source: ChadecheSource
    chemistry: Literal["nimh", "liion", "lfp", "lead-acid", "other"] = "nimh"
    capacity_ah: float = Field(gt=0, description="Rated capacity (C-rates, progress).")
    limits: ChannelLimits
    temperature_tag: str | None = Field(None, pattern=TAG_PATTERN)


class BenchConfig(Strict):
    """A bench: its scan, devices, extra tag mappings and channels."""

    bench: str = Field(pattern=NAME_PATTERN, description="Bench name (InfluxDB `bench` tag).")
    description: str = ""
    scan: ScanConfig = ScanConfig()
    hmi: HmiConfig = HmiConfig()
    state_dir: str = Field("var", description="Where retained state and results go.")
    devices: dict[str, Device] = Field(min_length=1)
    tags: list[TagMapping] = []
    channels: list[ChannelConfig] = []

    @field_validator("devices")
    @classmethod
    def _device_names(cls, v: dict[str, Device]) -> dict[str, Device]:
        import re

        for name in v:
            if not re.match(NAME_PATTERN, name):
                raise ValueError(f"device name {name!r} must be a plain identifier")
        return v
