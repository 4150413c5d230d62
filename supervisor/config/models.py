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
    threshold: float | None = Field(
        None, description="make a boolean tag: true when the scaled value >= threshold"
    )


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


LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


class NetworkDevice(Strict):
    host: str
    poll_period_s: float = Field(0.2, gt=0)
    stale_after_s: float = Field(1.0, gt=0)
    timeout_s: float = Field(1.0, gt=0, le=30)
    sim: bool = Field(False, description="serve a simulator of this device on host:port")

    @model_validator(mode="after")
    def _sim_on_loopback(self) -> NetworkDevice:
        if self.sim and self.host not in LOOPBACK_HOSTS:
            raise ValueError(
                f"a simulated device listens on loopback only; host {self.host!r}"
                " must be 127.0.0.1 (or set sim: false)"
            )
        return self


class AdamModuleConfig(Strict):
    kind: Literal["5017", "5018", "5060", "5069"]
    raw_format: Literal["offset", "twos"] = "offset"


ADAM_POINTS = {"5017": ("ai", 8), "5018": ("tc", 7), "5060": ("do", 6), "5069": ("do", 8)}


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
            if not 0 <= slot <= 7:
                raise ValueError(f"slot {slot} does not exist (ADAM-5000/TCP slots are 0..7)")
        return v

    def point_names(self) -> set[str]:
        out: set[str] = set()
        for slot, m in self.modules.items():
            prefix, n = ADAM_POINTS[m.kind]
            for k in range(n):
                out.add(f"slot{slot}.{prefix}{k}")
                if prefix == "do":
                    out.add(f"slot{slot}.do{k}_fb")
        return out


class EaDevice(NetworkDevice):
    """EA-PSB 10000 bidirectional supply over SCPI/TCP (seed 002 §2.2)."""

    driver: Literal["ea-psb"]
    port: int = Field(5025, ge=1, le=65535)
    expected_model: str | None = Field(None, description="refuse any other model")
    watchdog_s: float = Field(2.0, gt=0, description="interface monitoring timeout")
    sim_model: str = "PSB 10060-60"
    sim_nominal_v: float = Field(60.0, gt=0)
    sim_nominal_a: float = Field(60.0, gt=0)
    sim_nominal_w: float = Field(1500.0, gt=0)

    @model_validator(mode="after")
    def _keepalive(self) -> EaDevice:
        if self.watchdog_s < 3 * self.poll_period_s - 1e-9:
            raise ValueError(
                f"watchdog_s ({self.watchdog_s}) must be at least 3 x poll_period_s"
                f" ({self.poll_period_s}) so the keep-alive beats the supply's timeout"
            )
        return self

    def point_names(self) -> set[str]:
        return {
            "voltage",
            "current",
            "power",
            "output_on",
            "remote",
            "ques",
            "error",
            "output",
            "current_set",
            "voltage_set",
        }


class BmsDevice(Strict):
    """BMS over CAN (seed 002 §2.1): frames 0x1B0, 0x2B0, 0x3B0 decoded with the DBC."""

    driver: Literal["bms-can"]
    interface: Literal["socketcand", "socketcan", "virtual"] = "socketcand"
    channel: str = "can0"
    host: str = "127.0.0.1"
    port: int = Field(29536, ge=1, le=65535)
    poll_period_s: float = Field(0.05, gt=0)
    stale_factor: float = Field(3.0, ge=1.0, description="a value is stale after k x period")
    stale_after_s: float = Field(3.0, gt=0)
    sim: bool = False

    @model_validator(mode="after")
    def _sim_on_loopback(self) -> BmsDevice:
        if self.sim and self.interface == "socketcand" and self.host not in LOOPBACK_HOSTS:
            raise ValueError(f"a simulated BMS serves on loopback only; host {self.host!r}")
        if self.sim and self.interface == "socketcan":
            raise ValueError("a simulated BMS uses interface socketcand or virtual")
        return self

    def point_names(self) -> set[str]:
        return {
            "pack_voltage",
            "min_cell_voltage",
            "max_cell_voltage",
            "pack_current",
            "min_temp",
            "max_temp",
            "avg_temp",
            "frames_unknown",
            "frames_bad",
        }


class SimSupplyDevice(Strict):
    """An ideal bidirectional supply acting directly on the simulated pack (dry runs)."""

    driver: Literal["sim-supply"]
    poll_period_s: float = Field(0.1, gt=0)
    stale_after_s: float = Field(1.0, gt=0)

    def point_names(self) -> set[str]:
        return {"voltage", "current", "power", "output_on", "output", "current_set", "voltage_set"}


Device = Annotated[
    ChadecheDevice | AdamDevice | EaDevice | BmsDevice | SimSupplyDevice,
    Field(discriminator="driver"),
]


# --- channels ----------------------------------------------------------------------------
class ChannelSource(Strict):
    """The device that drives the channel: a Chadèche board or an EA supply."""

    device: str
    board: int | None = Field(None, ge=0, le=3, description="Chadèche board address")


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
    source: ChannelSource
    chemistry: Literal["nimh", "liion", "lfp", "lead-acid", "other"] = "nimh"
    capacity_ah: float = Field(gt=0, description="Rated capacity (C-rates, progress).")
    limits: ChannelLimits
    temperature_tag: str | None = Field(None, pattern=TAG_PATTERN)
    voltage_tag: str | None = Field(
        None, pattern=TAG_PATTERN, description="measure voltage here instead of the source"
    )
    current_tag: str | None = Field(
        None, pattern=TAG_PATTERN, description="measure current here instead of the source"
    )
    contactor_tag: str | None = Field(
        None, pattern=TAG_PATTERN, description="relay output tag closing the battery contactor"
    )
    permissives: list[str] = Field(
        [], description="boolean tags that must all be true and GOOD to drive current"
    )


class SimPoint(Strict):
    device: str
    point: str


class SimulationConfig(Strict):
    """The simulated seed-002 plant: one pack behind the EA supply, seen by ADAM and BMS."""

    pack: SimCell = SimCell(model="liion-pack", capacity_ah=10.0, soc=0.5, cells_series=4)
    ambient_c: float = 25.0
    lem_current: SimPoint | None = None
    lem_volts_per_amp: float = Field(4.0 / 300.0, description="LEM HAL 300-S: 4 V at 300 A")
    voltage_board: SimPoint | None = None
    voltage_board_ratio: float = Field(0.1, gt=0, description="1:10 divider board")
    estop_sense: SimPoint | None = None
    thermocouples: list[SimPoint] = []
    contactor: SimPoint | None = None


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
    simulation: SimulationConfig | None = None

    @field_validator("devices")
    @classmethod
    def _device_names(cls, v: dict[str, Device]) -> dict[str, Device]:
        import re

        for name in v:
            if not re.match(NAME_PATTERN, name):
                raise ValueError(f"device name {name!r} must be a plain identifier")
        return v
