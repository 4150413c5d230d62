"""``supervisor bench flood``: a flood of clients never costs a device its connection
(issue 27, finding 3 and its "Must show").

A real ``supervisor run`` of io_maps/sim.yaml (a temporary copy: free loopback ports, a
temporary state folder, login on, an operator added by ``supervisor opcua add-user``) runs
under a soft and hard ``RLIMIT_NOFILE`` of 1024 (what the shipped unit had without
``LimitNOFILE=``). With a test running on ch0 and the operator logged in on a connection
kept from before: 2000 idle TCP connections to the HTTP port and 200 to the OPC UA port,
then wrong-password logins at 100/s for 30 s. Throughout, every device's ``DEV.connected``
is read over the operator's connection. Figures: devices disconnected, trips, stalls, log
size, the operator's session valid, HTTP 503 answers beyond the cap, connections accepted,
logins/s achieved and their answers by status.

Only the supervisor runs under 1024: this process raises its own soft limit (its 2200
client sockets). Every child process is stopped by its pid.
"""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import re
import resource
import selectors
import signal
import socket
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import yaml

from supervisor.bench.ports import free_port

ROOT: Final = Path(__file__).resolve().parents[2]
SUPERVISOR_NOFILE: Final = 1024
"""The supervisor's soft and hard descriptor limit in the flood (systemd's default soft)."""
DEVICES: Final = ("chadeche", "adam", "ea", "bms")
OPERATOR: Final = ("operator", "operator-pw")
CHANNEL: Final = "ch0"
RECIPE: Final = "recipes/nimh-25h-slow-cycle.yaml"
"""A test that runs for hours: it must still be Running after the flood."""
WAIT_S: Final = 60.0
"""Upper bound for the supervisor to start on a loaded machine (not a timing claim)."""
MIB: Final = 1024 * 1024


def _say(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def flood_map(
    folder: Path,
    hmi: dict[str, Any] | None = None,
    recipe_folders: tuple[Path, ...] = (),
    recipes: dict[str, Any] | None = None,
) -> Path:
    """io_maps/sim.yaml on free loopback ports with its state in ``folder``, login on;
    ``hmi``: keys added to its ``hmi:`` section (a test's short header timeout);
    ``recipe_folders``: more recipe folders than the repository's ``recipes/``;
    ``recipes``: keys added to its ``recipes:`` section (a test's short check deadline)."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["hmi"].update({"port": 0, "login": True, **(hmi or {})})
    data["opcua"]["port"] = free_port()
    if "modbus_server" in data:
        data["modbus_server"]["port"] = free_port()
    for name in ("adam", "ea", "bms"):
        data["devices"][name]["port"] = free_port()
    data["state_dir"] = str(folder / "state")
    data["recipes"] = {
        "folders": [str(ROOT / "recipes"), *map(str, recipe_folders)],
        **(recipes or {}),
    }
    path = folder / "flood.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def add_user(io_map: Path, user: str, password: str, role: str) -> None:
    """``supervisor opcua add-user`` in a child process, the password on its stdin."""
    subprocess.run(
        [
            *(sys.executable, "-m", "supervisor.cli.main", "opcua", "add-user", user),
            *("--role", role, "--password-stdin", "--io-map", str(io_map)),
        ],
        input=password + "\n",
        text=True,
        check=True,
        capture_output=True,
        cwd=ROOT,
    )


def raise_own_limit(wanted: int) -> int:
    """This process's soft descriptor limit raised towards ``wanted`` (its client sockets)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if soft < target:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        soft = target
    return soft


def _limited() -> None:
    # In the child, before exec: the supervisor gets 1024 descriptors, soft and hard.
    resource.setrlimit(resource.RLIMIT_NOFILE, (SUPERVISOR_NOFILE, SUPERVISOR_NOFILE))


class Supervisor:
    """A ``supervisor run`` child under ``RLIMIT_NOFILE`` 1024, its log in a file."""

    def __init__(self, io_map: Path, log_path: Path, nofile: int | None = SUPERVISOR_NOFILE):
        self.log_path = log_path
        self._log = log_path.open("w", encoding="utf-8")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "supervisor.cli.main", "run", str(io_map)],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
            preexec_fn=_limited if nofile is not None else None,
        )
        self.banner: list[str] = []
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.banner.append(line.rstrip("\n"))
            if line.startswith("Ctrl-C"):
                break
        else:
            self.stop()
            raise RuntimeError(
                f"supervisor run ended before listening: {self.banner}\n{self.log_text()}"
            )
        text = "\n".join(self.banner)
        http_m = re.search(r"HTTP API listening on http://([\d.]+):(\d+)/api", text)
        opc_m = re.search(r"OPC UA server listening on opc\.tcp://([\d.]+):(\d+)/", text)
        assert http_m and opc_m, text
        self.host = http_m.group(1)
        self.http_port = int(http_m.group(2))
        self.opcua_port = int(opc_m.group(2))

    def log_text(self) -> str:
        self._log.flush()
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def log_size(self) -> int:
        self._log.flush()
        return self.log_path.stat().st_size

    def stop(self) -> int:
        """SIGTERM by pid, then SIGKILL after 30 s; the exit code."""
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()
        return self.proc.returncode


