"""A real InfluxDB server for the tests: InfluxDB 1.8.10 on loopback, its own data folder.

InfluxDB 1.8 serves the v2 write API and Flux that influxdb-client speaks (bucket
``db/rp``, token ``user:password``; docs/adr/0012). ``make test``
builds the binary once with ``go install`` into a cache shared by every clone
(``SUPERVISOR_INFLUXD`` names it); a missing binary is an error, not a skip, so CI never
passes without the server.

``InfluxServer`` starts and stops the process by its pid (an outage in a test is a
``stop()`` then a ``start()`` on the same port and data folder), and tears it down at
the end of the test; ``InfluxServer(root, auth=True)`` turns InfluxDB's authentication on
(an admin user, ``.token`` its ``user:password``), so that a wrong token gets a real 401.

``ScriptedInflux`` is not InfluxDB: a tiny HTTP server on loopback that answers the write
API as a test says (a 500, a 429 with ``Retry-After``, a 400 for some lines, no answer at
all), for the replies a real server cannot be made to give on demand.
"""

from __future__ import annotations

import http.server
import os
import shutil
import subprocess
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml

from supervisor.bench.processes import stop_with_parent
from supervisor.testing import free_tcp_port

__all__ = [
    "ADMIN_TOKEN",
    "DATABASE",
    "TOKEN",
    "InfluxServer",
    "Reply",
    "ScriptedInflux",
    "expected_points",
    "influxd_binary",
    "parse_line",
    "server_points",
    "sim_map",
]

DATABASE = "bench"
TOKEN = "user:password"  # any user:password while auth is off (InfluxDB 1.8)
ADMIN_TOKEN = "admin:secret"  # the admin user of a server started with auth=True
START_TIMEOUT_S = 30.0


def influxd_binary() -> Path:
    """The InfluxDB 1.8 server binary: ``$SUPERVISOR_INFLUXD``, else ``influxd`` on PATH."""
    named = os.environ.get("SUPERVISOR_INFLUXD")
    found = named or shutil.which("influxd")
    if not found or not Path(found).is_file():
        pytest.fail(
            "no InfluxDB server: run the tests with `make test` (it builds influxd 1.8.10"
            " once with `go install`) or set SUPERVISOR_INFLUXD to an influxd binary",
            pytrace=False,
        )
    return Path(found)


