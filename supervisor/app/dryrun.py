"""``supervisor dry-run``: a recipe against the battery model, on the virtual clock.

The same compiler, step-chain engine, channel logic and drivers as on a bench; only the
source is simulated (a Chadèche board with a NiMH cell, or an EA-PSB supply with a Li-ion
pack when the recipe needs constant voltage: the real EA driver talking SCPI to the EA
simulator in process) and time is virtual.

Or a channel of an I/O map (``io_map``, ``channel``): that channel's own plant, every
device of the map simulated in this process (its supply, its pack or cell, its sensors,
the contactor and the e-stop sense, wired as the map's ``simulation:`` section says), the
channel's own limits and tags, at the capacity asked for (default: the map's). Nothing of
the map's services (screens, OPC UA, Modbus server, InfluxDB, historian) is built.

Every dry run ends with a clear message in bounded memory: the chain reaches an end
(Complete, Stopped, Aborted, or Held by an alarm: ``finished``), or the run stops at the
``max_hours`` cap and says where it was (step, cycle, test time) instead of predicting a
duration. The timeline, the step sequence and the per-cycle figures keep their first and
last halves (``DRY_RUN_EVENTS_KEPT``, ``DRY_RUN_CYCLES_KEPT``) and count the rest; result
files (``results_dir``) are written row by row as the run goes.
"""

from __future__ import annotations

import gc
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final

from supervisor.app.bench import Bench, build_bench
from supervisor.chains.compiler import Target, compile_recipe
from supervisor.chains.engine import ChainRunner, State
from supervisor.chains.kinds import kind_of
from supervisor.chains.program import Program
from supervisor.chains.run import ChainSnapshot
from supervisor.commands.recipes import read_recipe_text
from supervisor.config.limits import DRY_RUN_CYCLES_KEPT, DRY_RUN_EVENTS_KEPT
from supervisor.config.models import (
    BenchConfig,
    DeviceConfig,
    LinearScaling,
    SimulationConfig,
    SpanScaling,
    TagMapping,
)
from supervisor.config.recipe import Recipe, load_recipe, load_recipe_text
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigError
from supervisor.core.heap import settle_after_start
from supervisor.core.records import Record
from supervisor.core.units import parse_quantity
from supervisor.devices.registry import bench_from_data
from supervisor.publish.provenance import Provenance, TestMetadata
from supervisor.publish.results import FirstAndLast, ResultCollector

TERMINAL = (State.COMPLETE, State.STOPPED, State.ABORTED, State.HELD)
DEFAULT_START = "08:00"
DEFAULT_PERIOD_S = 1.0
"""A dry run's scan period (``--period-s``), on the built-in bench or an I/O map's: time
resolution enough for hours-long steps; the map's own scan (0.1 s) made a dry run of ch4 on
io_maps/sim.yaml about seven times slower."""
DRY_RUN_CELL_TEMPERATURE_TAG = "cell0.temperature"
"""The NiMH dry-run bench's tag for the simulated cell's temperature."""
CHUNK_S = 600.0
"""Virtual time run between two looks at the chain's state (the last chunk stops at the
cap exactly)."""
DRY_RUN_YIELD_SCANS = 1000
"""Scans between two turns of the event loop in a dry run (``ScanEngine.yield_every_scans``)."""


@dataclass
class DryRunResult:
    program: Program
    state: State
    end_reason: str
    simulated_s: float
    wall_s: float
    summary: dict[str, Any]
    step_sequence: list[tuple[str, str]] = field(default_factory=list)  # (step id, cause)
    finished: bool = True
    """The chain came to an end (Complete, Stopped, Aborted, Held); False: the run stopped
    at ``max_hours`` with the chain still going (``supervisor dry-run`` exits 1)."""
    max_hours: float = 0.0
    steps_omitted: int = 0
    """Step starts between the first and the last halves of ``step_sequence``."""
    cpu_s: float = 0.0
    """This process's CPU time over the same loop as ``wall_s`` (``time.process_time``):
    what a loaded machine moves least (issue 29: at load average 3–12 one tree's wall ratio
    ranged 17,300–53,700×, its CPU-time ratio 48,500–54,000× in the same runs)."""

    @property
    def ratio(self) -> float:
        return self.simulated_s / self.wall_s if self.wall_s > 0 else float("inf")

    @property
    def cpu_ratio(self) -> float:
        """Simulated time over ``cpu_s``: the speed a benchmark on a shared machine can
        compare between two trees (docs/performance.md, issue 29)."""
        return self.simulated_s / self.cpu_s if self.cpu_s > 0 else float("inf")


