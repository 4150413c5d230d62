"""A small JSON API: read tags, give commands, see alarms. Listens on loopback by default.

Every write and command goes through the bench's one command path (``supervisor.commands``):
it is checked (role, state, interlocks), recorded with its actor, and answered
``{"accepted": bool, "reason": str, ...}`` with the status of its result — 200 accepted,
400 a wrong argument type or value, 403 a read-only tag or a command the actor may not
give, 404 an unknown tag, channel, alarm or recipe, 409 refused in this state or by an
interlock, 422 a recipe refused (``details``: file:line:col), 503 a recipe that took longer
than ``RECIPE_COMPILE_TIMEOUT_S`` to read and compile (README "Input limits"; it is
compiled in a worker thread, never on the scan's event loop). A write of a channel's
``command``, ``mode``, ``manual_current``, ``enable`` or ``ack`` tag is that command. The
scan takes the effect at its next start.

Every answer is JSON (RFC 8259), which has no NaN nor Infinity: a browser's ``JSON.parse``
refuses a whole snapshot for one of them. A request's ``NaN``/``Infinity`` is refused as
not JSON; a non-finite value in a tag (a device can still produce one) is sent as ``null``
with quality ``BAD`` (:func:`tag_json`), and any other non-finite number as ``null``
(:func:`json_dumps`).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from typing import Any, Final

from aiohttp import web

from supervisor.commands import Command, CommandPath, Result, ResultKind, Verb
from supervisor.core.clock import Clock
from supervisor.core.quality import Quality
from supervisor.hmi.history_api import HistoryQuery, add_history_routes
from supervisor.hmi.recipes_api import RecipesConfig, add_recipe_routes
from supervisor.hmi.tests_api import TestsConfig, add_test_routes
from supervisor.safety import Alarm, AlarmEvent
from supervisor.tags import Tag, TagDB

log = logging.getLogger(__name__)


ACTOR_KEY: Final = web.RequestKey[str]("actor")
"""Where the login middleware (``supervisor.hmi.auth``) leaves a request's actor."""

NOT_FINITE_REASON = "not a finite number"
"""The reason sent with a tag whose value is NaN or ±inf (sent as null, quality BAD)."""


def tag_json(tag: Tag, clock: Clock) -> dict[str, Any]:
    s = tag.spec
    value, quality, reason = tag.value, tag.quality.name, str(tag.reason)
    if isinstance(value, float) and not math.isfinite(value):
        value, quality, reason = None, Quality.BAD.name, f"{NOT_FINITE_REASON} ({value})"
    return {
        "name": tag.name,
        "value": value,
        "unit": s.unit,
        "quality": quality,
        "reason": reason,
        "forced": tag.forced,
        "access": s.access.name.lower(),
        "source_time": clock.to_wall(tag.source_t) if tag.source_t else None,
        "version": tag.version,
    }


def alarm_json(alarm: Alarm, clock: Clock) -> dict[str, Any]:
    now = clock.now()
    until = alarm.shelved_until if alarm.shelved(now) else None
    return {
        "id": alarm.id,
        "group": alarm.group,
        "state": alarm.state.value,
        "severity": int(alarm.severity),
        "severity_name": alarm.severity.name.lower(),
        "message": alarm.message,
        "latched": alarm.latched,
        "tripped": alarm.tripped,
        "first_out": alarm.first_out,
        "action": alarm.action,
        "activated_time": (
            clock.to_wall(alarm.activated_t) if alarm.activated_t is not None else None
        ),
        "acked_by": alarm.acked_by,
        "shelved": alarm.shelved(now),
        "shelved_until": clock.to_wall(until) if until is not None else None,
    }


def alarm_event_json(ev: AlarmEvent) -> dict[str, Any]:
    return {
        "time": ev.wall,
        "alarm": ev.alarm_id,
        "group": ev.group,
        "transition": ev.transition.value,
        "state": ev.state.value,
        "severity": int(ev.severity),
        "message": ev.message,
        "actor": ev.actor,
    }


ALARM_ACTIONS = ("acknowledge", "reset", "shelve", "unshelve")


