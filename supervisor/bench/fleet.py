"""``supervisor bench fleet --benches N [--tags T] [--seconds S]``: a lab of N benches
through one Mosquitto into the fleet (issue 35; docs/performance.md "Issue 35: a hundred
benches through one Mosquitto"; ADR 0053).

Started here, each stopped by its pid: Debian's Mosquitto on a free loopback port
(``fleetbroker``); the fleet's state code subscribed to the group in a process of its own
(``fleetsink``); N edge nodes, the real ``SparkplugPublisher`` each over a synthetic tag
database of T tags that all change every second, ``NODES_PER_PROCESS`` to a worker process
(``fleetnodes``). Once every node is born the window of S seconds is measured: each data
sample's latency (bench acquisition → the fleet's MQTT thread, one machine's clock) p50 and
p99, the broker's and the fleet's CPU (``/proc/<pid>/stat``), the fleet's RSS, the
workers' CPU (what the publishers cost), messages and samples a second.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from supervisor.bench import report
from supervisor.bench.fleetbroker import Broker
from supervisor.bench.fleetsink import percentile_ms
from supervisor.bench.processes import stop_with_parent

__all__ = ["FleetFigures", "fleet_benchmark", "run_fleet"]

NODES_PER_PROCESS: Final = 25
"""Simulated benches per worker process (their threads share its interpreter lock)."""
GROUP: Final = "benchfleet"
BIRTH_TIMEOUT_S: Final = 120.0
WARMUP_S: Final = 2.0
TARGET_P99_MS: Final = 1000.0


@dataclass(frozen=True)
class FleetFigures:
    benches: int
    tags: int
    seconds: float
    p50_ms: float
    p99_ms: float
    max_ms: float
    messages_per_s: float
    samples_per_s: float
    broker_cpu_pct: float
    fleet_cpu_pct: float
    fleet_rss_mb: float
    workers_cpu_pct: float
    born: int
    seq_gaps: int
    rebirths: int
    load_avg: tuple[float, float, float]


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of ``pid`` (``/proc/<pid>/stat``, fields 14 and 15)."""
    text = Path(f"/proc/{pid}/stat").read_text(encoding="ascii")
    fields = text[text.rindex(")") + 2 :].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text(encoding="ascii").splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _python(module: str, *args: object, log: Path) -> subprocess.Popen[bytes]:
    with log.open("ab") as err:
        return subprocess.Popen(
            [sys.executable, "-m", module, *map(str, args)],
            stdout=subprocess.DEVNULL,
            stderr=err,
            stdin=subprocess.DEVNULL,
            preexec_fn=stop_with_parent(),
        )


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        doc: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc


def _wait_for(path: Path, check: Any, what: str, timeout_s: float, sink: Any) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        doc = _read_json(path)
        if doc is not None and check(doc):
            return doc
        if sink.poll() is not None:
            raise RuntimeError(f"the fleet process exited with {sink.returncode}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} not within {timeout_s:g} s (last: {doc})")
        time.sleep(0.2)


def run_fleet(benches: int, tags: int, seconds: float, root: Path) -> FleetFigures:
    """Run the lab under ``root`` (the broker's files, the processes' logs); its figures."""
    broker = Broker(root / "broker")
    broker.start()
    status, out, log = root / "status.json", root / "fleet.json", root / "processes.log"
    sink = _python(
        "supervisor.bench.fleetsink",
        *("--port", broker.port, "--group", GROUP, "--status", status, "--out", out),
        log=log,
    )
    workers: list[subprocess.Popen[bytes]] = []
    try:
        _wait_for(status, lambda d: d["connected"], "the fleet's connection", 30.0, sink)
        run_s = BIRTH_TIMEOUT_S + WARMUP_S + seconds + 30.0  # they stop themselves after
        for first in range(0, benches, NODES_PER_PROCESS):
            count = min(NODES_PER_PROCESS, benches - first)
            workers.append(
                _python(
                    "supervisor.bench.fleetnodes",
                    *("--port", broker.port, "--group", GROUP, "--first", first),
                    *("--count", count, "--total", benches, "--tags", tags, "--seconds", run_s),
                    log=log,
                )
            )
        _wait_for(
            status, lambda d: d["born"] >= benches, "every bench's birth", BIRTH_TIMEOUT_S, sink
        )
        time.sleep(WARMUP_S)
        return _measure(broker, sink, workers, (benches, tags, seconds), out)
    finally:
        for w in workers:
            _stop(w)
        _stop(sink)
        broker.stop()


