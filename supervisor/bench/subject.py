"""``supervisor run`` as a benchmark's subject: a copy of an I/O map on free ports in a
temporary folder, the process started and stopped by its pid, its HTTP API polled.

The benchmarks that measure a whole supervisor (``supervisor bench load``, ``supervisor
bench memory``) measure the real command in a process of its own, never a bench built in
the benchmark's process: the clients that load it (OPC UA, WebSocket, HTTP) must not run
on the loop they measure.
"""

from __future__ import annotations

import json
import logging
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from supervisor.bench.ports import free_port
from supervisor.bench.processes import stop_with_parent

log = logging.getLogger(__name__)

START_TIMEOUT_S = 90.0
STOP_TIMEOUT_S = 30.0


def prepare(io_map: Path, root: Path, influx_url: str | None = None) -> tuple[Path, int, int]:
    """Write a copy of ``io_map`` in ``root``: every listening port free (HTTP, OPC UA, Modbus
    TCP, the simulated devices), its state in ``root/state``, InfluxDB at ``influx_url``
    (the section dropped when None). Returns the copy, its HTTP port and its OPC UA port
    (0: off)."""
    data: dict[str, Any] = yaml.safe_load(io_map.read_text(encoding="utf-8"))
    data["state_dir"] = str(root / "state")
    http_port = free_port()
    data.setdefault("hmi", {})["port"] = http_port
    data["hmi"]["host"] = "127.0.0.1"
    opcua_port = 0
    if (data.get("opcua") or {}).get("enabled"):
        opcua_port = free_port()
        data["opcua"]["port"] = opcua_port
        data["opcua"]["host"] = "127.0.0.1"
    if isinstance(data.get("modbus_server"), dict):
        data["modbus_server"]["port"] = free_port()
        data["modbus_server"]["host"] = "127.0.0.1"
    for dev in (data.get("devices") or {}).values():
        if "port" in dev:
            dev["port"] = free_port()
    if "influxdb" in data:
        if influx_url is None:
            del data["influxdb"]
        else:
            data["influxdb"]["url"] = influx_url
            token = data["influxdb"].get("token_file")
            if token is not None and not Path(token).is_absolute():
                data["influxdb"]["token_file"] = str((Path.cwd() / token).resolve())
    copy = root / io_map.name
    copy.write_text(yaml.safe_dump(data, allow_unicode=True, sort_keys=False), encoding="utf-8")
    return copy, http_port, opcua_port


