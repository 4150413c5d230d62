"""Benchmarks behind ``supervisor bench``: they print figures, tests never time things."""

from __future__ import annotations

import asyncio
import dataclasses
import math
import sys
import time
from typing import Any

from supervisor.bench import report
from supervisor.bench.loadgen import SignalGenerator
from supervisor.bench.ports import free_port
from supervisor.channels import Channel, ChannelLimits
from supervisor.core.clock import RealClock, VirtualClock
from supervisor.devices.registry import bench_from_data
from supervisor.scan import InputBinding, LogicPhase, OutputBinding, ScanEngine, ScanStats
from supervisor.tags import TagDB, TagSpec


def _say(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def _ms(x: float) -> str:
    return f"{x * 1000:.3f} ms"


SCAN_BENCH_RECIPE = """
recipe: scan-bench
description: a long charge and discharge whose conditions are read every scan
chemistry: nimh
capacity: 2000 mAh
parameters:
  v_top: 50 V
cycles: 1000
steps:
  - id: charge
    charge: 0.1 C
    duration: 10 h
    until:
      - delta_peak >= 3 mV and step_time > 4 min: next
      - voltage >= v_top: next
  - {id: rest, rest: 1 h}
  - id: discharge
    discharge: 0.2 C
    duration: 5 h
    until:
      - voltage <= -50 V: next
"""
"""``bench scan --recipes``: a chain on every channel evaluating its conditions each scan
(the signal generator's sines never end a step)."""

WARM_UP_S = 0.5
"""``bench scan``: scans run before the measured ones, then the heap is settled
(:func:`supervisor.core.heap.settle_after_start`) as ``supervisor run`` does."""


async def scan_benchmark(
    n_tags: int, period_s: float, seconds: float, *, recipes: bool = False, settle: bool = True
) -> int:
    """A bench of about ``n_tags`` tags on a real clock: p50/p99 scan duration and jitter.

    Composition: 16 channels (about 25 tags each, with their integration and protection
    logic) plus signal-generator inputs for the rest, all changing every scan. ``recipes``:
    a step chain runs :data:`SCAN_BENCH_RECIPE` on every channel (between its derive and
    drive phases, as on a bench). ``settle``: after :data:`WARM_UP_S` of scans, what is
    alive is collected and frozen (``supervisor run`` does it after start-up).
    """
    from supervisor.core.heap import settle_after_start

    clock = RealClock()
    db = TagDB()
    n_channels = 16
    channels = []
    phases = []
    runners = []
    for k in range(n_channels):
        ch = Channel(f"ch{k}", db, ChannelLimits((-5.0, 5.0), (0.0, 100.0)), capacity_ah=2.0)
        db.update(ch.mode, "manual")
        db.update(ch.enable, not recipes)  # a chain is loaded only with enable off
        db.update(ch.manual_current, 1.0)
        channels.append(ch)
        if recipes:
            runner = _bench_chain(ch, db, clock, period_s)
            runners.append(runner)
            phases.append(LogicPhase(f"derive:{ch.name}", ch.derive))
            phases.append(LogicPhase(f"chain:{ch.name}", runner.run))
            phases.append(LogicPhase(f"drive:{ch.name}", ch.drive))
        else:
            phases.append(LogicPhase(f"channel:{ch.name}", ch.run))
    base = len(db) + 7 + 2 * 2  # scan stats and per-driver tags come later
    n_ai = max(0, n_tags - base)
    gen = SignalGenerator("gen", clock, n_ai, n_out=n_channels, poll_period_s=period_s)
    src = SignalGenerator("src", clock, n_channels * 2, poll_period_s=period_s)
    inputs = []
    for k in range(n_ai):
        tag = db.add(TagSpec(f"gen.ai{k}", unit="V"))
        inputs.append(InputBinding(tag, gen, f"ai{k}", None, 1.0))
    for k, ch in enumerate(channels):
        inputs.append(InputBinding(ch.voltage, src, f"ai{2 * k}", None, 1.0))
        inputs.append(InputBinding(ch.current, src, f"ai{2 * k + 1}", None, 1.0))
    outputs = [OutputBinding(ch.current_cmd, gen, f"ao{k}") for k, ch in enumerate(channels)]
    engine = ScanEngine(clock, db, period_s, [gen, src], inputs, outputs, phases)
    for drv in (gen, src):  # first images in place, so no channel trips on "not connected"
        await drv.poll()
    for runner in runners:
        runner.command("start", "benchmark")
    loop = asyncio.get_running_loop()
    if settle:
        warm = asyncio.Event()
        loop.call_later(WARM_UP_S, warm.set)
        await engine.run(warm)
        settle_after_start()
        engine.stats = ScanStats()  # only the scans after start-up are measured
    stop = asyncio.Event()
    loop.call_later(seconds, stop.set)
    t0 = time.perf_counter()
    await engine.run(stop)
    wall = time.perf_counter() - t0
    st = engine.stats
    d, j = list(st.durations_s), list(st.jitters_s)
    p = ScanStats.percentile
    _say(f"scan benchmark: {len(db)} tags, period {_ms(period_s)}, {wall:.1f} s wall")
    _say(f"  scans            {st.count} (expected about {int(seconds / period_s)})")
    _say(f"  duration  p50 {_ms(p(d, 50))}  p99 {_ms(p(d, 99))}  max {_ms(max(d))}")
    _say(f"  jitter    p50 {_ms(p(j, 50))}  p99 {_ms(p(j, 99))}  max {_ms(max(j))}")
    _say(f"  overruns {st.overruns}, deadlines skipped {st.skipped}")
    report.record(
        f"scan duration p99 / period (scan alone: {len(db)} tags, no devices, no publishers)",
        p(d, 99) / period_s,
        "",
        "<= 0.3",
        f"jitter p99 {_ms(p(j, 99))}, {st.overruns} overruns in {st.count} scans",
        f"supervisor bench scan --tags {n_tags} --seconds {seconds:g}",
    )
    return 0


def _bench_chain(ch: Channel, db: TagDB, clock: RealClock, period_s: float) -> Any:
    """A chain on ``ch`` with :data:`SCAN_BENCH_RECIPE` loaded (started by the caller)."""
    from supervisor.chains.compiler import Target, compile_recipe
    from supervisor.chains.engine import ChainRunner
    from supervisor.chains.port import ChannelPort
    from supervisor.config.recipe import load_recipe_text

    recipe, pos = load_recipe_text(SCAN_BENCH_RECIPE, "scan-bench.yaml")
    target = Target(
        channel=ch.name,
        capacity_ah=ch.capacity_ah,
        current_limits_a=ch.limits.current_a,
        voltage_limits_v=ch.limits.voltage_v,
        scan_period_s=period_s,
    )
    program = compile_recipe(recipe, pos, "scan-bench.yaml", target)
    runner = ChainRunner(ChannelPort.from_tags(db, ch.name, "auto", "manual"), db, clock)
    runner.load(program, test_id=f"bench-{ch.name}")
    return runner


async def manual_charge_benchmark(hours: float) -> int:
    """Simulated hours of Manual charge on the sim bench, on the virtual clock."""
    from supervisor.app import build_bench

    cfg = bench_from_data(
        {
            "bench": "benchmark",
            "scan": {"period_s": 0.1},
            "devices": {
                "chadeche": {
                    "driver": "chadeche",
                    "boards": [
                        {"address": 0, "sim": {"model": "nimh-aa", "capacity_ah": 4.0, "soc": 0.1}}
                    ],
                }
            },
            "channels": [
                {
                    "name": "ch0",
                    "source": {"device": "chadeche", "board": 0},
                    "capacity_ah": 4.0,
                    "limits": {"current_a": [-0.4, 0.4], "voltage_v": [0.8, 1.9]},
                }
            ],
        }
    )
    clock = VirtualClock()
    bench = build_bench(cfg, clock)
    ch = bench.channels["ch0"]
    bench.db.write("ch0.manual_current", 0.3)
    bench.db.write("ch0.enable", True)
    t0 = time.perf_counter()
    await bench.engine.run_for(hours * 3600.0)
    wall = time.perf_counter() - t0
    sim_s = clock.now()
    ah = ch.charge_ah.as_float()
    _say(f"manual charge benchmark: {hours:g} simulated h at 0.3 A, scan 100 ms")
    _say(f"  scans {bench.engine.stats.count}, wall {wall:.2f} s")
    _say(f"  simulated/wall ratio {sim_s / wall:,.0f}x")
    _say(
        f"  charge counter {ah:.4f} Ah (expected {0.3 * sim_s / 3600:.4f} Ah),"
        f" cell voltage {ch.voltage.value:.3f} V"
    )
    await bench.shutdown()
    return 0


async def seed002_benchmark(io_map: str) -> int:
    """Latency of a 2 A charge through the seed 002 bench, and device-loss detection."""
    import socket
    import tempfile
    from pathlib import Path

    import yaml

    from supervisor.app import build_bench
    from supervisor.devices.bms.sim import SimulatedBms, SocketcandServer
    from supervisor.devices.kind import DeviceSimulator
    from supervisor.devices.registry import load_bench

    data = yaml.safe_load(Path(io_map).read_text(encoding="utf-8"))  # noqa: ASYNC240 - setup
    data["devices"] = {k: v for k, v in data["devices"].items() if k in ("adam", "ea", "bms")}
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    for dev in data["devices"].values():
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            dev["port"] = s.getsockname()[1]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "seed002.yaml"
        path.write_text(yaml.safe_dump(data), encoding="utf-8")
        bench = build_bench(load_bench(path), RealClock())
    db = bench.db
    stop = asyncio.Event()
    await bench.start()
    task = asyncio.create_task(bench.run(stop))

    async def until(pred, limit_s: float = 30.0) -> float:  # type: ignore[no-untyped-def]
        t0 = time.perf_counter()
        while not pred():
            if time.perf_counter() - t0 > limit_s:
                return float("nan")
            await asyncio.sleep(0.01)
        return time.perf_counter() - t0

    try:
        await until(lambda: db["bms.voltage"].good and db["pack.voltage"].good)
        t0 = time.perf_counter()
        db.write("ch4.manual_current", 2.0)
        db.write("ch4.enable", True)
        _say("seed 002 bench over loopback (ADAM Modbus TCP, EA SCPI, BMS socketcand):")
        for tag in ("ch4.current", "pack.current", "bms.current"):
            await until(lambda tag=tag: abs(db[tag].as_float() - 2.0) < 0.1)
            _say(f"  2 A seen in {tag:<14} after {time.perf_counter() - t0:.2f} s")
        _say(
            f"  agreement: LEM {db['pack.current'].as_float():.3f} A, BMS"
            f" {db['bms.current'].as_float():.3f} A, EA {db['ch4.current'].as_float():.3f} A"
        )
        sim = bench.sim
        assert sim is not None
        bms = sim.devices["bms"]
        assert isinstance(bms, SimulatedBms) and bms.server is not None
        servers: dict[str, DeviceSimulator | SocketcandServer] = {
            "adam": sim.devices["adam"],
            "ea": sim.devices["ea"],
            "bms": bms.server,  # the link only: the BMS itself keeps sending
        }
        probe = {"adam": "pack.voltage", "ea": "ch4.voltage", "bms": "bms.voltage"}
        for name, server in servers.items():
            await server.stop()
            bad = await until(lambda n=name: not db[probe[n]].good)
            await server.start()
            good = await until(lambda n=name: db[probe[n]].good)
            _say(
                f"  {name}: tags BAD {bad:.2f} s after its simulator stopped;"
                f" GOOD {good:.2f} s after restart"
            )
    finally:
        stop.set()
        await task
        await bench.shutdown()
    return 0


def _seed002_file(io_map: str, folder: str, period_s: float | None = None) -> str:
    """The seed 002 part of ``io_map`` (ADAM, EA, BMS and the EA channel) on free loopback
    ports, written into ``folder``; ``period_s`` overrides the scan period."""
    from pathlib import Path

    import yaml

    data = yaml.safe_load(Path(io_map).read_text(encoding="utf-8"))
    data["devices"] = {k: v for k, v in data["devices"].items() if k in ("adam", "ea", "bms")}
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    for dev in data["devices"].values():
        dev["port"] = free_port()
    if period_s is not None:
        data.setdefault("scan", {})["period_s"] = period_s
    path = Path(folder) / "seed002.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return str(path)


ESTOP_PHASE_SPREAD_S = 0.25
"""Each press waits a random 0..this after the channel is charging, so that it falls at any
phase of the scan and of every driver's poll."""
ESTOP_RELEASE_LIMIT_S = 30.0
"""Bound on one press or one re-arm: reaching it stops the benchmark with a message (it is
a hang, not a figure)."""
ESTOP_RESET_AGAIN_S = 0.1
"""The e-stop benchmark presses reset again this often until the channel's trips clear."""


async def estop_benchmark(io_map: str, presses: int = 100, period_s: float = 0.01) -> int:
    """E-stop latency on the seed 002 bench of ``io_map`` at a ``period_s`` scan, over
    loopback with the real drivers on the real clock.

    Each press is :meth:`SimulatedBench.press_estop` (what ``PUT /api/sim/estop`` does) while
    the EA channel charges at 2 A, at a random phase of the scan and the polls. Measured
    through the plant and the tags only: "supply off" when the plant's supply output is off
    and the channel's ``output_cmd`` is false; "contactor open" when the plant's battery
    contactor is open.
    Between presses the e-stop is released and the channel re-armed through the tags it has
    (``ack``, ``manual_current``, ``enable``).
    """
    import random
    import tempfile

    from supervisor.app import build_bench
    from supervisor.devices.registry import load_bench

    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_bench(_seed002_file(io_map, tmp, period_s))
    bench = build_bench(cfg, RealClock())
    (channel,) = (c.name for c in cfg.channels)
    db = bench.db
    sim = bench.sim
    assert sim is not None
    plant = sim.plant
    stop = asyncio.Event()
    await bench.start()
    task = asyncio.create_task(bench.run(stop))

    async def until(what: str, pred) -> None:  # type: ignore[no-untyped-def]
        t0 = time.perf_counter()
        while not pred():
            if time.perf_counter() - t0 > ESTOP_RELEASE_LIMIT_S:
                raise RuntimeError(f"e-stop benchmark: gave up waiting for {what}")
            await asyncio.sleep(0.005)

    async def reset(channel: str) -> None:
        """Acknowledge and reset the channel's trips, again until they clear, as an operator
        presses reset again: a reset is refused while a cause is still present (after the
        release, a read-back may still be settling)."""
        t0 = time.perf_counter()
        while db[f"{channel}.fault"].value:
            if time.perf_counter() - t0 > ESTOP_RELEASE_LIMIT_S:
                raise RuntimeError(
                    "e-stop benchmark: the channel's trips did not clear after the release:"
                    f" {db[f'{channel}.fault'].value}"
                )
            db.write(f"{channel}.ack", True)
            await asyncio.sleep(ESTOP_RESET_AGAIN_S)

    supply_s: list[float] = []
    contactor_s: list[float] = []
    rng = random.Random(2)  # same press phases on every run
    try:
        await until(
            "the devices",
            lambda: (
                all(db[f"{d}.connected"].value is True for d in ("adam", "ea", "bms"))
                and db["estop.ok"].value is True
            ),
        )
        for _ in range(presses):
            await reset(channel)
            db.write(f"{channel}.manual_current", 2.0)
            db.write(f"{channel}.enable", True)
            await until(
                "the channel to charge",
                lambda: (
                    plant.supply.output_on
                    and plant.contactor_closed
                    and db[f"{channel}.output_cmd"].value is True
                ),
            )
            # A random phase against every poll and scan period (the slowest poll is 0.2 s).
            await asyncio.sleep(rng.uniform(0.0, ESTOP_PHASE_SPREAD_S))
            t0 = time.perf_counter()
            sim.press_estop(True)
            supply = contactor = None
            while supply is None or contactor is None:
                now = time.perf_counter()
                if now - t0 > ESTOP_RELEASE_LIMIT_S:
                    raise RuntimeError("e-stop benchmark: the press never took effect")
                if (
                    supply is None
                    and not plant.supply.output_on
                    and db[f"{channel}.output_cmd"].value is False
                ):
                    supply = now - t0
                if contactor is None and not plant.contactor_closed:
                    contactor = now - t0
                await asyncio.sleep(0.0005)
            supply_s.append(supply)
            contactor_s.append(contactor)
            sim.press_estop(False)
            await until("the e-stop sense", lambda: db["estop.ok"].value is True)
    finally:
        stop.set()
        await task
        await bench.shutdown()
    p = ScanStats.percentile
    st = bench.engine.stats
    _say(
        f"e-stop benchmark: seed 002 bench of {io_map}, scan {_ms(period_s)}, {presses} presses,"
        " real drivers over loopback"
    )
    for label, xs in (("supply off", supply_s), ("contactor open", contactor_s)):
        _say(f"  {label:<15} p50 {_ms(p(xs, 50))}  p99 {_ms(p(xs, 99))}  max {_ms(max(xs))}")
    _say("  (supply off: plant output off and output_cmd false; contactor open: plant)")
    _say(f"  scans {st.count}, overruns {st.overruns}, deadlines skipped {st.skipped}")
    every = [max(a, b) for a, b in zip(supply_s, contactor_s, strict=True)]
    report.record(
        "e-stop press → every output safe p99 (simulated devices over loopback)",
        p(every, 99) * 1000,
        "ms",
        "<= 50",
        f"{presses} presses, scan {_ms(period_s)}",
        f"supervisor bench estop --presses {presses}",
    )
    return 0


# --- historian ---------------------------------------------------------------------------
def _load_rig(n_tags: int, period_s: float, publishers: list[Any]) -> ScanEngine:
    """``bench scan``'s load (16 channels with their logic, signal-generator inputs for
    the rest, every tag changing every scan) with ``publishers`` at scan end."""
    clock = RealClock()
    db = TagDB()
    channels, phases = [], []
    for k in range(16):
        ch = Channel(f"ch{k}", db, ChannelLimits((-5.0, 5.0), (0.0, 100.0)), capacity_ah=2.0)
        db.update(ch.mode, "manual")
        db.update(ch.enable, True)
        db.update(ch.manual_current, 1.0)
        channels.append(ch)
        phases.append(LogicPhase(f"channel:{ch.name}", ch.run))
    n_ai = max(0, n_tags - (len(db) + 7 + 2 * 2))
    gen = SignalGenerator("gen", clock, n_ai, n_out=16, poll_period_s=period_s)
    src = SignalGenerator("src", clock, 32, poll_period_s=period_s)
    inputs = [
        InputBinding(db.add(TagSpec(f"gen.ai{k}", unit="V")), gen, f"ai{k}", None, 1.0)
        for k in range(n_ai)
    ]
    for k, ch in enumerate(channels):
        inputs.append(InputBinding(ch.voltage, src, f"ai{2 * k}", None, 1.0))
        inputs.append(InputBinding(ch.current, src, f"ai{2 * k + 1}", None, 1.0))
    outputs = [OutputBinding(ch.current_cmd, gen, f"ao{k}") for k, ch in enumerate(channels)]
    return ScanEngine(clock, db, period_s, [gen, src], inputs, outputs, phases, publishers)


async def _run_load(engine: ScanEngine, seconds: float) -> float:
    for drv in engine.drivers:  # first images in place, so no channel trips
        await drv.poll()
    stop = asyncio.Event()
    asyncio.get_running_loop().call_later(seconds, stop.set)
    t0 = time.perf_counter()
    await engine.run(stop)
    return time.perf_counter() - t0


class _Timed:
    """The historian as a publisher, timed: its whole ``on_scan`` and the copy of the
    changes in it (``ChangeSnapshots``; the filter runs on the writer's thread); and the
    deepest its queue went."""

    name = "historian"

    def __init__(self, historian: Any) -> None:
        self.historian = historian
        self.on_scan_s: list[float] = []
        self.take_s: list[float] = []
        self.deepest_rows = 0

    def on_scan(self, db: TagDB, t: float) -> None:
        h = self.historian
        source = h.source
        batches = source.batches
        t0 = time.perf_counter()

        def timed() -> Any:
            t1 = time.perf_counter()
            out = batches()
            self.take_s.append(time.perf_counter() - t1)
            return out

        source.batches = timed
        try:
            h.on_scan(db, t)
        finally:
            del source.batches
        self.on_scan_s.append(time.perf_counter() - t0)
        self.deepest_rows = max(self.deepest_rows, h.writer.queued_rows)


async def historian_benchmark(n_tags: int, period_s: float, seconds: float) -> int:
    """The historian's insert rate under ``bench scan``'s load (every tag changing every
    scan), the scan's p50/p99 with it off and on, then what a week of 1 s data costs to
    draw and what retention gives back. Figures, never assertions."""
    import tempfile
    from pathlib import Path

    from supervisor.publish.historian import Historian, WriterSettings

    p = ScanStats.percentile
    off = _load_rig(n_tags, period_s, [])
    await _run_load(off, seconds)
    d_off = list(off.stats.durations_s)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "history.sqlite"
        engine = _load_rig(n_tags, period_s, [])
        historian = Historian(engine.db, engine.clock, path, WriterSettings())
        timed = _Timed(historian)
        engine.publishers.append(timed)
        historian.open()
        wall = await _run_load(engine, seconds)
        written_in_run = historian.writer.rows_written
        t0 = time.perf_counter()
        historian.close()  # the rows still queued: a clean stop writes them
        drain_s = time.perf_counter() - t0
        w = historian.writer
        d_on = list(engine.stats.durations_s)
        size = path.stat().st_size
        _say(
            f"historian benchmark: {len(engine.db)} tags, period {_ms(period_s)},"
            f" {seconds:g} s per run, every tag changing every scan"
        )
        _say(
            f"  scan duration off  p50 {_ms(p(d_off, 50))}  p99 {_ms(p(d_off, 99))}"
            f"  ({off.stats.count} scans, overruns {off.stats.overruns})"
        )
        _say(
            f"  scan duration on   p50 {_ms(p(d_on, 50))}  p99 {_ms(p(d_on, 99))}"
            f"  ({engine.stats.count} scans, overruns {engine.stats.overruns})"
        )
        _say(
            f"  of which historian.on_scan p50 {_ms(p(timed.on_scan_s, 50))}"
            f"  p99 {_ms(p(timed.on_scan_s, 99))}; the changes' copy p50"
            f" {_ms(p(timed.take_s, 50))}  p99 {_ms(p(timed.take_s, 99))}"
        )
        offered = w.rows_written + w.rows_dropped
        _say(
            f"  rows offered {offered / wall:,.0f}/s; written during the run"
            f" {written_in_run / wall:,.0f}/s, dropped {w.rows_dropped} (queue full),"
            f" deepest queue {timed.deepest_rows} rows"
        )
        _say(
            f"  stop wrote the last {w.rows_written - written_in_run} queued rows in"
            f" {drain_s:.2f} s; file {size / 1e6:.1f} MB, {size / max(w.rows_written, 1):.1f}"
            " bytes/row"
        )
        _say(_retention_figures(path, size))
    _say(_week_query_figures())
    return 0


def _retention_figures(path: Any, size: int) -> str:
    """Retention by size down to half the file: how long, and whether the file shrank."""
    from supervisor.publish.historian import HistoryWriter, TagInfo, WriterSettings

    settings = WriterSettings(max_bytes=size // 2, chunk_rows=20_000)
    writer = HistoryWriter(path, settings, TagInfo)
    writer.open()
    t0 = time.perf_counter()
    writer.flush(timeout_s=600.0, retention=True)
    took_s = time.perf_counter() - t0
    deleted = writer.rows_deleted
    writer.close()
    after = path.stat().st_size
    return (
        f"  retention to max_bytes {size // 2 / 1e6:.1f} MB: {deleted} rows deleted in"
        f" {took_s:.2f} s ({settings.chunk_rows} rows per transaction); file"
        f" {size / 1e6:.1f} MB -> {after / 1e6:.1f} MB"
    )


def _week_query_figures() -> str:
    """A week of one tag sampled every second: raw and aggregated reads, timed."""
    import tempfile
    from pathlib import Path

    from supervisor.publish.historian import HistoryQuery
    from supervisor.publish.historian.store import connect

    week_s = 7 * 86400
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "week.sqlite"
        conn = connect(path)
        conn.execute("INSERT INTO tags VALUES (1, 'ch0.voltage', 'V', 'float', '')")
        t0 = 1_767_225_600.0
        conn.execute("BEGIN")
        conn.executemany(
            "INSERT INTO samples VALUES (1, ?, ?, 0)",
            ((t0 + k, 3.6 + 0.5 * math.sin(k / 3600.0)) for k in range(week_s)),
        )
        conn.execute("COMMIT")
        conn.close()
        query = HistoryQuery(path)
        t1 = time.perf_counter()
        agg = query.aggregate("ch0.voltage", t0, t0 + week_s, week_s / 1000)
        agg_s = time.perf_counter() - t1
        t1 = time.perf_counter()
        raw = query.samples("ch0.voltage", t0, t0 + week_s, limit=10_000)
        raw_s = time.perf_counter() - t1
        query.close()
    return (
        f"  a week of 1 s samples ({week_s} rows): {len(agg.buckets)} buckets in"
        f" {agg_s * 1000:.0f} ms; the first {len(raw.samples)} raw samples in"
        f" {raw_s * 1000:.0f} ms"
    )


# --- OPC UA ------------------------------------------------------------------------------------
async def _opcua_clients(
    url: str, namespace: str, tags: list[str], clients: int, seconds: float
) -> tuple[float, list[str]]:
    """Updates per second that ``clients`` subscribed clients (in another process) receive,
    all together, over ``seconds`` once every client is subscribed."""
    import json

    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "supervisor.bench.opcuaclients",
        url,
        namespace,
        "--clients",
        str(clients),
        "--tags",
        ",".join(tags),
        "--seconds",
        str(seconds),
        stdout=asyncio.subprocess.PIPE,
    )
    out, _ = await proc.communicate()
    lines = out.decode().splitlines()
    result = json.loads(lines[-1]) if lines else {"updates": [], "errors": ["no output"]}
    return sum(result["updates"]) / seconds, list(result["errors"])


async def opcua_benchmark(
    clients: int = 10, seconds: float = 10.0, n_tags: int = 100, period_s: float = 0.05
) -> int:
    """Tag updates per second delivered to ``clients`` subscribed asyncua clients while the
    scan holds its period, with the server on its own thread (what ``supervisor run`` does)
    and on the scan's own loop, next to a bare asyncua server writing the same variables
    (docs/adr/0014-opcua-server.md). ``n_tags`` analog tags change at every scan."""
    import tempfile
    from datetime import UTC, datetime
    from pathlib import Path

    from asyncua import Server, ua

    from supervisor.publish.opcua import (
        Answer,
        OpcUaFeed,
        OpcUaServer,
        OpcUaSettings,
        Request,
        UserStore,
        namespace_uri,
        plan,
    )

    names = [f"gen.ai{k}" for k in range(n_tags)]
    offered = n_tags / period_s * clients
    rows: list[tuple[str, float, str]] = []

    async def served(threaded: bool, tmp: Path) -> None:
        clock = RealClock()
        db = TagDB()
        gen = SignalGenerator("gen", clock, n_tags, poll_period_s=period_s)
        inputs = [
            InputBinding(
                db.add(TagSpec(n, unit="V", range=(-10.0, 10.0))), gen, f"ai{k}", None, 1.0
            )
            for k, n in enumerate(names)
        ]
        engine = ScanEngine(clock, db, period_s, [gen], inputs)
        feed = OpcUaFeed(db)
        engine.publishers.append(feed)
        cfg = bench_from_data(
            {
                "bench": "opcuabench",
                "state_dir": str(tmp),
                # The engine's period: the server samples the scan at it (ADR 0021).
                "scan": {"period_s": period_s},
                "devices": {"gen": {"driver": "chadeche", "boards": [{"address": 0}]}},
            }
        )
        settings = dataclasses.replace(OpcUaSettings.of(cfg), port=free_port(), security=("none",))

        async def refuse(req: Request) -> Answer:
            return Answer(False, "benchmark", "refused")

        server = OpcUaServer(
            settings,
            db,
            clock,
            plan(cfg, db),
            feed,
            refuse,
            UserStore(tmp / "users.yaml"),
            threaded=threaded,
        )
        await gen.poll()
        await server.start()
        stop = asyncio.Event()
        task = asyncio.create_task(engine.run(stop))
        try:
            await asyncio.sleep(1.0)  # first scans, then the clients
            before = (engine.stats.overruns, engine.stats.skipped, len(engine.stats.jitters_s))
            written, dropped, t0 = server.written, feed.replaced, time.perf_counter()
            rate, errors = await _opcua_clients(
                server.endpoint, server.namespace, names, clients, seconds
            )
            st = engine.stats
            wall = time.perf_counter() - t0
            written = int((server.written - written) / wall)
            dropped = feed.replaced - dropped
            jitter = list(st.jitters_s)[before[2] :]
            where = "own thread" if threaded else "scan's loop"
            rows.append(
                (
                    f"supervisor, server on its {where}",
                    rate,
                    f"scan: overruns {st.overruns - before[0]}, deadlines skipped"
                    f" {st.skipped - before[1]}, jitter p99 {_ms(ScanStats.percentile(jitter, 99))}"
                    f", max {_ms(max(jitter, default=0.0))}; server wrote {written:,}/s,"
                    f" replaced before written {dropped}"
                    + (f"; client errors {errors}" if errors else ""),
                )
            )
        finally:
            stop.set()
            await task
            await server.stop()

    async def bare(tmp: Path) -> None:
        server = Server()
        await server.init()
        port = free_port()
        server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/bare")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        uri = namespace_uri("bare")
        idx = await server.register_namespace(uri)
        nodes = []
        for n in names:
            var = await server.nodes.objects.add_variable(ua.NodeId(n, idx), n, 0.0)
            nodes.append(var.nodeid)
        await server.start()
        stop = asyncio.Event()

        async def writer() -> None:
            # The same values at the same period, written as fast as asyncua takes them.
            k, start = 0, time.monotonic()
            while not stop.is_set():
                k += 1
                # What the supervisor writes: the value, its status and both timestamps.
                stamp = datetime.now(UTC)
                now = ua.DataValue(
                    ua.Variant(float(k), ua.VariantType.Double),
                    StatusCode=ua.StatusCode(ua.StatusCodes.Good),
                    SourceTimestamp=stamp,
                    ServerTimestamp=stamp,
                )
                for nid in nodes:
                    await server.write_attribute_value(nid, now)
                await asyncio.sleep(max(0.0, start + k * period_s - time.monotonic()))

        task = asyncio.create_task(writer())
        try:
            await asyncio.sleep(1.0)
            rate, errors = await _opcua_clients(
                f"opc.tcp://127.0.0.1:{port}/bare", uri, names, clients, seconds
            )
            rows.append(
                (
                    "bare asyncua server, same variables",
                    rate,
                    f"client errors {errors}" if errors else "",
                )
            )
        finally:
            stop.set()
            await task
            await server.stop()

    with tempfile.TemporaryDirectory() as tmp:
        await served(True, Path(tmp) / "thread")
        await served(False, Path(tmp) / "loop")
        await bare(Path(tmp) / "bare")
    _say(
        f"OPC UA benchmark: {n_tags} analog tags changing every scan of {_ms(period_s)},"
        f" {clients} subscribed asyncua clients in another process, {seconds:g} s each"
        f" (offered {offered:,.0f} updates/s)"
    )
    for label, rate, note in rows:
        _say(f"  {label:<40} {rate:>9,.0f} updates/s  {note}")
    bare_rate = rows[-1][1]
    for label, rate, _ in rows[:-1]:
        ratio = rate / bare_rate if bare_rate else float("nan")
        _say(f"  ratio {label} / bare: {ratio:.2f} (target >= 0.8)")
        report.record(
            f"OPC UA updates/s to {clients} clients vs bare asyncua ({label})",
            ratio,
            "",
            ">= 0.8",
            f"bare asyncua server {bare_rate:,.0f} updates/s",
            f"supervisor bench opcua --clients {clients}",
        )
    return 0