class Client:
    """One keep-alive HTTP connection with a session cookie (the operator's panel)."""

    def __init__(self, host: str, port: int, timeout_s: float = 10.0) -> None:
        self.conn = http.client.HTTPConnection(host, port, timeout=timeout_s)
        self.cookie = ""

    def call(self, method: str, path: str, body: object | None = None) -> tuple[int, Any]:
        headers = {"Content-Type": "application/json"}
        if self.cookie:
            headers["Cookie"] = self.cookie
        data = None if body is None else json.dumps(body).encode()
        self.conn.request(method, path, body=data, headers=headers)
        resp = self.conn.getresponse()
        raw = resp.read()
        cookie = resp.getheader("Set-Cookie")
        if cookie:
            self.cookie = cookie.split(";", 1)[0]
        return resp.status, json.loads(raw) if raw else None

    def close(self) -> None:
        self.conn.close()


NO_ANSWER = -1
"""``one_request``'s status for a request left without an answer for 10 s: a hang."""
REFUSED = 0
"""``one_request``'s status for a connection closed or reset before its answer: refused,
but not in words (beyond the cap and its lingering answers, ``supervisor.hmi.limits``)."""


def one_request(host: str, port: int, method: str, path: str, body: object = None) -> int:
    """A request on a new connection: its status, ``NO_ANSWER`` or ``REFUSED``."""
    try:
        c = Client(host, port)
        try:
            return c.call(method, path, body)[0]
        finally:
            c.close()
    except TimeoutError:
        return NO_ANSWER
    except (OSError, http.client.HTTPException, ValueError):
        return REFUSED


def devices_connected(c: Client) -> dict[str, bool]:
    out = {}
    for d in DEVICES:
        status, body = c.call("GET", f"/api/tags/{d}.connected")
        out[d] = status == 200 and body["value"] is True
    return out


def tag(c: Client, name: str) -> Any:
    status, body = c.call("GET", f"/api/tags/{name}")
    assert status == 200, (name, status, body)
    return body["value"]


def wait_ready(c: Client) -> None:
    deadline = time.monotonic() + WAIT_S
    while not all(devices_connected(c).values()) or tag(c, "estop.ok") is not True:
        if time.monotonic() > deadline:
            raise TimeoutError(f"devices not connected after {WAIT_S:g} s")
        time.sleep(0.2)


def start_test(c: Client) -> None:
    """Load and start the long recipe on ``CHANNEL``; wait until it runs."""
    status, body = c.call("PUT", f"/api/channels/{CHANNEL}/recipe", {"file": RECIPE})
    assert status == 200, body
    deadline = time.monotonic() + WAIT_S
    while True:
        status, body = c.call("POST", f"/api/channels/{CHANNEL}/commands/start", {})
        if status == 200 or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert status == 200, body
    while tag(c, f"{CHANNEL}.chain.state") != "Running":
        if time.monotonic() > deadline:
            raise TimeoutError(f"{CHANNEL} never Running")
        time.sleep(0.1)


