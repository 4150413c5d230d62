"""``supervisor bench load``: the scan of the load case (issue 13) with every client on.

``supervisor run io_maps/load16.yaml`` (16 channels, about 1000 tags, 10 ms, historian,
InfluxDB spool to a throwaway local influxd, OPC UA) runs in a process of its own on free
ports, benchmarks/load-cycle.yaml started on every channel. Its networked devices (the
ADAM-5000/TCP, the EA supply, the BMS's socketcand gateway) are simulated by ``supervisor
sim`` in another process, reached over loopback as real ones are over the bench's network
(``--no-sim``); the Chadèche boards, on the supervisor's own SPI buses, are simulated in
it. ``sim_in_process`` (``--sim-in-process``) runs them all inside the supervisor instead,
as ``make run`` does: their servers then share its event loop and interpreter lock.
Attached for the whole window: 10 subscribed OPC UA clients (``supervisor.bench.opcuaclients``,
another process) and 3 WebSocket pages (``/api/ws``, in this process). After a warm-up
the window alternates ``ALTERNATIONS`` times between two kinds of block:

1. *quiet*: those clients only;
2. *snapshots*: the same, plus full ``GET /api/tags`` requests at ``http_rate_hz``, whose
   latency (request sent → whole body read) is measured.

The clients and the throwaway influxd run at a lower priority (``clients_nice``, default
10) than the supervisor: on a bench they are other machines (SCADA, browsers, Grafana,
the InfluxDB server); on this 2-core machine, ten Python OPC UA sessions and the pages at
the supervisor's own priority would measure how the kernel shares two cores among
processes, not how the supervisor scans. ``--clients-nice 0`` measures that too.

Per-scan figures come from the supervisor's own historian after it stopped: every change
of ``scan.duration_s`` and ``scan.jitter_s`` is stored with its time, so each kind of block
gets its own percentiles (``/api/diagnostics`` keeps only the last 10 000 scans, warm-up
included). Overruns are the difference of ``scan.overruns`` across the window. The jitter
of the quiet blocks is the reference of the snapshot blocks': both from the same run.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sqlite3
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from supervisor.bench import report
from supervisor.bench.subject import Simulators, Supervisor, free_port, prepare, recipe_args

log = logging.getLogger(__name__)

LOAD_MAP = Path("io_maps/load16.yaml")
LOAD_RECIPE = Path("benchmarks/load-cycle.yaml")
OPCUA_CLIENTS = 10
WS_PAGES = 3
OPCUA_TAGS = 100
"""Tags each OPC UA client subscribes to (channel values, then signal tags)."""
CLIENTS_NICE = 10
"""The clients' and influxd's niceness (see above)."""
ALTERNATIONS = 3
"""The window's quiet and snapshot blocks alternate this many times (quiet first): a
machine that slows down or speeds up during the run then weighs on both alike, where two
halves compared the first against the second (issue 13: the same code gave 1.06 and 2.12
in two runs)."""


def _say(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def block_plan(seconds: float, alternations: int = ALTERNATIONS) -> list[tuple[str, float]]:
    """The window's blocks in order: (``"quiet"`` or ``"snapshots"``, seconds), quiet
    first, alternating, all of one length."""
    block_s = seconds / (2 * alternations)
    return [(kind, block_s) for _ in range(alternations) for kind in ("quiet", "snapshots")]


def _pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))]


@dataclass
class _Pages:
    """WebSocket pages on ``/api/ws``: messages received, errors."""

    messages: int = 0
    errors: int = 0


async def _page(url: str, pages: _Pages, stop: asyncio.Event) -> None:
    import aiohttp

    async with aiohttp.ClientSession() as session, session.ws_connect(url + "/api/ws") as ws:
        while not stop.is_set():
            try:
                msg = await asyncio.wait_for(ws.receive(), timeout=0.5)
            except TimeoutError:
                continue
            if msg.type == aiohttp.WSMsgType.TEXT:
                pages.messages += 1
            elif msg.type in (aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                pages.errors += 1
                return


async def _snapshots(url: str, rate_hz: float, seconds: float) -> tuple[list[float], int]:
    """Full ``GET /api/tags`` at ``rate_hz`` for ``seconds``: latencies (s) and bytes."""
    import aiohttp

    latencies: list[float] = []
    size = 0
    period = 1.0 / rate_hz
    async with aiohttp.ClientSession() as session:
        end = time.monotonic() + seconds
        nxt = time.monotonic()
        while time.monotonic() < end:
            t0 = time.perf_counter()
            async with session.get(url + "/api/tags") as r:
                body = await r.read()
            latencies.append(time.perf_counter() - t0)
            size = len(body)
            nxt += period
            await asyncio.sleep(max(0.0, nxt - time.monotonic()))
    return latencies, size


async def _opcua_clients(
    endpoint: str, namespace: str, tags: list[str]
) -> asyncio.subprocess.Process:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "supervisor.bench.opcuaclients",
        endpoint,
        namespace,
        "--clients",
        str(OPCUA_CLIENTS),
        "--tags",
        ",".join(tags),
        "--seconds",
        "0",
        stdout=asyncio.subprocess.PIPE,
    )
    assert proc.stdout is not None
    try:
        line = await asyncio.wait_for(proc.stdout.readline(), timeout=120)
        if line.strip() != b"subscribed":
            rest = await asyncio.wait_for(proc.stdout.read(), timeout=30)
            text = (line + rest).decode(errors="replace")[-500:]
            raise RuntimeError(f"OPC UA clients did not subscribe: {text}")
    except BaseException:
        if proc.returncode is None:
            proc.kill()
        await proc.wait()
        raise
    return proc


def _scan_samples(history: Path, name: str, t0: float, t1: float) -> list[float]:
    con = sqlite3.connect(f"file:{history}?mode=ro", uri=True)
    try:
        rows = con.execute(
            "SELECT s.value FROM samples s JOIN tags g ON g.id = s.tag_id"
            " WHERE g.name = ? AND s.t >= ? AND s.t < ?",
            (name, t0, t1),
        ).fetchall()
    finally:
        con.close()
    return [float(r[0]) for r in rows if r[0] is not None]


def _create_database(url: str, name: str) -> None:
    import urllib.parse
    import urllib.request

    data = urllib.parse.urlencode({"q": f'CREATE DATABASE "{name}"'}).encode()
    with urllib.request.urlopen(f"{url}/query", data=data, timeout=30):
        pass


def _tag_list(answer: Any) -> list[dict[str, Any]]:
    return list(answer if isinstance(answer, list) else answer.get("tags", []))


def _chain_states(answer: Any) -> dict[str, int]:
    """How many channels' step chains are in each state (all running, under load)."""
    states = [str(t.get("value")) for t in _tag_list(answer) if t["name"].endswith(".chain.state")]
    return dict(Counter(states))


