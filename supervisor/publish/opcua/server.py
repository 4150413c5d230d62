"""The OPC UA server of a bench (docs/adr/0014-opcua-server.md).

It runs on **its own thread with its own event loop** (measured: with 10 subscribed clients
asyncua's publishing work in the bench's loop delays scans by up to hundreds of
milliseconds; in a thread the scan waits at most the interpreter's switch interval for the
GIL). The bench and the server meet in three places only:

- the scan's publisher (``OpcUaFeed``): changed tags and events into bounded queues, the
  server woken, never awaited;
- method calls and writes: handed to the bench's loop (``call_soon_threadsafe``) and run
  there between two scans, through the one command path (``Operate``), as the HTTP API's
  commands are;
- start and stop, awaited by the bench's loop (``start`` raises ``OSError`` when the port is
  taken, as the HTTP API does).

``threaded=False`` runs the same server on the bench's own loop (what ``supervisor bench
opcua --same-loop`` measures against).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import dataclasses
import gc
import logging
import threading
from collections.abc import Awaitable, Callable, Sequence
from datetime import UTC, datetime
from typing import Any, Final, TypeVar

from asyncua import Server, ua
from asyncua.crypto.permission_rules import User as UaUser
from asyncua.crypto.permission_rules import UserRole
from asyncua.server.address_space import AttributeService

from supervisor.config.limits import RECIPE_COMPILE_TIMEOUT_S
from supervisor.config.users import ROLE_ACCESS, UserStore
from supervisor.core.clock import Clock
from supervisor.core.gate import ScanGate
from supervisor.core.logins import LoginThrottle
from supervisor.core.loops import await_thread_end, run_gated
from supervisor.core.quality import Quality
from supervisor.core.records import BenchEvent
from supervisor.publish.historian import HistoryQuery
from supervisor.publish.opcua import methods
from supervisor.publish.opcua.events import EventPublisher
from supervisor.publish.opcua.feed import AlarmView, OpcUaFeed, Update
from supervisor.publish.opcua.history import PAGE, HistoryService, HistorySpace, list_aggregates
from supervisor.publish.opcua.layout import Layout
from supervisor.publish.opcua.monitoring import serve_subscriptions
from supervisor.publish.opcua.nameplate import add_identification, fill_server_object
from supervisor.publish.opcua.objecttypes import condition_values
from supervisor.publish.opcua.ports import Answer, Operate, Request
from supervisor.publish.opcua.security import (
    PasswordUsers,
    Pki,
    SessionRules,
    TrustList,
    actor_of,
    current_user,
)
from supervisor.publish.opcua.sessions import BenchServer
from supervisor.publish.opcua.settings import OpcUaSettings
from supervisor.publish.opcua.shelf import ensure_shelf
from supervisor.publish.opcua.space import Built, build_space
from supervisor.publish.opcua.statuses import NO_VALUE, quality_status, refusal_status
from supervisor.publish.opcua.timestamps import Freshness
from supervisor.publish.opcua.timestamps import read as read_timestamps
from supervisor.tags import Access, TagDB

log = logging.getLogger(__name__)

S = ua.StatusCodes
VT = ua.VariantType
T = TypeVar("T")

WRITE_CHUNK: Final = 200
"""Values written between two yields to the server's loop: the publish task (which sends
notifications to the clients) runs at least every chunk (about 7 ms at 35 µs per write with
a subscriber, ecosystem.md)."""
BENCH_CALL_TIMEOUT_S: Final = 10.0
"""A method call or write waits this long at most for the bench's loop."""
STOP_TIMEOUT_S: Final = 10.0

POLICIES: Final = {
    "none": ua.SecurityPolicyType.NoSecurity,
    "sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
    "sign_and_encrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
}


