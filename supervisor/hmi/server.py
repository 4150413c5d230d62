"""A small JSON API: read tags, write operator tags. Listens on loopback by default.

Writes go through ``TagDB.write`` so access level, type and range are checked in one
place; the scan picks the new value up at its next start.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from aiohttp import web

from supervisor.core.clock import Clock
from supervisor.core.errors import ConfigError, ConfigErrors, OperatorError
from supervisor.tags import Access, Tag, TagDB

log = logging.getLogger(__name__)


def tag_json(tag: Tag, clock: Clock) -> dict[str, Any]:
    s = tag.spec
    return {
        "name": tag.name,
        "value": tag.value,
        "unit": s.unit,
        "quality": tag.quality.name,
        "reason": str(tag.reason),
        "forced": tag.forced,
        "access": s.access.name.lower(),
        "source_time": clock.to_wall(tag.source_t) if tag.source_t else None,
        "version": tag.version,
    }


class HttpApi:
    def __init__(
        self,
        db: TagDB,
        clock: Clock,
        host: str = "127.0.0.1",
        port: int = 8080,
        estop: Callable[[bool], None] | None = None,
        load_recipe: Callable[[str, str, dict[str, str]], str] | None = None,
        sim_state: Callable[[], dict[str, Any]] | None = None,
    ):
        self.db = db
        self._estop = estop
        self._sim_state = sim_state
        self._load_recipe = load_recipe
        self.clock = clock
        self.host = host
        self.port = port
        self._runner: web.AppRunner | None = None
        app = web.Application()
        app.add_routes(
            [
                web.get("/api/tags", self._list),
                web.get("/api/tags/{name}", self._get),
                web.put("/api/tags/{name}", self._put),
            ]
        )
        if load_recipe is not None:
            app.add_routes([web.put("/api/channels/{channel}/recipe", self._recipe)])
        if estop is not None:
            # Simulation only: the e-stop button of the simulated bench.
            app.add_routes([web.put("/api/sim/estop", self._sim_estop)])
        if sim_state is not None:
            # Simulation only: what the simulated plant does (contactor, supply), so that a
            # test or a person can see the hardware's side, not only the supervisor's.
            app.add_routes([web.get("/api/sim/state", self._sim_state_get)])
        self.app = app

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/api"

    async def start(self) -> None:
        self._runner = web.AppRunner(self.app, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port)
        await site.start()
        server = site._server
        if server is not None and self.port == 0:
            sockets = getattr(server, "sockets", None) or []
            if sockets:
                self.port = sockets[0].getsockname()[1]

    async def stop(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def _list(self, request: web.Request) -> web.Response:
        prefix = request.query.get("prefix", "")
        tags = [tag_json(t, self.clock) for t in self.db if t.name.startswith(prefix)]
        return web.json_response(tags)

    async def _get(self, request: web.Request) -> web.Response:
        tag = self.db.get(request.match_info["name"])
        if tag is None:
            return web.json_response({"error": "unknown tag"}, status=404)
        return web.json_response(tag_json(tag, self.clock))

    async def _recipe(self, request: web.Request) -> web.Response:
        """Load a recipe on a channel: ``{"file": "recipes/x.yaml", "parameters": {...}}``."""
        channel = request.match_info["channel"]
        try:
            body = await request.json()
        except ValueError:
            body = None
        if not isinstance(body, dict) or not isinstance(body.get("file"), str):
            return web.json_response({"error": 'body must be {"file": "...", ...}'}, status=400)
        params = body.get("parameters") or {}
        if not isinstance(params, dict):
            return web.json_response({"error": "parameters must be a mapping"}, status=400)
        assert self._load_recipe is not None
        try:
            test_id = self._load_recipe(
                channel, body["file"], {k: str(v) for k, v in params.items()}
            )
        except ConfigErrors as exc:
            return web.json_response(
                {"error": "recipe refused", "details": [e.location_message() for e in exc.errors]},
                status=422,
            )
        except (ConfigError, OperatorError) as exc:
            return web.json_response({"error": str(exc)}, status=409)
        log.info("http: recipe %s loaded on %s (test %s)", body["file"], channel, test_id)
        return web.json_response({"channel": channel, "test_id": test_id})

    async def _sim_estop(self, request: web.Request) -> web.Response:
        try:
            body = await request.json()
        except ValueError:
            body = None
        if not isinstance(body, dict) or not isinstance(body.get("pressed"), bool):
            return web.json_response({"error": 'body must be {"pressed": true|false}'}, status=400)
        assert self._estop is not None
        self._estop(body["pressed"])
        log.warning("simulation: e-stop %s", "PRESSED" if body["pressed"] else "released")
        return web.json_response({"pressed": body["pressed"]})

    async def _sim_state_get(self, request: web.Request) -> web.Response:
        assert self._sim_state is not None
        return web.json_response(self._sim_state())

    async def _put(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in self.db:
            return web.json_response({"error": f"unknown tag {name!r}"}, status=404)
        try:
            body = await request.json()
        except ValueError:
            return web.json_response({"error": 'body must be JSON {"value": ...}'}, status=400)
        if not isinstance(body, dict) or "value" not in body:
            return web.json_response({"error": 'body must be JSON {"value": ...}'}, status=400)
        try:
            tag = self.db.write(name, body["value"], Access.OPERATOR)
        except OperatorError as exc:
            return web.json_response({"error": str(exc)}, status=403)
        log.info("http: %s := %r", name, tag.value)
        return web.json_response(tag_json(tag, self.clock))