def _epoch(start: str) -> float:
    """Local wall time of today's (2026-01-01) HH:MM, for reproducible sleeps."""
    hh, mm = (int(x) for x in start.split(":"))
    return time.mktime((2026, 1, 1, hh, mm, 0, 0, 0, -1))


def dry_run_config(
    model: str, capacity_ah: float, soc: float, period_s: float, cells: int = 1
) -> BenchConfig:
    """The dry-run bench: one channel ``ch0`` on a simulated source.

    ``nimh-aa``: a Chadèche board with its cell; the cell's temperature comes through the
    simulated board's simulation-only ``b0.temperature`` point (a real board has no
    sensor) as the channel's ``temperature_tag``, so recipe temperature limits and
    terminations and the channel's temperature limit act in the dry run. Otherwise an
    EA-PSB supply (``sim: true``) on a Li-ion pack of ``cells`` in series; build it with
    ``in_process=True`` (the driver talks to the simulator in this process, nothing
    listens on its port).
    """
    if model == "nimh-aa":
        return bench_from_data(
            {
                "bench": "dry_run",
                "scan": {"period_s": period_s},
                "devices": {
                    "chadeche": {
                        "driver": "chadeche",
                        "poll_period_s": period_s,
                        "stale_after_s": max(1.0, 3 * period_s),
                        "boards": [
                            {
                                "address": 0,
                                "sim": {"model": model, "capacity_ah": capacity_ah, "soc": soc},
                            }
                        ],
                    }
                },
                "tags": [
                    {
                        "name": DRY_RUN_CELL_TEMPERATURE_TAG,
                        "device": "chadeche",
                        "point": "b0.temperature",
                        "unit": "degC",
                        "description": "simulated cell temperature (simulation only)",
                    }
                ],
                "channels": [
                    {
                        "name": "ch0",
                        "source": {"device": "chadeche", "board": 0},
                        "capacity_ah": capacity_ah,
                        "limits": {"current_a": [-0.4, 0.4], "voltage_v": [0.2, 2.0]},
                        "temperature_tag": DRY_RUN_CELL_TEMPERATURE_TAG,
                    }
                ],
            }
        )
    i_max_a = 10 * capacity_ah
    v_max = 4.35 * cells
    # The simulated unit is a PSB 10060-60 (60 V, 60 A, 1500 W), rated up to the channel's
    # limits where they are higher, as a real bench's unit must be: the EA driver refuses,
    # at connect, limits above the nominal ratings; and its power limit must not cut a
    # current the channel allows.
    nominal_v = max(60.0, v_max)
    nominal_a = max(60.0, i_max_a)
    nominal_w = max(1500.0, v_max * i_max_a)
    # The unit's interface watchdog: 10 polls, as io_maps/sim.yaml (2 s at 0.2 s). Nothing
    # stops polling in a dry run; it only has to satisfy the driver's keep-alive rule.
    watchdog_s = 10 * period_s
    return bench_from_data(
        {
            "bench": "dry_run",
            "scan": {"period_s": period_s},
            "devices": {
                "supply": {
                    "driver": "ea-psb",
                    "sim": True,
                    "host": "127.0.0.1",
                    "poll_period_s": period_s,
                    "stale_after_s": max(1.0, 3 * period_s),
                    "watchdog_s": watchdog_s,
                    "sim_nominal_v": nominal_v,
                    "sim_nominal_a": nominal_a,
                    "sim_nominal_w": nominal_w,
                }
            },
            "channels": [
                {
                    "name": "ch0",
                    "source": {"device": "supply"},
                    "chemistry": "liion",
                    "capacity_ah": capacity_ah,
                    "limits": {
                        "current_a": [-i_max_a, i_max_a],
                        "voltage_v": [2.0 * cells, v_max],
                    },
                }
            ],
            "simulation": {
                "pack": {
                    "model": "liion-pack",
                    "cells_series": cells,
                    "capacity_ah": capacity_ah,
                    "soc": soc,
                }
            },
        }
    )


