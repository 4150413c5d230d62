"""Build a running bench from its validated I/O map."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from supervisor.app.events import EventFeed
from supervisor.app.history import attach_historian
from supervisor.app.influx import build_influx
from supervisor.app.retained import RecipeSource, Retention
from supervisor.app.simulation import SimulatedBench, build_simulation
from supervisor.app.sparkplug import build_sparkplug, command_handler, keep_bd_seq
from supervisor.audit import AuditLog
from supervisor.chains.compiler import CC_ONLY, WITH_CV, Target
from supervisor.chains.engine import ChainRunner
from supervisor.chains.port import ChannelPort
from supervisor.chains.states import ACTIVE, FINAL
from supervisor.channels import Channel, ChannelLimits, Mode
from supervisor.commands import (
    Command,
    CommandPath,
    PreparedRecipe,
    compile_recipe_file,
)
from supervisor.commands.force import bench_safety_tags
from supervisor.commands.recipes import RecipeFolders
from supervisor.config.bench import record_columns
from supervisor.config.models import BenchConfig, LinearScaling, RecordColumn, TagMapping
from supervisor.core.clock import Clock
from supervisor.core.driver import Driver, DType
from supervisor.core.errors import OperatorError
from supervisor.core.gate import ScanGate
from supervisor.core.logins import LoginThrottle
from supervisor.core.realtime import RealtimePriority
from supervisor.core.records import ChainEvent, Record
from supervisor.core.units import UNITS, Dim
from supervisor.devices.kind import DriverWiring
from supervisor.devices.registry import REGISTRY, Registry
from supervisor.publish.changes import ChangeReader, SharedChanges
from supervisor.publish.display import ChadecheDisplay
from supervisor.publish.historian import Historian
from supervisor.publish.influx import InfluxWriter
from supervisor.publish.provenance import Provenance, TestMetadata
from supervisor.publish.results import TIMELINE_KINDS, ResultCollector, SummaryWriter
from supervisor.publish.rows import RowWriter
from supervisor.safety import AlarmManager, SafetyPhase, build_safety
from supervisor.safety.kpi import AlarmKpi
from supervisor.scan import (
    InputBinding,
    LogicPhase,
    OutputBinding,
    Publisher,
    ScanEngine,
    ScanPhases,
)
from supervisor.sim.battery import BatteryModel
from supervisor.tags import AlarmLimits, HistorySettings, Scaling, TagDB, TagSpec

if TYPE_CHECKING:  # imported by app/sparkplug.py for a bench that has the section only
    from supervisor.publish.sparkplug import SparkplugPublisher

log = logging.getLogger(__name__)

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
    sim: SimulatedBench | None = None
    runners: dict[str, ChainRunner] = field(default_factory=dict)
    safety: SafetyPhase = field(default_factory=SafetyPhase)
    alarms: AlarmManager | None = None
    results: dict[str, ResultCollector] = field(default_factory=dict)
    displays: dict[str, ChadecheDisplay] = field(default_factory=dict)
    recipes: dict[str, RecipeSource] = field(default_factory=dict)
    results_roots: dict[str, Path] = field(default_factory=dict)
    """Per channel, the folder its tests' result folders go in (given at load)."""
    record_columns: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Per channel, the headers of its result files' auxiliary columns (``record:``)."""
    test_metadata: dict[str, TestMetadata] = field(default_factory=dict)
    """Per channel, the metadata of its next test (given at load and at start: the cell,
    the comment...; the operator is the start's actor); ``new_collector`` takes them."""
    retention: Retention | None = None
    historian: Historian | None = None
    influx: InfluxWriter | None = None
    """The InfluxDB writer, when the I/O map has an ``influxdb:`` section."""
    sparkplug: SparkplugPublisher | None = None
    """The Sparkplug B edge node, when the I/O map has a ``sparkplug:`` section."""
    events: EventFeed = field(default_factory=EventFeed)
    """Chain steps, alarms and operator commands for the publishers that record events."""
    _started: bool = False
    _test_ids: set[str] = field(default_factory=set)
    """Test ids given out by this process (``new_test_id``)."""
    changes: SharedChanges | None = None
    """The change feed the historian and the InfluxDB writer share (``change_reader``)."""
    summaries: SummaryWriter | None = field(init=False, default=None)
    """Test summaries rewritten off the scan's thread (real clock; None on a virtual
    clock, where they are written at once, in the order of the simulated events)."""
    rows: RowWriter | None = field(init=False, default=None)
    """Result rows appended off the scan's thread (real clock only, likewise)."""
    gate: ScanGate | None = field(init=False, default=None)
    """Real clock: the publishers' threads keep out of the scan's way (``core/gate.py``)."""
    commands: CommandPath = field(init=False)
    """The one path of operator commands (HTTP, command line, the ``chN.command`` tags)."""
    audit: AuditLog | None = field(init=False, default=None)
    """Who did what (``app/audit.py``): opened and closed by ``supervisor run``
    (``build_supervisor``, ``Supervisor.release``)."""
    logins: LoginThrottle | None = field(init=False, default=None)
    """Failed-login counts shared by HTTP and OPC UA (``app/logins.py``: made by the first
    server that checks passwords)."""

    def __post_init__(self) -> None:
        if not self.clock.virtual:
            self.summaries = SummaryWriter(f"bench {self.cfg.bench}")
            self.rows = RowWriter(f"bench {self.cfg.bench}")
            self.gate = self.engine.gate = ScanGate()
            self.summaries.gate = self.rows.gate = self.gate
            if self.influx is not None:
                self.influx.writer.gate = self.gate
            if self.sparkplug is not None:
                self.sparkplug.gate = self.gate
        self.commands = CommandPath(
            self.db,
            self.clock,
            self.runners,
            self.safety.guards,
            self.alarms,
            loader=self,
            protected=bench_safety_tags(self.cfg),  # what a force may never touch
            recipe_folders=RecipeFolders.of(self.cfg.recipe_folders),  # ADR 0026
            estop=self.safety.estop,  # the software e-stop presses the same button
        )
        for name, runner in self.runners.items():
            runner.command_handler = self._command_tag(name)
            runner.new_test_id = partial(self.new_test_id, name)

    def change_reader(self) -> ChangeReader | None:
        """A reader of the shared change feed for a publisher attached before the first
        scan (None after it: that publisher needs a feed of its own, whose first batch is
        every tag)."""
        if self.changes is None or self.engine.stats.count:
            return None
        return self.changes.reader()

    def _command_tag(self, channel: str) -> Callable[[str], None]:
        """What a write of ``chN.command`` by an older client does: the same command path,
        so that a refusal is recorded with its reason like any other."""

        def handle(value: str) -> None:
            tag = f"{channel}.command"
            self.commands.execute(Command.write(tag, value, actor=f"operator via {tag}"))

        return handle

    def target(self, channel: str) -> Target:
        """What a recipe may ask of this channel (checked before start)."""
        c = next(c for c in self.cfg.channels if c.name == channel)
        spec = self.cfg.devices[c.source.device].channel_source()
        assert spec is not None  # refused by the bench checks
        return Target(
            channel=channel,
            capabilities=WITH_CV if spec.regulates_voltage else CC_ONLY,
            no_cv_reason=spec.no_cv_reason,
            capacity_ah=c.capacity_ah,
            current_limits_a=c.limits.current_a,
            voltage_limits_v=c.limits.voltage_v,
            temperature_limits_c=c.limits.temperature_c,
            tags=self.tag_dims(),
            scan_period_s=self.cfg.scan.period_s,
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
        load it, and record its result files under ``results_dir/<test id>/``.

        Loading does not touch the channel's mode or enable; it is refused while a test is
        under way or while the operator drives the channel in Manual (enable on)."""
        if channel not in self.runners:
            raise OperatorError(f"unknown channel {channel!r} ({', '.join(self.runners)})")
        prepared = compile_recipe_file(channel, path, self.target(channel), overrides)
        return self.install_recipe(prepared, results_dir, test_id)

    def install_recipe(
        self,
        prepared: PreparedRecipe,
        results_dir: Path | None = None,
        test_id: str | None = None,
    ) -> ChainRunner:
        """Load a compiled recipe on its channel (quick: on the event loop; the compiling
        may have run in a worker thread, ``CommandPath.execute_async``)."""
        channel, program = prepared.channel, prepared.program
        runner = self.runners[channel]
        # Absolute from the load on: a test's files stay where it began whatever the
        # process's working directory later is (a relative ``state_dir`` is the one of
        # the moment the recipe is loaded).
        root = (results_dir or Path(self.cfg.state_dir) / "results").absolute()
        previous_root = self.results_roots.get(channel)
        self.results_roots[channel] = root
        try:
            runner.load(program, test_id)
        except BaseException:
            if previous_root is None:
                self.results_roots.pop(channel, None)
            else:
                self.results_roots[channel] = previous_root
            raise
        folder = root / runner.test_id
        # Compiled from the text read then, which is what the retained state keeps: a
        # restart recompiles the same recipe even if the file changed or moved since.
        # Set first: the collector's provenance names it.
        self.recipes[channel] = RecipeSource(
            prepared.file, prepared.text, dict(prepared.parameters), str(folder.resolve())
        )
        # No file yet: the collector creates them when the test starts.
        collector = self.new_collector(channel, program.name, runner.test_id, folder)
        self.attach_results(channel, collector)
        return runner

    def new_collector(
        self, channel: str, recipe: str, test_id: str, folder: Path | None
    ) -> ResultCollector:
        """The result files of test ``test_id`` of ``channel`` in ``folder`` (the one place
        a test's collector is made: a new test, a test resumed after a restart)."""
        c = next(c for c in self.cfg.channels if c.name == channel)
        return ResultCollector(
            channel,
            recipe,
            test_id,
            folder,
            dba=c.source.board or 0,
            aux_columns=self.record_columns.get(channel, ()),
            writer=self.summaries,
            rows=self.rows,
            metadata=self.test_metadata.get(channel, TestMetadata()),
            provenance=self.provenance(channel, recipe, test_id),
        )

    def new_test_id(self, channel: str) -> str:
        """A new test id for ``channel``: ``<UTC date>-<UTC time>-<channel>``, with ``-2``,
        ``-3``… when that folder exists already or the id was given out in this process
        (two tests started in the same second: a reset and a start are quick)."""
        runner = self.runners[channel]
        wall = self.clock.to_wall(self.clock.now())
        base = time.strftime("%Y%m%d-%H%M%S", time.gmtime(wall)) + f"-{channel}"
        root = self.results_roots.get(channel, Path(self.cfg.state_dir) / "results")
        n, test_id = 1, base
        while test_id in self._test_ids or (root / test_id).exists() or test_id == runner.test_id:
            n += 1
            test_id = f"{base}-{n}"
        self._test_ids.add(test_id)
        return test_id

    def _begin_test(self, channel: str) -> ResultCollector:
        """The chain started a new test (a start after a reset): its own collector and
        folder, beside the previous test's (which ended and closed its files)."""
        runner = self.runners[channel]
        assert runner.program is not None
        root = self.results_roots.get(channel, Path(self.cfg.state_dir) / "results")
        folder = root / runner.test_id
        collector = self.new_collector(channel, runner.program.name, runner.test_id, folder)
        self.attach_results(channel, collector)
        src = self.recipes.get(channel)
        if src is not None:
            # What the retained state keeps: a restart resumes this test in its folder.
            self.recipes[channel] = replace(src, folder=str(folder.resolve()))
        log.info("%s: test %s started; results in %s", channel, runner.test_id, folder)
        return collector

    def provenance(self, channel: str, recipe: str, test_id: str) -> Provenance | None:
        """What produces test ``test_id`` of ``channel``: its recipe as loaded (None when
        none is, e.g. a test resumed whose ``provenance.json`` was written at its start),
        the I/O map and the channel's section of it."""
        src = self.recipes.get(channel)
        if src is None:
            return None
        program = self.runners[channel].program
        return Provenance(
            bench=self.cfg.bench,
            channel=channel,
            test_id=test_id,
            recipe_name=recipe,
            recipe_file=src.file,
            recipe_text=src.text,
            parameters_given=dict(src.parameters),
            parameters_resolved=dict(program.parameters) if program is not None else {},
            io_map_file=self.cfg.source_file,
            io_map_sha256=self.cfg.source_sha256,
            io_map_channel=self.channel_section(channel),
        )

    def channel_section(self, channel: str) -> dict[str, object]:
        """The I/O map's part that makes ``channel``'s measurements: its section (limits,
        tags), its source device (with its calibration) and the mappings (scaling) of the
        tags it names."""
        c = next(c for c in self.cfg.channels if c.name == channel)
        named = {
            t
            for t in (c.voltage_tag, c.current_tag, c.temperature_tag, c.contactor_tag)
            if t is not None
        }
        tags = [
            m.model_dump(mode="json")
            for m in self.cfg.tags
            if m.name in named or m.name.startswith(f"{channel}.")
        ]
        return {
            "channel": c.model_dump(mode="json"),
            "source_device": self.cfg.devices[c.source.device].model_dump(mode="json"),
            "tags": tags,
        }

    def set_test_metadata(self, channel: str, given: dict[str, Any], replace: bool) -> None:
        """The metadata of ``channel``'s next test: ``given`` (checked fields) over the
        pending ones (``replace``: instead of them, a new load). A collector made already
        whose test has not begun (the recipe was loaded before) takes them too."""
        base = TestMetadata() if replace else self.test_metadata.get(channel, TestMetadata())
        md = base.updated(given)
        self.test_metadata[channel] = md
        collector = self.results.get(channel)
        if collector is not None and collector.first_t is None and not collector.closed:
            collector.metadata = md
            self._publish_cell(channel, md.cell_id)

    def _publish_cell(self, channel: str, cell_id: str) -> None:
        """``chN.chain.cell_id``: the cell of the channel's test (historian, InfluxDB's
        ``cell_id`` tag, OPC UA), like ``chN.chain.test_id``."""
        tag = self.db.get(f"{channel}.chain.cell_id")
        if tag is not None and tag.value != cell_id:
            self.db.update(tag, cell_id)

    def cell_under_test(self, cell_id: str, channel: str) -> tuple[str, str] | None:
        """The channel and test other than ``channel`` under way with cell ``cell_id``."""
        for name, collector in self.results.items():
            if name == channel or collector.closed or collector.metadata.cell_id != cell_id:
                continue
            if self.runners[name].state in ACTIVE:
                return name, collector.test_id
        return None

    def attach_results(self, channel: str, collector: ResultCollector) -> None:
        """Feed ``channel``'s chain events and records to ``collector`` (instead of the
        previous test's): the summary is rewritten at every timeline event, final when
        the test ends. A start that makes a new test (``ChainRunner.new_test_id``) gets
        a collector of its own (``_begin_test``)."""
        self.detach_results(channel)
        runner = self.runners[channel]

        def on_event(ev: ChainEvent) -> None:
            if collector.test_id != runner.test_id:
                if collector.closed or collector.first_t is None:
                    if runner.state in ACTIVE and self.results.get(channel) is collector:
                        self._begin_test(channel).on_event(ev)
                    return
                # Never reached: a test under way keeps its id until it ends.
                log.error(
                    "%s: test %s under way while the chain runs %s; results kept in %s",
                    channel,
                    collector.test_id,
                    runner.test_id,
                    collector.folder,
                )
            if collector.first_t is None and runner.state not in ACTIVE:
                return  # not this test's yet (e.g. the next recipe being loaded)
            collector.on_event(ev)
            if ev.kind == "state" and runner.state in FINAL:
                collector.close(runner.end_reason, runner.state.value, now=ev.t)
                log.info("%s: results in %s", channel, collector.folder)
            elif ev.kind in TIMELINE_KINDS:
                collector.checkpoint(runner.state.value, now=ev.t)

        def on_record(rec: Record) -> None:
            collector.on_record(rec)

        self._publish_cell(channel, collector.metadata.cell_id)
        on_event._results = True  # type: ignore[attr-defined]
        on_record._results = True  # type: ignore[attr-defined]
        runner.listeners.append(on_event)
        runner.recorders.append(on_record)
        self.results[channel] = collector

    def detach_results(self, channel: str) -> None:
        runner = self.runners[channel]
        runner.listeners[:] = [e for e in runner.listeners if not getattr(e, "_results", False)]
        runner.recorders[:] = [r for r in runner.recorders if not getattr(r, "_results", False)]
        self.results.pop(channel, None)

    def retain(self) -> list[str]:
        """Keep this bench's state under ``<state_dir>/state.sqlite``: bring back what the
        last run left (before the first scan), then save it from every scan on. Returns
        what the restore did or could not do, one line each."""
        if self.retention is None:
            self.retention = Retention.attach(self)
        return self.retention.report

    def record_history(self) -> Historian | None:
        """Record this bench's history (``<state_dir>/history.sqlite`` unless configured
        otherwise; none when ``history.enabled`` is false or InfluxDB is configured): from
        ``start`` on, until ``shutdown`` writes what is queued."""
        if self.historian is None:
            self.historian = attach_historian(self)
        return self.historian

    def tag_dims(self) -> dict[str, Dim]:
        out: dict[str, Dim] = {}
        for t in self.db:
            if t.spec.dtype == "bool":
                out[t.name] = Dim.BOOL
            elif t.spec.dtype in ("float", "int"):
                out[t.name] = UNIT_DIMS.get(t.spec.unit, Dim.NONE)
        return out

    @property
    def cells(self) -> dict[str, BatteryModel]:
        """Battery models of the simulated Chadèche boards, by ``<device>.b<address>``."""
        return self.sim.cells if self.sim is not None else {}

    async def start(self) -> None:
        """Start the in-process simulators (if the I/O map has any) and the InfluxDB
        writer's threads before scanning."""
        if self.sim is not None and not self._started:
            await self.sim.start()
        if self.historian is not None and not self.historian.writer.running:
            await self.historian.start()  # its file checked and opened before the first scan
        if self.influx is not None and not self._started:
            # Opening the spool checks the file (off the loop: it may be large).
            await asyncio.to_thread(self.influx.start)
        if self.sparkplug is not None and not self._started:
            # Its bdSeq in the retained state (``retain`` came first), on disk before the
            # CONNECT that carries it: off the loop.
            keep_bd_seq(self.sparkplug, self.retention.store if self.retention else None)
            self.sparkplug.commander = command_handler(self.commands, asyncio.get_running_loop())
            await asyncio.to_thread(self.sparkplug.start)
        self._started = True

    async def run(self, stop: asyncio.Event) -> None:
        await self.start()
        await self.engine.run(stop)

    async def shutdown(self) -> dict[str, str]:
        """Every output to its safe state, then close; continue past failures.

        Returns the devices that could not confirm their safe state, each with why (empty:
        every device confirmed it). A stop never claims what it did not see.
        """
        for ch in self.channels.values():
            ch.go_safe()
        self.engine.scan_once()  # queue the zero setpoints
        now = self.clock.now()
        # Safety first: every device safe before anything is written to disk.
        unconfirmed: dict[str, str] = {}
        for name, d in self.drivers.items():
            try:
                await d.poll()  # flush the queued safe writes through the normal path
            except Exception:
                log.exception("%s: flushing safe writes failed", d.name)
            try:
                why = await d.safe_state()
            except Exception as exc:  # a driver bug must not hide the others' state
                log.exception("%s: safe state failed", d.name)
                why = f"safe state failed: {exc}"
            if why is not None:
                unconfirmed[name] = why
            try:
                await d.close()
            except Exception:
                log.exception("%s: close failed", d.name)
        for name, collector in self.results.items():
            runner = self.runners[name]
            if runner.state in ACTIVE:
                # Not the end of the test: it is retained and comes back Held at the next
                # start, so its summary is not final.
                collector.close("supervisor stopped", runner.state.value, complete=False, now=now)
            elif runner.state not in FINAL:
                collector.close("supervisor stopped", runner.state.value, now=now)
        if self.rows is not None:
            # Every row on disk (each test's close wrote its own) and the thread ended.
            await asyncio.to_thread(self.rows.stop)
        if self.summaries is not None:
            # Every checkpoint on disk and the writer's thread ended (a later checkpoint,
            # a bench started again, is written at once).
            await asyncio.to_thread(self.summaries.stop)
        if self.historian is not None:
            await self.historian.stop()  # everything queued written: a clean stop loses none
        await self._close_stores()
        if self.sim is not None:
            await self.sim.stop()
        self._started = False
        if unconfirmed:
            log.error(
                "bench %s: safe state NOT confirmed for %s",
                self.cfg.bench,
                "; ".join(f"{n}: {why}" for n, why in unconfirmed.items()),
            )
        else:
            log.info("bench %s: all outputs safe", self.cfg.bench)
        return unconfirmed

    async def _close_stores(self) -> None:
        """The Sparkplug edge node, the retained state and InfluxDB's writer, closed off the
        event loop (each waits for its thread)."""
        if self.sparkplug is not None:
            # What is queued, then the NDEATH and a clean disconnect (before the retained
            # state closes: a reconnection in between would save its bdSeq there).
            await asyncio.to_thread(self.sparkplug.close)
        if self.retention is not None:
            # Waits for the writer thread (the last save on disk): not on the event loop.
            await asyncio.to_thread(self.retention.close)
            self.retention = None
        if self.influx is not None:
            # Spools what is queued, sends for at most influxdb.stop_flush_s, keeps the rest.
            await asyncio.to_thread(self.influx.close)


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


def _scan_publishers(
    given: list[Publisher] | None, alarms: AlarmManager, db: TagDB, *more: Publisher | None
) -> list[Publisher]:
    """The scan's publishers: the caller's, the alarm KPIs (the ``alarms.*`` tags, ISA-18.2
    figures refreshed once a second: before InfluxDB and Sparkplug, which then send them the
    same scan), then ``more`` that are configured (InfluxDB's writer, the Sparkplug edge
    node)."""
    return [*(given or []), AlarmKpi(alarms, db), *(p for p in more if p is not None)]


def _chain_runners(
    db: TagDB, clock: Clock, channels: dict[str, Channel], recorded: dict[str, list[RecordColumn]]
) -> dict[str, ChainRunner]:
    """One chain runner per channel: it sees its channel through the channel's tags only
    (chains/port.py)."""
    return {
        name: ChainRunner(
            ChannelPort.from_tags(
                db, name, Mode.AUTO.value, Mode.MANUAL.value, tuple(r.tag for r in recorded[name])
            ),
            db,
            clock,
        )
        for name in channels
    }


def build_bench(
    cfg: BenchConfig,
    clock: Clock,
    publishers: list[Publisher] | None = None,
    *,
    simulate: bool = True,
    in_process: bool = False,
    registry: Registry = REGISTRY,
) -> Bench:
    """Wire a bench.

    ``simulate=False`` skips the simulators of ``sim: true`` devices (another process, e.g.
    ``supervisor sim``, serves them). ``in_process=True`` has every driver of a simulated
    device talk to its simulator in this process instead of over loopback (dry runs and
    virtual-clock tests: deterministic, nothing listens). A kind whose simulator cannot be
    served (a simulated SPI bus) is always in process. ``registry``: the device kinds
    ``cfg`` was loaded with.
    """
    db = TagDB()
    sim = build_simulation(
        cfg, clock, in_process_only=not simulate, in_process=in_process, registry=registry
    )
    drivers: dict[str, Driver] = {}
    stale: dict[str, float] = {}
    for name, dev in cfg.devices.items():
        kind = registry.kind_of(dev)
        own = sim.devices.get(name) if sim is not None else None
        linked = own is not None and (in_process or kind.in_process_only)
        wiring = DriverWiring(clock, cfg, own if linked else None)
        drivers[name] = kind.build_driver(name, dev, wiring)
        stale[name] = dev.stale_after_s

    inputs: list[InputBinding] = []
    outputs: list[OutputBinding] = []
    for m in cfg.tags:
        drv = drivers[m.device]
        info = cfg.devices[m.device].points()[m.point]
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
        source = cfg.devices[c.source.device].channel_source()
        assert source is not None and source.points is not None  # refused by the bench checks
        pts = source.points(c.source.board)
        ch = Channel(
            c.name,
            db,
            ChannelLimits(c.limits.current_a, c.limits.voltage_v, c.limits.temperature_c),
            capacity_ah=c.capacity_ah,
            temperature_tag=c.temperature_tag,
            voltage_tag=c.voltage_tag,
            current_tag=c.current_tag,
            contactor_tag=c.contactor_tag,
            has_output_switch=pts.output is not None,
            has_output_feedback=pts.output_fb is not None,
            has_voltage_setpoint=pts.voltage_set is not None,
        )
        drv = drivers[c.source.device]
        st = stale[c.source.device]
        if c.voltage_tag is None:
            inputs.append(InputBinding(ch.voltage, drv, pts.voltage, None, st))
        if c.current_tag is None:
            inputs.append(InputBinding(ch.current, drv, pts.current, None, st))
        outputs.append(OutputBinding(ch.current_cmd, drv, pts.current_set))
        if ch.output_cmd is not None and pts.output is not None:
            outputs.append(OutputBinding(ch.output_cmd, drv, pts.output))
        if ch.output_fb is not None and pts.output_fb is not None:
            inputs.append(InputBinding(ch.output_fb, drv, pts.output_fb, None, st))
        if ch.voltage_cmd is not None and pts.voltage_set is not None:
            outputs.append(OutputBinding(ch.voltage_cmd, drv, pts.voltage_set))
        channels[c.name] = ch

    # The chain sees its channel through the channel's tags only (chains/port.py).
    recorded = {c.name: record_columns(cfg, c) for c in cfg.channels}
    runners = _chain_runners(db, clock, channels, recorded)
    displays: dict[str, ChadecheDisplay] = {}
    for c in cfg.channels:
        displays[c.name] = ChadecheDisplay(c.name, dba=c.source.board or 0)
        runners[c.name].samplers.append(displays[c.name])
    alarms = AlarmManager(clock)
    safety = build_safety(cfg, db, alarms)
    # The historian (attach_historian) and the InfluxDB writer store the same changes by
    # the same rule: one feed, filtered once per scan.
    changes = SharedChanges(db, clock)
    influx = build_influx(cfg, db, clock, alarms, changes)
    sparkplug = build_sparkplug(cfg, db, clock, changes, alarms)
    phases = ScanPhases(
        derived=[LogicPhase(f"derive:{n}", ch.derive) for n, ch in channels.items()],
        safety=[LogicPhase("safety", safety.run)],
        chains=[LogicPhase(f"chain:{n}", r.run) for n, r in runners.items()],
        # The chain requests, then the channel protects: a chain never overrides a trip.
        outputs=[LogicPhase(f"drive:{n}", ch.drive) for n, ch in channels.items()],
    )
    engine = ScanEngine(
        clock,
        db,
        cfg.scan.period_s,
        drivers=list(drivers.values()),
        inputs=inputs,
        outputs=outputs,
        phases=phases.ordered(),
        publishers=_scan_publishers(publishers, alarms, db, influx, sparkplug),
    )
    if cfg.scan.realtime_priority is not None:
        engine.realtime = RealtimePriority(cfg.scan.realtime_priority)
    bench = Bench(
        cfg,
        clock,
        db,
        engine,
        drivers,
        channels,
        sim,
        runners,
        safety=safety,
        alarms=alarms,
        displays=displays,
        influx=influx,
        sparkplug=sparkplug,
        record_columns={n: tuple(r.label for r in cols) for n, cols in recorded.items()},
    )
    bench.changes = changes
    if influx is not None:
        bench.events.sinks.append(influx)
        bench.events.attach(bench)
    return bench