def _finite_only(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None (JSON has no NaN/Infinity)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_only(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite_only(v) for v in obj]
    return obj


def json_dumps(obj: Any) -> str:
    """JSON text that any JSON parser reads: NaN and ±inf become null (never emitted)."""
    try:
        return json.dumps(obj, allow_nan=False)
    except ValueError:  # a non-finite float somewhere: the rare case pays for the walk
        return json.dumps(_finite_only(obj), allow_nan=False)


def _no_constant(name: str) -> Any:
    # json.loads takes NaN, Infinity and -Infinity, which RFC 8259 does not.
    raise ValueError(f"{name} is not JSON")


def _json_loads(text: str) -> Any:
    return json.loads(text, parse_constant=_no_constant)


def _json(data: Any, status: int = 200) -> web.Response:
    return web.json_response(data, status=status, dumps=json_dumps)


class HttpApi:
    def __init__(
        self,
        db: TagDB,
        clock: Clock,
        host: str = "127.0.0.1",
        port: int = 8080,
        estop: Callable[[bool], None] | None = None,
        commands: CommandPath | None = None,
        sim_state: Callable[[], dict[str, Any]] | None = None,
        history: HistoryQuery | None = None,
        recipes: RecipesConfig | None = None,
        tests: TestsConfig | None = None,
    ):
        self.db = db
        self._estop = estop
        self._sim_state = sim_state
        # Without a bench (``supervisor sim``'s control API) writes still take the path.
        self.commands = commands if commands is not None else CommandPath(db, clock)
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
                web.put("/api/channels/{channel}/recipe", self._recipe),
                web.post("/api/channels/{channel}/commands/{verb}", self._channel_command),
                web.get("/api/alarms", self._alarms),
                web.post("/api/alarms/{alarm}/{action}", self._alarm_command),
            ]
        )
        if history is not None:  # GET /api/history, /api/events (hmi/history_api.py)
            add_history_routes(app, history, db, clock, self.commands.runners)
        if recipes is not None:  # /api/recipes… (hmi/recipes_api.py)
            add_recipe_routes(app, recipes)
        if tests is not None:  # /api/tests… (hmi/tests_api.py)
            add_test_routes(app, tests, clock)
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
        return _json(tags)

    async def _get(self, request: web.Request) -> web.Response:
        tag = self.db.get(request.match_info["name"])
        if tag is None:
            return _json({"error": "unknown tag"}, status=404)
        return _json(tag_json(tag, self.clock))

    # --- commands -------------------------------------------------------------------------
    @staticmethod
    def actor(request: web.Request) -> str:
        """Who sends the command: ``hmi:<user>`` as the login middleware found it
        (``supervisor.hmi.auth``); without logins everyone on the (loopback) API is the
        operator."""
        actor: str = request.get(ACTOR_KEY, "operator")
        return actor

    async def _answer(self, command: Command) -> web.Response:
        # A recipe to load is compiled in a worker thread, never on the scan's loop.
        result = await self.commands.execute_async(command)
        return self._respond(result)

    def _respond(self, result: Result) -> web.Response:
        body = result.as_json()
        if result.tag is not None and result.tag in self.db:
            body["tag"] = tag_json(self.db[result.tag], self.clock)
        return _json(body, status=result.http_status)

    def _bad(self, reason: str, kind: ResultKind = ResultKind.BAD_ARGUMENT) -> web.Response:
        """A request that is not a command yet (no JSON, an unknown route verb)."""
        return self._respond(Result.refused(kind, reason))

    async def _body(self, request: web.Request, empty_ok: bool) -> dict[str, Any] | None:
        """The JSON object of the body ({} for an empty body when ``empty_ok``), or None."""
        if empty_ok and not await request.read():
            return {}
        try:
            body = await request.json(loads=_json_loads)
        except ValueError:
            return None
        return body if isinstance(body, dict) else None

    async def _recipe(self, request: web.Request) -> web.Response:
        """Load a recipe on a channel: ``{"file": "recipes/x.yaml", "parameters": {...}}``."""
        channel = request.match_info["channel"]
        body = await self._body(request, empty_ok=False)
        if body is None or not isinstance(body.get("file"), str):
            return self._bad('body must be JSON {"file": "...", "parameters": {...}}')
        args = {"recipe": body.pop("file"), **body}
        return await self._answer(Command.channel(channel, Verb.LOAD, self.actor(request), **args))

    async def _channel_command(self, request: web.Request) -> web.Response:
        """``POST /api/channels/{ch}/commands/{verb}`` with the verb's arguments as JSON."""
        channel, name = request.match_info["channel"], request.match_info["verb"]
        verb = Verb.parse(name)
        if verb is None:
            return self._bad(f"unknown command {name!r}", ResultKind.NOT_FOUND)
        args = await self._body(request, empty_ok=True)
        if args is None:
            return self._bad(f"{name}: the arguments must be a JSON object")
        return await self._answer(Command.channel(channel, verb, self.actor(request), **args))

    async def _alarm_command(self, request: web.Request) -> web.Response:
        """``POST /api/alarms/{id}/acknowledge|reset|shelve|unshelve`` (shelve:
        ``{"duration_s": 3600}``)."""
        alarm, action = request.match_info["alarm"], request.match_info["action"]
        if action not in ALARM_ACTIONS:
            return self._bad(
                f"unknown alarm command {action!r} ({', '.join(ALARM_ACTIONS)})",
                ResultKind.NOT_FOUND,
            )
        args = await self._body(request, empty_ok=True)
        if args is None:
            return self._bad(f"{action}: the arguments must be a JSON object")
        return await self._answer(Command.alarm(alarm, Verb(action), self.actor(request), **args))

    async def _alarms(self, request: web.Request) -> web.Response:
        """Alarms not in their normal state (first-out first), and the latest transitions
        (``?limit=N``, default 200, newest last)."""
        try:
            limit = int(request.query.get("limit", "200"))
        except ValueError:
            return self._bad("limit must be an integer")
        alarms = self.commands.alarms
        active = [] if alarms is None else [a for a in alarms if a.in_alarm]
        active.sort(key=lambda a: (not a.first_out, a.activated_t or 0.0))
        history = list(alarms.history)[-limit:] if alarms is not None and limit > 0 else []
        return _json(
            {
                "accepted": True,
                "reason": "",
                "active": [alarm_json(a, self.clock) for a in active],
                "history": [alarm_event_json(e) for e in history],
            }
        )

    async def _sim_estop(self, request: web.Request) -> web.Response:
        try:
            body = await request.json()
        except ValueError:
            body = None
        if not isinstance(body, dict) or not isinstance(body.get("pressed"), bool):
            return _json({"error": 'body must be {"pressed": true|false}'}, status=400)
        assert self._estop is not None
        self._estop(body["pressed"])
        log.warning("simulation: e-stop %s", "PRESSED" if body["pressed"] else "released")
        return _json({"pressed": body["pressed"]})

    async def _sim_state_get(self, request: web.Request) -> web.Response:
        assert self._sim_state is not None
        return _json(self._sim_state())

    async def _put(self, request: web.Request) -> web.Response:
        """``PUT /api/tags/{name}`` ``{"value": ...}``: a write through the command path."""
        name = request.match_info["name"]
        body = await self._body(request, empty_ok=False)
        if body is None or "value" not in body:
            return self._bad('body must be JSON {"value": ...}')
        return await self._answer(Command.write(name, body["value"], self.actor(request)))