class InfluxServer:
    """One influxd on 127.0.0.1 with its data in ``root``."""

    def __init__(self, root: Path, *, auth: bool = False) -> None:
        self.binary = influxd_binary()
        self.auth = auth
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.port = free_tcp_port()
        self.rpc_port = free_tcp_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.bucket = f"{DATABASE}/autogen"
        self.token = ADMIN_TOKEN if auth else TOKEN
        self.org = "-"
        self._proc: subprocess.Popen[bytes] | None = None
        self.config = root / "influxdb.conf"
        self.config.write_text(self._config_text(), encoding="utf-8")
        self.log = root / "influxd.log"

    def _config_text(self) -> str:
        r = self.root
        return f"""reporting-disabled = true
bind-address = "127.0.0.1:{self.rpc_port}"
[meta]
  dir = "{r / "meta"}"
[data]
  dir = "{r / "data"}"
  wal-dir = "{r / "wal"}"
  query-log-enabled = false
[monitor]
  store-enabled = false
[http]
  bind-address = "127.0.0.1:{self.port}"
  flux-enabled = true
  log-enabled = false
  auth-enabled = {"true" if self.auth else "false"}
[logging]
  level = "warn"
"""

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self) -> None:
        if self.running:
            return
        with self.log.open("ab") as log:
            self._proc = subprocess.Popen(
                [str(self.binary), "-config", str(self.config)],
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                preexec_fn=stop_with_parent(),  # no influxd left behind by a killed run
            )
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self._ping():
            if self._proc.poll() is not None:
                raise RuntimeError(f"influxd exited with {self._proc.returncode}: {self.log}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"influxd did not answer in {START_TIMEOUT_S:g} s: {self.log}")
            time.sleep(0.05)
        if self.auth:
            # With auth on and no user yet, 1.8 takes this one statement unauthenticated;
            # after a restart the user exists (and the statement is refused: fine).
            user, password = ADMIN_TOKEN.split(":")
            statement = f"CREATE USER {user} WITH PASSWORD '{password}' WITH ALL PRIVILEGES"
            try:
                self._post_query({"q": statement}, authenticated=False)
            except urllib.error.HTTPError as exc:
                if exc.code not in (401, 403):
                    raise
        self.query(f"CREATE DATABASE {DATABASE}")

    def stop(self) -> None:
        """Stop the server (by its pid): SIGTERM, SIGKILL when it does not stop in 10 s."""
        proc, self._proc = self._proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

    def _ping(self) -> bool:
        try:
            with urllib.request.urlopen(f"{self.url}/ping", timeout=1) as r:
                return bool(r.status == 204)
        except (urllib.error.URLError, OSError):
            return False

    def query(self, influxql: str, database: str = DATABASE) -> dict[str, object]:
        """An InfluxQL statement (POST /query), the JSON answer."""
        return self._post_query({"q": influxql, "db": database})

    def _post_query(self, params: dict[str, str], authenticated: bool = True) -> dict[str, object]:
        import base64
        import json

        data = urllib.parse.urlencode(params).encode()
        req = urllib.request.Request(f"{self.url}/query", data=data, method="POST")
        if self.auth and authenticated:
            basic = base64.b64encode(ADMIN_TOKEN.encode()).decode()
            req.add_header("Authorization", f"Basic {basic}")
        with urllib.request.urlopen(req, timeout=30) as r:
            answer: dict[str, object] = json.loads(r.read())
        return answer

    def points(
        self, measurement: str, database: str = DATABASE
    ) -> dict[tuple[frozenset[tuple[str, str]], int], dict]:  # type: ignore[type-arg]
        """Every point of ``measurement``: (its tags, its ns timestamp) → its fields."""
        import base64
        import json

        q = {"q": f'SELECT * FROM "{measurement}" GROUP BY *', "db": database, "epoch": "ns"}
        req = urllib.request.Request(
            f"{self.url}/query", data=urllib.parse.urlencode(q).encode(), method="POST"
        )
        if self.auth:
            req.add_header(
                "Authorization", f"Basic {base64.b64encode(ADMIN_TOKEN.encode()).decode()}"
            )
        with urllib.request.urlopen(req, timeout=120) as resp:
            answer = json.loads(resp.read())
        out: dict[tuple[frozenset[tuple[str, str]], int], dict] = {}  # type: ignore[type-arg]
        for series in answer["results"][0].get("series", []):
            tags = frozenset((k, v) for k, v in series.get("tags", {}).items() if v != "")
            columns = series["columns"]
            for row in series["values"]:
                fields = {c: v for c, v in zip(columns[1:], row[1:], strict=True) if v is not None}
                out[(tags, int(row[0]))] = fields
        return out

    def count(self, measurement: str, field: str) -> int:
        """How many points of ``measurement`` have ``field`` (InfluxQL COUNT)."""
        answer = self.query(f'SELECT COUNT("{field}") FROM "{measurement}"')
        try:
            series = answer["results"][0]["series"]  # type: ignore[index]
        except (KeyError, IndexError, TypeError):
            return 0
        return int(series[0]["values"][0][1])


@pytest.fixture
def influx(tmp_path: Path) -> Iterator[InfluxServer]:
    """A running InfluxDB with an empty database ``bench``, stopped after the test."""
    server = InfluxServer(tmp_path / "influxdb")
    server.start()
    try:
        yield server
    finally:
        server.stop()


# --- the simulated bench publishing into a test server ----------------------------------------
Key = tuple[str, frozenset[tuple[str, str]], int]  # measurement, tags, ns


def sim_map(tmp: Path, influx: InfluxServer, **overrides: Any) -> Path:
    """io_maps/sim.yaml on free loopback ports, its state under ``tmp``, publishing into
    ``influx``."""
    data = yaml.safe_load(
        (Path(__file__).resolve().parents[1] / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    )
    for dev in data["devices"].values():
        if "port" in dev:
            dev["port"] = free_tcp_port()
    data["hmi"]["port"] = 0
    data["hmi"]["login"] = False  # its HTTP clients do not log in
    data.pop("modbus_server", None)  # 1502 may be taken (Modbus is not what it tests)
    data["state_dir"] = str(tmp / "var")
    token = tmp / "influx.token"
    token.write_text(influx.token + "\n", encoding="utf-8")
    data["influxdb"] = {
        "url": influx.url,
        "org": influx.org,
        "bucket": influx.bucket,
        "token_file": str(token),
        "flush_interval_s": 0.5,
        "retry_max_s": 1.0,
        **overrides,
    }
    path = tmp / "sim-influx.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def expected_points(lines: list[str]) -> dict[Key, dict[str, object]]:
    """What the server must hold: points by (measurement, tags, time), fields merged (a
    later write of the same field at the same instant overwrites, as on the server)."""
    out: dict[Key, dict[str, object]] = {}
    for line in lines:
        m, tags, fields, ts = parse_line(line)
        out.setdefault((m, frozenset(tags.items()), ts), {}).update(fields)
    return out


def server_points(influx: InfluxServer) -> dict[Key, dict[str, object]]:
    out: dict[Key, dict[str, object]] = {}
    for m in ("channel", "device", "diagnostics", "event"):
        for (tags, ts), fields in influx.points(m).items():
            out[(m, tags, ts)] = fields
    return out


# --- a scripted stand-in for the write API ----------------------------------------------------
@dataclass
class Reply:
    """What ``ScriptedInflux`` answers to one write."""

    status: int = 204
    body: str = ""
    headers: dict[str, str] = field(default_factory=dict)
    silent: bool = False  # read the request, never answer (until the server stops)
    hang_up: bool = False  # answer, then close the kept-alive connection without saying so


class ScriptedInflux:
    """An HTTP server on 127.0.0.1 answering ``POST /api/v2/write`` with ``answer(body)``
    (default: 204); keeps every request body and the lines it accepted, in order."""

    def __init__(self, answer: Callable[[bytes], Reply] | None = None, port: int = 0) -> None:
        self.answer = answer or (lambda body: Reply())
        self.requests: list[bytes] = []
        self.accepted: list[bytes] = []  # lines of the requests answered with a 2xx
        self._release = threading.Event()
        rig = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def do_POST(self) -> None:
                n = int(self.headers.get("Content-Length", "0"))
                body = self.rfile.read(n)
                rig.requests.append(body)
                reply = rig.answer(body)
                if reply.silent:
                    rig._release.wait(60)
                    self.close_connection = True
                    return
                if 200 <= reply.status < 300:
                    rig.accepted.extend(body.split(b"\n"))
                data = reply.body.encode()
                self.send_response(reply.status)
                for k, v in reply.headers.items():
                    self.send_header(k, v)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)
                if reply.hang_up:
                    self.close_connection = True

            def log_message(self, format: str, *args: object) -> None:
                pass

        self._server = http.server.ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self._server.daemon_threads = True
        self.port = int(self._server.server_address[1])
        self.url = f"http://127.0.0.1:{self.port}"
        self._thread = threading.Thread(
            target=self._server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        self._release.set()  # silent handlers end
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(10)


@pytest.fixture
def influx_auth(tmp_path: Path) -> Iterator[InfluxServer]:
    """A running InfluxDB with authentication on (``.token``: its admin user)."""
    server = InfluxServer(tmp_path / "influxdb-auth", auth=True)
    server.start()
    try:
        yield server
    finally:
        server.stop()


# --- a small parser of the line protocol (the spec, not the encoder under test) -------------
def _split_unescaped(text: str, sep: str) -> list[str]:
    """Split at ``sep`` where it is not preceded by a backslash escape."""
    out, cur, k = [], [], 0
    while k < len(text):
        c = text[k]
        if c == "\\" and k + 1 < len(text):
            cur.append(text[k : k + 2])
            k += 2
            continue
        if c == sep:
            out.append("".join(cur))
            cur = []
        else:
            cur.append(c)
        k += 1
    out.append("".join(cur))
    return out


def _unescape_key(text: str) -> str:
    for c in (",", "=", " "):
        text = text.replace("\\" + c, c)
    return text


def _fields(text: str) -> list[tuple[str, str]]:
    """(raw key, raw value) pairs. A key ends at its first unescaped ``=``; quotes matter
    only in values (as InfluxDB's scanner has it); a field ends at a comma outside them."""
    out: list[tuple[str, str]] = []
    k, n = 0, len(text)
    while k < n:
        key = []
        while text[k] != "=":
            step = 2 if text[k] == "\\" and k + 1 < n else 1
            key.append(text[k : k + step])
            k += step
        k += 1  # the '='
        start = k
        if k < n and text[k] == '"':
            k += 1
            while text[k] != '"':
                k += 2 if text[k] == "\\" else 1
            k += 1
        else:
            while k < n and text[k] != ",":
                k += 1
        out.append(("".join(key), text[start:k]))
        assert k == n or text[k] == ",", f"junk after a field value at {k}: {text!r}"
        k += 1
    return out


def _unescape_string(text: str) -> str:
    out, k = [], 0
    while k < len(text):
        if text[k] == "\\" and k + 1 < len(text) and text[k + 1] in '"\\':
            out.append(text[k + 1])
            k += 2
        else:
            out.append(text[k])
            k += 1
    return "".join(out)


def parse_line(line: str) -> tuple[str, dict[str, str], dict[str, object], int]:
    """(measurement, tags, fields, timestamp) of one line."""
    assert "\n" not in line
    head_fields, _, ts = line.rpartition(" ")
    # The head ends at the first unescaped space; field strings may hold spaces.
    parts = _split_unescaped(head_fields, " ")
    head, fields_text = parts[0], " ".join(parts[1:])
    series = _split_unescaped(head, ",")
    measurement = _unescape_key(series[0])
    tags = {}
    for item in series[1:]:
        k, v = _split_unescaped(item, "=")
        tags[_unescape_key(k)] = _unescape_key(v)
    fields: dict[str, object] = {}
    for k, v in _fields(fields_text):
        key = _unescape_key(k)
        if v.startswith('"'):
            assert v.endswith('"') and len(v) >= 2
            fields[key] = _unescape_string(v[1:-1])
        elif v in ("true", "false"):
            fields[key] = v == "true"
        else:
            assert not v.endswith("i"), f"an integer field: {k}={v}"
            fields[key] = float(v)
    return measurement, tags, fields, int(ts)
