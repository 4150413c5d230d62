"""``supervisor run`` with ``hmi.login: true`` (as io_maps/sim.yaml): the operator logs in
with a user added by ``supervisor opcua add-user``, commands as ``hmi:<user>``, and an
anonymous command is refused. A real process on loopback (wall time: the process runs on
the real clock; waits are bounded, nothing asserts a duration)."""

from __future__ import annotations

import http.cookiejar
import io
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
from commandrig import chadeche_map

from supervisor.cli.main import main

pytestmark = pytest.mark.integration


def _call(opener: urllib.request.OpenerDirector, method: str, url: str, body: Any = None) -> Any:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        url, data=data, method=method, headers={"Content-Type": "application/json"}
    )
    try:
        with opener.open(req, timeout=5) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        with exc:
            return exc.code, json.loads(exc.read())


def test_supervisor_run_with_login_takes_commands_from_logged_in_operators(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    io_map = chadeche_map(tmp_path)
    text = Path(io_map).read_text(encoding="utf-8").replace("login: false", "login: true")
    Path(io_map).write_text(text, encoding="utf-8")
    # The operator, as `make run` adds its demo users.
    monkeypatch.setattr("sys.stdin", io.StringIO("otto-pw\n"))
    add = ["opcua", "add-user", "otto", "--role", "operator", "--password-stdin"]
    code = main([*add, "--io-map", io_map])
    assert code == 0
    proc = subprocess.Popen(
        [sys.executable, "-m", "supervisor.cli.main", "run", io_map, "--http-port", "0"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    try:
        assert proc.stdout is not None
        url = screens = None
        for line in proc.stdout:
            m = re.search(r"HTTP API listening on (http://127\.0\.0\.1:\d+)/api", line)
            url = m.group(1) if m else url
            if line.startswith("operator screens:"):
                screens = line
            if line.startswith("Ctrl-C"):
                break
        assert url, "the bench never said where it listens"
        assert screens is not None and "login: the users of" in screens
        anonymous = urllib.request.build_opener()
        status, body = _call(anonymous, "POST", f"{url}/api/channels/ch0/commands/reset", {})
        assert status == 401 and body["accepted"] is False
        jar = http.cookiejar.CookieJar()
        otto = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(jar))
        status, body = _call(
            otto, "POST", f"{url}/api/login", {"user": "otto", "password": "otto-pw"}
        )
        assert (status, body["role"]) == (200, "operator")
        status, body = _call(
            otto, "POST", f"{url}/api/channels/ch0/commands/mode", {"value": "manual"}
        )
        assert status == 200, body
        deadline = time.monotonic() + 20  # a bound for a slow machine, not a timing claim
        mode = None
        while time.monotonic() < deadline:
            _, mode = _call(otto, "GET", f"{url}/api/tags/ch0.mode")
            if mode["value"] == "manual":
                break
            time.sleep(0.1)
        assert mode is not None and mode["value"] == "manual"
        # Saving a recipe needs an engineer's session, as in the HMI's roles.
        recipe = {"text": (Path.cwd() / "recipes" / "nimh-ds2710.yaml").read_text("utf-8")}
        status, body = _call(anonymous, "PUT", f"{url}/api/recipes/otto-made", recipe)
        assert status == 401, body
        status, body = _call(otto, "PUT", f"{url}/api/recipes/otto-made", recipe)
        assert status == 403 and "operator may not save recipes" in body["reason"], body
        assert not list(tmp_path.rglob("otto-made.yaml"))
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        assert "stopped: all outputs safe" in out
        assert "Traceback" not in err
        assert "hmi: otto logged in (operator)" in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
