"""The notifier: alarm and test-end events in, messages out, never in the scan's way.

The scan's side is two cheap calls: the alarm model's and the step chains' listeners
append a ``Notice`` to an in-memory inbox (a deque append), and ``on_scan`` (a publisher
at scan end) copies the counts the task last computed into the ``notify.*`` tags and
raises or clears ``notify.failing``. Everything else — routing, the SQLite queue, SMTP and
HTTP — runs in the notifier's asyncio task, the disk and SMTP in worker threads
(``pump``). A route that fails holds its own messages only (each route has its backoff).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sqlite3
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import aiohttp

from supervisor.chains.states import FINAL
from supervisor.config.notifications import NotificationsConfig
from supervisor.core.clock import Clock
from supervisor.core.driver import Value
from supervisor.core.records import ChainEvent
from supervisor.notify.delivery import Sender, sender_of
from supervisor.notify.router import Notice, Outgoing, Router, message_key
from supervisor.notify.store import Counts, NotifyStore, Queued, notify_path
from supervisor.safety.alarms import Alarm, AlarmEvent, AlarmManager, Severity, Transition
from supervisor.tags import Tag, TagDB, TagSpec

__all__ = ["ALARM_FAILING", "POLL_S", "Notifier", "send_test"]

log = logging.getLogger(__name__)

ALARM_FAILING: Final = "notify.failing"
POLL_S: Final = 0.1
"""How often the task looks at its inbox and its queue (real clock)."""
STOP_SEND_S: Final = 3.0
"""A clean stop sends what is due for at most this long; the rest stays queued."""

_STATUS_TAGS: Final = (
    TagSpec("notify.queued", "int", description="Notifications waiting to be delivered"),
    TagSpec("notify.retrying", "int", description="Waiting after at least one failed attempt"),
    TagSpec("notify.sent", "int", description="Notifications delivered (the queue's total)"),
    TagSpec("notify.failed", "int", description="Failed delivery attempts since the start"),
    TagSpec("notify.last_error", "str", initial="", description="The last failure ('' if none)"),
)


_INITIAL: Final[dict[str, Value]] = {"int": 0, "bool": False, "str": ""}


def _route_tags(routes: list[str]) -> list[TagSpec]:
    """Per route: its waiting messages and whether it is failing (``notify.failing``'s rule)."""
    specs: list[TagSpec] = []
    for r in routes:
        specs.append(TagSpec(f"notify.route.{r}.queued", "int", description=f"Waiting on {r}"))
        specs.append(
            TagSpec(f"notify.route.{r}.failing", "bool", description=f"Route {r} keeps failing")
        )
    return specs


@dataclass
class _RouteHealth:
    failures: int = 0  # consecutive failed attempts
    since: float | None = None  # wall time of the first of them
    blocked_until: float = 0.0  # the route's next attempt (backoff)
    error: str = ""


@dataclass
class _Status:
    counts: Counts = field(default_factory=lambda: Counts(0, 0, 0, None))
    failed: int = 0
    last_error: str = ""
    failing: str = ""  # the alarm's message; "" when no route is failing
    failing_routes: frozenset[str] = frozenset()


class Notifier:
    """One bench's notifications (``supervisor.notify``'s docstring)."""

    name = "notify"

    def __init__(
        self,
        cfg: NotificationsConfig,
        bench: str,
        clock: Clock,
        state_dir: str | Path,
        *,
        db: TagDB | None = None,
        alarms: AlarmManager | None = None,
        senders: Mapping[str, Sender] | None = None,
    ) -> None:
        self.cfg = cfg
        self.bench = bench
        self.clock = clock
        self.router = Router(bench, cfg.routes, cfg.zone())
        self.store = NotifyStore(notify_path(state_dir))
        self._session: aiohttp.ClientSession | None = None
        self.senders: dict[str, Sender] = dict(senders or {})
        for r in cfg.routes:
            if r.name not in self.senders:
                self.senders[r.name] = sender_of(r, bench, self._http)
        self.inbox: deque[Notice] = deque()
        self._kept: set[str] = set()
        """The identities of the events the queue keeps for the router (``store.keep``)."""
        self._due_at: float | None = None
        """When the queue's next message is due (None: nothing waits)."""
        self._unqueued: list[Outgoing] = []
        self._queue_error = ""
        """Messages the queue could not take yet (a disk error): tried again each round."""
        self.health = {r.name: _RouteHealth() for r in cfg.routes}
        self.status = _Status()
        self._shown: tuple[object, ...] = ()
        self._tags: dict[str, Tag] = {}
        if db is not None:
            for spec in (*_STATUS_TAGS, *_route_tags([r.name for r in cfg.routes])):
                tag = self._tags[spec.name] = db.get(spec.name) or db.add(spec)
                db.update(tag, _INITIAL[spec.dtype])  # never None, before the first scan too
        self._alarms = alarms
        self._failing: Alarm | None = None
        if alarms is not None:
            self._failing = alarms.declare(ALARM_FAILING, severity=Severity.MEDIUM)
        self._task: asyncio.Task[None] | None = None
        self._stop = asyncio.Event()

    # --- the scan's side (cheap, never waits) -----------------------------------------
    def on_alarm(self, ev: AlarmEvent) -> None:
        if ev.transition is Transition.ACTIVATED:
            kind = "alarm"
        elif ev.transition is Transition.ACKNOWLEDGED:
            kind = "ack"
        else:
            return
        priority = Severity(ev.severity).name.lower()
        self.inbox.append(Notice(ev.wall, kind, ev.alarm_id, ev.group, priority, ev.message))

    def chain_listener(self, channel: str) -> Callable[[ChainEvent], None]:
        """A step chain's listener: its test's end (Complete, Stopped, Aborted)."""
        ends = tuple(f"→ {s.value}" for s in FINAL)

        def on_chain(ev: ChainEvent) -> None:
            if ev.kind == "state" and not ev.echo and any(e in ev.text for e in ends):
                self.inbox.append(Notice(ev.wall, "test_end", channel, channel, "low", ev.text))

        return on_chain

    def on_scan(self, db: TagDB, t: float) -> None:
        """At scan end: the counts into the tags, the alarm raised or cleared."""
        s = self.status
        shown = (s.counts, s.failed, s.last_error, s.failing, s.failing_routes)
        if shown == self._shown:
            return
        self._shown = shown
        if self._tags:
            tags = self._tags
            db.update(tags["notify.queued"], s.counts.queued)
            db.update(tags["notify.retrying"], s.counts.retrying)
            db.update(tags["notify.sent"], s.counts.sent)
            db.update(tags["notify.failed"], s.failed)
            db.update(tags["notify.last_error"], s.last_error)
            queued = dict(s.counts.queued_by_route)
            for r in self.cfg.routes:
                db.update(tags[f"notify.route.{r.name}.queued"], queued.get(r.name, 0))
                db.update(tags[f"notify.route.{r.name}.failing"], r.name in s.failing_routes)
        if self._alarms is not None and self._failing is not None:
            self._alarms.set(self._failing, bool(s.failing), s.failing)

    # --- life (real clock) --------------------------------------------------------------
    async def start(self) -> None:
        """Open the queue (a restart resumes what it holds) and start the task."""
        await asyncio.to_thread(self.store.open)
        counts = await asyncio.to_thread(self.store.counts)
        self.status.counts = counts
        self._due_at = await asyncio.to_thread(self.store.next_at)
        kept = await asyncio.to_thread(self.store.kept)
        for n in kept:  # an open window, quiet hours, escalations: as they were
            self.router.offer(n)
        self._kept = {n.identity() for n in kept}
        if kept:
            log.info("notifications: %d events of the last run routed again", len(kept))
        if counts.queued:
            log.info(
                "notifications %s: %d messages waiting from the last run; sending them",
                self.store.path,
                counts.queued,
            )
        if self._task is None and not self.clock.virtual:
            self._stop.clear()
            self._task = asyncio.create_task(self._run(), name="notifier")

    async def stop(self) -> None:
        """Every notice routed and queued (flood windows closed early), what is due sent
        for at most ``STOP_SEND_S``, the queue closed; what is left waits for the next run."""
        if self._task is not None:
            self._stop.set()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None
        try:
            await self.pump(self.clock.wall(), flush=True, budget_s=STOP_SEND_S)
        except Exception:
            log.exception("notifications: last delivery at stop failed")
        if self._session is not None:
            await self._session.close()
            self._session = None
        await asyncio.to_thread(self.store.close)

    async def _run(self) -> None:
        while not self._stop.is_set():
            try:
                await self.pump(self.clock.wall())
            except Exception:  # the disk, a bug: logged, tried again; the scan goes on
                log.exception("notifications: delivery round failed")
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), POLL_S)

    def _http(self) -> aiohttp.ClientSession:
        if self._session is None:
            self._session = aiohttp.ClientSession()
        return self._session

    # --- one round ----------------------------------------------------------------------
    async def pump(
        self, wall: float, *, flush: bool = False, budget_s: float | None = None
    ) -> None:
        """Route the inbox, queue what is due (with ``flush``: every open window), deliver
        what the queue holds that is due at ``wall``."""
        new: list[Notice] = []
        while self.inbox:
            new.append(self.inbox.popleft())
        await self._keep([n for n in new if n.kind != "ack"])  # before routing: a kill loses none
        for n in new:
            self.router.offer(n)
        out = self._unqueued + (self.router.flush() if flush else self.router.due(wall))
        released = self._kept - self.router.held()
        if out or released:
            await self._enqueue(out, wall, released)
        # The queue is read only when something in it is due (idle: no disk at all).
        if budget_s is not None or (self._due_at is not None and wall >= self._due_at):
            due = await asyncio.to_thread(self.store.due, wall)
            if due:
                await self._deliver(due, wall, budget_s)
            self._due_at = await asyncio.to_thread(self.store.next_at)
            self.status.counts = await asyncio.to_thread(self.store.counts)
        self._check_failing(wall)

    async def _keep(self, notices: list[Notice]) -> None:
        if not notices:
            return
        try:
            await asyncio.to_thread(self.store.keep, notices)
        except sqlite3.Error as exc:  # routed all the same; only a kill would lose them
            self._queue_failed(f"events not kept: {exc}")
            return
        self._kept.update(n.identity() for n in notices)

    async def _enqueue(self, out: list[Outgoing], wall: float, released: set[str]) -> None:
        try:
            new = await asyncio.to_thread(self.store.enqueue, out, wall, released)
        except sqlite3.Error as exc:  # kept in memory, tried again next round: never dropped
            self._unqueued = out
            self._queue_failed(f"{len(out)} messages not queued: {exc}")
            return
        self._unqueued = []
        self._kept -= released
        if out:
            self._due_at = wall
        for m in out:
            log.info(
                "notification %s queued on route %s: %s (%d events, %s)",
                m.key,
                m.route,
                m.subject,
                len(m.notices),
                m.kind,
            )
        if new < len(out):
            log.info("notifications: %d already queued (same key)", len(out) - new)

    async def _deliver(self, due: list[Queued], wall: float, budget_s: float | None) -> None:
        by_route: dict[str, list[Queued]] = {}
        for q in due:
            if self.health[q.message.route].blocked_until <= wall or budget_s is not None:
                by_route.setdefault(q.message.route, []).append(q)
        rounds = [self._route_round(route, qs) for route, qs in by_route.items()]
        if budget_s is None:
            await asyncio.gather(*rounds)
        else:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.gather(*rounds), budget_s)

    async def _route_round(self, route: str, queued: list[Queued]) -> None:
        """Oldest first; the first failure stops the route's round (its backoff)."""
        health = self.health[route]
        for q in queued:
            m = q.message
            started = time.monotonic()
            try:
                await self.senders[route](m)
            except Exception as exc:
                why = str(exc) or type(exc).__name__
                await self._failed(route, q, why)
                return
            await asyncio.to_thread(self.store.sent, m.key, self.clock.wall())
            log.info(
                "notification %s sent on route %s (attempt %d, %.2f s): %s",
                m.key,
                route,
                q.attempts + 1,
                time.monotonic() - started,
                m.subject,
            )
            if health.failures:
                log.warning("notification route %s delivers again", route)
            health.failures, health.since, health.error = 0, None, ""

    async def _failed(self, route: str, q: Queued, why: str) -> None:
        health = self.health[route]
        wall = self.clock.wall()
        attempts = q.attempts + 1
        wait_s = min(self.cfg.retry_max_s, self.cfg.retry_min_s * 2 ** min(attempts - 1, 30))
        health.failures += 1
        health.since = wall if health.since is None else health.since
        health.blocked_until = wall + wait_s
        health.error = why
        self.status.failed += 1
        self.status.last_error = f"{route}: {why}"
        await asyncio.to_thread(self.store.failed, q.message, why, wall + wait_s)
        log.warning(
            "notification %s on route %s not delivered (attempt %d): %s; next in %g s",
            q.message.key,
            route,
            attempts,
            why,
            wait_s,
        )

    def _queue_failed(self, why: str) -> None:
        text = f"notification queue {self.store.path}: {why}"
        if self.status.last_error != text:
            log.error("%s; retrying", text)
        self.status.last_error = text
        self._queue_error = text

    def _check_failing(self, wall: float) -> None:
        routes = frozenset(
            name
            for name, h in self.health.items()
            if h.failures >= self.cfg.failing_after_attempts
            or (h.since is not None and wall - h.since >= self.cfg.failing_after_s)
        )
        self.status.failing_routes = routes
        failing = [
            f"{name} ({h.failures} attempts: {h.error})"
            for name, h in self.health.items()
            if name in routes
        ]
        if self._queue_error and not self._unqueued:
            self._queue_error = ""  # written again
        if self._queue_error:
            failing.append(self._queue_error)
        text = ("Notifications not delivered: " + "; ".join(failing)) if failing else ""
        if text and not self.status.failing:
            log.error("%s (%d waiting)", text, self.status.counts.queued)
        self.status.failing = text


async def send_test(cfg: NotificationsConfig, bench: str, wall: float) -> dict[str, str | None]:
    """``supervisor notify test``: one test message through every route, now, without the
    queue; per route None (delivered) or why not."""
    results: dict[str, str | None] = {}
    async with aiohttp.ClientSession() as session:
        for r in cfg.routes:
            n = Notice(wall, "test", "notify.test", "", "low", "test message")
            m = Outgoing(
                r.name,
                message_key(bench, r.name, "test", [n]),
                "test",
                "low",
                f"[{bench}] test message of route {r.name}",
                f"A test of the notification route {r.name} of bench {bench}: if you read"
                " this, it works.",
                (n,),
            )
            try:
                await sender_of(r, bench, lambda: session)(m)
            except Exception as exc:
                results[r.name] = str(exc) or type(exc).__name__
            else:
                results[r.name] = None
    return results
