"""A real InfluxDB server for the tests: InfluxDB 1.8.10 on loopback, its own data folder.

InfluxDB 1.8 serves the v2 write API and Flux that influxdb-client speaks (bucket
``db/rp``, token ``user:password``; ``../shared/reference/ecosystem.md``). ``make test``
builds the binary once with ``go install`` into a cache shared by every clone
(``SUPERVISOR_INFLUXD`` names it); a missing binary is an error, not a skip, so CI never
passes without the server.

``InfluxServer`` starts and stops the process by its pid (an outage in a test is a
``stop()`` then a ``start()`` on the same port and data folder), and tears it down at
the end of the test.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from supervisor.testing import free_tcp_port

__all__ = ["DATABASE", "TOKEN", "InfluxServer", "influxd_binary"]

DATABASE = "bench"
TOKEN = "user:password"  # any user:password while auth is off (InfluxDB 1.8)
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

    def __init__(self, root: Path) -> None:
        self.binary = influxd_binary()
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.port = free_tcp_port()
        self.rpc_port = free_tcp_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.bucket = f"{DATABASE}/autogen"
        self.token = TOKEN
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
        import json

        data = urllib.parse.urlencode({"q": influxql, "db": DATABASE}).encode()
        req = urllib.request.Request(f"{self.url}/query", data=data, method="POST")
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
