"""A small JSON API: read tags, give commands, see alarms. Listens on loopback by default.

Every write and command goes through the bench's one command path (``supervisor.commands``):
it is checked (role, state, interlocks), recorded with its actor, and answered
``{"accepted": bool, "reason": str, ...}`` with the status of its result — 200 accepted,
400 a wrong argument type or value, 403 a read-only tag or a command the actor may not
give, 404 an unknown tag, channel, alarm or recipe, 409 refused in this state or by an
interlock, 422 a recipe refused (``details``: file:line:col), 503 a recipe that took longer
than ``RECIPE_COMPILE_TIMEOUT_S`` to read and compile (README "Input limits"; it is
compiled in a worker thread, never on the scan's event loop). Before any of it, a command
not declared ``application/json`` is 415 and one from a page of another origin 403
(:mod:`supervisor.hmi.csrf`). Every route is described in ``openapi.yaml``. A write of a channel's
``command``, ``mode``, ``manual_current``, ``enable`` or ``ack`` tag is that command. The
scan takes the effect at its next start.

Every answer is JSON (RFC 8259), which has no NaN nor Infinity: a browser's ``JSON.parse``
refuses a whole snapshot for one of them. A request's ``NaN``/``Infinity`` is refused as
not JSON; a non-finite value in a tag (a device can still produce one) is sent as ``null``
with quality ``BAD`` (:func:`tag_json`), and any other non-finite number as ``null``
(:func:`json_dumps`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Awaitable, Callable, Iterable
from json.encoder import encode_basestring_ascii as _quote
from typing import Any, Final, Protocol

from aiohttp import web

from supervisor.commands import Command, CommandPath, Result, ResultKind, Target, Verb
from supervisor.core.clock import Clock
from supervisor.core.driver import Value
from supervisor.core.quality import Quality, Reason
from supervisor.hmi.body import BodyError, read_json, read_json_object, refuse_unknown
from supervisor.hmi.compress import GzipMemo, gzip_json, json_text_response
from supervisor.hmi.csrf import RequestOrigins
from supervisor.hmi.history_api import HistoryQuery, add_history_routes
from supervisor.hmi.limits import ConnectionGuard, ConnectionLimits
from supervisor.hmi.openapi import add_openapi_route
from supervisor.hmi.profiles_api import add_profile_routes
from supervisor.hmi.recipes_api import RecipesConfig, add_recipe_routes
from supervisor.hmi.silence_api import add_silence_route
from supervisor.hmi.tests_api import TestsConfig, add_test_routes
from supervisor.safety import Alarm, AlarmEvent
from supervisor.tags import Access, Tag, TagDB

log = logging.getLogger(__name__)


ACTOR_KEY: Final = web.RequestKey[str]("actor")
"""Where the login middleware (``supervisor.hmi.auth``) leaves a request's actor."""

NOT_FINITE_REASON = "not a finite number"
"""The reason sent with a tag whose value is NaN or ±inf (sent as null, quality BAD)."""


def tag_json(tag: Tag, clock: Clock) -> dict[str, Any]:
    return row_json(tag_row(tag), clock)


TagRow = tuple[Tag, Value | None, Quality, Reason, bool, float, int]
"""What a tag's JSON shows, copied at one instant: the tag (its name and spec do not
change), value, quality, reason, forced, source time, version."""


def tag_row(tag: Tag) -> TagRow:
    return (tag, tag.value, tag.quality, tag.reason, tag.forced, tag.source_t, tag.version)


