"""Must show (issue 10), second half: the same outage with the supervisor SIGKILLed during
it and restarted. ``supervisor run`` on a copy of io_maps/sim.yaml with an ``influxdb:``
section pointing at the test's InfluxDB, killed by pid while the server is down; the
restart resumes draining the spool in order once the server is back.

Zero lost except what the kill itself can lose: the points still in memory, not yet
committed to the spool — at most one ``spool_commit_interval_s`` of production (0.2 s).
Every line the spool held at the kill (read from the file right after it) is on the server,
the spool's books balance (produced = sent, nothing dropped or dead-lettered), and the
server holds exactly as many points as the spool recorded as produced. The window the kill
lost is measured on the scan's own series (``scan.count`` is stored every scan: its run-1
values on the server run 1..K without a hole; the time from its last one to the kill is
logged, not asserted). Wall time: a 30 s outage.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sqlite3
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from influxrig import InfluxServer, expected_points, server_points, sim_map

OUTAGE_S = 30.0
LIMIT_S = 120.0  # a bound for a loaded machine, not a timing claim
COMMIT_INTERVAL_S = 0.2  # the default spool_commit_interval_s
pytestmark = pytest.mark.integration
log = logging.getLogger(__name__)


class Supervisor:
    """``supervisor run`` as a child process, stopped by its pid."""

    def __init__(self, io_map: Path, log_path: Path) -> None:
        self._log = log_path.open("a", encoding="utf-8")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "supervisor.cli.main", "run", str(io_map)],
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        self.banner: list[str] = []
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.banner.append(line.rstrip("\n"))
            if line.startswith("Ctrl-C"):
                break
        else:
            raise RuntimeError(f"supervisor ended before its banner: {self.banner}")
        (url,) = [x.split()[-1] for x in self.banner if x.startswith("HTTP API listening")]
        self.url = url.removesuffix("/tags")

    def tag(self, name: str) -> Any:
        with urllib.request.urlopen(f"{self.url}/tags/{name}", timeout=10) as r:
            return json.loads(r.read())["value"]

    def write(self, name: str, value: object) -> None:
        req = urllib.request.Request(
            f"{self.url}/tags/{name}",
            data=json.dumps({"value": value}).encode(),
            method="PUT",
            headers={"Content-Type": "application/json"},
        )
        with urllib.request.urlopen(req, timeout=10):
            pass

    def charge(self) -> None:
        """Every Chadèche channel at 0.2 A: currents, voltages and counters move."""
        wait_for(lambda: self.tag("chadeche.connected") is True, "the boards")
        for ch in ("ch0", "ch1", "ch2", "ch3"):
            self.write(f"{ch}.manual_current", 0.2)
            self.write(f"{ch}.enable", True)

    def kill(self) -> float:
        os.kill(self.proc.pid, signal.SIGKILL)
        t = time.time()
        self.proc.wait()
        self._close()
        return t

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._close()
        return self.proc.returncode

    def _close(self) -> None:
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._log.close()


def wait_for(condition: Callable[[], bool], what: str, limit_s: float = LIMIT_S) -> None:
    deadline = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up after {limit_s:g} s waiting for {what}")
        time.sleep(0.1)


def spool_state(path: Path) -> tuple[dict[str, int], list[str]]:
    """A spool file's counters and its waiting lines (read-only, from outside)."""
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        counters = {k: int(v) for k, v in conn.execute("SELECT name, value FROM counter")}
        row = conn.execute("SELECT value FROM meta WHERE key = 'acked_id'").fetchone()
        acked = int(row[0]) if row else 0
        lines: list[str] = []
        for (body,) in conn.execute("SELECT body FROM chunk WHERE id > ? ORDER BY id", (acked,)):
            lines.extend(bytes(body).decode().split("\n"))
    finally:
        conn.close()
    return counters, lines


def total(counters: dict[str, int], what: str) -> int:
    return sum(v for k, v in counters.items() if k.startswith(f"{what}:"))


@pytest.mark.timeout(400)
def test_a_supervisor_killed_during_the_outage_resumes_and_loses_only_its_last_commit_interval(
    tmp_path: Path, influx: InfluxServer
) -> None:
    io_map = sim_map(tmp_path, influx)
    spool = tmp_path / "var" / "influx-spool.sqlite"
    run1 = Supervisor(io_map, tmp_path / "run1.log")
    try:
        run1.charge()
        wait_for(lambda: run1.tag("influx.sent") > 0, "the first delivery")
        influx.stop()
        t_down = time.monotonic()
        wait_for(lambda: run1.tag("influx.connected") is False, "the outage seen")
        time.sleep(OUTAGE_S / 3)
        assert run1.tag("influx.spool_depth") > 0
    except BaseException:
        run1.stop()
        raise
    t_kill = run1.kill()
    counters_at_kill, waiting_at_kill = spool_state(spool)
    assert waiting_at_kill, "the kill found nothing in the spool"

    run2 = Supervisor(io_map, tmp_path / "run2.log")
    try:
        resumed = [x for x in run2.banner if x.startswith("InfluxDB:")]
        assert resumed and f"({len(waiting_at_kill)} points waiting)" in resumed[0], resumed
        run2.charge()
        time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - t_down)))
        influx.start()
        wait_for(
            lambda: run2.tag("influx.connected") is True and run2.tag("influx.spool_depth") < 200,
            "the backlog drained",
        )
        time.sleep(2.0)
    finally:
        code = run2.stop()
    assert code == 0, (tmp_path / "run2.log").read_text(encoding="utf-8")[-3000:]

    counters, waiting = spool_state(spool)
    produced, sent = total(counters, "produced"), total(counters, "sent")
    assert not waiting
    assert (total(counters, "dropped"), total(counters, "dead")) == (0, 0)
    assert produced == sent > total(counters_at_kill, "produced")

    on_server = server_points(influx)
    # Everything the spool held when the process died reached the server, values included.
    expected = expected_points(waiting_at_kill)
    missing = [k for k in expected if k not in on_server]
    assert not missing, f"{len(missing)} spooled points lost, e.g. {missing[:3]}"
    assert all(on_server[k] == f for k, f in expected.items())
    # And nothing else is missing: the server holds every point the spool ever produced.
    by_measurement = {
        k.split(":", 1)[1]: v for k, v in counters.items() if k.startswith("produced:")
    }
    for m, n in by_measurement.items():
        assert sum(1 for k in on_server if k[0] == m) == n, m

    # The kill's own loss: run 1's scan counter is stored every scan; on the server it runs
    # 1..K without a hole, and its last point is within a commit interval of the kill.
    scan_key = frozenset({("bench", "sim"), ("source", "scan")})
    run1_counts = sorted(
        (ts, int(f["count"]))
        for (m, tags, ts), f in on_server.items()
        if m == "diagnostics" and tags == scan_key and "count" in f and ts < t_kill * 1e9
    )
    values = [v for _, v in run1_counts]
    first = values[0]
    assert values == list(range(first, first + len(values))), "a hole in run 1's scans"
    lost_s = t_kill - run1_counts[-1][0] / 1e9
    log.info(
        "SIGKILL lost the last %.3f s of run 1 (scan period 0.1 s, commit interval %.1f s):"
        " about %d scans; spool at the kill: %d points waiting, %d produced",
        lost_s,
        COMMIT_INTERVAL_S,
        round(lost_s / 0.1),
        len(waiting_at_kill),
        total(counters_at_kill, "produced"),
    )
