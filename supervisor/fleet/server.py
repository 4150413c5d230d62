"""The fleet's HTTP side: ``GET /api/fleet`` and the fleet page, behind the HMI's login
(docs/fleet.md).

Everything about who may look is the HMI's own code (``supervisor.hmi.auth``): the same
users file, scrypt check, throttle, sessions and cookie, the same cross-site refusals
(``supervisor.hmi.csrf``), headers and JSON errors (``supervisor.hmi.server``). Without a
users file the fleet, like a bench with ``hmi.login`` off, answers anyone: it then listens
on loopback only (the command line refuses another address).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path

from aiohttp import web

from supervisor.config.models import HMI_SESSION_TIMEOUT_S
from supervisor.config.users import UserStore
from supervisor.core.logins import LoginThrottle
from supervisor.fleet.state import Fleet
from supervisor.fleet.view import fleet_json
from supervisor.hmi.auth import HmiAccess, Sessions
from supervisor.hmi.csrf import RequestOrigins
from supervisor.hmi.screens import DEFAULT_ROOT
from supervisor.hmi.server import SECURITY_HEADERS, json_dumps, json_errors
from supervisor.hmi.static import StaticFiles

__all__ = ["FLEET_PAGE", "FleetServer"]

FLEET_PAGE = "fleet.html"


async def _security_headers(request: web.Request, response: web.StreamResponse) -> None:
    for name, value in SECURITY_HEADERS.items():
        response.headers.setdefault(name, value)


class FleetServer:
    def __init__(
        self,
        fleet: Fleet,
        connected: Callable[[], bool],
        *,
        users: UserStore | None,
        host: str = "127.0.0.1",
        port: int = 8090,
        root: Path = DEFAULT_ROOT,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        self.fleet = fleet
        self.connected = connected
        self.host, self.port = host, port
        app = web.Application()
        RequestOrigins().install(app)
        app.middlewares.insert(0, json_errors)
        app.on_response_prepare.append(_security_headers)
        # The HMI's rules: a session per login, expiring after the HMI's default idle time;
        # no anonymous viewers (a fleet shows every bench of the lab).
        sessions = Sessions(HMI_SESSION_TIMEOUT_S, now)
        login = users is not None
        self.access = HmiAccess(users, sessions, login, False, LoginThrottle(now))
        self.access.install(app)
        app.add_routes([web.get("/api/fleet", self._fleet)])
        StaticFiles(root, FLEET_PAGE).install(app)
        self.app = app
        self._runner: web.AppRunner | None = None

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    async def _fleet(self, request: web.Request) -> web.Response:
        body = fleet_json(self.fleet, connected=self.connected(), now_ms=round(time.time() * 1000))
        return web.json_response(body, dumps=json_dumps, headers={"Cache-Control": "no-store"})

    async def start(self) -> None:
        self._runner = web.AppRunner(self.app, access_log=None)
        await self._runner.setup()
        # A socket of our own: port 0 (the tests) is the port the system chose.
        sock = socket.create_server((self.host, self.port), reuse_port=False)
        self.port = sock.getsockname()[1]
        await web.SockSite(self._runner, sock).start()

    async def stop(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