@dataclass
class Flood:
    """Idle TCP connections opened to one port; how many were answered 503."""

    host: str
    port: int
    socks: list[socket.socket] = field(default_factory=list)
    refused_503: int = 0
    closed: int = 0

    def open(self, n: int) -> None:
        for _ in range(n):
            s = socket.socket()
            s.setblocking(False)
            with contextlib.suppress(BlockingIOError):
                s.connect((self.host, self.port))
            self.socks.append(s)

    def read_answers(self, wait_s: float) -> None:
        """Read what the server sent on the idle connections (503s, closes) for ``wait_s``."""
        sel = selectors.DefaultSelector()
        for s in self.socks:
            with contextlib.suppress(ValueError, OSError):
                sel.register(s, selectors.EVENT_READ, s)
        end = time.monotonic() + wait_s
        try:
            while time.monotonic() < end:
                for key, _ in sel.select(timeout=0.1):
                    conn: socket.socket = key.data
                    try:
                        data = conn.recv(4096)
                    except (BlockingIOError, InterruptedError):
                        continue
                    except OSError:
                        data = b""
                    if data.startswith(b"HTTP/1.1 503"):
                        self.refused_503 += 1
                    if not data or data.startswith(b"HTTP/1.1 503"):
                        self.closed += 1
                        sel.unregister(conn)
        finally:
            sel.close()

    def close(self) -> None:
        for s in self.socks:
            s.close()
        self.socks.clear()


@dataclass
class Figures:
    devices_disconnected: int = 0
    disconnected: list[str] = field(default_factory=list)
    polls: int = 0
    trips: int = 0
    faults: dict[str, str] = field(default_factory=dict)
    test_state: str = ""
    stalls: int = 0
    overruns: int = 0
    log_bytes: int = 0
    too_many_files_lines: int = 0
    session_valid: bool = False
    http_503: int = 0
    http_connections: int = 0
    http_accepted: int = 0
    opcua_connections: int = 0
    new_requests: Counter[int] = field(default_factory=Counter)
    recipe_load: int = 0
    """The status of a recipe load on ch1 during the flood (it opens a file)."""
    logins: int = 0
    logins_per_s: float = 0.0
    login_answers: Counter[int] = field(default_factory=Counter)


@contextlib.contextmanager
def bench_run(
    folder: Path,
    hmi: dict[str, Any] | None = None,
    recipe_folders: tuple[Path, ...] = (),
    recipes: dict[str, Any] | None = None,
) -> Iterator[Supervisor]:
    """A flood map in ``folder`` with its operator, its supervisor started (and stopped)."""
    io_map = flood_map(folder, hmi, recipe_folders, recipes)
    add_user(io_map, *OPERATOR, role="operator")
    sup = Supervisor(io_map, folder / "supervisor.log")
    try:
        yield sup
    finally:
        sup.stop()


def flood(
    sup: Supervisor,
    http_connections: int = 2000,
    opcua_connections: int = 200,
    login_rate: float = 100.0,
    login_s: float = 30.0,
) -> Figures:
    """The flood against ``sup`` (started), as the module says; the figures."""
    raise_own_limit(http_connections + opcua_connections + 256)
    fig = Figures(http_connections=http_connections, opcua_connections=opcua_connections)
    op = Client(sup.host, sup.http_port)
    status, body = op.call("POST", "/api/login", {"user": OPERATOR[0], "password": OPERATOR[1]})
    assert status == 200, body
    wait_ready(op)
    start_test(op)
    stalls0, overruns0 = tag(op, "scan.stalls"), tag(op, "scan.overruns")

    def poll() -> None:
        fig.polls += 1
        for d, ok in devices_connected(op).items():
            if not ok:
                fig.disconnected.append(d)

    web = Flood(sup.host, sup.http_port)
    opc = Flood(sup.host, sup.opcua_port)
    try:
        web.open(http_connections)
        opc.open(opcua_connections)
        web.read_answers(2.0)  # the 503s beyond the cap come at once
        poll()
        # The bench opens files during the flood (a recipe to load): descriptors were kept.
        fig.recipe_load = op.call("PUT", "/api/channels/ch1/recipe", {"file": RECIPE})[0]
        # A new request during the flood: answered (503 or served), never left hanging.
        fig.new_requests[one_request(sup.host, sup.http_port, "GET", "/api/session")] += 1
        # Wrong passwords at ``login_rate``, each on a connection of its own.
        t0 = time.monotonic()
        next_t = t0
        while time.monotonic() - t0 < login_s:
            answer = one_request(
                sup.host,
                sup.http_port,
                "POST",
                "/api/login",
                {"user": OPERATOR[0], "password": f"wrong-{fig.logins}"},
            )
            fig.login_answers[answer] += 1
            fig.logins += 1
            if fig.logins % max(1, int(login_rate)) == 0:
                poll()
            next_t += 1.0 / login_rate
            pause = next_t - time.monotonic()
            if pause > 0:
                time.sleep(pause)
        fig.logins_per_s = fig.logins / (time.monotonic() - t0)
        web.read_answers(0.5)
        poll()
    finally:
        web.close()
        opc.close()
    fig.http_503 = web.refused_503
    fig.devices_disconnected = len(set(fig.disconnected))
    for ch in ("ch0", "ch1", "ch2", "ch3", "ch4"):
        fault = tag(op, f"{ch}.fault")
        if fault:
            fig.faults[ch] = str(fault)
    fig.trips = len(fig.faults)
    fig.test_state = str(tag(op, f"{CHANNEL}.chain.state"))
    fig.stalls = int(tag(op, "scan.stalls")) - int(stalls0)
    fig.overruns = int(tag(op, "scan.overruns")) - int(overruns0)
    status, body = op.call("GET", "/api/session")
    fig.session_valid = status == 200 and body.get("user") == OPERATOR[0]
    op.close()
    fig.log_bytes = sup.log_size()
    fig.too_many_files_lines = sup.log_text().count("Too many open files")
    fig.http_accepted = fig.http_connections - fig.http_503
    return fig


