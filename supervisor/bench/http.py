"""``supervisor bench http``: the HTTP API and the WebSocket hub against a 10 ms scan
(issue 13 "HTTP/WebSocket: full tag snapshot latency p99 while the scan runs at 10 ms ≤ 20
ms, scan jitter unchanged"; docs/adr/0019-http-off-the-scan.md).

One process runs a bench of about 1000 tags on a real clock (``bench scan``'s load: 16
channels with their logic, signal-generator inputs for the rest, every tag changing every
scan), its ``HttpApi`` and a ``LiveHub`` on the scan's event loop, as ``supervisor run``
does. The clients run in a process of their own (a browser is one too): ``--http-clients``
loops of back-to-back ``GET /api/tags`` and ``--ws-clients`` pages reading ``/api/ws``.
In the same run it prints the scan's start jitter without clients (the reference), then
with them, and the snapshot latency the clients saw; first, on a bench of its own that is
not scanning, the CPU one full image costs by share of the tags changed since the last one
(``snapshot_cpu``: a wall-clock-free figure, comparable on a busy machine).
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
from typing import Any, Final

from supervisor.bench.loadgen import SignalGenerator
from supervisor.channels import Channel, ChannelLimits
from supervisor.core.clock import RealClock
from supervisor.core.heap import collect_when_idle, settle_after_start
from supervisor.scan import InputBinding, LogicPhase, OutputBinding, ScanEngine, ScanStats
from supervisor.tags import TagDB, TagSpec


def _say(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def _ms(x: float) -> str:
    return f"{x * 1000:.3f} ms"


class _Jitters:
    """A publisher that keeps each scan's start lateness, split into phases."""

    name = "jitters"

    def __init__(self, engine_stats: ScanStats) -> None:
        self.stats = engine_stats
        self.phase = "idle"
        self.by_phase: dict[str, list[float]] = {}
        self.durations: dict[str, list[float]] = {}

    def on_scan(self, db: TagDB, t: float) -> None:
        if self.phase == "idle" or not self.stats.jitters_s:
            return
        self.by_phase.setdefault(self.phase, []).append(self.stats.jitters_s[-1])
        if self.stats.durations_s:
            self.durations.setdefault(self.phase, []).append(self.stats.durations_s[-1])


def _engine(n_tags: int, period_s: float) -> ScanEngine:
    """``bench scan``'s composition (supervisor/bench/benchmarks.py::scan_benchmark)."""
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
    n_ai = max(0, n_tags - (len(db) + 7 + 2 * 2 + 2))  # scan, driver and hmi tags later
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
    return ScanEngine(clock, db, period_s, [gen, src], inputs, outputs, phases)


SNAPSHOT_CHANGES: Final = (0.001, 0.1, 0.5, 1.0)
"""Shares of the tags changed between two images for ``snapshot_cpu`` (one tag at least)."""


async def snapshot_cpu(n_tags: int, period_s: float, images: int = 50) -> dict[float, float]:
    """CPU seconds (this thread's) per full ``GET /api/tags`` image, by share of the tags
    changed since the last one, on a bench of ``n_tags`` that is not scanning (nothing
    else runs on the loop meanwhile): before each image every tag's source time moves,
    as each poll moves it, and the share given gets a new value."""
    from supervisor.hmi.server import TagSnapshots

    engine = _engine(n_tags, period_s)
    db, clock = engine.db, engine.clock
    snapshots = TagSnapshots(db, clock)
    tags = list(db)
    await snapshots.image()
    out: dict[float, float] = {}
    for share in SNAPSHOT_CHANGES:
        step = max(1, round(1 / share))
        cpu_s = 0.0
        for k in range(images):
            db.set_scan_time(clock.now())
            for tag in tags:
                db.update(tag, tag.value)  # a poll: a new source time, no new version
            for tag in tags[k % step :: step]:
                db.update(tag, float(k) + tag.index * 1e-3)
            t0 = time.thread_time()
            await snapshots.image()
            cpu_s += time.thread_time() - t0
        out[share] = cpu_s / images
    return out


