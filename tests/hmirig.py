"""A bench with its operator screens for HMI tests: commandrig's bench (four Chadèche
channels, the ADAM e-stop sense, in process, virtual clock), the HTTP API on a free
loopback port, demo users in the bench's users file, and clients that keep cookies."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp
from commandrig import started_bench

from supervisor.app import Bench
from supervisor.app.hmi import build_screens
from supervisor.config.models import HmiConfig
from supervisor.config.users import add_user
from supervisor.hmi import HttpApi
from supervisor.hmi.screens import Screens
from supervisor.publish.opcua import OpcUaSettings
from supervisor.testing import run_scans

JSON = {"Content-Type": "application/json"}
"""What every command declares, a body or not (supervisor.hmi.csrf)."""

USERS = {"vera": "viewer", "otto": "operator", "erin": "engineer"}
"""Name → role; each password is `password(name)`."""


def password(user: str) -> str:
    return user[::-1] + "-pw"


class HttpCalls:
    """Cookie-keeping HTTP clients of one HMI (``base``), each a browser's session: a
    subclass gives ``base`` and ``sessions``."""

    base: str
    sessions: list[aiohttp.ClientSession]

    async def client(self) -> aiohttp.ClientSession:
        # unsafe=True: aiohttp keeps no cookie of an IP host otherwise (browsers do).
        s = aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True))
        self.sessions.append(s)
        return s

    async def call(
        self, s: aiohttp.ClientSession, method: str, path: str, body: Any = None
    ) -> tuple[int, Any]:
        kw: dict[str, Any] = {"headers": JSON} if body is None else {"json": body}
        async with s.request(method, self.base + path, **kw) as resp:
            return resp.status, await resp.json()


@dataclass
class Hmi(HttpCalls):
    bench: Bench
    api: HttpApi
    screens: Screens
    sessions: list[aiohttp.ClientSession] = field(default_factory=list)

    @property
    def base(self) -> str:  # type: ignore[override]  # the API's port, known once started
        return f"http://127.0.0.1:{self.api.port}"

    async def login(self, user: str) -> aiohttp.ClientSession:
        s = await self.client()
        status, body = await self.call(
            s, "POST", "/api/login", {"user": user, "password": password(user)}
        )
        assert status == 200, body
        return s

    async def scans(self, n: int) -> None:
        await run_scans(self.bench.engine, n)
        await asyncio.sleep(0)  # the live publisher's task runs between two scans


@asynccontextmanager
async def hmi_bench(
    tmp: Path,
    cfg: HmiConfig | None = None,
    root: Path | None = None,
    queue_size: int = 256,
    estop: bool = False,
) -> AsyncIterator[Hmi]:
    """``estop``: with the simulated e-stop button (``PUT /api/sim/estop``)."""
    bench = await started_bench(tmp)
    users_file = OpcUaSettings.of(bench.cfg).users_file
    for user, role in USERS.items():
        add_user(users_file, user, role, password(user))
    cfg = cfg or HmiConfig(login=True)
    press = bench.sim.press_estop if estop and bench.sim is not None else None
    api = HttpApi(
        bench.db,
        bench.clock,
        "127.0.0.1",
        0,
        commands=bench.commands,
        estop=press,
        allowed_origins=cfg.allowed_origins,
    )
    screens = build_screens(bench, api, root=root or tmp / "no-hmi", queue_size=queue_size, cfg=cfg)
    await api.start()
    hmi = Hmi(bench, api, screens)
    try:
        yield hmi
    finally:
        for s in hmi.sessions:
            await s.close()
        await api.stop()
        await bench.shutdown()