class Supervisor:
    """``supervisor run COPY`` in a child process (its output in ``log_path``)."""

    def __init__(
        self,
        io_map: Path,
        http_port: int,
        args: list[str],
        log_path: Path,
        env: Mapping[str, str] | None = None,
        prefix: Sequence[str] = (),
    ) -> None:
        """``prefix``: a command the supervisor runs under (``supervisor bench pi-budget``:
        valgrind's instruction counter)."""
        self.url = f"http://127.0.0.1:{http_port}"
        self.log_path = log_path
        self._log = log_path.open("ab")
        cmd = [*prefix, sys.executable, "-m", "supervisor.cli.main", "run", str(io_map), *args]
        cmd += ["--log-level", "warning"]
        self.proc = subprocess.Popen(
            cmd,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            preexec_fn=stop_with_parent(),  # no supervisor left behind by a killed run
            env=None if env is None else dict(env),
        )
        self.pid = self.proc.pid

    def get(self, path: str, timeout_s: float = 10.0) -> Any:
        with urllib.request.urlopen(self.url + path, timeout=timeout_s) as r:
            return json.loads(r.read())

    def wait_ready(self, timeout_s: float = START_TIMEOUT_S) -> dict[str, Any]:
        """Until the scan runs (``/api/diagnostics`` answers with scans counted)."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"supervisor run exited with {self.proc.returncode}: {self.tail()}"
                )
            try:
                diag: dict[str, Any] = self.get("/api/diagnostics", timeout_s=2.0)
                if diag["scan"]["count"] > 0:
                    return diag
            except (urllib.error.URLError, OSError, ValueError, KeyError):
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"supervisor run did not start in {timeout_s:.0f} s")
            time.sleep(0.2)

    def memory_kib(self) -> tuple[int, dict[str, int]]:
        """The bench's memory, in KiB: the proportional set size (PSS: a page shared by
        several processes counted once, split among them) of the supervisor and every
        process it started — its OPC UA server (ADR 0029) and its recipe checks (ADR 0027)
        — and each process's share by what it runs. ``VmRSS`` where the kernel gives no
        ``smaps_rollup``."""
        total = 0
        by: dict[str, int] = {}
        for pid in process_tree(self.pid):
            kib = _pss_kib(pid)
            if kib is None:
                continue  # ended meanwhile
            total += kib
            label = _label(pid)
            by[label] = by.get(label, 0) + kib
        if total == 0:
            raise RuntimeError(f"no memory figures in /proc/{self.pid}")
        return total, by

    def tail(self, n: int = 15) -> str:
        if not self._log.closed:
            self._log.flush()
        try:
            lines = self.log_path.read_text(encoding="utf-8", errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])

    def stop(self) -> int:
        """SIGTERM (every output safe, publishers flushed), SIGKILL if it does not exit."""
        code = _terminate(self.proc, "supervisor run")
        self._log.close()
        return code


class Simulators:
    """``supervisor sim COPY`` in a child process: the I/O map's served simulators (the
    ADAM-5000/TCP, the EA supply, the BMS's CAN gateway) on their ports, the devices a
    ``supervisor run COPY --no-sim`` reaches over loopback as it would reach real ones on
    the bench's network. Its e-stop button API is on ``control_port``."""

    def __init__(self, io_map: Path, control_port: int, log_path: Path) -> None:
        self.control_url = f"http://127.0.0.1:{control_port}"
        self.log_path = log_path
        self._log = log_path.open("ab")
        cmd = [sys.executable, "-m", "supervisor.cli.main", "sim", str(io_map)]
        cmd += ["--control-port", str(control_port), "--log-level", "info"]
        self.proc = subprocess.Popen(
            cmd,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            preexec_fn=stop_with_parent(),
        )
        self.pid = self.proc.pid

    def wait_ready(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Until its plant answers (``GET /api/sim/state``): every simulator is listening."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self.proc.poll() is not None:
                tail = self.log_path.read_text(encoding="utf-8", errors="replace")[-2000:]
                raise RuntimeError(f"supervisor sim exited with {self.proc.returncode}: {tail}")
            try:
                with urllib.request.urlopen(self.control_url + "/api/sim/state", timeout=2.0):
                    return
            except (urllib.error.URLError, OSError):
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"supervisor sim did not start in {timeout_s:.0f} s")
            time.sleep(0.2)

    def stop(self) -> int:
        """SIGTERM, SIGKILL if it does not exit."""
        code = _terminate(self.proc, "supervisor sim")
        self._log.close()
        return code


def _terminate(proc: subprocess.Popen[bytes], what: str) -> int:
    """Stop a child by its pid: SIGTERM, then SIGKILL after ``STOP_TIMEOUT_S``."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            log.warning("%s (pid %d) did not stop: killed", what, proc.pid)
            proc.kill()
            proc.wait()
    return int(proc.returncode)


def recipe_args(channels: list[str], recipe: Path) -> list[str]:
    """``--start --recipe CH=FILE`` for every channel."""
    out = ["--start"]
    for ch in channels:
        out += ["--recipe", f"{ch}={recipe.resolve()}"]
    return out


def process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants (``/proc/<pid>/task/<tid>/children``), parents first."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop(0)
        out.append(p)
        try:
            tasks = list(Path(f"/proc/{p}/task").iterdir())
        except OSError:
            continue
        for task in tasks:
            try:
                todo.extend(int(c) for c in (task / "children").read_text().split())
            except (OSError, ValueError):
                continue
    return out


def _pss_kib(pid: int) -> int | None:
    for name, key in (("smaps_rollup", "Pss:"), ("status", "VmRSS:")):
        try:
            text = Path(f"/proc/{pid}/{name}").read_text(encoding="utf-8")
        except OSError:
            continue
        for line in text.splitlines():
            if line.startswith(key):
                return int(line.split()[1])
    return None


_ROLES = {
    "supervisor.cli.main": "supervisor",
    "supervisor.publish.opcua.child": "OPC UA server",
    "supervisor.commands.childjob": "recipe checks",
}


def _label(pid: int) -> str:
    """What a process of the bench runs: its module after ``-m`` (the supervisor's own
    command line for the supervisor)."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return str(pid)
    words = [a.decode(errors="replace") for a in argv if a]
    if "-m" in words and words.index("-m") + 1 < len(words):
        module = words[words.index("-m") + 1]
        return _ROLES.get(module, module)
    return words[0] if words else str(pid)