def _subscribed_tags(tags: list[dict[str, Any]]) -> list[str]:
    names = [str(t["name"]) for t in tags]
    values = [n for n in names if n.startswith("ch") and n.endswith((".voltage", ".current"))]
    values += [n for n in names if n.startswith("load.sig")]
    return (["scan.count", *values])[:OPCUA_TAGS]


async def _measure(
    sup: Supervisor,
    endpoint: str,
    namespace: str,
    seconds: float,
    warmup_s: float,
    http_rate_hz: float,
) -> dict[str, Any]:
    tag_list = _tag_list(sup.get("/api/tags"))
    n_tags = len(tag_list)
    opcua = await _opcua_clients(endpoint, namespace, _subscribed_tags(tag_list))
    pages, stop = _Pages(), asyncio.Event()
    page_tasks = [asyncio.create_task(_page(sup.url, pages, stop)) for _ in range(WS_PAGES)]
    try:
        await asyncio.sleep(warmup_s)
        d0 = await asyncio.to_thread(sup.get, "/api/diagnostics")
        blocks: list[tuple[str, float, float]] = []
        latencies: list[float] = []
        size = 0
        # The CPUs' ticks at each block's start and end, by kind (the hypervisor's steal).
        ticks: dict[str, list[tuple[report.CpuTicks, report.CpuTicks]]] = {}
        for kind, block_s in block_plan(seconds):
            t0 = time.time()
            ticks0 = report.cpu_ticks()
            if kind == "quiet":
                await asyncio.sleep(block_s)
            else:
                lat, size = await _snapshots(sup.url, http_rate_hz, block_s)
                latencies += lat
            ticks1 = report.cpu_ticks()
            blocks.append((kind, t0, time.time()))
            if ticks0 is not None and ticks1 is not None:
                ticks.setdefault(kind, []).append((ticks0, ticks1))
        d1 = await asyncio.to_thread(sup.get, "/api/diagnostics")
        chains = _chain_states(await asyncio.to_thread(sup.get, "/api/tags"))
        answer = await asyncio.to_thread(sup.get, "/api/alarms?limit=0")
        alarms = [f"{a['id']}: {a['message']}" for a in answer.get("active", [])]
        ws_messages, ws_errors = pages.messages, pages.errors
    finally:
        stop.set()
        await asyncio.gather(*page_tasks, return_exceptions=True)
        if opcua.returncode is None:
            opcua.terminate()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(opcua.wait(), timeout=20)
    return {
        "tags": n_tags,
        "blocks": blocks,
        "steal": {kind: report.steal_share(spans) for kind, spans in ticks.items()},
        "diag": (d0, d1),
        "latencies": latencies,
        "snapshot_bytes": size,
        "ws_messages": ws_messages,
        "ws_errors": ws_errors,
        "chains": chains,
        "alarms": alarms,
    }


