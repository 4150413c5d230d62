"""``supervisor bench influx``: points per second the InfluxDB writer sustains through its
spool into a local InfluxDB, next to raw influxdb-client batch writes in the same run.

Both write the same line-protocol strings (5 float fields per point, batches of 5000, the
influxdb-client's published throughput figure) into one local InfluxDB 1.8
started for the run (``$SUPERVISOR_INFLUXD`` or ``influxd`` on PATH; ``make influxd``
builds it): the raw side with ``write_api(SYNCHRONOUS)``, one request after the other; the
spool side through the in-memory queue, the spool on disk and the forwarder, timed until
InfluxDB acknowledged the last point. Rounds alternate so that neither side profits from a
warmer server. Also printed: the encoder's rate (samples → lines, on the scan's thread).
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

from supervisor.bench import report
from supervisor.bench.ports import free_port
from supervisor.bench.processes import stop_with_parent
from supervisor.core.quality import Quality
from supervisor.publish.changes import Sample
from supervisor.publish.influx import Forwarder, LineEncoder, Spool, WriteClient
from supervisor.publish.influx.writer import SpoolWriter

__all__ = ["influx_benchmark"]

BATCH = 5000
DATABASE = "bench"
START_TIMEOUT_S = 30.0
TOKEN = "user:password"  # any user:password: auth is off on the bench's server


def _say(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def _influxd() -> Path | None:
    named = os.environ.get("SUPERVISOR_INFLUXD") or shutil.which("influxd")
    return Path(named) if named and Path(named).is_file() else None


class _Server:
    """A throwaway influxd on loopback with its data in ``root``, stopped by its pid."""

    def __init__(self, binary: Path, root: Path) -> None:
        root.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        conf = root / "influxdb.conf"
        conf.write_text(
            f"""reporting-disabled = true
bind-address = "127.0.0.1:{free_port()}"
[meta]
  dir = "{root / "meta"}"
[data]
  dir = "{root / "data"}"
  wal-dir = "{root / "wal"}"
  query-log-enabled = false
[monitor]
  store-enabled = false
[http]
  bind-address = "127.0.0.1:{self.port}"
  log-enabled = false
[logging]
  level = "warn"
