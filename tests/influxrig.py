"""A real InfluxDB server for the tests: InfluxDB 1.8.10 on loopback, its own data folder.

InfluxDB 1.8 serves the v2 write API and Flux that influxdb-client speaks (bucket
``db/rp``, token ``user:password``; ``../shared/reference/ecosystem.md``). ``make test``
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

import pytest

from supervisor.testing import free_tcp_port

__all__ = [
    "ADMIN_TOKEN",
    "DATABASE",
    "TOKEN",
    "InfluxServer",
    "Reply",
    "ScriptedInflux",
    "influxd_binary",
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

    def query(self, influxql: str) -> dict[str, object]:
        """An InfluxQL statement (POST /query), the JSON answer."""
        return self._post_query({"q": influxql, "db": DATABASE})

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


# --- a scripted stand-in for the write API ----------------------------------------------------
@dataclass
class Reply:
    """What ``ScriptedInflux`` answers to one write."""

    status: int = 204
    body: str = ""
    headers: dict[str, str] = field(default_factory=dict)
    silent: bool = False  # read the request, never answer (until the server stops)


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
