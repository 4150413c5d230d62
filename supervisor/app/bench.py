"""Build a running bench from its validated I/O map."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import can

from supervisor.app.simulation import SimulatedBench, build_simulation, cell_model, make_plant
from supervisor.chains.compiler import CC_ONLY, WITH_CV, Target, compile_recipe
from supervisor.chains.engine import ChainEvent, ChainRunner, Record, State
from supervisor.channels import Channel, ChannelLimits
from supervisor.config.models import (
    AdamDevice,
    BenchConfig,
    BmsDevice,
    ChadecheDevice,
    ChannelConfig,
    EaDevice,
    LinearScaling,
    SimSupplyDevice,
    TagMapping,
)
from supervisor.config.recipe import load_recipe
from supervisor.core.clock import Clock
from supervisor.core.driver import Driver, DType
from supervisor.core.errors import OperatorError
from supervisor.core.units import UNITS, Dim
from supervisor.devices.adam.driver import AdamDriver, AdamModule
from supervisor.devices.bms.driver import BmsDriver, socketcand_bus_factory
from supervisor.devices.chadeche import ChadecheDriver
from supervisor.devices.chadeche.bus import ChadecheBus, SpidevBus
from supervisor.devices.chadeche.protocol import Calibration
from supervisor.devices.chadeche.sim import SimBoard, SimChadecheBus
from supervisor.devices.ea.driver import EaDriver
from supervisor.devices.sim_supply.driver import PlantSupplyDriver
from supervisor.publish.results import ResultCollector
from supervisor.scan import InputBinding, LogicPhase, OutputBinding, Publisher, ScanEngine
from supervisor.sim.battery import BatteryModel
from supervisor.sim.plant import BenchPlant
from supervisor.tags import AlarmLimits, HistorySettings, Scaling, TagDB, TagSpec

log = logging.getLogger(__name__)

FINAL_STATES = (State.COMPLETE, State.STOPPED, State.ABORTED)
UNIT_DIMS = {u: d for u, (d, f) in UNITS.items() if f == 1.0}


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
    sim: SimulatedBench | None = None
    runners: dict[str, ChainRunner] = field(default_factory=dict)
    plant: BenchPlant | None = None  # the dry-run supply's battery
    results: dict[str, ResultCollector] = field(default_factory=dict)
    _started: bool = False

    def target(self, channel: str) -> Target:
        """What a recipe may ask of this channel (checked before start)."""
        c = next(c for c in self.cfg.channels if c.name == channel)
        dev = self.cfg.devices[c.source.device]
        cv = not isinstance(dev, ChadecheDevice)
        return Target(
            channel=channel,
            capabilities=WITH_CV if cv else CC_ONLY,
            no_cv_reason="a Chadèche board drives a constant current only (no voltage regulation)",
            capacity_ah=c.capacity_ah,
            current_limits_a=c.limits.current_a,
            tags=self.tag_dims(),
        )

    def load_recipe(
        self,
        channel: str,
        path: str | Path,
        overrides: dict[str, str] | None = None,
        results_dir: Path | None = None,
        test_id: str | None = None,
    ) -> ChainRunner:
        """Compile a recipe for a channel (refused before start if it cannot run there),
        load it, and record its result files under ``results_dir/<test id>/``."""
        if channel not in self.runners:
            raise OperatorError(f"unknown channel {channel!r} ({', '.join(self.runners)})")
        recipe, pos = load_recipe(path)
        program = compile_recipe(recipe, pos, str(path), self.target(channel), overrides or {})
        runner = self.runners[channel]
        runner.load(program, test_id)
        folder = (results_dir or Path(self.cfg.state_dir) / "results") / runner.test_id
        c = self.cfg.channels[[c.name for c in self.cfg.channels].index(channel)]
        collector = ResultCollector(
            channel, program.name, runner.test_id, folder, dba=c.source.board or 0
        )
        runner.listeners[:] = [e for e in runner.listeners if not getattr(e, "_results", False)]
        runner.recorders[:] = [r for r in runner.recorders if not getattr(r, "_results", False)]

        def on_event(ev: ChainEvent) -> None:
            collector.on_event(ev)
            if ev.kind == "state" and runner.state in FINAL_STATES:
                collector.close(runner.end_reason, runner.state.value)
                log.info("%s: results in %s", channel, folder)

        def on_record(rec: Record) -> None:
            collector.on_record(rec)

        on_event._results = True  # type: ignore[attr-defined]
        on_record._results = True  # type: ignore[attr-defined]
        runner.listeners.append(on_event)
        runner.recorders.append(on_record)
        self.results[channel] = collector
        return runner

    def tag_dims(self) -> dict[str, Dim]:
        out: dict[str, Dim] = {}
        for t in self.db:
            if t.spec.dtype == "bool":
                out[t.name] = Dim.BOOL
            elif t.spec.dtype in ("float", "int"):
                out[t.name] = UNIT_DIMS.get(t.spec.unit, Dim.NONE)
        return out

    async def start(self) -> None:
        """Start the in-process simulators (if the I/O map has any) before scanning."""
        if self.sim is not None and not self._started:
            await self.sim.start()
        self._started = True

    async def run(self, stop: asyncio.Event) -> None:
        await self.start()
        await self.engine.run(stop)

    async def shutdown(self) -> None:
        """Every output to its safe state, then close; continue past failures."""
        for ch in self.channels.values():
            ch.go_safe()
        self.engine.scan_once()  # queue the zero setpoints
        for name, collector in self.results.items():
            runner = self.runners[name]
            if runner.state not in FINAL_STATES:
                collector.close("supervisor stopped", runner.state.value)
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
        if self.sim is not None and self._started:
            await self.sim.stop()
            self._started = False
        log.info("bench %s: all outputs safe", self.cfg.bench)


def _tag_spec(m: TagMapping, dtype: DType) -> TagSpec:
    alarms = None
    if m.alarms is not None:
        a = m.alarms
        alarms = AlarmLimits(a.hh, a.h, a.l, a.ll, a.deadband, a.delay_s)
    h = m.history
    return TagSpec(
        name=m.name,
        dtype=dtype,
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
    *,
    simulate: bool = True,
) -> Bench:
    """Wire a bench. ``simulate=False`` skips the in-process simulators of ``sim: true``
    devices (another process, e.g. ``supervisor sim``, serves them)."""
    db = TagDB()
    drivers: dict[str, Driver] = {}
    cells: dict[str, BatteryModel] = {}
    buses: list[ChadecheBus] = []
    stale: dict[str, float] = {}
    plant: BenchPlant | None = None
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
                    cell = cell_model(b.sim)
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
        elif isinstance(dev, AdamDevice):
            drivers[name] = AdamDriver(
                name,
                clock,
                dev.host,
                dev.port,
                {slot: AdamModule(m.kind, m.raw_format) for slot, m in sorted(dev.modules.items())},
                unit_id=dev.unit_id,
                poll_period_s=dev.poll_period_s,
                timeout_s=dev.timeout_s,
            )
            stale[name] = dev.stale_after_s
        elif isinstance(dev, EaDevice):
            owner = _owner(cfg, name)
            lo, hi = owner.limits.current_a
            drivers[name] = EaDriver(
                name,
                clock,
                dev.host,
                dev.port,
                v_min=owner.limits.voltage_v[0],
                v_max=owner.limits.voltage_v[1],
                i_charge_max_a=hi,
                i_discharge_max_a=-lo,
                expected_model=dev.expected_model,
                poll_period_s=dev.poll_period_s,
                watchdog_s=dev.watchdog_s,
                timeout_s=dev.timeout_s,
            )
            stale[name] = dev.stale_after_s
        elif isinstance(dev, SimSupplyDevice):
            owner = _owner(cfg, name)
            if plant is None:
                plant = make_plant(cfg, clock)
            drivers[name] = PlantSupplyDriver(
                name,
                clock,
                plant,
                v_min=owner.limits.voltage_v[0],
                v_max=owner.limits.voltage_v[1],
                poll_period_s=dev.poll_period_s,
            )
            stale[name] = dev.stale_after_s
        elif isinstance(dev, BmsDevice):
            drivers[name] = BmsDriver(
                name,
                clock,
                _can_factory(dev),
                poll_period_s=dev.poll_period_s,
                stale_factor=dev.stale_factor,
            )
            stale[name] = dev.stale_after_s

    inputs: list[InputBinding] = []
    outputs: list[OutputBinding] = []
    for m in cfg.tags:
        drv = drivers[m.device]
        info = drv.points()[m.point]
        spec = _tag_spec(m, "bool" if m.threshold is not None else info.dtype)
        tag = db.add(spec)
        if info.direction == "in":
            inputs.append(
                InputBinding(
                    tag,
                    drv,
                    m.point,
                    spec.scaling,
                    m.stale_after_s or stale[m.device],
                    threshold=m.threshold,
                )
            )
        else:
            outputs.append(OutputBinding(tag, drv, m.point, spec.scaling))

    channels: dict[str, Channel] = {}
    for c in cfg.channels:
        dev = cfg.devices[c.source.device]
        is_ea = isinstance(dev, EaDevice | SimSupplyDevice)
        ch = Channel(
            c.name,
            db,
            ChannelLimits(c.limits.current_a, c.limits.voltage_v, c.limits.temperature_c),
            capacity_ah=c.capacity_ah,
            temperature_tag=c.temperature_tag,
            voltage_tag=c.voltage_tag,
            current_tag=c.current_tag,
            contactor_tag=c.contactor_tag,
            permissives=tuple(c.permissives),
            has_output_switch=is_ea,
            has_voltage_setpoint=is_ea,
        )
        drv = drivers[c.source.device]
        prefix = "" if is_ea else f"b{c.source.board}."
        st = stale[c.source.device]
        if c.voltage_tag is None:
            inputs.append(InputBinding(ch.voltage, drv, f"{prefix}voltage", None, st))
        if c.current_tag is None:
            inputs.append(InputBinding(ch.current, drv, f"{prefix}current", None, st))
        outputs.append(OutputBinding(ch.current_cmd, drv, f"{prefix}current_set"))
        if ch.output_cmd is not None:
            outputs.append(OutputBinding(ch.output_cmd, drv, "output"))
        if ch.voltage_cmd is not None:
            outputs.append(OutputBinding(ch.voltage_cmd, drv, "voltage_set"))
        channels[c.name] = ch

    runners = {name: ChainRunner(ch, db, clock) for name, ch in channels.items()}
    for c in cfg.channels:
        runners[c.name].dba = c.source.board or 0
    phases = []
    for name, ch in channels.items():
        # The chain requests, then the channel protects: a chain never overrides a trip.
        phases.append(LogicPhase(f"chain:{name}", runners[name].run))
        phases.append(LogicPhase(f"channel:{name}", ch.run))
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
    sim = build_simulation(cfg, clock) if simulate else None
    bench = Bench(cfg, clock, db, engine, drivers, channels, cells, buses, sim, runners)
    bench.plant = plant
    return bench


def _owner(cfg: BenchConfig, device: str) -> ChannelConfig:
    for c in cfg.channels:
        if c.source.device == device:
            return c
    raise ValueError(f"device {device!r} drives no channel")  # refused by check_bench


def _can_factory(dev: BmsDevice) -> Callable[[], can.BusABC]:
    if dev.interface == "socketcand":
        # Probes the server first: python-can's client otherwise spins while it is down.
        return socketcand_bus_factory(dev.host, dev.port, dev.channel)
    return lambda: can.Bus(interface=dev.interface, channel=dev.channel)