""",
            encoding="utf-8",
        )
        self._log = (root / "influxd.log").open("ab")
        self.proc = subprocess.Popen(
            [str(binary), "-config", str(conf)],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            preexec_fn=stop_with_parent(),  # no influxd left behind by a killed run
        )
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self._ping():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"influxd did not start (log: {root / 'influxd.log'})")
            time.sleep(0.05)
        data = urllib.parse.urlencode({"q": f"CREATE DATABASE {DATABASE}"}).encode()
        with urllib.request.urlopen(f"{self.url}/query", data=data, timeout=30):
            pass

    def _ping(self) -> bool:
        try:
            with urllib.request.urlopen(f"{self.url}/ping", timeout=1) as r:
                return bool(r.status == 204)
        except (urllib.error.URLError, OSError):
            return False

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


def _lines(n: int, base_ns: int, channels: int = 16) -> list[str]:
    """``n`` channel points of 5 float fields, one every 10 ms per channel."""
    out = []
    for k in range(n):
        ch, step = k % channels, k // channels
        v = 1.2 + (k % 997) * 1e-4
        out.append(
            f"channel,bench=b1,channel=ch{ch} voltage={v!r},current=0.3,temperature=25.5,"
            f"power={v * 0.3!r},charge_ah={step * 1e-6!r} {base_ns + step * 10_000_000}"
        )
    return out


def _raw(url: str, lines: list[str]) -> float:
    from influxdb_client.client.influxdb_client import InfluxDBClient
    from influxdb_client.client.write_api import SYNCHRONOUS

    with InfluxDBClient(url=url, token=TOKEN, org="-", timeout=60_000) as client:
        api = client.write_api(write_options=SYNCHRONOUS)
        t0 = time.perf_counter()
        for k in range(0, len(lines), BATCH):
            api.write(bucket=f"{DATABASE}/autogen", record=lines[k : k + BATCH])
        return time.perf_counter() - t0


def _spooled(url: str, lines: list[str], folder: Path) -> float:
    """Lines through queue → spool → forwarder; seconds until the last one was acked."""
    spool = Spool(folder / "influx-spool.sqlite", max_bytes=1 << 34)
    spool.open()
    client = WriteClient(url, "-", f"{DATABASE}/autogen", TOKEN, timeout_s=60.0)
    forwarder = Forwarder(spool, client, batch_size=BATCH, flush_interval_s=0.05, retry_max_s=1.0)
    writer = SpoolWriter(
        spool,
        commit_interval_s=0.02,
        chunk_points=BATCH,
        max_queue_points=4 * BATCH * 10,
        on_commit=forwarder.notify,
    )
    done = threading.Event()
    total = len(lines)
    delivered = [0]

    def on_delivery(d: object) -> None:
        delivered[0] += getattr(d, "points", 0)
        if delivered[0] >= total:
            done.set()

    forwarder.listeners.append(on_delivery)
    writer.start()
    forwarder.start()
    try:
        t0 = time.perf_counter()
        for k in range(0, total, BATCH):
            # The scan never waits; the benchmark's producer does, to stay within the queue.
            while writer.queued > writer.max_queue_points - BATCH:
                time.sleep(0.0005)
            writer.put("channel", lines[k : k + BATCH])
        if not done.wait(600):
            raise RuntimeError(f"spool benchmark: only {delivered[0]} of {total} acknowledged")
        elapsed = time.perf_counter() - t0
    finally:
        writer.stop()
        forwarder.stop(0.0)
        spool.close()
    return elapsed


def _encoder_rate(n: int = 200_000) -> float:
    """Samples → lines per second (what the scan's thread does each scan)."""
    names = [f"ch{k % 16}.{f}" for k, f in enumerate(("voltage", "current", "temperature") * 8)]
    enc = LineEncoder("b1", [f"ch{k}" for k in range(16)], lambda name: "float")
    samples = [
        Sample(names[k % len(names)], 1.0 + k * 1e-6, Quality.GOOD, 0.0, 1.7e9 + k * 1e-3)
        for k in range(n)
    ]
    t0 = time.perf_counter()
    for k in range(0, n, 1000):
        enc.encode(samples[k : k + 1000])
    return n / (time.perf_counter() - t0)


def influx_benchmark(points: int = 200_000, rounds: int = 3) -> int:
    binary = _influxd()
    if binary is None:
        _say(
            "influx benchmark: no InfluxDB server binary. Set SUPERVISOR_INFLUXD to an influxd"
            " 1.8 binary or put influxd on PATH (`make influxd` builds 1.8.10 with Go)."
        )
        return 2
    points = max(BATCH, points - points % BATCH)
    rounds = max(1, rounds)
    raw_s: list[float] = []
    spool_s: list[float] = []
    with tempfile.TemporaryDirectory(prefix="influx-bench-") as tmp:
        root = Path(tmp)
        server = _Server(binary, root / "influxd")
        try:
            base = 1_700_000_000 * 10**9
            _raw(server.url, _lines(BATCH, base - 10**12))  # warm-up: series, shard, caches
            for r in range(rounds):
                raw_lines = _lines(points, base + (2 * r) * 10**12)
                spool_lines = _lines(points, base + (2 * r + 1) * 10**12)
                folder = root / f"spool{r}"
                folder.mkdir()
                # Each round is a pair, in alternating order: neither side always meets
                # the server right after the other's writes (its compactions, its cache).
                if r % 2 == 0:
                    raw_s.append(_raw(server.url, raw_lines))
                    spool_s.append(_spooled(server.url, spool_lines, folder))
                else:
                    spool_s.append(_spooled(server.url, spool_lines, folder))
                    raw_s.append(_raw(server.url, raw_lines))
        finally:
            server.stop()
    raw_rates = [points / s for s in raw_s]
    spool_rates = [points / s for s in spool_s]
    ratios = [sp / raw for sp, raw in zip(spool_rates, raw_rates, strict=True)]
    _say(
        f"influx benchmark: {points} points × 5 float fields per round, batches of {BATCH},"
        f" local InfluxDB 1.8 ({binary}), {rounds} rounds"
    )
    _say(
        "  raw influxdb-client (SYNCHRONOUS)             "
        + ", ".join(f"{x:,.0f}" for x in raw_rates)
        + f" points/s; median {statistics.median(raw_rates):,.0f}"
    )
    _say(
        "  through the spool (queue → SQLite → forwarder) "
        + ", ".join(f"{x:,.0f}" for x in spool_rates)
        + f" points/s; median {statistics.median(spool_rates):,.0f}"
    )
    _say(
        "  ratio spool/raw per round "
        + ", ".join(f"{x:.2f}" for x in ratios)
        + f"; median {statistics.median(ratios):.2f} (target ≥ 0.9)"
    )
    _say(f"  encoder (samples → lines, scan thread) {_encoder_rate():,.0f} samples/s")
    report.record(
        "InfluxDB ingest through the spool vs raw influxdb-client batches",
        statistics.median(ratios),
        "",
        ">= 0.9",
        f"raw influxdb-client {statistics.median(raw_rates):,.0f} points/s",
        f"supervisor bench influx --points {points} --rounds {rounds}",
    )
    return 0
