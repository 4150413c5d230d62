"""``supervisor run --recipe ch0=FILE --start`` as a process: the test starts through the
command path (recorded with the actor "command line"), and the HTTP API commands it.

Wall time: a real process on the real clock (bounded waits, never a timing claim).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from commandrig import DISCHARGE, chadeche_map, recipe

pytestmark = pytest.mark.integration


def _call(method: str, url: str, body: object | None = None) -> tuple[int, Any]:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        url, data=data, method=method, headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(req, timeout=5) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        with exc:
            return exc.code, json.loads(exc.read())


def test_a_recipe_started_from_the_command_line_runs_and_takes_http_commands(
    tmp_path: Path,
) -> None:
    io_map = chadeche_map(tmp_path)
    file = recipe(tmp_path, DISCHARGE)
    cli = [sys.executable, "-m", "supervisor.cli.main", "run", io_map, "--http-port", "0"]
    proc = subprocess.Popen(
        [*cli, "--recipe", f"ch0={file}", "--start"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    try:
        assert proc.stdout is not None
        url = None
        for line in proc.stdout:
            m = re.search(r"HTTP API listening on (http://127\.0\.0\.1:\d+/api)", line)
            url = m.group(1) if m else url
            if line.startswith("Ctrl-C"):
                break
        assert url, "the bench never said where it listens"
        deadline = time.monotonic() + 20  # an upper bound for a slow machine
        state = None
        while time.monotonic() < deadline:
            _, state = _call("GET", f"{url}/tags/ch0.chain.state")
            if state["value"] == "Running":
                break
            time.sleep(0.1)
        assert state is not None and state["value"] == "Running"
        status, body = _call("PUT", f"{url}/tags/ch0.enable", {"value": True})
        assert status == 409 and body["reason"] == (
            "channel ch0 is in auto (step chain): switch to manual first"
        )
        status, body = _call("POST", f"{url}/channels/ch0/commands/hold", {})
        assert status == 200 and body["state"] == "Holding"
        status, body = _call("GET", f"{url}/alarms")
        assert status == 200 and body["active"] == []
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        assert "stopped: all outputs safe" in out
        # Loaded before anything is served, started once the channel's inputs read GOOD.
        assert f"load {file} by command line: accepted" in err
        assert "command on ch0: start by command line: accepted" in err
        assert "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