def channel_dry_run_config(
    cfg: BenchConfig,
    channel: str,
    capacity_ah: float | None = None,
    soc: float | None = None,
    period_s: float | None = None,
) -> BenchConfig:
    """``cfg``'s bench made a dry run's for ``channel``: every device simulated (in process,
    on loopback addresses nothing listens on), no services; ``capacity_ah``/``soc`` (None:
    the map's) set the channel's cell or pack in the plant and the channel's rated capacity
    (C-rates); ``period_s`` (None: the map's) the scan period. ConfigError for a channel
    the map does not have."""
    names = [c.name for c in cfg.channels]
    if channel not in names:
        raise ConfigError(
            f"no channel {channel!r} in the I/O map (it has {', '.join(names) or 'none'})",
            cfg.source_file or None,
        )
    data = cfg.model_dump(mode="python", exclude_unset=True)
    for key in MAP_SERVICES:
        data.pop(key, None)
    data["history"] = {"enabled": False}
    data["devices"] = {name: _simulated(dev) for name, dev in cfg.devices.items()}
    if period_s is not None:
        data["scan"] = {**data.get("scan", {}), "period_s": period_s}
        data["scan"].pop("realtime_priority", None)
    ch = next(c for c in data["channels"] if c["name"] == channel)
    if cfg.simulation is None:
        data["simulation"] = implied_simulation(cfg, channel)
    cell = _cell_of(data, ch)
    if capacity_ah is not None:
        cell["capacity_ah"] = ch["capacity_ah"] = capacity_ah
    if soc is not None:
        cell["soc"] = soc
    return bench_from_data(data, cfg.source_file or "<dry run>")


MAP_WARMUP_S: Final = 5.0
"""Scanned before a dry run on an I/O map starts its recipe: every device connected and
every slow input in (the BMS sends its pack voltage once a second), as an operator starts
a test on a bench that has been up a while."""
MAP_SERVICES: Final = (
    "hmi",
    "opcua",
    "modbus_server",
    "influxdb",
    "sparkplug",
    "identification",
    "recipes",
)
"""What a dry run on an I/O map leaves out: it serves nothing and publishes nothing."""


def _simulated(dev: DeviceConfig) -> dict[str, Any]:
    """A device's I/O map entry made simulated, whatever its kind says a simulation is: a
    Chadèche ``backend: sim``, a network device's ``sim: true`` on loopback (a BMS on
    kernel SocketCAN through the socketcand simulator)."""
    data = dev.model_dump(mode="python", exclude_unset=True)
    fields = type(dev).model_fields
    if "backend" in fields:
        data["backend"] = "sim"
    elif "sim" in fields:
        data["sim"] = True
    if "host" in fields:
        data["host"] = "127.0.0.1"
    if data.get("interface") == "socketcan":
        data["interface"] = "socketcand"
    return data


LIION_CELL_MAX_V: Final = 4.2
"""A Li-ion cell's charge voltage: how many cells in series a channel's limit implies."""


