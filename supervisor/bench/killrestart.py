"""``supervisor bench kill-restart``: SIGKILL the supervisor at random points of a running
recipe, restart it, and check the test comes back Held where it was and completes.

Processes: ``supervisor sim`` serves the seed-002 devices in one process (so the battery
model survives the kill), ``supervisor run --no-sim`` is the supervisor being killed; every
process is stopped by its pid.
"""

from __future__ import annotations

import itertools
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from supervisor.bench.ports import free_port
from supervisor.publish.results import read_timeline
from supervisor.scan import ScanStats


def _say(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


# --- kill-restart: SIGKILL the supervisor at random points of a running recipe ------------
KILL_RESTART_CHANNEL = "ch4"
KILL_RESTART_RECIPE = """\
recipe: kill-restart
description: short cycle on the seed 002 pack, for supervisor bench kill-restart
logging: {period: 1 s}
steps:
  - {id: charge, charge: 5 A, duration: 3 s}
  - {id: rest, rest: 1 s}
  - {id: discharge, discharge: 5 A, duration: 3 s}
"""
KILL_RESTART_LENGTH_S = 7.0  # the recipe's duration
COUNTER_TOLERANCE = 0.001  # restored counters within 0.1 % of the last save
COUNTER_FLOOR_AH = 1e-6  # below this a counter is compared absolutely
COUNTERS = ("charge_ah", "charged_ah", "discharged_ah", "energy_wh", "charged_wh", "discharged_wh")
WAIT_S = 60.0
"""Upper bound for anything to happen on a loaded machine (not a timing claim)."""


@dataclass
class KillRestart:
    """One kill and restart: what was saved, what came back, how the test ended."""

    index: int
    kill_after_s: float  # after the start command (seeded, random)
    saved_state: str = ""
    saved_step: str = ""
    restored_state: str = ""
    restored_step: str = ""
    counter_error: float = 0.0  # largest relative deviation of a restored counter
    contactor_open_s: float = 0.0  # kill → the simulated contactor open (its watchdogs)
    restart_to_held_s: float = 0.0  # from the restart to the channel reported Held
    final_state: str = ""
    restart_noted: bool = False  # the summary's timeline records the interruption
    outputs_off: bool = False  # Held with no current asked and nothing enabled
    bdf_continues: bool = False  # one header, record index 1..n without a gap
    bdf_backwards_ah: float = 0.0  # largest drop of a BDF capacity column across the kill
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def _http(method: str, url: str, body: object | None = None) -> Any:
    import json
    import urllib.request

    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        url, data=data, method=method, headers={"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(req, timeout=5) as resp:
        return json.loads(resp.read())


def _wait(what: str, pred: Callable[[], bool], limit_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + limit_s
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"gave up after {limit_s:g} s waiting for {what}")
        time.sleep(0.05)


class _Process:
    """A child process we started, stopped by its pid (SIGTERM, then SIGKILL)."""

    def __init__(self, args: list[str], cwd: Path, log_path: Path) -> None:
        import os
        import subprocess

        self._log = log_path.open("a", encoding="utf-8")
        self.proc = subprocess.Popen(
            args,
            cwd=cwd,
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        self.pid = self.proc.pid

    def banner(self, until: str) -> list[str]:
        """stdout lines up to the one starting with ``until``."""
        assert self.proc.stdout is not None
        lines = []
        for line in self.proc.stdout:
            lines.append(line.rstrip("\n"))
            if line.startswith(until):
                return lines
        raise RuntimeError(f"pid {self.pid} ended before {until!r}: {lines}")

    def kill(self) -> None:
        import os
        import signal

        os.kill(self.pid, signal.SIGKILL)
        self.proc.wait()

    def stop(self, timeout_s: float = 20.0) -> int:
        import signal
        import subprocess

        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                # Stuck: its stacks into the log (supervisor run dumps them on SIGUSR1).
                self.proc.send_signal(signal.SIGUSR1)  # threads
                self.proc.send_signal(signal.SIGUSR2)  # asyncio tasks
                time.sleep(1.0)
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._log.close()
        return self.proc.returncode


def _connected(url: str) -> bool:
    tags = ("ea.connected", "adam.connected", "bms.connected", "estop.ok")
    return all(_http("GET", f"{url}/tags/{t}")["value"] is True for t in tags)


def _in_state(url: str, states: tuple[str, ...]) -> bool:
    return _http("GET", f"{url}/tags/{KILL_RESTART_CHANNEL}.chain.state")["value"] in states


def _ended(url: str) -> bool:
    """The test ended, or an alarm holds it (it would wait for an operator)."""
    ch = KILL_RESTART_CHANNEL
    if _in_state(url, ("Complete", "Idle", "Stopped", "Aborted")):
        return True
    return bool(_http("GET", f"{url}/tags/{ch}.chain.alarm")["value"]) or bool(
        _http("GET", f"{url}/tags/{ch}.fault")["value"]
    )


def kill_restart_map(workdir: Path, io_map: str = "io_maps/sim.yaml") -> Path:
    """The seed 002 bench of ``io_map`` alone (no Chadèche stack: its simulated cell lives
    in the supervisor's process and would restart with it), on free loopback ports, its
    state under ``workdir``."""
    import yaml

    data = yaml.safe_load(Path(io_map).read_text(encoding="utf-8"))
    data["devices"] = {k: v for k, v in data["devices"].items() if k in ("adam", "ea", "bms")}
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    if any(t["name"] == "pack.voltage" for t in data.get("tags", [])):
        for c in data["channels"]:
            # Battery side: the supply's terminals read 0 V until the contactor closes,
            # which a test resumed in a discharge would take for an empty pack.
            c.setdefault("voltage_tag", "pack.voltage")
    for dev in data["devices"].values():
        dev["port"] = free_port()
    data["hmi"]["port"] = 0
    data["hmi"]["login"] = False  # its HTTP client does not log in (loopback)
    data.pop("opcua", None)  # not what this measures (and 4840 may be taken)
    data.pop("modbus_server", None)  # likewise (and 1502)
    data["state_dir"] = str(workdir / "var")
    data["recipes"] = {"folders": [str(workdir)]}  # where its recipe is written
    path = workdir / "seed002.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def kill_restart(
    iterations: int,
    seed: int,
    workdir: Path,
    io_map: str = "io_maps/sim.yaml",
    say: Callable[[str], None] = lambda _msg: None,
) -> list[KillRestart]:
    """``supervisor sim`` serves the seed 002 devices (their plant outlives the
    supervisor); ``supervisor run --no-sim`` is started, given the kill-restart recipe over
    HTTP, SIGKILLed at a random (seeded) moment of it, restarted, checked (Held at the
    saved step, counters as saved, outputs off), resumed and run to completion; then
    stopped with SIGTERM. Every process is stopped by its pid, whatever happens."""
    import random
    import sys

    from supervisor.publish.retain import STATE_NAME, RetainStore

    rng = random.Random(seed)
    bench_map = kill_restart_map(workdir, io_map)
    recipe = workdir / "kill-restart.yaml"
    recipe.write_text(KILL_RESTART_RECIPE, encoding="utf-8")
    logs = workdir / "logs.txt"
    exe = [sys.executable, "-m", "supervisor.cli.main"]
    ch = KILL_RESTART_CHANNEL
    state_file = workdir / "var" / STATE_NAME
    results: list[KillRestart] = []
    control_port = free_port()
    control = f"http://127.0.0.1:{control_port}/api"  # the sim's plant state and e-stop
    sim = _Process(
        [*exe, "sim", str(bench_map), "--control-port", str(control_port)], workdir, logs
    )
    running: list[_Process] = []

    def start_supervisor() -> tuple[_Process, str]:
        p = _Process(
            [*exe, "run", "--no-sim", str(bench_map), "--log-level", "warning"], workdir, logs
        )
        running.append(p)
        url = ""
        for line in p.banner("Ctrl-C"):
            if line.startswith("HTTP API listening on "):
                url = line.split()[-1].removesuffix("/tags")
        return p, url

    def tag(url: str, name: str) -> Any:
        return _http("GET", f"{url}/tags/{name}")["value"]

    try:
        sim.banner("e-stop button")
        for k in range(1, iterations + 1):
            res = KillRestart(k, round(rng.uniform(0.3, KILL_RESTART_LENGTH_S - 0.3), 2))
            results.append(res)
            p, url = start_supervisor()
            _wait("devices connected", partial(_connected, url))
            _http("PUT", f"{url}/channels/{ch}/recipe", {"file": str(recipe)})
            _http("PUT", f"{url}/tags/{ch}.command", {"value": "start"})
            _wait("Running", partial(_in_state, url, ("Running",)))
            time.sleep(res.kill_after_s)
            p.kill()
            t_kill = time.monotonic()
            # Nothing drives the bench now: its watchdogs must open the contactor by themselves.
            _wait(
                "the contactor opened by its watchdogs",
                lambda: _http("GET", f"{control}/sim/state")["contactor_closed"] is False,
            )
            res.contactor_open_s = time.monotonic() - t_kill
            running.remove(p)
            p.stop()
            saved = RetainStore(state_file).read()[f"channel:{ch}"]
            chain = saved["chain"] or {}
            res.saved_state, res.saved_step = chain.get("state", ""), chain.get("step_id", "")
            t0 = time.monotonic()
            p, url = start_supervisor()
            res.restored_state = tag(url, f"{ch}.chain.state")
            res.restart_to_held_s = time.monotonic() - t0
            res.restored_step = tag(url, f"{ch}.chain.step")
            for name in COUNTERS:
                want = float(saved["tags"][f"{ch}.{name}"])
                got = float(tag(url, f"{ch}.{name}"))
                err = abs(got - want) / max(abs(want), COUNTER_FLOOR_AH)
                res.counter_error = max(res.counter_error, err)
            if res.saved_state in ("Running", "Holding", "Held", "Resuming"):
                if res.restored_state != "Held":
                    res.problems.append(f"came back {res.restored_state}, not Held")
                if res.restored_step != res.saved_step:
                    res.problems.append(f"step {res.restored_step!r} != saved {res.saved_step!r}")
                res.outputs_off = (
                    tag(url, f"{ch}.current_cmd") == 0.0
                    and tag(url, f"{ch}.enable") is False
                    and tag(url, f"{ch}.auto_active") is False
                )
                if not res.outputs_off:
                    res.problems.append("re-energised on its own after the restart")
                _wait("devices connected", partial(_connected, url))
                _http("PUT", f"{url}/tags/{ch}.command", {"value": "resume"})
            elif res.restored_state != "Idle":
                res.problems.append(f"an ended test came back {res.restored_state}, not Idle")
            if res.counter_error > COUNTER_TOLERANCE:
                res.problems.append(f"counters off by {res.counter_error:.2%}")
            _wait("the test ends", partial(_ended, url))
            res.final_state = tag(url, f"{ch}.chain.state")
            why = tag(url, f"{ch}.chain.alarm") or tag(url, f"{ch}.fault")
            if why:
                res.problems.append(f"held by an alarm: {why}")
            test_id = tag(url, f"{ch}.chain.test_id")
            folder = workdir / "var" / "results" / test_id
            summary = _read_summary(folder / "summary.json")
            # Every event, in the timeline file (the summary has the first and the latest).
            res.restart_noted = any(
                str(e.get("text", "")).startswith("supervisor restarted after")
                for e in read_timeline(folder)
            )
            res.bdf_continues, res.bdf_backwards_ah = _bdf_continuity(
                workdir / "var" / "results" / test_id / f"{test_id}.bdf.csv"
            )
            if not res.bdf_continues:
                res.problems.append("the BDF file does not continue (header or record index)")
            if res.saved_state != "Complete":
                if res.final_state != "Complete" or summary.get("complete") is not True:
                    res.problems.append(f"ended {res.final_state}, summary {summary.get('state')}")
                if not res.restart_noted:
                    res.problems.append("the summary's timeline does not record the restart")
            running.remove(p)
            code = p.stop()
            if code != 0:
                res.problems.append(f"supervisor exited {code} on SIGTERM")
            say(
                f"  {k:2d}: killed {res.kill_after_s:4.2f} s after start, saved"
                f" {res.saved_state} in {res.saved_step or '-'}; back {res.restored_state} in"
                f" {res.restored_step or '-'} ({res.restart_to_held_s:.2f} s), counters"
                f" {res.counter_error:.1e}; contactor open {res.contactor_open_s:.2f} s after the"
                f" kill; ended {res.final_state}; BDF drop"
                f" {res.bdf_backwards_ah * 1000:.3f} mAh"
                + ("" if res.ok else f"  PROBLEMS: {'; '.join(res.problems)}")
            )
    finally:
        for p in running:
            p.stop()
        sim.stop()
    return results


def _watchdog_s(workdir: Path) -> float:
    """The watchdog relay's time in the bench map the benchmark ran (0: none fitted)."""
    import yaml

    data = yaml.safe_load((workdir / "seed002.yaml").read_text(encoding="utf-8"))
    relay = (data.get("simulation") or {}).get("watchdog_relay") or {}
    return float(relay.get("timeout_s", 0.0))


def _bdf_continuity(path: Path) -> tuple[bool, float]:
    """(one header and record indexes 1..n, largest drop of a capacity column): rows
    written after the last save of a killed supervisor are followed by rows counted from
    that save, so a capacity column may step back by what those rows had added."""
    import csv

    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError:
        return False, 0.0
    rows = list(csv.DictReader(lines))
    header_once = sum(1 for line in lines if line.startswith("Test Time / s")) == 1
    index = [int(r["Record Index / 1"]) for r in rows]
    drop = 0.0
    for col in ("Charging Capacity / Ah", "Discharging Capacity / Ah"):
        values = [float(r[col]) for r in rows if r[col]]
        for a, b in itertools.pairwise(values):
            drop = max(drop, a - b)
    return header_once and index == list(range(1, len(rows) + 1)), drop


def _read_summary(path: Path) -> dict[str, Any]:
    import json

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def kill_restart_benchmark(iterations: int, seed: int) -> int:
    """``supervisor bench kill-restart``: figures printed, exit 1 if any restart failed."""
    import shutil
    import tempfile

    _say(f"kill-restart: {iterations} SIGKILLs at random points of a {KILL_RESTART_LENGTH_S:g} s")
    _say(f"  recipe on the seed 002 bench (seed {seed}; devices served by supervisor sim)")
    workdir = Path(tempfile.mkdtemp(prefix="kill-restart-"))
    try:
        results = kill_restart(iterations, seed, workdir, say=_say)
    except Exception as exc:
        _say(f"  failed: {exc} (logs kept in {workdir})")
        return 1
    good = [r for r in results if r.ok]
    held = [r.restart_to_held_s for r in results]
    _say(
        f"  {len(good)}/{len(results)} restarts came back as saved and completed;"
        f" restart to Held p50 {ScanStats.percentile(held, 50):.2f} s,"
        f" max {max(held):.2f} s; largest counter deviation"
        f" {max(r.counter_error for r in results):.1e}; largest BDF capacity drop"
        f" {max(r.bdf_backwards_ah for r in results) * 1000:.3f} mAh"
        f" ({sum(r.bdf_backwards_ah > 0 for r in results)} of {len(results)} kills)"
    )
    opened = [r.contactor_open_s for r in results]
    _say(
        f"  contactor opened by the watchdogs after each kill: p50"
        f" {ScanStats.percentile(opened, 50):.2f} s, max {max(opened):.2f} s"
        f" (watchdog relay {_watchdog_s(workdir):g} s)"
    )
    if len(good) == len(results):
        shutil.rmtree(workdir, ignore_errors=True)
        return 0
    _say(f"  logs kept in {workdir}")
    return 1