def _measure(
    broker: Broker,
    sink: subprocess.Popen[bytes],
    workers: list[subprocess.Popen[bytes]],
    shape: tuple[int, int, float],
    out: Path,
) -> FleetFigures:
    benches, tags, seconds = shape
    pids = [broker.pid, sink.pid, *(w.pid for w in workers)]
    sink.send_signal(signal.SIGUSR1)
    before = [_cpu_s(p) for p in pids]
    t0 = time.monotonic()
    time.sleep(seconds)
    after = [_cpu_s(p) for p in pids]
    wall = time.monotonic() - t0
    rss = _rss_mb(sink.pid)
    sink.send_signal(signal.SIGUSR2)
    res = _wait_for(out, lambda d: True, "the fleet's figures", 30.0, sink)
    hist = [(int(ms), int(c)) for ms, c in res["latency_ms"]]
    used = [(a - b) / wall * 100 for a, b in zip(after, before, strict=True)]
    return FleetFigures(
        benches,
        tags,
        seconds,
        percentile_ms(hist, 0.50),
        percentile_ms(hist, 0.99),
        float(hist[-1][0]) if hist else math.nan,
        res["messages"] / res["window_s"],
        res["samples"] / res["window_s"],
        used[0],
        used[1],
        rss,
        sum(used[2:]),
        int(res["online"]),
        int(res["seq_gaps"]),
        int(res["rebirths"]),
        os.getloadavg(),
    )


def lines(f: FleetFigures) -> list[str]:
    load = " ".join(f"{x:.2f}" for x in f.load_avg)
    return [
        f"fleet: {f.benches} benches × {f.tags} tags changing every second, one Mosquitto,"
        f" {f.seconds:g} s measured (load average {load}; {os.cpu_count()} CPUs)",
        f"  latency sample → fleet: p50 {f.p50_ms:.0f} ms, p99 {f.p99_ms:.0f} ms,"
        f" max {f.max_ms:.0f} ms (target p99 <= {TARGET_P99_MS:.0f} ms)",
        f"  {f.messages_per_s:,.0f} messages/s, {f.samples_per_s:,.0f} samples/s;"
        f" {f.born} of {f.benches} benches online, {f.seq_gaps} seq gaps, {f.rebirths} rebirths",
        f"  broker CPU {f.broker_cpu_pct:.1f} % of a core"
        f" ({_per_k(f.broker_cpu_pct, f.messages_per_s)} % per 1000 msg/s)",
        f"  fleet process CPU {f.fleet_cpu_pct:.1f} % of a core, RSS {f.fleet_rss_mb:.0f} MB",
        f"  edge nodes (the {f.benches} publishers, {NODES_PER_PROCESS} a process)"
        f" CPU {f.workers_cpu_pct:.1f} % of a core",
    ]


def _per_k(cpu_pct: float, per_s: float) -> str:
    return f"{cpu_pct / per_s * 1000:.2f}" if per_s > 0 else "n/a"


def _record(f: FleetFigures) -> None:
    cmd = f"supervisor bench fleet --benches {f.benches} --tags {f.tags} --seconds {f.seconds:g}"
    name = f"fleet {f.benches} benches × {f.tags} tags"
    load = "load average " + " ".join(f"{x:.2f}" for x in f.load_avg)
    ctx = f"{f.messages_per_s:,.0f} msg/s, {f.samples_per_s:,.0f} samples/s, {load}"
    report.record(f"{name}: latency p99", f.p99_ms, "ms", f"<= {TARGET_P99_MS:.0f}", ctx, cmd)
    report.record(f"{name}: latency p50", f.p50_ms, "ms", "", ctx, cmd)
    report.record(f"{name}: broker CPU", f.broker_cpu_pct, "% of a core", "", ctx, cmd)
    report.record(f"{name}: fleet process CPU", f.fleet_cpu_pct, "% of a core", "", ctx, cmd)
    report.record(f"{name}: fleet process RSS", f.fleet_rss_mb, "MB", "", ctx, cmd)
    report.record(f"{name}: messages", f.messages_per_s, "messages/s", "", ctx, cmd)


def fleet_benchmark(benches: int, tags: int, seconds: float, say: Any) -> int:
    """Run, print and record; exit 1 when a bench is not online at the end or p99 misses."""
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp:
        try:
            figures = run_fleet(benches, tags, seconds, Path(tmp))
        except RuntimeError as exc:
            log = Path(tmp) / "processes.log"
            tail = log.read_text(encoding="utf-8", errors="replace")[-2000:] if log.exists() else ""
            say(f"fleet: {exc}\n{tail}")
            return 1
    for line in lines(figures):
        say(line)
    _record(figures)
    ok = figures.born == benches and figures.p99_ms <= TARGET_P99_MS
    return 0 if ok else 1