def implied_simulation(cfg: BenchConfig, channel: str) -> dict[str, Any]:
    """The ``simulation:`` section a map without one implies for ``channel`` (a real bench's:
    its devices are not simulated, so it may not wire a simulation itself): the inputs and
    outputs the channel's tags name outside its source (current sensor, voltage board,
    temperature, contactor and its auxiliary contact; the e-stop sense the safety section or
    a permissive names), with the sensors' scale from the tags' scaling, and a Li-ion pack
    of the channel's capacity with as many cells in series as its upper voltage limit
    holds."""
    c = next(c for c in cfg.channels if c.name == channel)
    tags = {t.name: t for t in cfg.tags}

    def wired(tag: str | None, relay: bool = False) -> TagMapping | None:
        m = tags.get(tag) if tag is not None else None
        if m is None or m.device == c.source.device:
            return None
        info = cfg.devices[m.device].points().get(m.point)
        is_relay = info is not None and info.direction == "out" and info.dtype == "bool"
        analog = info is not None and info.direction == "in" and info.dtype == "float"
        return m if (is_relay if relay else analog) else None

    estop = cfg.safety.estop.tag if cfg.safety.estop is not None else None
    sense = wired(estop) or next((wired(p) for p in c.permissives if wired(p)), None)
    points: dict[str, TagMapping | None] = {
        "lem_current": wired(c.current_tag),
        "voltage_board": wired(c.voltage_tag),
        "estop_sense": sense,
        "contactor": wired(c.contactor_tag, relay=True),
        "contactor_feedback": wired(c.contactor_feedback_tag),
    }
    out: dict[str, Any] = {
        k: {"device": m.device, "point": m.point} for k, m in points.items() if m is not None
    }
    for ratio_key, m in (
        ("lem_volts_per_amp", points["lem_current"]),
        ("voltage_board_ratio", points["voltage_board"]),
    ):
        if m is not None and m.scaling is not None:
            out[ratio_key] = _raw_per_unit(m)
    temperature = wired(c.temperature_tag)
    if temperature is not None:
        out["thermocouples"] = [{"device": temperature.device, "point": temperature.point}]
    cells = max(1, int(c.limits.voltage_v[1] / LIION_CELL_MAX_V + 1e-9))
    out["pack"] = {"model": "liion-pack", "cells_series": cells, "capacity_ah": c.capacity_ah}
    return out


def _raw_per_unit(m: TagMapping) -> float:
    """A sensor's raw units per engineering unit from its tag's scaling (V/A, V/V)."""
    scaling = m.scaling
    if isinstance(scaling, SpanScaling):
        return (scaling.raw[1] - scaling.raw[0]) / (scaling.eu[1] - scaling.eu[0])
    assert isinstance(scaling, LinearScaling)
    return 1.0 / scaling.a


def _cell_of(data: dict[str, Any], ch: dict[str, Any]) -> dict[str, Any]:
    """The simulated battery behind a channel in the bench's data (made in place): a
    board's cell (``boards[].sim``) or the plant's pack (``simulation.pack``)."""
    source = ch["source"]
    boards = data["devices"][source["device"]].get("boards")
    if source.get("board") is not None and boards is not None:
        board = next(b for b in boards if b.get("address") == source["board"])
        cell: dict[str, Any] = board.setdefault("sim", {})
        return cell
    simulation = data.setdefault("simulation", {})
    pack: dict[str, Any] = simulation.setdefault(
        "pack", SimulationConfig().pack.model_dump(mode="python")
    )
    return pack


@dataclass
class _Plant:
    """The bench a dry run runs on and the channel it runs."""

    bench: Bench
    channel: str
    warmup_s: float
    """Scanned before the start: every device connected, its first images in."""
    scan_period_s: float | None = None
    """The real bench's scan period, which the recipe is checked against (a pulse shorter
    than it is refused there, not because the dry run scans more coarsely); None: the
    dry-run bench's own."""
    io_map_file: str = ""
    io_map_sha256: str = ""

    def target(self) -> Target:
        """What the recipe may ask of the channel, checked as on the real bench."""
        target = self.bench.target(self.channel)
        if self.scan_period_s is None:
            return target
        return replace(target, scan_period_s=self.scan_period_s)


def _builtin_plant(
    recipe: Recipe,
    clock: VirtualClock,
    model: str | None,
    capacity_ah: float | None,
    soc: float | None,
    cells: int,
    period_s: float,
) -> _Plant:
    """The dry-run bench of :func:`dry_run_config`: a model the recipe suggests (a Li-ion
    pack when it needs constant voltage or says so), at the recipe's capacity by default."""
    needs_cv = any(kind_of(s.kind).needs_cv for s in recipe.steps)
    if model is None:
        model = "liion-pack" if needs_cv or recipe.chemistry in ("liion", "lfp") else "nimh-aa"
    cap = capacity_ah
    if cap is None and recipe.capacity is not None:
        cap = parse_quantity(recipe.capacity).value
    cap = cap if cap is not None else 2.0
    if soc is None:
        soc = 0.9 if model == "nimh-aa" else 0.5
    bench = build_bench(dry_run_config(model, cap, soc, period_s, cells), clock, in_process=True)
    assert bench.sim is not None  # every dry-run source is simulated
    # The dry-run bench has no contactor relay (no ADAM), but the plant only lets current
    # flow between supply and pack with its contactor closed: close it for good (the
    # ideal supply that dry runs used before did the same at connect).
    bench.sim.plant.set_contactor(True)
    return _Plant(bench, "ch0", 3 * period_s)


