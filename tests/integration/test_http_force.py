"""Forcing over the HTTP API: ``PUT /api/tags/{name}/force {"value"}`` and ``DELETE
/api/tags/{name}/force``, the same command path as OPC UA's ForceTag (engineers only; never
a tag the e-stop or a channel's guard uses): 200, 403, 409, 400, 404 with the reason.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from commandrig import started_bench

from supervisor.app import Bench
from supervisor.commands import Command
from supervisor.hmi import HttpApi
from supervisor.tags import Access
from supervisor.testing import run_scans

JSON = {"Content-Type": "application/json"}
"""What every command declares, a body or not (supervisor.hmi.csrf)."""

pytestmark = pytest.mark.integration


class Engineers:
    """Everyone on the API is an engineer (the HTTP API has no users yet)."""

    def access_of(self, actor: str) -> Access:
        return Access.ENGINEER

    def refuses(self, command: Command) -> str:
        return ""


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[tuple[Bench, HttpApi, aiohttp.ClientSession]]:
    bench = await started_bench(tmp_path)
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, commands=bench.commands)
    await api.start()
    try:
        async with aiohttp.ClientSession() as session:
            yield bench, api, session
    finally:
        await api.stop()
        await bench.shutdown()


async def call(
    api: HttpApi, s: aiohttp.ClientSession, method: str, tag: str, body: Any = None
) -> tuple[int, Any]:
    kw: dict[str, Any] = {"headers": JSON} if body is None else {"json": body}
    async with s.request(method, f"{api.url}/tags/{tag}/force", **kw) as resp:
        return resp.status, await resp.json()


async def test_force_and_unforce_over_http(
    api: tuple[Bench, HttpApi, aiohttp.ClientSession],
) -> None:
    bench, http, s = api
    bench.commands.roles = Engineers()
    status, body = await call(http, s, "PUT", "room.temp", {"value": 31.5})
    assert status == 200, body
    assert body["tag"]["value"] == 31.5 and body["tag"]["reason"] == "forced"
    await run_scans(bench.engine, 5)
    assert bench.db["room.temp"].value == 31.5
    status, body = await call(http, s, "DELETE", "room.temp")
    assert status == 200 and "unforced" in body["reason"]
    assert not bench.db["room.temp"].forced


async def test_http_force_refusals(api: tuple[Bench, HttpApi, aiohttp.ClientSession]) -> None:
    bench, http, s = api
    status, body = await call(http, s, "PUT", "room.temp", {"value": 31.5})
    assert status == 403 and "needs engineer access" in body["reason"]  # the default: operator
    bench.commands.roles = Engineers()
    status, body = await call(http, s, "PUT", "estop.ok", {"value": True})
    assert status == 409 and "the e-stop reads it" in body["reason"]
    status, body = await call(http, s, "PUT", "room.temp", {"value": "warm"})
    assert status == 400 and "expected a number" in body["reason"]
    status, body = await call(http, s, "PUT", "no.tag", {"value": 1})
    assert status == 404
    status, body = await call(http, s, "PUT", "room.temp", {"v": 1})
    # Issue 28: a member other than "value" is refused by name (it was "body must be ...").
    assert status == 400 and body["reason"] == "room.temp: unknown member 'v' (expected: value)"
