"""Live data for the screens: ``GET /api/ws`` (WebSocket), deltas at the publish rate.

Server → client JSON text messages (docs/adr/0016 "Live data"):

- ``{"type": "snapshot", "version": N, "tags": {name: TAG}}`` once at connect (TAG is
  ``tag_json`` without its name), then ``{"type": "alarms", "alarms": [...]}``;
- ``{"type": "delta", "version": N, "tags": {name: TAG}}`` every ``hmi.publish_period_s``
  when something changed: only the tags whose version is newer than what this client
  already has (``TagDB.changed_since``, O(changes));
- ``{"type": "alarms", "alarms": [alarm_json...]}`` (the alarms not in their normal state,
  first-out first, as ``GET /api/alarms`` "active") after any alarm transition;
- ``{"type": "event", "event": {...}}`` for each bench event (step and state changes,
  commands with their actor, alarm transitions: ``BenchEvent``).

The scan never waits on a client (STYLE.md: publish hooks use bounded queues with drop
counters): the scan's publisher hook (``on_scan``) only notes that a publication is due;
a task of its own builds each delta once, between two scans, and puts the same text in
every client's queue without awaiting. Each client has one sender task that writes its
queue to the socket. A client that does not read fills its TCP window, then its queue
(``queue_size`` messages, about a minute of deltas); it is then closed with code 1008
"too slow" and counted (``hmi.ws_dropped``). The page reconnects and gets a new snapshot.

Deltas take every change, not ``ChangeFeed``'s: the feed keeps what a trend should store
(history deadbands, minimum intervals, tags with history off are skipped), while a screen
must show the value the bench has now.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import asdict
from typing import Any, Final

from aiohttp import WSCloseCode, WSMsgType, web

from supervisor.core.clock import Clock
from supervisor.core.records import BenchEvent
from supervisor.hmi.auth import VALID_KEY
from supervisor.hmi.limits import MAX_WEBSOCKETS
from supervisor.hmi.server import (
    Collected,
    TagSnapshots,
    alarm_json,
    json_dumps,
    tag_json,
)
from supervisor.safety import AlarmEvent, AlarmManager
from supervisor.tags import Tag, TagDB, TagSpec

log = logging.getLogger(__name__)

QUEUE_SIZE: Final = 256
"""Messages waiting for one client at most (about 50 s of deltas at 0.2 s, with room for
an alarm storm's events) before it counts as too slow."""
EVENTS_WAITING: Final = 1000
"""Bench events kept for the next publication at most (an e-stop's burst is tens)."""
TOO_SLOW_CODE: Final = int(WSCloseCode.POLICY_VIOLATION)  # 1008 (RFC 6455 §7.4.1)
TOO_SLOW: Final = "too slow"
CLOSE_TIMEOUT_S: Final = 10.0
"""How long the close frame of a dropped client may wait for its socket (wall time) before
the connection is cut (aborted: a client that never reads would hold it for ever)."""
HEARTBEAT_S: Final = 30.0
"""aiohttp pings every client this often: a page on a sleeping tablet is seen gone."""


def tag_entry(tag: Tag, clock: Clock) -> dict[str, Any]:
    """``tag_json`` without the name (the name is the key of the message's ``tags``)."""
    entry = tag_json(tag, clock)
    del entry["name"]
    return entry


class LiveClient:
    """One WebSocket client: its queue, the version it has, its sender task."""

    def __init__(
        self,
        ws: web.WebSocketResponse,
        version: int,
        queue_size: int,
        valid: Callable[[], bool],
        transport: asyncio.Transport | None = None,
    ) -> None:
        self.ws = ws
        self.transport = transport
        self.version = version
        self.queue: asyncio.Queue[str] = asyncio.Queue(queue_size)
        self.valid = valid
        self.dropped = False
        self.sender: asyncio.Task[None] | None = None
        self.closer: asyncio.Task[None] | None = None

    async def send_loop(self) -> None:
        while True:
            text = await self.queue.get()
            await self.ws.send_str(text)


class LiveHub:
    """The scan's publisher for the screens and the ``/api/ws`` handler."""

    name = "hmi"

    def __init__(
        self,
        db: TagDB,
        clock: Clock,
        publish_period_s: float = 0.2,
        alarms: AlarmManager | None = None,
        queue_size: int = QUEUE_SIZE,
        max_clients: int = MAX_WEBSOCKETS,
    ) -> None:
        self.db = db
        self.clock = clock
        self.publish_period_s = publish_period_s
        self.alarms = alarms
        self.queue_size = queue_size
        self.clients: set[LiveClient] = set()
        self.max_clients = max_clients
        """Screens connected at most (``hmi.max_websockets``); one more is answered 503."""
        self.refused = 0
        self._admitted = 0  # clients past the cap's check, connected or still connecting
        self.dropped = 0
        self.published = 0
        self._version = db.version
        self._next_t: float | None = None
        self._due = asyncio.Event()
        self._alarms_changed = False
        self._events: deque[BenchEvent] = deque()  # for the next publication
        self._task: asyncio.Task[None] | None = None
        self.snapshots = TagSnapshots(db, clock)
        self._clients_tag = _declare(db, "hmi.ws_clients", "WebSocket clients (screens) connected")
        self._dropped_tag = _declare(
            db, "hmi.ws_dropped", "WebSocket clients closed because they did not read"
        )
        if alarms is not None:
            alarms.listeners.append(self._on_alarm)

    @property
    def version(self) -> int:
        """The tag database's version at the last publication."""
        return self._version

    # --- the scan side (never blocks, never awaits) -----------------------------------
    def on_scan(self, db: TagDB, t: float) -> None:
        if self._clients_tag.value != len(self.clients):
            db.update(self._clients_tag, len(self.clients))
        if self._dropped_tag.value != self.dropped:
            db.update(self._dropped_tag, self.dropped)
        # Absolute deadlines (start + k·period), no burst after a late scan (ADR 0002).
        if self._next_t is None or t >= self._next_t - 1e-9:
            nxt = (self._next_t or t) + self.publish_period_s
            self._next_t = nxt if nxt > t else t + self.publish_period_s
            self._due.set()

    def on_event(self, event: BenchEvent) -> None:
        """An ``EventSink`` (chain steps, commands, alarm transitions), from the scan or a
        command: kept, and sent to every client by the next publication, before its delta.
        Encoded there, not here: 16 channels changing step in one scan were 16 JSON texts
        made on the scan's thread (issue 13)."""
        if not self.clients:
            return
        if len(self._events) >= EVENTS_WAITING:
            self.dropped += 1  # the publication is stuck: the clients get the newest
            self._events.popleft()
        self._events.append(event)

    def _send_events(self) -> None:
        while self._events:
            body = asdict(self._events.popleft())
            del body["t"]  # the clock's own axis: meaningless to a browser
            self._broadcast(json_dumps({"type": "event", "event": body}))

    def _on_alarm(self, ev: AlarmEvent) -> None:
        self._alarms_changed = True

    # --- publishing (a task of its own, between two scans) ----------------------------
    async def run(self) -> None:
        while True:
            await self._due.wait()
            self._due.clear()
            try:
                await self.publish()
            except Exception:  # a bug here must not end live data for good
                log.exception("hmi: live publication failed")

    async def publish(self) -> None:
        """Send every client what changed since the version it has (and the alarms if any
        changed); drop the clients that went invalid (an expired session). The changed
        tags are collected at once from the kept texts of the snapshots
        (``TagFragments``), what changed encoded in slices: scans may run in between, and
        the delta still describes one version."""
        db = self.db
        base, now_version = self._version, db.version
        for c in list(self.clients):
            if not c.valid():
                self._kick(c, WSCloseCode.POLICY_VIOLATION, "session expired")
        self._send_events()
        if not self.clients:
            self._version, self._alarms_changed = now_version, False
            return
        alarms_changed, self._alarms_changed = self._alarms_changed, False
        if now_version != base:
            self._version = now_version
            tags = _changed(db, base)
            # Every client's tags are chosen and collected now, before the first yield (one
            # version): their kept texts, or their state copied to be encoded.
            fragments = self.snapshots.fragments[True]
            wanted: dict[int, Collected] = {}  # since → what to send a client at since
            todo: list[tuple[LiveClient, int]] = []
            for c in list(self.clients):
                since = c.version
                if since >= now_version:
                    continue
                if since not in wanted:
                    if since == base:  # has everything up to base: the shared delta
                        chosen = tags
                    elif since > base:  # joined since the last delta
                        chosen = [t for t in tags if t.version > since]
                    else:  # its snapshot was encoded while a delta left: catch up
                        chosen = _changed(db, since)
                    wanted[since] = fragments.collect(chosen)
                c.version = now_version
                todo.append((c, since))
            texts = {
                since: _delta(now_version, await fragments.finish(*found))
                for since, found in wanted.items()
            }
            for c, since in todo:
                if c in self.clients:
                    self._put(c, texts[since])
            self.published += 1
        self._version = now_version
        if alarms_changed:
            self._broadcast(self._alarms_text())

    def _alarms_text(self) -> str:
        alarms = self.alarms
        active = [] if alarms is None else [a for a in alarms if a.in_alarm]
        active.sort(key=lambda a: (not a.first_out, a.activated_t or 0.0))
        return json_dumps({"type": "alarms", "alarms": [alarm_json(a, self.clock) for a in active]})

    def _broadcast(self, text: str) -> None:
        for c in list(self.clients):
            self._put(c, text)

    def _put(self, c: LiveClient, text: str) -> None:
        if c.dropped:
            return
        try:
            c.queue.put_nowait(text)
        except asyncio.QueueFull:
            self.dropped += 1
            log.warning(
                "hmi: a WebSocket client did not read %d messages: closed (%s), %d dropped so far",
                self.queue_size,
                TOO_SLOW,
                self.dropped,
            )
            self._kick(c, TOO_SLOW_CODE, TOO_SLOW)

    def _kick(self, c: LiveClient, code: int, reason: str) -> None:
        """Close ``c`` (its sender may be stuck on a full socket: cancelled first)."""
        if c.dropped:
            return
        c.dropped = True
        self.clients.discard(c)
        if c.sender is not None:
            c.sender.cancel()
        c.closer = asyncio.get_running_loop().create_task(_close(c, code, reason))

    # --- the WebSocket route -----------------------------------------------------------
    def install(self, app: web.Application) -> None:
        app.add_routes([web.get("/api/ws", self.handle)])
        app.on_startup.append(self._start)
        app.on_shutdown.append(self._shutdown)

    async def _start(self, app: web.Application) -> None:
        self._task = asyncio.get_running_loop().create_task(self.run(), name="hmi-live")

    async def _shutdown(self, app: web.Application) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        for c in list(self.clients):
            self._kick(c, WSCloseCode.GOING_AWAY, "supervisor stopping")
        # The handlers end when their sockets close; aiohttp waits for them.

    async def handle(
        self, request: web.Request, valid: Callable[[], bool] | None = None
    ) -> web.StreamResponse:
        """``GET /api/ws``: the snapshot, the alarms, then deltas and events until either
        side closes. (Authenticated before the upgrade by the login middleware.) Beyond
        ``max_clients`` screens: 503 before the upgrade (issue 27, finding 3)."""
        if self._admitted >= self.max_clients:
            self.refused += 1
            log.warning(
                "hmi: %d screens connected (hmi.max_websockets): one more refused",
                self._admitted,
            )
            reason = f"too many screens connected (hmi.max_websockets: {self.max_clients})"
            return web.json_response(
                {"accepted": False, "reason": reason}, status=503, headers={"Retry-After": "5"}
            )
        self._admitted += 1
        try:
            return await self._serve(request, valid)
        finally:
            self._admitted -= 1

    async def _serve(
        self, request: web.Request, valid: Callable[[], bool] | None
    ) -> web.StreamResponse:
        ws = web.WebSocketResponse(heartbeat=HEARTBEAT_S)
        await ws.prepare(request)
        found: Callable[[], bool] = request.get(VALID_KEY, _always)
        check = valid or found
        # One consistent image at one version, copied between two scans, encoded in
        # slices and shared by the pages that connect at that version.
        version, tags = await self.snapshots.image(as_map=True)
        snapshot = f'{{"type": "snapshot", "version": {version}, "tags": {tags}}}'
        client = LiveClient(ws, version, self.queue_size, check, request.transport)
        client.queue.put_nowait(snapshot)
        client.queue.put_nowait(self._alarms_text())
        self.clients.add(client)
        client.sender = asyncio.get_running_loop().create_task(client.send_loop())
        try:
            async for msg in ws:  # nothing expected from the page; read to see it close
                if msg.type is WSMsgType.ERROR:
                    break
        finally:
            self.clients.discard(client)
            if client.sender is not None:
                client.sender.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await client.sender
            if client.closer is not None:
                with contextlib.suppress(asyncio.CancelledError):
                    await client.closer
        return ws


def _changed(db: TagDB, since: int) -> list[Tag]:
    """``db.changed_since(since)``, the same tags in the same order (of their last change);
    when more changes were logged than there are tags (every tag changing every scan: 20
    scans of 1000 changes between two publications at 0.2 s), a pass over the tags is
    cheaper than the walk back through the log (0.08 ms against 0.5 ms on the bench's
    machine), and it is all on the scan's loop."""
    if db.version - since <= len(db):
        return db.changed_since(since)
    return sorted((t for t in db if t.version > since), key=_version_of)


def _version_of(tag: Tag) -> int:
    return tag.version


def _delta(version: int, tags: str) -> str:
    return f'{{"type": "delta", "version": {version}, "tags": {tags}}}'


async def _close(c: LiveClient, code: int, reason: str) -> None:
    try:
        async with asyncio.timeout(CLOSE_TIMEOUT_S):
            await c.ws.close(code=code, message=reason.encode())
    except TimeoutError:
        if c.transport is not None:
            c.transport.abort()  # its buffers full: drop what it never read
    except (ConnectionError, RuntimeError):
        pass  # already gone


def _always() -> bool:
    return True


def _declare(db: TagDB, name: str, description: str) -> Tag:
    tag = db.get(name) or db.add(TagSpec(name, dtype="int", description=description))
    db.update(tag, 0)
    return tag