def _map_plant(
    cfg: BenchConfig,
    channel: str | None,
    clock: VirtualClock,
    capacity_ah: float | None,
    soc: float | None,
    period_s: float,
) -> _Plant:
    """A channel of an I/O map on its own plant (:func:`channel_dry_run_config`); the only
    channel when none is named."""
    if channel is None:
        if len(cfg.channels) != 1:
            names = ", ".join(c.name for c in cfg.channels)
            raise ConfigError(
                f"name the channel to dry-run (the I/O map has {names})", cfg.source_file or None
            )
        channel = cfg.channels[0].name
    dry = channel_dry_run_config(cfg, channel, capacity_ah, soc, period_s)
    bench = build_bench(dry, clock, in_process=True)
    return _Plant(
        bench, channel, MAP_WARMUP_S, cfg.scan.period_s, cfg.source_file, cfg.source_sha256
    )


async def dry_run(
    recipe_path: str | Path,
    *,
    model: str | None = None,
    params: dict[str, str] | None = None,
    capacity_ah: float | None = None,
    soc: float | None = None,
    cells: int = 1,
    period_s: float = DEFAULT_PERIOD_S,
    start: str = DEFAULT_START,
    max_hours: float = 1000.0,
    results_dir: Path | None = None,
    text: str | None = None,
    recorders: Sequence[Callable[[Record], None]] = (),
    should_stop: Callable[[], bool] | None = None,
    io_map: BenchConfig | None = None,
    channel: str | None = None,
) -> DryRunResult:
    """``text``: the recipe's text (an upload not saved yet; ``recipe_path`` then only names
    it in messages and finds its profile CSVs). ``recorders`` get every result record (the
    HMI's preview trace). ``should_stop``: asked between chunks; True stops the run as the
    ``max_hours`` cap does (``finished`` False; the HMI's time limit). ``io_map``: run on
    ``channel``'s own plant in that bench (``model`` and ``cells`` are then the map's; its
    scan runs at ``period_s`` too: a dry run's resolution, not the bench's reaction time);
    without it, on the built-in dry-run bench."""
    if text is not None:
        recipe, pos = load_recipe_text(text, str(recipe_path))
    else:
        recipe, pos = load_recipe(recipe_path)
    clock = VirtualClock(wall_epoch_s=_epoch(start))
    if io_map is None:
        plant = _builtin_plant(recipe, clock, model, capacity_ah, soc, cells, period_s)
    else:
        plant = _map_plant(io_map, channel, clock, capacity_ah, soc, period_s)
    bench, ch = plant.bench, plant.channel
    runner = bench.runners[ch]
    bench.displays[ch].period_s = float("inf")  # a dry run shows its report instead
    # Refused here, before anything is started or connected: nothing to shut down.
    program = compile_recipe(recipe, pos, str(recipe_path), plant.target(), params or {})
    runner.load(program, test_id=f"dryrun-{program.name}")
    collector = _collector(plant, program, recipe, recipe_path, text, params, results_dir)
    runner.listeners.append(collector.on_event)
    runner.recorders.append(collector.on_record)
    runner.recorders.extend(recorders)
    sequence: FirstAndLast[tuple[str, str]] = FirstAndLast(DRY_RUN_EVENTS_KEPT)

    def steps(ev: Any) -> None:
        text = ev.text
        if ev.kind == "step" and text.startswith("starting step"):
            cause = text[text.rfind("(") + 1 : -1]
            sequence.append((ev.step_id, cause))

    runner.listeners.append(steps)
    await bench.start()
    # The run's speed is measured as a whole (simulated over wall time), not scan by scan;
    # from the first scan on: a timed scan takes a branch by its wall duration (a new
    # longest scan), which made a dry run's bytecodes differ from run to run
    # (tests/unit/test_dry_run_cost.py).
    bench.engine.measure_durations = False
    await bench.engine.run_for(plant.warmup_s)  # first images in
    runner.command("start", actor="dry-run")
    # Nothing else runs on this loop during a chunk (should_stop is asked between chunks).
    bench.engine.yield_every_scans = DRY_RUN_YIELD_SCANS
    wall, cpu, sim0 = await _timed_run(bench, runner, clock, max_hours, should_stop)
    finished = runner.state in TERMINAL
    runner.listeners.remove(steps)  # the shutdown's last scans are not part of the run
    end = _end_reason(bench, ch, runner)
    snap = runner.snapshot()
    if not finished and snap is not None:
        end = cap_message(max_hours, snap, program)
    summary = collector.close(end, runner.state.value)
    await bench.shutdown()
    if finished:
        # The test ends at its last event, not at the end of the last simulated chunk.
        timeline = summary["timeline"]
        simulated = float(timeline[-1]["test_time_s"]) if timeline else clock.now() - sim0
    else:
        simulated = snap.test_time_s if snap is not None else clock.now() - sim0
    return DryRunResult(
        program,
        runner.state,
        end,
        simulated,
        wall,
        summary,
        list(sequence),
        finished=finished,
        max_hours=max_hours,
        steps_omitted=sequence.omitted,
        cpu_s=cpu,
    )