async def http_benchmark(
    n_tags: int, period_s: float, seconds: float, http_clients: int, ws_clients: int
) -> int:
    from supervisor.hmi.live import LiveHub
    from supervisor.hmi.server import HttpApi

    cpu = await snapshot_cpu(n_tags, period_s)
    engine = _engine(n_tags, period_s)
    db, clock = engine.db, engine.clock
    api = HttpApi(db, clock, "127.0.0.1", 0, pacing=engine)  # as supervisor run does
    hub = LiveHub(db, clock, 0.2)
    hub.install(api.app)
    jit = _Jitters(engine.stats)
    engine.publishers = [*engine.publishers, hub, jit]
    await api.start()
    for drv in engine.drivers:  # first images in place, so no channel trips
        await drv.poll()
    settle_after_start()  # as `supervisor run` does before its scan (ADR 0018)
    engine.idle = collect_when_idle
    stop = asyncio.Event()
    scan = asyncio.get_running_loop().create_task(engine.run(stop))
    try:
        await asyncio.sleep(1.0)  # warm-up: first scans, first garbage collections
        jit.phase = "alone"
        await asyncio.sleep(seconds)
        jit.phase = "clients"
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "supervisor.bench.http",
            api.url + "/tags",
            f"http://{api.host}:{api.port}/api/ws",
            str(seconds),
            str(http_clients),
            str(ws_clients),
            stdout=subprocess.PIPE,
        )
        out, _ = await proc.communicate()
        jit.phase = "idle"
    finally:
        stop.set()
        await scan
        await api.stop()
    got: dict[str, Any] = json.loads(out or b"{}")
    lat = got.get("latencies_s", [])
    p = ScanStats.percentile
    _say(
        f"http benchmark: {len(db)} tags, period {_ms(period_s)}, {seconds:g} s per phase,"
        f" {http_clients} HTTP clients (GET /api/tags back to back), {ws_clients} WebSocket"
    )
    _say(
        "  snapshot build CPU per image (no scan running): "
        + ", ".join(f"{share:.1%} changed {_ms(cpu_s)}" for share, cpu_s in cpu.items())
    )
    for phase in ("alone", "clients"):
        j = jit.by_phase.get(phase, [0.0])
        d = jit.durations.get(phase, [0.0])
        _say(
            f"  scan {phase:<8} jitter p50 {_ms(p(j, 50))}  p99 {_ms(p(j, 99))}"
            f"  max {_ms(max(j))}  duration p99 {_ms(p(d, 99))}  ({len(j)} scans)"
        )
    if lat:
        _say(
            f"  GET /api/tags    p50 {_ms(p(lat, 50))}  p99 {_ms(p(lat, 99))}"
            f"  max {_ms(max(lat))}  ({len(lat)} requests, {got.get('bytes', 0)} bytes each)"
        )
    _say(
        f"  WebSocket        {got.get('ws_messages', 0)} messages to {ws_clients} clients,"
        f" {hub.dropped} dropped; overruns {engine.stats.overruns},"
        f" skipped {engine.stats.skipped}"
    )
    from supervisor.bench import report

    alone = p(jit.by_phase.get("alone", [0.0]), 99)
    with_clients = p(jit.by_phase.get("clients", [0.0]), 99)
    command = f"supervisor bench http --seconds {seconds:g} --http-clients {http_clients}"
    if lat:
        report.record(
            "GET /api/tags p99, scan engine alone (1000 tags, 10 ms)",
            p(lat, 99) * 1000,
            "ms",
            "<= 20",
            f"{len(lat)} requests by {http_clients} clients back to back",
            command,
        )
    rise_ms, reference = report.jitter_change(alone * 1000, with_clients * 1000)
    _say(f"  start jitter p99 rise with clients {rise_ms:+.3f} ms ({reference})")
    report.record(
        "scan jitter p99 rise with HTTP clients, same run",
        rise_ms,
        "ms",
        f"<= {report.JITTER_UNCHANGED_MS:g}",
        reference,
        command,
    )
    return 0


# --- the clients' process ---------------------------------------------------------------
async def _clients(url: str, ws_url: str, seconds: float, n_http: int, n_ws: int) -> None:
    import aiohttp

    latencies: list[float] = []
    sizes: list[int] = []
    ws_messages = 0
    end = time.monotonic() + seconds

    async def hammer(s: aiohttp.ClientSession) -> None:
        while time.monotonic() < end:
            t0 = time.perf_counter()
            async with s.get(url) as resp:
                body = await resp.read()
            latencies.append(time.perf_counter() - t0)
            sizes.append(len(body))

    async def page(s: aiohttp.ClientSession) -> None:
        nonlocal ws_messages
        async with s.ws_connect(ws_url) as ws:
            while time.monotonic() < end:
                try:
                    await asyncio.wait_for(ws.receive(), timeout=max(0.01, end - time.monotonic()))
                except TimeoutError:
                    break
                ws_messages += 1

    async with aiohttp.ClientSession() as s:
        await asyncio.gather(*(hammer(s) for _ in range(n_http)), *(page(s) for _ in range(n_ws)))
    body = {"latencies_s": latencies, "bytes": max(sizes, default=0), "ws_messages": ws_messages}
    sys.stdout.write(json.dumps(body))


if __name__ == "__main__":
    u, w, secs, nh, nw = sys.argv[1:6]
    asyncio.run(_clients(u, w, float(secs), int(nh), int(nw)))