def row_json(row: TagRow, clock: Clock) -> dict[str, Any]:
    """``tag_json`` of a tag as ``row`` copied it."""
    tag, value, q, r, forced, source_t, version = row
    s = tag.spec
    quality, reason = q.name, str(r)
    if isinstance(value, float) and not math.isfinite(value):
        value, quality, reason = None, Quality.BAD.name, f"{NOT_FINITE_REASON} ({value})"
    return {
        "name": tag.name,
        "value": value,
        "unit": s.unit,
        "quality": quality,
        "reason": reason,
        "forced": forced,
        "access": s.access.name.lower(),
        "source_time": clock.to_wall(source_t) if source_t else None,
        "version": version,
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
        # For a screen in another language: the message's kind and figures, and the tags
        # behind it (issue 33, finding 6; supervisor/safety/alarms.py AlarmText).
        "code": alarm.code,
        "params": alarm.params,
        "detail": alarm.detail,
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
        "code": ev.code,
        "params": dict(ev.params),
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


_ENCODER: Final = json.JSONEncoder(allow_nan=False)
"""``json.dumps(obj, allow_nan=False)`` without building an encoder at each call."""


def json_dumps(obj: Any) -> str:
    """JSON text that any JSON parser reads: NaN and ±inf become null (never emitted)."""
    try:
        return _ENCODER.encode(obj)
    except ValueError:  # a non-finite float somewhere: the rare case pays for the walk
        return _ENCODER.encode(_finite_only(obj))


# --- snapshots off the scan's critical path (docs/adr/0019-http-off-the-scan.md) ----------
SLICE_TAGS: Final = 512
"""Tags (re-)encoded between two yields to the event loop. Snapshots keep each tag's text
(:class:`TagFragments`) and re-encode only the tags that changed, so a snapshot with at
most this many changed tags is built in one go, in the request's own turn of the loop
(about 0.7 ms of CPU on the bench's machine at most): one turn of a loop shared with the
scan, the drivers and the publishers instead of ten (issue 13: the latency of a snapshot
encoded 100 tags at a time was the number of its turns under load). Only a larger
re-encoding (every one of ~1000 tags changed: two slices) yields, so a scan falling due
waits at most about one slice."""


class ScanPacing(Protocol):
    """When the scan sharing the event loop falls due (``ScanEngine`` is one)."""

    next_deadline: float | None
    """The next scan's start, on the clock's axis (None: not scanning on a real clock)."""

    def after_next_scan(self) -> Awaitable[None]:
        """Done once the next scan is (at most two periods later)."""
        ...


CLEAR_MARGIN_S: Final = 0.0003
"""Added to the usual image turn: the response's own writing follows the image in the same
callback (:meth:`TagSnapshots.clear_of_scan`)."""
TURN_WEIGHT: Final = 0.1
"""Weight of the newest turn in :attr:`TagSnapshots.turn_s` (an exponential average)."""


_FLOAT_TEXT: Final = float.__repr__  # what json.dumps writes for a finite float
_INT_TEXT: Final = int.__repr__
_isfinite: Final = math.isfinite

_MIDDLES: dict[tuple[str, Quality, Reason, bool, Access], str] = {}
"""``, "unit": …, "source_time": `` of each (unit, quality, reason, forced, access) seen:
``Enum.name`` and ``str(Reason)`` are Python-level calls (0.1-1 µs each), a dict lookup
is not. Bounded by the units of the configuration times 3 × 13 × 2 × 3."""


def _middle(unit: str, q: Quality, r: Reason, forced: bool, access: Access) -> str:
    key = (unit, q, r, forced, access)
    text = _MIDDLES.get(key)
    if text is None:
        text = _MIDDLES[key] = (
            f', "unit": {_quote(unit)}, "quality": "{q.name}", "reason": {_quote(str(r))},'
            f' "forced": {"true" if forced else "false"}, "access": "{access.name.lower()}",'
            ' "source_time": '
        )
    return text


def _value_text(value: Value | None) -> str | None:
    """What ``json_dumps`` writes for ``value``; None for a non-finite or unusual one."""
    kind = type(value)
    if kind is float:
        return _FLOAT_TEXT(value) if _isfinite(value) else None  # type: ignore[arg-type]
    if kind is str:
        return _quote(value)  # type: ignore[arg-type]
    if kind is bool:
        return "true" if value else "false"
    if kind is int:
        return _INT_TEXT(value)
    if value is None:
        return "null"
    return None


def _prefix(tag: Tag, as_map: bool) -> str:
    """The text before a tag's value: ``{"name": N, "value": `` or ``N: {"value": ``."""
    name = _quote(tag.name)
    return f'{name}: {{"value": ' if as_map else f'{{"name": {name}, "value": '


def _general_text(row: TagRow, clock: Clock, as_map: bool) -> str:
    """The item (or member) of ``row`` through ``row_json`` and ``json_dumps``."""
    entry = row_json(row, clock)
    if not as_map:
        return json_dumps(entry)
    del entry["name"]
    return f"{_quote(row[0].name)}: {json_dumps(entry)}"


def _when_text(source_t: float, clock: Clock) -> str:
    return _FLOAT_TEXT(clock.to_wall(source_t)) if source_t else "null"


def _row_text(row: TagRow, clock: Clock, as_map: bool) -> str:
    """``json_dumps(row_json(row, clock))`` (``as_map``: its member in the object by name),
    formatted directly (a third of the CPU of a dict and its encoding), nothing kept."""
    tag, value, q, r, forced, source_t, version = row
    v = _value_text(value)
    if v is None:
        return _general_text(row, clock, as_map)
    s = tag.spec
    middle = _middle(s.unit, q, r, forced, s.access)
    when = _when_text(source_t, clock)
    return f'{_prefix(tag, as_map)}{v}{middle}{when}, "version": {version}}}'


async def encode_rows(rows: list[TagRow], clock: Clock, as_map: bool) -> str:
    """``json_dumps`` of ``[tag_json...]`` (or, ``as_map``, of ``{name: tag_json without
    its name}``) of ``rows``, the same text, encoded ``SLICE_TAGS`` at a time with a
    yield to the event loop between two slices, nothing kept. ``rows`` were copied at one
    instant, so the text is one consistent image even when scans run in between."""
    parts: list[str] = []
    for i in range(0, len(rows), SLICE_TAGS):
        if i:
            await asyncio.sleep(0)  # a scan that is due starts here
        parts.extend([_row_text(row, clock, as_map) for row in rows[i : i + SLICE_TAGS]])
    body = ", ".join(parts)  # json.dumps separates items and members with ", "
    return "{" + body + "}" if as_map else "[" + body + "]"


_Entry = tuple[int, bool, str | None, str]
"""A tag's kept text: the version and forced flag it was encoded at, its head (None: the
general path, every time) and its tail followed by the separator ``", "``."""
_NO_ENTRY: Final[_Entry] = (-1, False, None, "")
Collected = tuple[list[str], list[tuple[int, TagRow]], dict[float, str]]
"""What :meth:`TagFragments.collect` found: the texts in order, with an empty place for
each tag to encode; those places and the tags' states copied; the source times written."""
_Fixed = tuple[str, Quality, Reason, bool, str]
"""A tag's text before its value and, for the quality, reason and forced flag it was made
for, the text between its value and its source time."""


class TagFragments:
    """Each tag's JSON text in one form (list items or members by name), kept between
    snapshots and re-encoded only when the tag's version (or forced flag) moved: an image
    is then the join of the kept texts, with every source time written afresh (it moves at
    every poll without a new version). The texts are exactly those of ``json_dumps`` of
    the same ``tag_json`` list (or object)."""

    def __init__(self, db: TagDB, clock: Clock, as_map: bool) -> None:
        self.db = db
        self.clock = clock
        self.as_map = as_map
        self.encoded = 0
        """Tags (re-)encoded so far (the others were joined from their kept text)."""
        self._entries: list[_Entry] = []
        self._statics: list[_Fixed | None] = []

    async def encode(self, tags: Iterable[Tag]) -> str:
        """The JSON text of ``tags`` as they are when called (one version, even when the
        re-encoding yields between slices). Without a ``await`` point when at most
        ``SLICE_TAGS`` of them changed since they were last encoded."""
        return await self.finish(*self.collect(tags))

    def collect(self, tags: Iterable[Tag]) -> Collected:
        """The kept texts of ``tags`` in order with a place for each tag to re-encode, whose
        state is copied now (``tag_row``); the source times written so far."""
        entries, n = self._entries, len(self.db)
        if len(entries) < n:  # tags declared since (TagDB.add): indices go on from 0
            entries.extend([_NO_ENTRY] * (n - len(entries)))
            self._statics.extend([None] * (n - len(self._statics)))
        clock = self.clock
        whens: dict[float, str] = {}  # the tags of one poll share their source time
        parts: list[str] = ["{" if self.as_map else "["]
        append = parts.append
        todo: list[tuple[int, TagRow]] = []
        for tag in tags:
            version, forced, head, tail = entries[tag.index]
            if version == tag.version and forced is tag.forced and head is not None:
                st = tag.source_t
                when = whens.get(st)
                if when is None:
                    when = whens[st] = _when_text(st, clock)
                append(head)
                append(when)
                append(tail)
            else:
                todo.append((len(parts), tag_row(tag)))
                append("")
        return parts, todo, whens

    def fill(
        self, parts: list[str], todo: list[tuple[int, TagRow]], whens: dict[float, str]
    ) -> None:
        """Encode the tags of ``todo`` into their places in ``parts`` and keep their texts."""
        entries, statics, clock, as_map = self._entries, self._statics, self.clock, self.as_map
        for at, row in todo:
            tag, value, q, r, forced, st, version = row
            i = tag.index
            v = _value_text(value)
            if v is None:
                parts[at] = _general_text(row, clock, as_map) + ", "
                entry: _Entry = (version, forced, None, "")
            else:
                # Most changes are of the value only: the text around it is kept per tag
                # (compared by identity: hashing an Enum is a Python-level call).
                fixed = statics[i]
                if (
                    fixed is None
                    or fixed[1] is not q
                    or fixed[2] is not r
                    or fixed[3] is not forced
                ):
                    s = tag.spec
                    middle = _middle(s.unit, q, r, forced, s.access)
                    fixed = statics[i] = (_prefix(tag, as_map), q, r, forced, middle)
                head = f"{fixed[0]}{v}{fixed[4]}"
                tail = f', "version": {version}}}, '
                when = whens.get(st)
                if when is None:
                    when = whens[st] = _when_text(st, clock)
                parts[at] = f"{head}{when}{tail}"
                entry = (version, forced, head, tail)
            if entries[i][0] <= version:  # never over a newer text
                entries[i] = entry
        self.encoded += len(todo)

    async def finish(
        self, parts: list[str], todo: list[tuple[int, TagRow]], whens: dict[float, str]
    ) -> str:
        """The text of what ``collect`` found: ``todo`` encoded ``SLICE_TAGS`` at a time
        with a yield to the event loop between two slices, then joined. The rows were
        copied at one instant, so the text is one image even when scans run meanwhile."""
        for i in range(0, len(todo), SLICE_TAGS):
            if i:
                await asyncio.sleep(0)  # a scan that is due starts here
            self.fill(parts, todo[i : i + SLICE_TAGS], whens)
        return self.join(parts)

    def join(self, parts: list[str]) -> str:
        """The text of ``parts`` once every place is filled (it ends ``parts``)."""
        if len(parts) == 1:
            return "{}" if self.as_map else "[]"
        parts[-1] = parts[-1][:-2]  # no separator after the last one
        parts.append("}" if self.as_map else "]")
        return "".join(parts)


class TagSnapshots:
    """Encoded images of the whole tag database for ``GET /api/tags`` and the WebSocket
    snapshot, from each tag's kept text (:class:`TagFragments`): in one go when few tags
    changed since the last image, else copied at once and re-encoded in slices; built once
    per database version and shared by every request at that version (in flight or done)."""

    def __init__(self, db: TagDB, clock: Clock, pacing: ScanPacing | None = None) -> None:
        self.db = db
        self.clock = clock
        self.pacing = pacing
        """The scan on this loop: an image's turn starts only when it ends before the next
        scan is due, else right after that scan (None: at once)."""
        self.built = 0
        """Images encoded so far (each serves every request at its version)."""
        self.deferred = 0
        """Image turns started after a scan because that scan was due too soon."""
        self.turn_s = 0.0
        """The usual image turn (an exponential average): the time an image's turn needs
        clear of the next scan. Not the longest: a turn longer than the window delays the
        scan by what is left of it only when the deadline falls in that remainder, rare
        enough for the jitter's p99 (a window of twice the longest recent turn deferred
        most requests and doubled the snapshot's median latency)."""
        self.fragments = {as_map: TagFragments(db, clock, as_map) for as_map in (False, True)}
        self._done: dict[bool, tuple[int, str]] = {}
        self._building: dict[bool, tuple[int, asyncio.Task[str]]] = {}

    async def image(self, as_map: bool = False) -> tuple[int, str]:
        """The database's version now and the JSON of every tag at it (a list of
        ``tag_json``, or ``as_map`` the object name → ``tag_json`` without its name)."""
        version = self.db.version
        done = self._done.get(as_map)
        if done is not None and done[0] == version:
            return done
        building = self._building.get(as_map)
        if (building is None or building[0] != version) and await self.clear_of_scan():
            # A scan ran meanwhile: the image of the version it left (once: no second
            # wait, whatever the clock says now).
            version = self.db.version
            done = self._done.get(as_map)
            if done is not None and done[0] == version:
                return done
            building = self._building.get(as_map)
        if building is None or building[0] != version:
            t0 = time.perf_counter()
            fragments = self.fragments[as_map]
            parts, todo, whens = fragments.collect(self.db)
            # The first slice at once, in this turn of the loop: most images need no other.
            fragments.fill(parts, todo[:SLICE_TAGS], whens)
            if len(todo) <= SLICE_TAGS:
                text = fragments.join(parts)
                self.timed(time.perf_counter() - t0)
                return self._keep(as_map, version, text)
            self.timed(time.perf_counter() - t0)
            # The rest from the next turn on (a task: a scan due meanwhile goes first).
            rest = todo[SLICE_TAGS:]
            task = asyncio.get_running_loop().create_task(
                self._build(as_map, version, parts, rest, whens)
            )
            building = (version, task)
            self._building[as_map] = building
        # Shielded: a request that goes away does not cancel the others' image.
        return version, await asyncio.shield(building[1])

    async def _build(
        self,
        as_map: bool,
        version: int,
        parts: list[str],
        todo: list[tuple[int, TagRow]],
        whens: dict[float, str],
    ) -> str:
        try:
            text = await self.fragments[as_map].finish(parts, todo, whens)
        finally:
            if self._building.get(as_map, (None,))[0] == version:
                del self._building[as_map]
        return self._keep(as_map, version, text)[1]

    async def clear_of_scan(self) -> bool:
        """Wait for the next scan's end when that scan falls due before an image's turn
        would be over (True: it waited). A turn of the loop cannot be interrupted by the
        scan that shares it: started just before a deadline, a full image (0.5-1.5 ms)
        made that scan start late by what was left of it (issue 13: the start jitter p99
        0.04 ms without snapshots, 0.65 ms with them, in the load case). Started right
        after a scan, it is done long before the next one."""
        pacing = self.pacing
        if pacing is None:
            return False
        due = pacing.next_deadline
        if due is None or due - self.clock.now() > self.turn_s + CLEAR_MARGIN_S:
            return False
        self.deferred += 1
        await pacing.after_next_scan()
        return True

    def timed(self, turn_s: float) -> None:
        """Note how long an image's turn took (see :attr:`turn_s`)."""
        # The first turn timed is the average; the next ones move it.
        self.turn_s = (
            turn_s if self.turn_s == 0.0 else self.turn_s + TURN_WEIGHT * (turn_s - self.turn_s)
        )

    def _keep(self, as_map: bool, version: int, text: str) -> tuple[int, str]:
        self.built += 1
        done = self._done.get(as_map)
        if done is None or done[0] < version:
            self._done[as_map] = (version, text)
        return version, text


def _json(data: Any, status: int = 200) -> web.Response:
    return web.json_response(data, status=status, dumps=json_dumps)


# --- what every answer carries (issue 27, finding 7; docs/adr/0026-threat-model.md) --------
SECURITY_HEADERS: Final = {
    # Only the supervisor's own scripts, styles and connections (the WebSocket to the same
    # host is 'self' in CSP 3), never inside another site's frame (clickjacking of a
    # command button), no plug-ins, no <base> to elsewhere, forms only to this server.
    "Content-Security-Policy": (
        "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:;"
        " connect-src 'self'; frame-ancestors 'none'; object-src 'none'; base-uri 'self';"
        " form-action 'self'"
    ),
    "X-Frame-Options": "DENY",  # frame-ancestors for browsers without CSP 2
    "X-Content-Type-Options": "nosniff",  # a JSON answer is never run as a script
    "Referrer-Policy": "same-origin",
}


async def _security_headers(request: web.Request, response: web.StreamResponse) -> None:
    """On every answer, just before its headers leave (pages, JSON, files, WebSocket
    upgrades and aiohttp's own errors alike: a signal, not a middleware, so that a
    response prepared inside its handler gets them too)."""
    for name, value in SECURITY_HEADERS.items():
        response.headers.setdefault(name, value)


Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


@web.middleware
async def json_errors(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Every error answer under ``/api/`` is JSON ``{"accepted": false, "reason", "kind"}``
    like the API's own refusals, including aiohttp's (413 request too large, 404 no such
    route, 405 method not allowed) and an unexpected exception's 500, never its text/plain
    page (a client parsing JSON got a parse error instead of the reason)."""
    try:
        return await handler(request)
    except web.HTTPException as exc:
        if exc.status < 400 or not request.path.startswith("/api/"):
            raise
        reason = exc.text or exc.reason
        if exc.text and exc.content_type == "text/plain":
            reason = exc.text.removeprefix(f"{exc.status}: ")
        body = {"accepted": False, "reason": reason, "kind": exc.reason.lower()}
        headers = {k: v for k, v in exc.headers.items() if k.lower() in ("allow", "retry-after")}
        response = _json(body, status=exc.status)
        response.headers.update(headers)
        return response
    except Exception as exc:
        if not request.path.startswith("/api/"):
            raise
        log.exception("HTTP %s %s failed", request.method, request.path)
        return _json(
            {"accepted": False, "reason": f"internal error: {exc}", "kind": "internal error"}, 500
        )


def _application(allowed_origins: Iterable[str]) -> web.Application:
    """The API's application with what every request and answer goes through."""
    app = web.Application()
    # Cross-site request forgery: JSON bodies and same-origin pages only (issue 27).
    RequestOrigins(allowed_origins).install(app)
    # Outermost: every error under /api/ is JSON, aiohttp's own and the refusals too.
    app.middlewares.insert(0, json_errors)
    # Outside it, so that a large error answer is compressed too (supervisor.hmi.compress).
    app.middlewares.insert(0, gzip_json)
    app.on_response_prepare.append(_security_headers)
    return app


VALUE_BODY: Final = '{"value": ...}'
RECIPE_BODY: Final = '{"file": "...", "parameters": {...}}'


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
        pacing: ScanPacing | None = None,
        allowed_origins: Iterable[str] = (),
        limits: ConnectionLimits | None = None,
    ):
        """``pacing``: the scan sharing this event loop (``ScanEngine``): a full image's turn
        then starts only when it is over before that scan is due (ADR 0019).
        ``allowed_origins``: pages of these origins may command, besides the API's own
        (``hmi.allowed_origins``, :mod:`supervisor.hmi.csrf`). ``limits``: the connection
        cap and timeouts (``supervisor.hmi.limits``; the defaults without)."""
        self.db = db
        self._estop = estop
        self._sim_state = sim_state
        # Without a bench (``supervisor sim``'s control API) writes still take the path.
        self.commands = commands if commands is not None else CommandPath(db, clock)
        self.clock = clock
        self.host = host
        self.port = port
        self._runner: web.AppRunner | None = None
        self._listener: asyncio.Server | None = None
        self.limits = limits or ConnectionLimits()
        self.guard: ConnectionGuard | None = None
        """The listener's connection counts (after ``start``)."""
        self.snapshots = TagSnapshots(db, clock, pacing)
        self._tags_gzip = GzipMemo()
        app = _application(allowed_origins)
        app.add_routes(
            [
                web.get("/api/tags", self._list),
                web.get("/api/tags/{name}", self._get),
                web.put("/api/tags/{name}", self._put),
                web.put("/api/channels/{channel}/recipe", self._recipe),
                web.post("/api/channels/{channel}/commands/{verb}", self._channel_command),
            ]
        )
        self._add_alarm_routes(app)
        add_openapi_route(app)  # GET /api/openapi.json (hmi/openapi.yaml)
        # Forcing (engineers only; never a tag the safety phase uses): ADR 0015.
        app.add_routes(
            [
                web.put("/api/tags/{name}/force", self._force),
                web.delete("/api/tags/{name}/force", self._unforce),
            ]
        )
        if history is not None:  # GET /api/history, /api/events (hmi/history_api.py)
            add_history_routes(app, history, db, clock, self.commands.runners)
        if recipes is not None:  # /api/recipes…, /api/profiles… (recipes_api, profiles_api)
            add_profile_routes(app, add_recipe_routes(app, recipes), self.commands, self.actor)
        if tests is not None:  # /api/tests… (hmi/tests_api.py)
            add_test_routes(app, tests, clock)
        self._add_estop_routes(app)
        self.app = app

    def _add_alarm_routes(self, app: web.Application) -> None:
        """The alarms, their commands, and a screen's alarm sound silenced (recorded with
        its actor: hmi/silence_api.py)."""
        app.add_routes(
            [
                web.get("/api/alarms", self._alarms),
                web.post("/api/alarms/{alarm}/{action}", self._alarm_command),
            ]
        )
        add_silence_route(
            app, lambda: self.commands.alarms, self.actor, lambda: self.commands.audit
        )

    def _add_estop_routes(self, app: web.Application) -> None:
        """The bench-wide software e-stop (seed 002 §1.5) and its reset, on every bench; the
        simulated bench's e-stop button and plant state when this API has them."""
        app.add_routes(
            [
                web.post("/api/estop", self._estop_command),
                web.post("/api/estop/reset", self._estop_command),
            ]
        )
        if self._estop is not None:
            # Simulation only: the e-stop button of the simulated bench.
            app.add_routes([web.put("/api/sim/estop", self._sim_estop)])
        if self._sim_state is not None:
            # Simulation only: what the simulated plant does (contactor, supply), so that a
            # test or a person can see the hardware's side, not only the supervisor's.
            app.add_routes([web.get("/api/sim/state", self._sim_state_get)])

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/api"

    async def start(self) -> None:
        limits = self.limits
        # keepalive_timeout: an idle keep-alive connection is closed (aiohttp's default
        # kept it for an hour).
        self._runner = web.AppRunner(
            self.app, access_log=None, keepalive_timeout=limits.idle_timeout_s
        )
        await self._runner.setup()
        handler = self._runner.server
        assert handler is not None
        # Our own listener instead of aiohttp's TCPSite: each accepted connection goes
        # through the guard (cap, header timeout) before aiohttp sees it.
        self.guard = ConnectionGuard(handler, limits)
        self._listener = await asyncio.get_running_loop().create_server(
            self.guard.protocol, self.host, self.port, backlog=limits.backlog
        )
        if self.port == 0 and self._listener.sockets:
            self.port = self._listener.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        if self._listener is not None:
            self._listener.close()  # no new connection; aiohttp closes the open ones
            self._listener = None
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def _list(self, request: web.Request) -> web.Response:
        prefix = request.query.get("prefix", "")
        if prefix:  # from the kept texts too, unshared
            await self.snapshots.clear_of_scan()
            tags = [t for t in self.db if t.name.startswith(prefix)]
            text = await self.snapshots.fragments[False].encode(tags)
            return await json_text_response(request, text)
        version, text = await self.snapshots.image()
        # gzip for a client that takes it, once per version (supervisor.hmi.compress).
        return await json_text_response(request, text, self._tags_gzip, version)

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

    async def _value_body(self, request: web.Request, name: str) -> dict[str, Any] | web.Response:
        """A tag write's body ``{"value": ...}``, or the answer refusing it (another member
        is refused by name: a typo such as ``"valeu"`` beside ``"value"`` is never
        ignored)."""
        try:
            body = await read_json_object(request, shape=VALUE_BODY)
            refuse_unknown(body, ("value",), name)
        except BodyError as exc:
            return exc.response()
        if "value" not in body:
            return self._bad(f"body must be JSON {VALUE_BODY}")
        return body

    async def _recipe(self, request: web.Request) -> web.Response:
        """Load a recipe on a channel: ``{"file": "recipes/x.yaml", "parameters": {...}}``."""
        channel = request.match_info["channel"]
        try:
            body = await read_json_object(request, shape=RECIPE_BODY)
        except BodyError as exc:
            return exc.response()
        if not isinstance(body.get("file"), str):
            return self._bad(f"body must be JSON {RECIPE_BODY}")
        args = {"recipe": body.pop("file"), **body}
        return await self._answer(
            Command(Target.channel(channel), Verb.LOAD, args, self.actor(request))
        )

    async def _channel_command(self, request: web.Request) -> web.Response:
        """``POST /api/channels/{ch}/commands/{verb}`` with the verb's arguments as JSON."""
        channel, name = request.match_info["channel"], request.match_info["verb"]
        verb = Verb.parse(name)
        if verb is None:
            return self._bad(f"unknown command {name!r}", ResultKind.NOT_FOUND)
        try:
            args = await read_json_object(request, empty_ok=True, what=f"{name}: the arguments")
        except BodyError as exc:
            return exc.response()
        # The arguments as a mapping, never as keywords: a member named like a parameter of
        # ``Command.channel`` (``actor``, ``verb``, ``cls``) was a TypeError, a 500; now
        # the command path refuses it as an unknown argument, by name.
        return await self._answer(Command(Target.channel(channel), verb, args, self.actor(request)))

    async def _alarm_command(self, request: web.Request) -> web.Response:
        """``POST /api/alarms/{id}/acknowledge|reset|shelve|unshelve`` (shelve:
        ``{"duration_s": 3600}``)."""
        alarm, action = request.match_info["alarm"], request.match_info["action"]
        if action not in ALARM_ACTIONS:
            return self._bad(
                f"unknown alarm command {action!r} ({', '.join(ALARM_ACTIONS)})",
                ResultKind.NOT_FOUND,
            )
        try:
            args = await read_json_object(request, empty_ok=True, what=f"{action}: the arguments")
        except BodyError as exc:
            return exc.response()
        command = Command(Target.alarm(alarm), Verb(action), args, self.actor(request))
        return await self._answer(command)

    async def _estop_command(self, request: web.Request) -> web.Response:
        """``POST /api/estop`` presses the software e-stop (every channel tripped, as by the
        button); ``POST /api/estop/reset`` releases it once acknowledged. No arguments."""
        reset = request.path.endswith("/reset")
        what = "estop reset" if reset else "estop"
        try:
            args = await read_json_object(request, empty_ok=True, what=f"{what}: the arguments")
        except BodyError as exc:
            return exc.response()
        verb = Verb.ESTOP_RESET if reset else Verb.ESTOP
        return await self._answer(Command(Target.bench(), verb, args, self.actor(request)))

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
        # An operator's button (issue 27: a viewer's press aborted a held test).
        actor = self.actor(request)
        if self.commands.roles.access_of(actor) < Access.OPERATOR:
            who = actor.removeprefix("hmi:")
            return self._bad(
                f"viewer may not press the simulated e-stop ({who} is a viewer): log in as an"
                " operator",
                ResultKind.FORBIDDEN,
            )
        try:
            body = await read_json(request)
        except BodyError as exc:
            return exc.response()
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
        body = await self._value_body(request, name)
        if isinstance(body, web.Response):
            return body
        return await self._answer(Command.write(name, body["value"], self.actor(request)))

    async def _force(self, request: web.Request) -> web.Response:
        """``PUT /api/tags/{name}/force`` ``{"value": ...}``: force the tag (a text is read as
        the tag's type) until ``DELETE``; 403 below engineer, 409 for a tag the safety phase
        reads or drives, 400 a wrong value, 404 an unknown tag."""
        name = request.match_info["name"]
        body = await self._value_body(request, name)
        if isinstance(body, web.Response):
            return body
        return await self._answer(Command.force(name, body["value"], self.actor(request)))

    async def _unforce(self, request: web.Request) -> web.Response:
        """``DELETE /api/tags/{name}/force``: hand the tag back to the process."""
        return await self._answer(Command.unforce(request.match_info["name"], self.actor(request)))