async def _timed_run(
    bench: Bench,
    runner: ChainRunner,
    clock: VirtualClock,
    max_hours: float,
    should_stop: Callable[[], bool] | None,
) -> tuple[float, float, float]:
    """The measured part of a dry run: chunks of virtual time until the chain ends, the
    ``max_hours`` cap or ``should_stop``; its wall and CPU seconds (``DryRunResult.wall_s``,
    ``cpu_s``) and the virtual time it began at."""
    with settled_heap():
        t0 = time.perf_counter()
        cpu0 = time.process_time()
        sim0 = clock.now()
        limit = sim0 + max_hours * 3600
        while runner.state not in TERMINAL and clock.now() < limit:
            if should_stop is not None and should_stop():
                break
            await bench.engine.run_for(min(CHUNK_S, limit - clock.now()))
        return time.perf_counter() - t0, time.process_time() - cpu0, sim0


def _collector(
    plant: _Plant,
    program: Program,
    recipe: Recipe,
    recipe_path: str | Path,
    text: str | None,
    params: dict[str, str] | None,
    results_dir: Path | None,
) -> ResultCollector:
    """The run's result files and summary, with what a real run's folder says: the I/O map
    the channel comes from (none for the built-in bench, built in code: its channel section
    stands for it)."""
    bench, ch = plant.bench, plant.channel
    test_id = bench.runners[ch].test_id
    return ResultCollector(
        ch,
        program.name,
        test_id,
        results_dir / test_id if results_dir else None,
        events_kept=DRY_RUN_EVENTS_KEPT,
        cycles_kept=DRY_RUN_CYCLES_KEPT,
        metadata=TestMetadata(chemistry=recipe.chemistry or "", operator="dry-run"),
        provenance=Provenance(
            bench=bench.cfg.bench,
            channel=ch,
            test_id=test_id,
            recipe_name=program.name,
            recipe_file=str(recipe_path),
            recipe_text=text if text is not None else read_recipe_text(recipe_path),
            parameters_given=dict(params or {}),
            parameters_resolved=dict(program.parameters),
            io_map_file=plant.io_map_file,
            io_map_sha256=plant.io_map_sha256,
            io_map_channel=bench.channel_section(ch),
        ),
    )


def _end_reason(bench: Bench, ch: str, runner: ChainRunner) -> str:
    """How the chain ended; Held: the alarm, fault or condition that held it."""
    end = runner.end_reason
    if runner.state is State.HELD:
        end = str(
            bench.db[f"{ch}.chain.alarm"].value
            or bench.db[f"{ch}.fault"].value
            or runner.hold_reason  # an until's `hold`: the condition that came true
            or end
        )
    return end