def load_benchmark(
    seconds: float = 60.0,
    warmup_s: float = 10.0,
    http_rate_hz: float = 10.0,
    io_map: Path = LOAD_MAP,
    recipe: Path = LOAD_RECIPE,
    clients_nice: int = CLIENTS_NICE,
    sim_in_process: bool = False,
) -> int:
    """Run the load case and print (and record) its figures; 0, or 2 without influxd."""
    from supervisor.bench.influx import _influxd, _Server
    from supervisor.devices.registry import load_bench
    from supervisor.publish.opcua.layout import namespace_uri

    binary = _influxd()
    if binary is None:
        _say(
            "load benchmark: no InfluxDB server binary. Set SUPERVISOR_INFLUXD to an influxd"
            " 1.8 binary or put influxd on PATH (`make influxd` builds 1.8.10 with Go)."
        )
        return 2
    cfg = load_bench(io_map)
    period_s = cfg.scan.period_s
    channels = [c.name for c in cfg.channels]
    with tempfile.TemporaryDirectory(prefix="bench-load-") as tmp:
        root = Path(tmp)
        influx = _Server(binary, root / "influxd")
        try:
            if cfg.influxdb is not None:  # the map's bucket (db/rp), or every write is refused
                _create_database(influx.url, cfg.influxdb.bucket.split("/")[0])
            copy, http_port, opcua_port = prepare(io_map, root, influx.url)
            args = recipe_args(channels, recipe)
            sims = None
            if not sim_in_process:
                sims = Simulators(copy, free_port(), root / "sim.log")
                args.append("--no-sim")
            sup = None
            try:
                if sims is not None:
                    sims.wait_ready()
                sup = Supervisor(copy, http_port, args, root / "run.log")
                sup.wait_ready()
                if clients_nice:
                    # Started at the supervisor's priority (it inherits ours); from here on
                    # this process (the pages, the snapshots, the OPC UA clients it starts)
                    # and influxd run below it.
                    # The simulated devices keep the supervisor's priority: real ones answer
                    # in their own time, whatever this machine does.
                    os.setpriority(os.PRIO_PROCESS, influx.proc.pid, clients_nice)
                    os.nice(clients_nice)
                endpoint = f"opc.tcp://127.0.0.1:{opcua_port}/supervisor"
                res = asyncio.run(
                    _measure(
                        sup, endpoint, namespace_uri(cfg.bench), seconds, warmup_s, http_rate_hz
                    )
                )
            finally:
                # The supervisor first: its stop drives the simulated devices safe.
                if sup is not None:
                    code = sup.stop()
                    if code != 0:
                        _say(f"  supervisor run exited with {code}: {sup.tail()}")
                if sims is not None:
                    sims.stop()
            history = root / "state" / (cfg.history.path if cfg.history else "history.sqlite")
            samples: dict[tuple[str, str], list[float]] = {}
            for kind, t0, t1 in res["blocks"]:
                for tag in ("scan.duration_s", "scan.jitter_s"):
                    got = _scan_samples(history, tag, t0, t1)
                    samples.setdefault((tag, kind), []).extend(got)
            dur_q = samples.get(("scan.duration_s", "quiet"), [])
            dur_s = samples.get(("scan.duration_s", "snapshots"), [])
            jit_q = samples.get(("scan.jitter_s", "quiet"), [])
            jit_s = samples.get(("scan.jitter_s", "snapshots"), [])
        finally:
            influx.stop()
    d0, d1 = res["diag"]
    overruns = d1["scan"]["overruns"] - d0["scan"]["overruns"]
    skipped = d1["scan"]["skipped"] - d0["scan"]["skipped"]
    scans = d1["scan"]["count"] - d0["scan"]["count"]
    durations = dur_q + dur_s
    ratio = _pct(durations, 99) / period_s
    jit_all = _pct(jit_q + jit_s, 99) * 1000
    jit_quiet, jit_snap = _pct(jit_q, 99) * 1000, _pct(jit_s, 99) * 1000
    jit_ratio = jit_snap / jit_quiet if jit_quiet else float("nan")
    lat = res["latencies"]
    lat_p99 = _pct(lat, 99) * 1000
    cmd = f"supervisor bench load --seconds {seconds:g}" + (
        f" --clients-nice {clients_nice}" if clients_nice != CLIENTS_NICE else ""
    )
    if sim_in_process:
        cmd += " --sim-in-process"
    load1, load5, _ = os.getloadavg()
    _say(
        f"load benchmark: {io_map} — {len(channels)} channels, {res['tags']} tags, scan"
        f" {period_s * 1000:g} ms, recipes on every channel, historian + InfluxDB spool +"
        f" OPC UA ({OPCUA_CLIENTS} clients × {min(OPCUA_TAGS, res['tags'])} tags) +"
        f" WebSocket ({WS_PAGES} pages, {res['ws_messages']} messages, {res['ws_errors']}"
        f" errors; clients and influxd at nice {clients_nice}); window {seconds:g} s after"
        f" {warmup_s:g} s warm-up, {scans} scans"
        f" ({len(durations)} scan samples in the historian); machine load average"
        f" {load1:.2f} (1 min), {load5:.2f} (5 min) at the end"
    )
    _say(
        "  simulated ADAM, EA and BMS: "
        + ("inside the supervisor" if sim_in_process else "a supervisor sim process")
    )
    _say(f"  step chains at the window's end: {res['chains']}")
    if res["alarms"]:  # a chain held by an alarm no longer loads the scan as a running one
        shown = "; ".join(res["alarms"][:8])
        more = f" (+{len(res['alarms']) - 8} more)" if len(res["alarms"]) > 8 else ""
        _say(f"  alarms active at the window's end: {shown}{more}")
    _say(
        f"  scan duration p50 {_pct(durations, 50) * 1000:.2f} ms, p99"
        f" {_pct(durations, 99) * 1000:.2f} ms, max {max(durations, default=0) * 1000:.1f} ms;"
        f" p99/period {ratio:.3f} (target ≤ 0.3)"
    )
    _say(f"  overruns in the window {overruns} (target 0); skipped deadlines {skipped}")
    _say(f"  start jitter p99 {jit_all:.2f} ms over the window (target ≤ 1 ms)")
    _say(
        f"  GET /api/tags ({res['snapshot_bytes'] / 1024:.0f} KiB) at {http_rate_hz:g}/s:"
        f" {len(lat)} requests, p50 {_pct(lat, 50) * 1000:.1f} ms, p99 {lat_p99:.1f} ms"
        f" (target ≤ 20 ms)"
    )
    rise_ms, reference = report.jitter_change(jit_quiet, jit_snap)
    steal = res["steal"]
    # The machine's own noise, block by block (a virtual machine's CPUs given to others):
    # a scan at a real-time priority waits for it like anyone else.
    quiet, snapshots = steal.get("quiet"), steal.get("snapshots")
    noise = (
        f"hypervisor steal {quiet * 100:.2f} % of the CPUs' time without,"
        f" {snapshots * 100:.2f} % with"
        if quiet is not None and snapshots is not None
        else "hypervisor steal not known (no /proc/stat)"
    )
    _say(
        f"  start jitter p99 without snapshots {jit_quiet:.2f} ms, with {jit_snap:.2f} ms"
        f" ({ALTERNATIONS} blocks of each, alternating): rise {rise_ms:+.3f} ms,"
        f" ratio {jit_ratio:.2f} (target: unchanged, a rise of at most"
        f" {report.JITTER_UNCHANGED_MS:g} ms)"
    )
    _say(f"  {noise}")
    rec = report.record
    load = "16 ch, ~1000 tags, 10 ms, every publisher on"
    rec(
        f"scan duration p99 / period ({load})",
        ratio,
        "",
        "<= 0.3",
        f"period {period_s * 1000:g} ms",
        cmd,
    )
    rec(f"overruns in {seconds:g} s (same load)", overruns, "", "== 0", f"{scans} scans", cmd)
    rec(
        "scan start jitter p99 (same load)",
        jit_all,
        "ms",
        "<= 1",
        f"{len(jit_q) + len(jit_s)} scans; {noise}",
        cmd,
    )
    running = res["chains"].get("Running", 0)
    rec(
        "step chains still Running at the load window's end",
        running,
        "",
        f"== {len(channels)}",
        f"{len(channels)} started; {len(res['alarms'])} alarms active",
        cmd,
    )
    rec(
        "GET /api/tags full snapshot p99 while the scan runs",
        lat_p99,
        "ms",
        "<= 20",
        f"{len(lat)} requests at {http_rate_hz:g}/s",
        cmd,
    )
    rec(
        "scan jitter p99 rise with snapshots (same run)",
        rise_ms,
        "ms",
        f"<= {report.JITTER_UNCHANGED_MS:g}",
        f"{reference}; {ALTERNATIONS} alternating blocks of each; {noise}",
        cmd,
    )
    return 0
