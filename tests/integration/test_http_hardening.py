"""Issue 27, finding 7, against the real aiohttp server on loopback:

(a) every answer — the page, the JSON API, aiohttp's own errors — carries a
    Content-Security-Policy (no other origin's script, no framing), X-Frame-Options and
    X-Content-Type-Options;
(b) every error answer of the API is JSON in the API's shape, aiohttp's 413 (a body over
    its limit), 404 (no such route) and 405 included;
(c) the simulated e-stop button needs an operator: a viewer's press is refused (403) and
    presses nothing;
(d) ``supervisor sim`` takes its control port from the map (default 0: a free port,
    printed), so two simulated benches run side by side.
"""

from __future__ import annotations

import asyncio
import io
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Mapping
from pathlib import Path

import aiohttp
import pytest
import yaml
from hmirig import Hmi, hmi_bench

from supervisor.config.models import HmiConfig
from supervisor.testing import free_tcp_port

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
async def hmi(tmp_path: Path) -> AsyncIterator[Hmi]:
    root = tmp_path / "hmi"
    (root / "js").mkdir(parents=True)
    (root / "index.html").write_text("<!doctype html><title>x</title>", encoding="utf-8")
    (root / "js" / "app.js").write_text("export {};\n", encoding="utf-8")
    async with hmi_bench(tmp_path, HmiConfig(login=True), root=root, estop=True) as h:
        yield h


def assert_secured(headers: Mapping[str, str], what: str) -> None:
    h = {k.lower(): v for k, v in headers.items()}
    csp = h.get("content-security-policy", "")
    for directive in (
        "default-src 'self'",
        "script-src 'self'",
        "connect-src 'self'",
        "frame-ancestors 'none'",
        "object-src 'none'",
        "base-uri 'self'",
    ):
        assert directive in csp, (what, csp)
    assert "unsafe-inline" not in csp and "unsafe-eval" not in csp, what
    assert h.get("x-frame-options") == "DENY", what
    assert h.get("x-content-type-options") == "nosniff", what


async def test_every_answer_carries_the_security_headers(hmi: Hmi) -> None:
    s = await hmi.client()
    for method, path in (
        ("GET", "/"),
        ("GET", "/static/js/app.js"),
        ("GET", "/static/nothing.js"),  # a 404 of the static files
        ("GET", "/api/tags"),
        ("GET", "/api/nothing"),  # aiohttp's own 404
        ("POST", "/api/channels/ch0/commands/hold"),  # 401 without a session
        ("PUT", "/api/sim/estop"),
    ):
        async with s.request(method, hmi.base + path) as resp:
            assert_secured(resp.headers, f"{method} {path} ({resp.status})")


async def test_aiohttp_s_own_errors_of_the_api_are_json(hmi: Hmi) -> None:
    s = await hmi.login("otto")
    big = '{"value": "' + "x" * (2 * 1024 * 1024) + '"}'
    async with s.put(
        hmi.base + "/api/tags/ch0.manual_current",
        data=io.BytesIO(big.encode()),
        headers={"Content-Type": "application/json"},
    ) as resp:
        assert resp.status == 413
        assert resp.content_type == "application/json"
        body = await resp.json()
    assert body["accepted"] is False and "Maximum request body size" in body["reason"], body
    assert body["kind"] == "request entity too large"
    async with s.get(hmi.base + "/api/no/such/route") as resp:
        assert resp.status == 404 and resp.content_type == "application/json"
        assert (await resp.json())["accepted"] is False
    async with s.delete(hmi.base + "/api/tags") as resp:
        assert resp.status == 405 and resp.content_type == "application/json"
        assert "GET" in resp.headers["Allow"]
        assert (await resp.json())["kind"] == "method not allowed"


async def test_a_viewer_cannot_press_the_simulated_estop(hmi: Hmi) -> None:
    assert hmi.bench.sim is not None
    viewer = await hmi.login("vera")
    status, body = await hmi.call(viewer, "PUT", "/api/sim/estop", {"pressed": True})
    assert status == 403, body
    assert body["accepted"] is False and "log in as an operator" in body["reason"]
    await hmi.scans(10)
    assert hmi.bench.db["estop.ok"].value is True  # nothing pressed
    operator = await hmi.login("otto")
    status, body = await hmi.call(operator, "PUT", "/api/sim/estop", {"pressed": True})
    assert status == 200 and body == {"pressed": True}
    await hmi.scans(10)
    assert hmi.bench.db["estop.ok"].value is False
    await hmi.call(operator, "PUT", "/api/sim/estop", {"pressed": False})


# --- (d) supervisor sim ----------------------------------------------------------------------
def seed002_map(tmp: Path, name: str) -> Path:
    """sim.yaml's seed 002 devices on free ports; no control port given (the default)."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    del data["devices"]["chadeche"]
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    for device in ("adam", "ea", "bms"):
        data["devices"][device]["port"] = free_tcp_port()
    data.pop("opcua", None)
    data.pop("modbus_server", None)  # nor Modbus (1502 may be taken)
    assert "control_port" not in (data.get("simulation") or {})
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


async def _estop_url(sim: subprocess.Popen[str]) -> str:
    assert sim.stdout is not None
    while True:
        line = await asyncio.to_thread(sim.stdout.readline)
        assert line, "supervisor sim exited"
        if line.startswith("e-stop button: PUT "):
            return line.split()[3]


async def test_two_simulated_benches_run_side_by_side(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    logs = [(tmp_path / f"{n}.log").open("w") for n in ("one", "two")]
    sims = [
        subprocess.Popen(  # noqa: ASYNC220 - Popen only starts it; reads go to threads
            [sys.executable, "-m", "supervisor.cli.main", "sim", str(seed002_map(tmp_path, n))],
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            env=env,
        )
        for n, log in zip(("one", "two"), logs, strict=True)
    ]
    try:
        urls = [await asyncio.wait_for(_estop_url(p), 60) for p in sims]
        assert urls[0] != urls[1]
        assert all(":8081/" not in u for u in urls)
        async with aiohttp.ClientSession() as s:
            for url in urls:
                async with s.get(url.replace("/estop", "/state")) as resp:
                    assert resp.status == 200
        assert all(p.poll() is None for p in sims)  # neither died of a taken port
    finally:
        for p in sims:
            p.terminate()
        for p in sims:
            await asyncio.to_thread(p.wait, 30)
            assert p.stdout is not None
            p.stdout.close()
        for log in logs:
            log.close()