def report(fig: Figures) -> list[str]:
    names = {NO_ANSWER: "no answer", REFUSED: "closed or reset"}
    answers = ", ".join(f"{names.get(k, k)}: {v}" for k, v in sorted(fig.login_answers.items()))
    return [
        f"flood under RLIMIT_NOFILE {SUPERVISOR_NOFILE}: {fig.http_connections} idle TCP"
        f" connections to HTTP, {fig.opcua_connections} to OPC UA, then {fig.logins} wrong"
        " logins",
        f"  devices disconnected:        {fig.devices_disconnected} ({fig.polls} polls of"
        f" {', '.join(DEVICES)}.connected)",
        f"  trips:                       {fig.trips} {fig.faults or ''}".rstrip(),
        f"  running test ({CHANNEL}):        {fig.test_state}",
        f"  scan stalls / overruns:      {fig.stalls} / {fig.overruns}",
        f"  log:                         {fig.log_bytes / MIB:.3f} MiB,"
        f" {fig.too_many_files_lines} 'Too many open files' lines",
        f"  operator session valid:      {'yes' if fig.session_valid else 'no'}",
        f"  HTTP 503 beyond the cap:     {fig.http_503} (not answered 503: {fig.http_accepted},"
        " held within the cap until the header timeout)",
        f"  a new request in the flood:  {dict(fig.new_requests)}",
        f"  a recipe loaded in the flood: HTTP {fig.recipe_load}",
        f"  logins/s achieved:           {fig.logins_per_s:.1f} (answers: {answers})",
    ]


def flood_benchmark(
    http_connections: int = 2000,
    opcua_connections: int = 200,
    login_rate: float = 100.0,
    login_s: float = 30.0,
) -> int:
    import tempfile

    from supervisor.bench.report import record

    with tempfile.TemporaryDirectory(prefix="bench-flood-") as tmp:
        with bench_run(Path(tmp)) as sup:
            fig = flood(sup, http_connections, opcua_connections, login_rate, login_s)
        for line in report(fig):
            _say(line)
    cmd = "supervisor bench flood"
    ref = f"{http_connections} HTTP + {opcua_connections} OPC UA idle connections, logins"
    record("flood: devices disconnected", fig.devices_disconnected, "", "== 0", ref, cmd)
    record("flood: trips", fig.trips, "", "== 0", ref, cmd)
    record("flood: scan stalls", fig.stalls, "", "== 0", ref, cmd)
    record("flood: log size", fig.log_bytes / MIB, "MiB", "< 1", ref, cmd)
    record("flood: operator session valid", float(fig.session_valid), "", "== 1", ref, cmd)
    record("flood: HTTP 503 beyond the cap", fig.http_503, "", "> 0", ref, cmd)
    record("flood: wrong logins per second", fig.logins_per_s, "/s", ">= 50", ref, cmd)
    ok = (
        fig.devices_disconnected == 0
        and fig.trips == 0
        and fig.stalls == 0
        and fig.log_bytes < MIB
        and fig.session_valid
        and fig.http_503 > 0
    )
    return 0 if ok else 1
