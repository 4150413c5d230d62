"""Build a running bench from its validated I/O map."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field

from supervisor.channels import Channel, ChannelLimits
from supervisor.config.models import BenchConfig, ChadecheDevice, LinearScaling, TagMapping
from supervisor.core.clock import Clock
from supervisor.core.driver import Driver
from supervisor.drivers.chadeche import ChadecheDriver
from supervisor.drivers.chadeche.bus import ChadecheBus, SpidevBus
from supervisor.protocols.chadeche import Calibration
from supervisor.scan import InputBinding, LogicPhase, OutputBinding, Publisher, ScanEngine
from supervisor.sim.battery import BatteryModel, make_model
from supervisor.sim.chadeche import SimBoard, SimChadecheBus
from supervisor.tags import AlarmLimits, HistorySettings, Scaling, TagDB, TagSpec

log = logging.getLogger(__name__)


@dataclass
class Bench:
    """Everything one bench process runs: tags, drivers, channels, the scan."""

    cfg: BenchConfig
    clock: Clock
    db: TagDB
    engine: ScanEngine
    drivers: dict[str, Driver]
    channels: dict[str, Channel]
    cells: dict[str, BatteryModel] = field(default_factory=dict)  # simulation only
    buses: list[ChadecheBus] = field(default_factory=list)

    async def run(self, stop: asyncio.Event) -> None:
        await self.engine.run(stop)

    async def shutdown(self) -> None:
        """Every output to its safe state, then close; continue past failures."""
        for ch in self.channels.values():
            ch.go_safe()
        self.engine.scan_once()  # queue the zero setpoints
        for d in self.drivers.values():
            try:
                await d.poll()  # flush the queued safe writes through the normal path
            except Exception:
                log.exception("%s: flushing safe writes failed", d.name)
            await d.safe_state()
            try:
                await d.close()
            except Exception:
                log.exception("%s: close failed", d.name)
        for bus in self.buses:
            try:
                bus.close()
            except Exception:
                log.exception("bus close failed")
        log.info("bench %s: all outputs safe", self.cfg.bench)


def _tag_spec(m: TagMapping) -> TagSpec:
    alarms = None
    if m.alarms is not None:
        a = m.alarms
        alarms = AlarmLimits(a.hh, a.h, a.l, a.ll, a.deadband, a.delay_s)
    h = m.history
    return TagSpec(
        name=m.name,
        unit=m.unit,
        description=m.description,
        range=m.range,
        scaling=_scaling(m),
        retain=m.retain,
        stale_after_s=m.stale_after_s,
        alarms=alarms,
        history=HistorySettings(h.enabled, h.deadband, h.min_interval_s),
    )


def _scaling(m: TagMapping) -> Scaling | None:
    if m.scaling is None:
        return None
    if isinstance(m.scaling, LinearScaling):
        return Scaling(m.scaling.a, m.scaling.b)
    a, b = m.scaling.linear()
    return Scaling(a, b)


def build_bench(
    cfg: BenchConfig,
    clock: Clock,
    publishers: list[Publisher] | None = None,
) -> Bench:
    db = TagDB()
    drivers: dict[str, Driver] = {}
    cells: dict[str, BatteryModel] = {}
    buses: list[ChadecheBus] = []
    stale: dict[str, float] = {}
    for name, dev in cfg.devices.items():
        if isinstance(dev, ChadecheDevice):
            cal = {
                b.address: Calibration(
                    current_slope=b.calibration.current_slope,
                    current_offset_ma=b.calibration.current_offset_ma,
                    voltage_slope=b.calibration.voltage_slope,
                    voltage_offset_v=b.calibration.voltage_offset_v,
                )
                for b in dev.boards
            }
            bus: ChadecheBus
            if dev.backend == "sim":
                sim_boards = {}
                for b in dev.boards:
                    params: dict[str, float] = {
                        "capacity_ah": b.sim.capacity_ah,
                        "soc": b.sim.soc,
                        "temperature_c": b.sim.temperature_c,
                    }
                    if b.sim.cells_series is not None:
                        params["cells_series"] = b.sim.cells_series
                    cell = make_model(b.sim.model, **params)
                    cells[f"{name}.b{b.address}"] = cell
                    sim_boards[b.address] = SimBoard(cell)
                bus = SimChadecheBus(clock, sim_boards)
            else:
                bus = SpidevBus(
                    spi_bus=dev.spi.bus,
                    spi_device=dev.spi.device,
                    max_speed_hz=dev.spi.max_speed_hz,
                    lock_dir=dev.lock_dir,
                )
            buses.append(bus)
            drivers[name] = ChadecheDriver(
                name, clock, bus, cal, poll_period_s=dev.poll_period_s, lock_dir=dev.lock_dir
            )
            stale[name] = dev.stale_after_s

    inputs: list[InputBinding] = []
    outputs: list[OutputBinding] = []
    for m in cfg.tags:
        spec = _tag_spec(m)
        tag = db.add(spec)
        drv = drivers[m.device]
        info = drv.points()[m.point]
        if info.direction == "in":
            inputs.append(
                InputBinding(tag, drv, m.point, spec.scaling, m.stale_after_s or stale[m.device])
            )
        else:
            outputs.append(OutputBinding(tag, drv, m.point, spec.scaling))

    channels: dict[str, Channel] = {}
    for c in cfg.channels:
        ch = Channel(
            c.name,
            db,
            ChannelLimits(c.limits.current_a, c.limits.voltage_v, c.limits.temperature_c),
            capacity_ah=c.capacity_ah,
            temperature_tag=c.temperature_tag,
        )
        drv = drivers[c.source.device]
        n = c.source.board
        st = stale[c.source.device]
        inputs.append(InputBinding(ch.voltage, drv, f"b{n}.voltage", None, st))
        inputs.append(InputBinding(ch.current, drv, f"b{n}.current", None, st))
        outputs.append(OutputBinding(ch.current_cmd, drv, f"b{n}.current_set"))
        channels[c.name] = ch

    phases = [LogicPhase(f"channel:{ch.name}", ch.run) for ch in channels.values()]
    engine = ScanEngine(
        clock,
        db,
        cfg.scan.period_s,
        drivers=list(drivers.values()),
        inputs=inputs,
        outputs=outputs,
        phases=phases,
        publishers=publishers or [],
    )
    return Bench(cfg, clock, db, engine, drivers, channels, cells, buses)