@contextmanager
def settled_heap() -> Iterator[bool]:
    """The heap settled for the run, as ``supervisor run`` settles it after start-up
    (``core/heap.py::settle_after_start``: collect, freeze what is alive, the collector's
    thresholds and the switch interval; ADR 0018 "Dry run"), and put back as it was after:
    ``dry_run`` is also called in long-lived processes (the HMI's preview worker, tests),
    which must not keep every object of each run frozen. Settled only when nothing else
    froze objects in this process (un-freezing would also release theirs); yields whether
    it settled. Nothing a run computes depends on it: only when the collector runs."""
    if gc.get_freeze_count() != 0:
        yield False
        return
    thresholds = gc.get_threshold()
    switch_s = sys.getswitchinterval()
    settle_after_start()
    try:
        yield True
    finally:
        gc.unfreeze()
        gc.set_threshold(*thresholds)
        sys.setswitchinterval(switch_s)


def cap_message(max_hours: float, snap: ChainSnapshot, program: Program) -> str:
    """Where a dry run stood when it reached its ``max_hours`` cap, and the likely why."""
    step = program.steps[snap.step]
    n = snap.step_count
    text = (
        f"did not finish within {max_hours:g} h (--max-hours): at test time"
        f" {hms(snap.test_time_s)} in step {snap.step_id!r} ({snap.step + 1} of"
        f" {len(program.steps)}) of cycle {snap.cycle} of {program.cycles},"
        f" after {n} step start{'s' if n != 1 else ''}"
    )
    ends_itself = kind_of(step.kind).ends_by_itself
    if step.duration_s is None and step.transitions and not ends_itself:
        text += (
            f"; step {step.id!r} has no duration and none of its until conditions came true"
            f" in {hms(snap.step_time_s)}"
        )
    return text


def hms(s: float) -> str:
    """``H:MM:SS`` (hours unbounded: ``1000:00:00``)."""
    s = round(s)
    return f"{s // 3600:d}:{s % 3600 // 60:02d}:{s % 60:02d}"


def _efficiency_note(cycle: dict[str, Any]) -> str:
    """Why a finished cycle has no efficiency, for its line of the report ("" otherwise)."""
    note = cycle["efficiency_note"]
    if cycle["coulombic_efficiency"] is not None or not cycle["complete"] or not note:
        return ""
    prefix = f"cycle {cycle['cycle']} "
    return f" ({note.removeprefix(prefix)})"


def format_report(res: DryRunResult) -> list[str]:
    summary = res.summary
    lines = [f"dry run of recipe {res.program.name!r} ({res.program.file})", "timeline:"]
    omitted, omitted_at = summary.get("timeline_omitted", 0), summary.get("timeline_omitted_at")
    for k, e in enumerate(summary["timeline"]):
        if omitted and k == omitted_at:
            lines.append(f"  … {omitted} events omitted …")
        if e["kind"] in ("step", "alarm"):
            lines.append(f"  {hms(e['test_time_s']):>10}  cycle {e['cycle']}  {e['text']}")
    lines.append("per cycle:")
    previous: int | None = None
    for c in summary["cycles"]:
        if previous is not None and c["cycle"] > previous + 1 and summary.get("cycles_omitted"):
            lines.append(f"  … {summary['cycles_omitted']} cycles omitted …")
        previous = c["cycle"]
        ce = c["coulombic_efficiency"]
        lines.append(
            f"  cycle {c['cycle']}: charged {c['charge_capacity_ah'] * 1000:.1f} mAh"
            f" ({c['charge_energy_wh']:.3f} Wh), discharged {c['discharge_capacity_ah'] * 1000:.1f}"
            f" mAh ({c['discharge_energy_wh']:.3f} Wh)"
            + (f", coulombic efficiency {ce:.3f}" if ce is not None else "")
            + _efficiency_note(c)
        )
    if res.finished:
        lines.append(f"predicted duration: {hms(res.simulated_s)} ({res.simulated_s / 3600:.2f} h)")
    else:
        lines.append(f"predicted duration: did not finish within {res.max_hours:g} h")
    lines.append(f"end: {res.state.value}: {res.end_reason}")
    lines.append(f"computed in {res.wall_s:.2f} s: simulated/wall ratio {res.ratio:,.0f}x")
    return lines