class OpcUaServer:
    """Serves a bench over OPC UA; ``start`` before the scan runs, ``stop`` after it."""

    def __init__(
        self,
        settings: OpcUaSettings,
        db: TagDB,
        clock: Clock,
        layout: Layout,
        feed: OpcUaFeed,
        operate: Operate,
        users: UserStore,
        alarms: Callable[[], Sequence[AlarmView]] = tuple,
        *,
        threaded: bool = True,
        history: HistoryQuery | None = None,
        gate: ScanGate | None = None,
        throttle: LoginThrottle | None = None,
    ) -> None:
        self.settings = settings
        self.throttle = throttle or LoginThrottle(clock.now)
        """Failed logins, counted with the HMI's (``supervisor.core.logins``)."""
        self.on_login: Callable[[str, str, str], None] | None = None
        """Told each password login's outcome (the bench's audit trail; set before start)."""
        self.gate = gate
        """On its own thread: each turn of its event loop waits while a scan runs."""
        self.history = history
        self.db = db
        self.clock = clock
        self.layout = layout
        self.feed = feed
        feed.sampling_interval_s = settings.sampling_interval_s
        self.operate = operate
        self.users = users
        self.alarms = alarms
        self.threaded = threaded
        self.endpoint = settings.endpoint
        self.namespace = layout.uri
        self.written = 0  # values written into the address space since start
        self._closing = False
        self._frozen = False
        self._busy = False
        self._server: Server | None = None
        self._built = Built()
        self._events: EventPublisher | None = None
        self._by_index: dict[int, tuple[ua.NodeId, str]] = {}
        self._by_node: dict[ua.NodeId, str] = {}
        self.fresh = Freshness(self._by_node)
        """A tag's ServerTimestamp: when the scan last handed over (timestamps.py)."""
        self._bench_loop: asyncio.AbstractEventLoop | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._task: asyncio.Task[None] | None = None
        self._done: concurrent.futures.Future[None] | None = None

    # --- the bench's side ------------------------------------------------------------------
    async def start(self) -> None:
        """Build the address space, listen, and serve until ``stop``. Raises ``OSError`` when
        the endpoint cannot be bound and ``ConfigError`` for a bad users file."""
        self._bench_loop = asyncio.get_running_loop()
        ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._done = concurrent.futures.Future()
        if self.threaded:
            self._thread = threading.Thread(
                target=self._thread_main, args=(ready,), name="opcua-server", daemon=True
            )
            self._thread.start()
        else:
            self._task = asyncio.create_task(self._main(ready), name="opcua-server")
        try:
            await asyncio.wrap_future(ready)
        except BaseException:
            await self._wait_done()
            raise
        # The address space is tens of thousands of objects that live as long as the server;
        # a full garbage collection walking them stopped every thread for 470 ms with 20
        # clients connecting (measured, ADR 0014): the scan missed its deadlines. Collected
        # once now, before the first scan, then kept out of the collector's way.
        gc.collect()
        gc.freeze()
        self._frozen = True
        log.info("OPC UA server listening on %s (namespace %s)", self.endpoint, self.namespace)

    @property
    def idle(self) -> bool:
        """Nothing waits to be written or sent (what tests and benchmarks wait for)."""
        return not self._busy and self.feed.empty()

    def closing(self) -> None:
        """Refuse commands from now on (the bench is going to its safe state)."""
        self._closing = True

    async def stop(self) -> None:
        self._closing = True
        if self._frozen:
            gc.unfreeze()  # what the server leaves behind may be collected again
            self._frozen = False
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop already ended
                loop.call_soon_threadsafe(stop.set)
        await self._wait_done()

    async def _wait_done(self) -> None:
        await await_thread_end(self._done, self._thread, STOP_TIMEOUT_S, "OPC UA server")
        self._thread = None
        self._task = None

    async def _call_bench(self, fn: Callable[[], T]) -> T:
        """Run ``fn`` on the bench's loop (between two scans) and return what it returns."""
        bench = self._bench_loop
        assert bench is not None
        if not self.threaded:
            return fn()
        fut: concurrent.futures.Future[T] = concurrent.futures.Future()

        def run() -> None:
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn())
                except BaseException as exc:
                    fut.set_exception(exc)

        bench.call_soon_threadsafe(run)
        return await asyncio.wait_for(asyncio.wrap_future(fut), BENCH_CALL_TIMEOUT_S)

    async def _call_bench_async(self, fn: Callable[[], Awaitable[T]]) -> T:
        """Await ``fn()`` on the bench's loop: a command that loads a recipe compiles it in a
        worker thread there (the command path's time limit, plus a margin, bounds the wait)."""
        bench = self._bench_loop
        assert bench is not None
        if not self.threaded:
            return await fn()

        async def run() -> T:
            return await fn()

        fut = asyncio.run_coroutine_threadsafe(run(), bench)
        limit_s = max(BENCH_CALL_TIMEOUT_S, RECIPE_COMPILE_TIMEOUT_S + BENCH_CALL_TIMEOUT_S)
        return await asyncio.wait_for(asyncio.wrap_future(fut), limit_s)

    # --- the server's thread -----------------------------------------------------------------
    def _thread_main(self, ready: concurrent.futures.Future[None]) -> None:
        run_gated(self._main(ready), ready, self.gate, "OPC UA server")

    async def _main(self, ready: concurrent.futures.Future[None]) -> None:
        assert self._done is not None
        try:
            await self._serve(ready)
        except BaseException as exc:
            if not ready.done():
                ready.set_exception(exc)
            elif not isinstance(exc, asyncio.CancelledError):
                log.exception("OPC UA server failed")
        finally:
            self.feed.stop()
            self._loop = None
            if not self._done.done():
                self._done.set_result(None)

    async def _serve(self, ready: concurrent.futures.Future[None]) -> None:
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._stop = asyncio.Event()
        server = await self._setup()
        pump = asyncio.create_task(self._pump(), name="opcua-pump")
        try:
            ready.set_result(None)
            await self._stop.wait()
        finally:
            pump.cancel()
            await asyncio.gather(pump, return_exceptions=True)
            self.feed.stop()
            # asyncua's clock task sleeps 1 s between updates and its stop waits for it.
            clock_task = getattr(server.iserver, "time_task", None)
            if clock_task is not None:
                clock_task.cancel()
                await asyncio.gather(clock_task, return_exceptions=True)
                server.iserver.time_task = None
            await server.stop()
            log.info("OPC UA server stopped")

    async def _setup(self) -> Server:
        s = self.settings
        if logging.getLogger("asyncua").level == logging.NOTSET:
            # asyncua logs every request at INFO; the bench's own log says what matters.
            logging.getLogger("asyncua").setLevel(logging.WARNING)
        # asyncua's server, but no password in clear and each request run as the session
        # whose token it carries (``sessions.py``).
        users = PasswordUsers(self.users, s.anonymous, self.throttle, self.on_login)
        server = BenchServer(user_manager=users)
        # Deadbands and TimestampsToReturn on monitored items (monitoring.py), before
        # ``init`` binds the condition methods to the subscription service it finds.
        serve_subscriptions(server.iserver, self.fresh.stamp)
        # asyncua's RefreshStart/RefreshEnd events (ConditionRefresh is ours: events.py).
        server.iserver.bind_condition_methods = True
        # Issue 27, finding 3: a flood of clients must not take the descriptors the devices
        # need. asyncua closes a connection beyond its cap at once, and one that has not
        # activated a session in time (an idle socket, a stalled handshake).
        server.iserver.max_connections = s.max_connections
        server.iserver.max_pending_activation_seconds = s.activation_timeout_s
        self._server = server
        # The standard address space from the machine's shared shelf: its nodes are read
        # when first asked for instead of all kept in memory (ADR 0020; None: in memory).
        await server.init(shelf_file=await ensure_shelf())
        server.set_endpoint(self.endpoint)
        server.set_server_name(f"bench-supervisor {s.bench}")
        server.allow_remote_admin(False)
        await server.set_application_uri(self.namespace)
        server.product_uri = "urn:bench-supervisor"
        await self._secure(server)
        idx = await server.register_namespace(self.namespace)
        built = await build_space(
            server, idx, self.layout, s.sampling_interval_s or s.scan_period_s, self._historised()
        )
        self._built = built
        await self._describe(server, built)
        await self._serve_history(server, built, self.history)
        self._link_methods(server, built)
        await self._method_references(server, built)
        server.iserver.attribute_service = GuardedWrites(server.iserver.aspace, self)
        events = EventPublisher(server, built, s.bench)
        await events.init()
        self._events = events
        self._index_nodes(built)
        # First values: the whole tag database as it is, then changes as they come.
        wake_up = self._wake_up()
        first = await self._call_bench(lambda: self.feed.start(self.db, wake_up))
        await self._write(server, first)
        for a in await self._call_bench(lambda: list(self.alarms())):
            await self._alarm(a)
        # A port already taken is the caller's to report, in one line (asyncua would log
        # its traceback first).
        quiet = logging.getLogger("asyncua.server.server")
        level = quiet.level
        quiet.setLevel(logging.CRITICAL)
        try:
            await server.start()
        finally:
            quiet.setLevel(level)
        return server

    def _index_nodes(self, built: Built) -> None:
        """Each tag's node by the tag's index (what the feed's updates carry), and each
        node's tag."""
        index_of = {t.name: t.index for t in self.db}
        for name, (nid, kind) in built.tags.items():
            self._by_index[index_of[name]] = (nid, kind)
            self._by_node[nid] = name

    def _wake_up(self) -> Callable[[], None]:
        """How the feed wakes the pump when a scan has changes (called on the scan's
        thread): at once on the server's own loop when it shares the scan's, else from the
        other thread, once the scan is done when there is a scan gate."""
        loop = asyncio.get_running_loop()
        wake = self._wake
        assert wake is not None

        def signal() -> None:
            with contextlib.suppress(RuntimeError):  # the server's loop has ended
                loop.call_soon_threadsafe(wake.set)

        gate = self.gate

        def wake_up() -> None:
            if not self.threaded:
                wake.set()
            elif gate is not None:
                gate.after_scan(signal)  # the pipe write once the scan is done
            else:
                signal()

        return wake_up

    async def _secure(self, server: Server) -> None:
        """Who may connect and how: the identity tokens, the security policies, and the
        server's certificate (with a trust list when a policy signs or encrypts)."""
        s = self.settings
        tokens: list[type] = [ua.UserNameIdentityToken]
        if s.anonymous:
            tokens.insert(0, ua.AnonymousIdentityToken)
        server.set_identity_tokens(tokens)
        server.set_security_policy(
            [POLICIES[p] for p in s.security], permission_ruleset=SessionRules()
        )
        # The server's certificate even with only the None policy: a password is encrypted
        # with it on every endpoint that does not encrypt the channel (issue 27).
        pki = Pki(s.pki_dir)
        await pki.ensure(self.namespace, s.bench)
        await server.load_certificate(pki.cert)
        await server.load_private_key(pki.key)
        if any(p != "none" for p in s.security):
            server.set_certificate_validator(TrustList(pki))

    def _link_methods(self, server: Server, built: Built) -> None:
        """The handlers of the methods a client calls: the channels' and the bench's, and
        the alarm conditions' (Acknowledge, ConditionRefresh, Confirm, the shelving ones)."""
        for nid, (channel, m) in built.methods.items():
            server.iserver.isession.add_method_callback(nid, self._method_handler(channel, m))
        for method_ids, handler in (
            ((O.AcknowledgeableConditionType_Acknowledge,), self._acknowledge),
            ((O.ConditionType_ConditionRefresh,), self._condition_refresh(methods.REFRESH)),
            ((O.ConditionType_ConditionRefresh2,), self._condition_refresh(methods.REFRESH2)),
            (SHELVE_IDS, self._shelving("shelve")),
            (ONE_SHOT_IDS, self._shelving("one shot")),
            (UNSHELVE_IDS, self._shelving("unshelve")),
            ((O.AcknowledgeableConditionType_Confirm,), self._confirm),
        ):
            for mid in method_ids:
                server.link_method(server.get_node(ua.NodeId(mid)), handler)

    # --- values --------------------------------------------------------------------------
    async def _pump(self) -> None:
        server, wake = self._server, self._wake
        assert server is not None and wake is not None and self._events is not None
        while True:
            await wake.wait()
            wake.clear()
            self._busy = True
            await self._write(server, self.feed.take())
            for item in self.feed.take_events():
                try:
                    if isinstance(item, AlarmView):
                        await self._alarm(item)
                    else:
                        await self._bench_event(item)
                except Exception:
                    log.exception("OPC UA event %r not sent", item)
            bserver = getattr(server, "bserver", None)
            self.feed.clients = len(getattr(bserver, "clients", ()))
            self._busy = False

    async def _describe(self, server: Server, built: Built) -> None:
        """The Server object filled and the bench's Identification (nameplate.py)."""
        await fill_server_object(server, self.settings, history=self.history is not None, page=PAGE)
        await add_identification(server, self.settings, built.bench, self.namespace)

    def _historised(self) -> frozenset[str]:
        """The tags the historian keeps (none without one): each tag's history settings."""
        if self.history is None:
            return frozenset()
        names = (t.name for t in self.db if t.spec.history.enabled)
        variables = self.layout.variables
        # A state machine's CurrentState (its PackML name) has its history in its Number.
        return frozenset(n for n in names if n in variables and variables[n].kind != "statename")

    async def _serve_history(
        self, server: Server, built: Built, query: HistoryQuery | None
    ) -> None:
        """HistoryRead answered from the historian's file (history.py), not asyncua's own;
        without a historian every node answers Bad_HistoryOperationUnsupported."""
        historised = self._historised()
        space = HistorySpace(
            tags={
                nid: (name, kind) for name, (nid, kind) in built.tags.items() if name in historised
            },
            event_sources={}
            if query is None
            else {built.bench: None, **{nid: ch for ch, nid in built.channels.items()}},
            event_types={
                # The type each kind has when it is notified live (events.py).
                "step": built.chain_event,
                "state": built.chain_event,
                "message": built.chain_event,
                "command": built.command_event,
                "alarm": ua.NodeId(ua.ObjectIds.AlarmConditionType),
            },
            supertypes={
                built.chain_event: (built.bench_event,),
                built.command_event: (built.bench_event,),
                ua.NodeId(ua.ObjectIds.AlarmConditionType): tuple(
                    ua.NodeId(t)
                    for t in (
                        ua.ObjectIds.AcknowledgeableConditionType,
                        ua.ObjectIds.ConditionType,
                    )
                ),
            },
            conditions=dict(built.alarms),
        )
        server.iserver.history_manager = HistoryService(server.iserver, query, space, _variant)
        if query is not None:  # the aggregates HistoryRead then serves, listed (finding 7)
            await list_aggregates(server)

    async def _write(self, server: Server, updates: list[Update]) -> None:
        aspace = server.iserver.aspace
        gate = self.gate
        for n, u in enumerate(updates, 1):
            target = self._by_index.get(u.tag_index)
            if target is None:
                continue  # declared after the server started
            if gate is not None:
                # Between two writes, not only at the loop's selects: a batch of a few
                # hundred writes (each with its subscriptions' notifications) held the
                # interpreter lock for milliseconds, against the scan (ADR 0021).
                gate.wait()
            nid, kind = target
            if kind == "statename":
                continue  # CurrentState: shown by its state's number (below)
            dv = self._value(u, kind)
            await aspace.write_attribute_value(nid, ua.AttributeIds.Value, dv)
            self.written += 1
            machine = self._built.state_machines.get(nid) if kind == "state" else None
            if machine is not None:  # the state's name and Id follow its number
                for other, odv in machine.derived(dv):
                    await aspace.write_attribute_value(other, ua.AttributeIds.Value, odv)
            if n % WRITE_CHUNK == 0:
                await asyncio.sleep(0)  # let the publish task send notifications
        self._heard(updates)

    def _heard(self, updates: list[Update]) -> None:
        """The scan's changes are in: every tag is known current as of the latest of them
        (a hand-over carries the scan's counters, which change every scan)."""
        latest = max((u.server_t for u in updates), default=0.0)
        if latest > 0.0 or (updates and self.clock.virtual):
            self.fresh.heard(_utc(self.clock.to_wall(latest)))

    def _value(self, u: Update, kind: str) -> ua.DataValue:
        clock = self.clock
        if u.server_t <= 0.0 and not clock.virtual:
            # Set before the first scan (TagDB's scan time is still 0): no time to tell.
            server_t = source_t = None
        else:
            server_t = _utc(clock.to_wall(u.server_t))
            source_t = _utc(clock.to_wall(u.source_t))
        status = None
        variant = ua.Variant(None)
        if u.quality is Quality.BAD:
            status = quality_status(u.quality, u.reason)
        elif u.value is None:
            status = NO_VALUE
        else:
            try:
                variant = _variant(u.value, kind)
            except (TypeError, ValueError):
                status = S.BadConfigurationError  # a tag holding the wrong type: a bug
            else:
                status = quality_status(u.quality, u.reason)
        return ua.DataValue(
            variant,
            StatusCode=ua.StatusCode(status),
            SourceTimestamp=source_t,
            ServerTimestamp=server_t,
        )

    # --- events --------------------------------------------------------------------------
    def on_event(self, event: BenchEvent) -> None:
        """An ``EventSink`` (supervisor.app.events.EventFeed): queued, never awaited."""
        self.feed.on_event(event)

    def on_alarm(self, alarm: AlarmView) -> None:
        self.feed.on_alarm(alarm)

    async def _bench_event(self, ev: BenchEvent) -> None:
        assert self._events is not None
        await self._events.bench_event(ev)

    async def _alarm(self, a: AlarmView) -> None:
        assert self._events is not None and self._server is not None
        aspace = self._server.iserver.aspace
        fields = self._built.alarm_fields
        values = {
            "State": ua.Variant(a.state, VT.String),
            "Active": ua.Variant(a.active, VT.Boolean),
            "Acked": ua.Variant(a.acked, VT.Boolean),
            "Severity": ua.Variant(max(0, min(1000, a.severity)), VT.UInt16),
            "Message": ua.Variant(a.message, VT.String),
            "Tripped": ua.Variant(a.tripped, VT.Boolean),
            "Shelved": ua.Variant(a.shelved, VT.Boolean),
        }
        values |= condition_values(  # the condition's standard variables (Part 9)
            a.active, a.acked, a.retained, a.shelved, a.id, a.severity, a.actor
        )
        when = _utc(a.wall) if a.wall else datetime.now(UTC)
        for name, variant in values.items():
            nid = fields.get((a.id, name))
            if nid is not None:
                dv = ua.DataValue(variant, SourceTimestamp=when, ServerTimestamp=when)
                await aspace.write_attribute_value(nid, ua.AttributeIds.Value, dv)
        if a.id in self._built.alarms and (a.transition or a.retained):
            await self._events.alarm(a)

    # --- methods -------------------------------------------------------------------------
    def _method_handler(self, channel: str, method: methods.Method) -> Callable[..., Any]:
        owner = self._built.channels.get(channel, self._built.bench)

        async def handler(parent: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
            actor = actor_of(current_user())
            wrong = methods.not_on(method, parent, owner)
            if wrong is not None:
                log.warning("OPC UA call by %s refused: %s", actor, wrong.reason)
                return _result(wrong.status, wrong.reason, len(args))
            if self._closing:
                return _result(S.BadShutdown, "the supervisor is stopping", len(args))
            bad = methods.check(method, args)
            if bad is None and method.verb in ("force", "unforce"):
                return await self._force(method, args, actor)
            req = methods.request(method, channel, args, actor) if bad is None else bad
            if isinstance(req, methods.Invalid):
                log.warning(
                    "OPC UA %s.%s by %s refused: %s", channel, method.name, actor, req.reason
                )
                return _result(req.status, req.reason, len(args), req.arg_results)
            answer = await self._ask(req)
            status = S.Good if answer.accepted else refusal_status(answer.refusal)
            return _result(status, answer.reason, len(args))

        return handler

    async def _force(
        self, method: methods.Method, args: Sequence[ua.Variant], actor: str
    ) -> ua.CallMethodResult:
        """ForceTag(Tag, Value) / UnforceTag(Tag) on the Bench object (ADR 0015): the value
        text read as the tag's type here (Bad_TypeMismatch), then the command path (role:
        Bad_UserAccessDenied, range or choices: Bad_OutOfRange, a tag the safety phase
        reads or drives: Bad_NotSupported, with the reason)."""
        n = len(args)
        name = str(args[0].Value)
        variable = self.layout.variables.get(name)
        if variable is None:
            return _result(S.BadNodeIdUnknown, f"{method.name}: unknown tag {name!r}", n)
        req = methods.request(method, "", args, actor)
        assert isinstance(req, Request)
        if method.verb == "force":
            text = str(args[1].Value)
            try:
                value = methods.parse_value(text, variable.kind)
            except ValueError:
                wants = methods.KIND_WORDS.get(variable.kind, variable.kind)
                reason = f"ForceTag: {name} takes {wants}, not {text!r}"
                log.warning("OPC UA ForceTag by %s refused: %s", actor, reason)
                return _result(S.BadTypeMismatch, reason, n, (S.Good, S.BadTypeMismatch))
            req = Request(req.kind, req.target, req.verb, {"tag": name, "value": value}, actor)
        answer = await self._ask(req)
        if answer.accepted:
            return _result(S.Good, answer.reason, n)
        status = {
            "bad argument": S.BadOutOfRange,  # the type was right: the value is not
            "not found": S.BadNodeIdUnknown,
            "refused": S.BadNotSupported,  # never forceable: the safety phase uses it
        }.get(answer.refusal) or refusal_status(answer.refusal)
        return _result(status, answer.reason, n)

    async def _acknowledge(self, parent: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
        """AcknowledgeableConditionType.Acknowledge(EventId, Comment) on an alarm's
        condition: the alarm model acknowledges it (through the command path)."""
        actor = actor_of(current_user())
        alarm = next((a for a, nid in self._built.alarms.items() if nid == parent), None)
        if alarm is None:
            return _not_a_condition(parent, len(args))
        if self._closing:
            return _result(S.BadShutdown, "the supervisor is stopping", len(args))
        refused = self._occurrence_refusal(alarm, methods.ACKNOWLEDGE, args, actor)
        if refused is not None:
            return refused
        answer = await self._ask(Request("alarm", alarm, "acknowledge", {}, actor))
        if answer.accepted:
            return _result(S.Good, answer.reason, len(args), out=False)
        # Part 9: acknowledging what is not waiting for it is Bad_ConditionBranchAlreadyAcked.
        status = (
            S.BadConditionBranchAlreadyAcked
            if answer.refusal == "refused" and "not waiting" in answer.reason
            else refusal_status(answer.refusal)
        )
        return _result(status, answer.reason, len(args), out=False)

    async def _method_references(self, server: Server, built: Built) -> None:
        """Each condition has Acknowledge and Confirm, each ShelvingState its three methods
        (the standard method nodes, referenced as instances share them), for browsing."""
        refs = []
        for alarm, cond in built.alarms.items():
            owned: list[tuple[ua.NodeId, int]] = [
                (cond, O.AcknowledgeableConditionType_Acknowledge),
                (cond, O.AcknowledgeableConditionType_Confirm),
            ]
            shelving = built.shelving.get(alarm)
            if shelving is not None:
                owned += [(shelving, m) for m in (*SHELVE_IDS[:1], *ONE_SHOT_IDS[:1])]
                owned.append((shelving, UNSHELVE_IDS[0]))
            for source, method in owned:
                ref = ua.AddReferencesItem()
                ref.IsForward = True
                ref.ReferenceTypeId = ua.NodeId(O.HasComponent)
                ref.SourceNodeId = source
                ref.TargetNodeClass = ua.NodeClass.Method
                ref.TargetNodeId = ua.NodeId(method)
                refs.append(ref)
        await server.iserver.isession.add_references(refs)

    def _alarm_of(self, parent: ua.NodeId) -> str | None:
        """The alarm whose condition (or ShelvingState) object ``parent`` is."""
        for alarm, nid in self._built.alarms.items():
            if nid == parent or self._built.shelving.get(alarm) == parent:
                return alarm
        return None

    def _shelving(self, what: str) -> Callable[..., Any]:
        """TimedShelve(ShelvingTime ms), OneShotShelve(), Unshelve() of Part 9's
        ShelvedStateMachineType, bound to the alarm model's shelve / unshelve (ADR 0015)."""

        async def handler(parent: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
            n = len(args)
            actor = actor_of(current_user())
            alarm = self._alarm_of(parent)
            if alarm is None:
                return _not_a_condition(parent, n)
            if self._closing:
                return _result(S.BadShutdown, "the supervisor is stopping", n, out=False)
            if what == "one shot":
                # ISA-18.2 shelving is for a time: a one-shot shelve (until it clears) would
                # hide a trip-worthy recurrence for ever; the alarm model has none.
                return _result(
                    S.BadNotSupported,
                    f"alarm {alarm}: OneShotShelve is not offered: shelve for a time"
                    " (TimedShelve, at most 7 days)",
                    n,
                )
            if what == "shelve":
                want = (VT.Double, VT.Float, VT.Int32, VT.UInt32, VT.Int64, VT.UInt64)
                if n != 1 or args[0].VariantType not in want or isinstance(args[0].Value, list):
                    status = S.BadArgumentsMissing if n == 0 else S.BadInvalidArgument
                    if n > 1:
                        status = S.BadTooManyArguments
                    return _result(status, "TimedShelve takes ShelvingTime (Duration, ms)", n)
                duration_s = float(args[0].Value) / 1000.0
                req = Request("alarm", alarm, "shelve", {"duration_s": duration_s}, actor)
            else:
                req = Request("alarm", alarm, "unshelve", {}, actor)
            answer = await self._ask(req)
            if answer.accepted:  # Part 9 declares no output: the reason only with a refusal
                return _result(S.Good, answer.reason, n, out=False)
            reason = answer.reason
            if answer.refusal != "refused":
                status = refusal_status(answer.refusal)
            elif "is a trip" in reason:
                status = S.BadNotSupported  # a trip protects its channel: never shelved
            elif "shelving lasts" in reason:
                status = S.BadShelvingTimeOutOfRange
            elif "is not shelved" in reason:
                status = S.BadConditionNotShelved
            else:
                status = S.BadInvalidState
            return _result(status, reason, n)

        return handler

    async def _confirm(self, parent: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
        """AcknowledgeableConditionType.Confirm(EventId, Comment): the reset of a latched
        trip whose cause is gone (ISA-18.2's reset is what Part 9 calls confirming that the
        condition was dealt with; ADR 0015)."""
        n = len(args)
        actor = actor_of(current_user())
        alarm = self._alarm_of(parent)
        if alarm is None:
            return _not_a_condition(parent, n)
        if self._closing:
            return _result(S.BadShutdown, "the supervisor is stopping", n, out=False)
        refused = self._occurrence_refusal(alarm, methods.CONFIRM, args, actor)
        if refused is not None:
            return refused
        answer = await self._ask(Request("alarm", alarm, "reset", {}, actor))
        if answer.accepted:
            return _result(S.Good, answer.reason, n, out=False)
        if answer.refusal == "refused" and "not a trip waiting" in answer.reason:
            status = S.BadConditionBranchAlreadyConfirmed
        else:
            status = refusal_status(answer.refusal)
        return _result(status, answer.reason, n)  # the reason as text, with the Bad code

    def _condition_refresh(self, method: methods.Method) -> Callable[..., Any]:
        """ConditionRefresh(SubscriptionId), ConditionRefresh2(SubscriptionId,
        MonitoredItemId): the alarm model's views now first (those the server has not sent:
        a closing event lost or still on its way), then the retained conditions replayed
        (events.py; issue 31, finding 8: never a closed one)."""

        async def handler(parent: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
            n = len(args)
            bad = methods.check(method, args)
            if bad is not None:
                return _result(bad.status, bad.reason, n, bad.arg_results, out=False)
            assert self._events is not None
            views = await self._call_bench(lambda: list(self.alarms()))
            for v in self._events.stale(views):
                await self._alarm(dataclasses.replace(v, transition=v.transition or "current"))
            ids = [int(a.Value) for a in args]
            status = await self._events.refresh(ids[0], ids[1] if n > 1 else None)
            return _result(status, "", n, out=False)

        return handler

    def _occurrence_refusal(
        self, alarm: str, method: methods.Method, args: Sequence[ua.Variant], actor: str
    ) -> ua.CallMethodResult | None:
        """Acknowledge and Confirm (EventId, Comment): the arguments' types, then whether the
        EventId names the condition's occurrence that waits (events.py; issue 31, finding 3).
        None: the call may go to the command path. A session that may not acknowledge is
        refused first, and learns nothing of the occurrences (the command path would refuse
        it the same way)."""
        access = self._access(current_user())
        if access is not None and access < Access.OPERATOR:
            reason = f"{method.name} of alarm {alarm}: {actor} may not ({access.name.lower()})"
            log.warning("OPC UA %s refused: %s", method.name, reason)
            return _result(S.BadUserAccessDenied, reason, len(args), out=False)
        bad = methods.check(method, args)
        if bad is None:
            assert self._events is not None
            found = self._events.refusal(
                self._built.alarms[alarm],
                args[0].Value,
                "acked" if method is methods.ACKNOWLEDGE else "confirmed",
            )
            if found is None:
                return None
            bad = methods.Invalid(found[0], f"{method.name} of alarm {alarm}: {found[1]}")
        log.warning("OPC UA %s by %s refused: %s", method.name, actor, bad.reason)
        return _result(bad.status, bad.reason, len(args), bad.arg_results, out=False)

    async def _ask(self, req: Request) -> Answer:
        try:
            return await self._call_bench_async(lambda: self.operate(req))
        except TimeoutError:
            return Answer(False, "the bench did not answer in time", "internal error")
        except Exception as exc:
            log.exception("OPC UA request %r failed", req)
            return Answer(False, f"internal error: {exc}", "internal error")

    # --- per-user access ------------------------------------------------------------------
    def _access(self, user: UaUser | None) -> Access | None:
        """The session's tag access (None: the server's own Admin session, unrestricted)."""
        if user is not None and user.role is UserRole.Admin:
            return None
        name = getattr(user, "name", None)
        # The users file's role now (it is read again when it changes), as the command
        # path's role hook sees it.
        role = (self.users.role_of(name) if name else None) or "viewer"
        return ROLE_ACCESS.get(role, Access.READ_ONLY)

    def user_access_level(self, nid: ua.NodeId, user: UaUser | None) -> int | None:
        """A tag variable's AccessLevel without CurrentWrite when the session's role may not
        write it (a viewer reads only; an operator writes operator tags, an engineer also
        engineer tags); None for any other node (asyncua's answer stands)."""
        name = self._by_node.get(nid)
        server = self._server
        if name is None or server is None:
            return None
        access = self._access(user)
        dv = server.iserver.aspace.read_attribute_value(nid, ua.AttributeIds.AccessLevel)
        level = int(dv.Value.Value) if dv.Value is not None and dv.Value.Value is not None else 0
        tag = self.db.get(name)
        needs = tag.spec.access if tag is not None else Access.READ_ONLY
        if access is not None and (needs is Access.READ_ONLY or access < needs):
            level &= ~ua.AccessLevel.CurrentWrite.mask
        return level

    def user_executable(self, nid: ua.NodeId, user: UaUser | None) -> bool | None:
        """A bench or channel method is executable for an operator (channel methods) or an
        engineer (also ForceTag / UnforceTag), never for a viewer; None for other nodes."""
        found = self._built.methods.get(nid)
        if found is None:
            return None
        access = self._access(user)
        if access is None:
            return True
        _, method = found
        needs = Access.ENGINEER if method.verb in ("force", "unforce") else Access.OPERATOR
        return access >= needs

    # --- writes --------------------------------------------------------------------------
    async def write_tag(self, wv: ua.WriteValue, user: UaUser) -> ua.StatusCode:
        """A client's write of a tag variable: type checked here, then the command path
        (role, range, choices, Manual vs Auto), with its actor."""
        name = self._by_node.get(wv.NodeId)
        if name is None:
            known = self._server is not None and wv.NodeId in self._server.iserver.aspace
            return ua.StatusCode(S.BadNotWritable if known else S.BadNodeIdUnknown)
        variable = self.layout.variables[name]
        if wv.AttributeId != ua.AttributeIds.Value or not variable.writable:
            return ua.StatusCode(S.BadNotWritable)
        if wv.IndexRange:
            return ua.StatusCode(S.BadWriteNotSupported)
        if self._closing:
            return ua.StatusCode(S.BadShutdown)
        variant = wv.Value.Value if wv.Value is not None else None
        value = variant.Value if variant is not None else None
        if variant is None or not _type_ok(variable.kind, variant):
            log.warning(
                "OPC UA write %s by %s refused: %s is not a %s",
                name,
                actor_of(user),
                variant.VariantType.name if variant is not None else "Null",
                variable.kind,
            )
            return ua.StatusCode(S.BadTypeMismatch)
        answer = await self._ask(
            Request("bench", "", "write", {"tag": name, "value": value}, actor_of(user))
        )
        if answer.accepted:
            return ua.StatusCode(S.Good)
        if answer.refusal == "bad argument":
            return ua.StatusCode(S.BadOutOfRange)  # the type was right: the value is not
        if answer.refusal == "forbidden" and not variable.writable:
            return ua.StatusCode(S.BadNotWritable)
        return ua.StatusCode(refusal_status(answer.refusal))


O = ua.ObjectIds  # noqa: E741 - asyncua's own abbreviation
SHELVE_IDS: Final = (
    O.ShelvedStateMachineType_TimedShelve,
    O.AlarmConditionType_ShelvingState_TimedShelve,
)
ONE_SHOT_IDS: Final = (
    O.ShelvedStateMachineType_OneShotShelve,
    O.AlarmConditionType_ShelvingState_OneShotShelve,
)
UNSHELVE_IDS: Final = (
    O.ShelvedStateMachineType_Unshelve,
    O.AlarmConditionType_ShelvingState_Unshelve,
)
"""Part 9's shelving methods: the type's own and AlarmConditionType's instance declaration
(clients call either on a condition's ShelvingState)."""

_ADMIN: Final = UaUser(role=UserRole.Admin)


class GuardedWrites(AttributeService):  # type: ignore[misc]
    """asyncua's attribute service with clients' writes routed through the command path
    (the server's own writes, by its internal Admin session, go straight in)."""

    def __init__(self, aspace: Any, owner: OpcUaServer) -> None:
        super().__init__(aspace)
        self.owner = owner

    def read(self, params: ua.ReadParameters) -> list[ua.DataValue]:
        """asyncua's read, with UserAccessLevel and UserExecutable answered for the session's
        role (its user is the request's, ``current_user``: the read runs on the request's
        task right after ``SessionRules`` saw it)."""
        results: list[ua.DataValue] = super().read(params)
        user = current_user()
        for i, rv in enumerate(params.NodesToRead):
            if rv.AttributeId == ua.AttributeIds.UserAccessLevel:
                level = self.owner.user_access_level(rv.NodeId, user)
                if level is not None:
                    results[i] = ua.DataValue(ua.Variant(level, VT.Byte))
            elif rv.AttributeId == ua.AttributeIds.UserExecutable:
                executable = self.owner.user_executable(rv.NodeId, user)
                if executable is not None:
                    results[i] = ua.DataValue(ua.Variant(executable, VT.Boolean))
        # The timestamps asked for, a tag's ServerTimestamp when it was last known current.
        return read_timestamps(params, results, self.owner.fresh)

    async def write(self, params: ua.WriteParameters, user: UaUser = _ADMIN) -> list[ua.StatusCode]:
        if user.role is UserRole.Admin:
            written: list[ua.StatusCode] = await super().write(params, user)
            return written
        return [await self.owner.write_tag(wv, user) for wv in params.NodesToWrite]


def _utc(wall: float) -> datetime:
    return datetime.fromtimestamp(wall, UTC)


INTEGER_TYPES: Final = (
    VT.SByte,
    VT.Byte,
    VT.Int16,
    VT.UInt16,
    VT.Int32,
    VT.UInt32,
    VT.Int64,
    VT.UInt64,
)


def _type_ok(kind: str, v: ua.Variant) -> bool:
    if v.is_array or isinstance(v.Value, list):
        return False
    t = v.VariantType
    if kind == "analog":
        return t in (VT.Double, VT.Float, *INTEGER_TYPES)
    if kind in ("int", "state"):
        return t in INTEGER_TYPES
    if kind == "bool":
        return t is VT.Boolean
    return t is VT.String


def _variant(value: object, kind: str) -> ua.Variant:
    if kind == "analog":
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError(value)
        return ua.Variant(float(value), VT.Double)
    if kind in ("int", "state"):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError(value)
        return ua.Variant(int(value), VT.UInt32 if kind == "state" else VT.Int64)
    if kind == "bool":
        if not isinstance(value, bool):
            raise TypeError(value)
        return ua.Variant(value, VT.Boolean)
    if kind == "statename":
        return ua.Variant(ua.LocalizedText(str(value)), VT.LocalizedText)
    return ua.Variant(str(value), VT.String)


def _result(
    status: int, reason: str, n_args: int, arg_results: Sequence[int] = (), out: bool = True
) -> ua.CallMethodResult:
    res = ua.CallMethodResult()
    res.StatusCode = ua.StatusCode(status)
    res.InputArgumentResults = [ua.StatusCode(c) for c in arg_results] or [
        ua.StatusCode() for _ in range(n_args)
    ]
    res.OutputArguments = [ua.Variant(reason, VT.String)] if out else []
    return res


def _not_a_condition(parent: ua.NodeId, n_args: int) -> ua.CallMethodResult:
    """A condition's method called on an object that is no alarm's condition: Part 9 §5.7.3
    asks Bad_NodeIdInvalid for the condition type itself (any standard node here), else
    Bad_MethodInvalid (the method is not one of that object's)."""
    status = S.BadNodeIdInvalid if parent.NamespaceIndex == 0 else S.BadMethodInvalid
    return _result(status, f"{parent.to_string()} is not an alarm", n_args)
