"""The Sparkplug B edge node as the bench sees it: a scan publisher (docs/sparkplug.md).

Two threads of control besides the network's, so that the scan never waits on the broker
(docs/design.md "Publishing"):

1. the scan's side (``on_scan``): takes the scan's batch of changes (a copy, made at scan
   end: ``supervisor.publish.changes``) and appends it to a queue; returns at once. A queue
   that grows past ``queue_max_changes`` (the thread stalls) is folded into one batch with
   the latest change of each tag: the births stay right, the intermediate values are lost
   and counted in ``sparkplug.dropped``;
2. the edge node's thread (``_run``): keeps each published tag's latest state (what a
   birth carries), sends one NDATA and one DDATA per changed device for what the queue held
   (every change, each with its acquisition time: at most one message per device per
   scan), the births after each connection and on a rebirth request. While disconnected
   (or when a message cannot be handed over), the changes go to the spool on disk
   (``SampleSpool``, bounded: the oldest dropped past it, counted in
   ``sparkplug.spool_dropped`` and alarmed as ``sparkplug.spool_full``); after the births
   of the next session they are replayed, oldest first, each metric flagged
   ``is_historical`` with its own timestamp, before any live data.

``bdSeq`` survives restarts (``BdSeqStore``: the bench's retained-state store): each
CONNECT carries the next one in its will (the NDEATH), so a host application can tell a
late will of the previous run from the death of this one.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final, NamedTuple, Protocol

from google.protobuf.message import DecodeError

from supervisor.core.clock import Clock
from supervisor.core.gate import ScanGate
from supervisor.core.quality import Quality
from supervisor.core.threads import run_restarting
from supervisor.publish.changes import ChangeBatch, ChangeSnapshots, ChangeSource, RawChange
from supervisor.publish.retain import RetainStore
from supervisor.publish.sparkplug.commands import (
    ACTOR_PREFIX,
    COMMAND_PREFIX,
    LAST_RESULT,
    CommandHandler,
    CommandSettings,
    HostState,
    command_metrics,
    requested,
    state_topic,
)
from supervisor.publish.sparkplug.mqtt import PahoTransport, Transport
from supervisor.publish.sparkplug.node import (
    SEQ_MODULO,
    Layout,
    Message,
    Metric,
    Session,
    is_rebirth,
)
from supervisor.publish.sparkplug.payload import decode
from supervisor.publish.sparkplug.spool import SampleSpool
from supervisor.tags import Tag, TagDB, TagSpec

__all__ = [
    "ALARMS",
    "ALARMS_ACTIVE",
    "ALARM_DISCONNECTED",
    "ALARM_SPOOL_FULL",
    "BD_SEQ_KEY",
    "HMI_URL",
    "AlarmHook",
    "AlarmSpec",
    "BdSeqStore",
    "MemoryBdSeq",
    "RetainedBdSeq",
    "SparkplugPublisher",
    "SparkplugSettings",
]

log = logging.getLogger(__name__)

BD_SEQ_KEY = "sparkplug"
"""The retained-state document holding the last CONNECT's bdSeq."""
HMI_URL: Final = "hmi.url"
ALARMS_ACTIVE: Final = "alarms.active"
"""Node metrics a host application (``supervisor fleet``) reads: the bench's screens and
its annunciated alarms (bench-level tags: ADR 0052)."""
STATUS_PERIOD_S = 0.1
RETRY_S = 1.0
REPLAY_CHUNK: Final = 2000
"""Spooled samples per replayed round of messages (one NDATA/DDATA per device each): the
scan gets the interpreter between two rounds."""

RESEND_KEEPALIVES: Final = 1.5
"""How long, in keep-alives, data handed to MQTT is kept for a resend: MQTT's bound for
noticing a silent connection (a broker that went away without closing it)."""

RESEND_MAX_SAMPLES: Final = 200_000
"""At most this many samples kept for a resend (a busy bench's memory stays bounded; the
oldest, the likeliest delivered, go first)."""

AlarmHook = Callable[[str, bool, str], None]
"""``(alarm id, active, message)``: the composition root puts it on the alarm model."""


class AlarmSpec(NamedTuple):
    id: str
    severity: str  # the alarm model's names: "low" | "medium" | "high" | "critical"
    description: str


ALARM_DISCONNECTED: Final = "sparkplug.disconnected"
ALARM_SPOOL_FULL: Final = "sparkplug.spool_full"
ALARMS: Final = (
    AlarmSpec(
        ALARM_DISCONNECTED,
        "low",
        "The MQTT broker has been unreachable for disconnected_alarm_s: data is spooled",
    ),
    AlarmSpec(
        ALARM_SPOOL_FULL,
        "medium",
        "The Sparkplug spool is full: its oldest samples are dropped",
    ),
)


@dataclass(frozen=True, slots=True)
class SparkplugSettings:
    """What the edge node needs (``supervisor.app.sparkplug`` builds it from the I/O map)."""

    host: str
    port: int
    group: str
    edge_node: str
    keepalive_s: int = 30
    queue_max_changes: int = 200_000
    spool_path: Path | None = None
    """The store-and-forward file (None: in memory, lost with the process)."""
    spool_max_bytes: int = 64 * 1024 * 1024
    """0: no store and forward (changes while disconnected are dropped and counted)."""
    disconnected_alarm_s: float = 30.0
    commands: CommandSettings | None = None
    """Commands over Sparkplug and the primary host (None: no DCMD nor STATE subscribed)."""


class BdSeqStore(Protocol):
    def load(self) -> int | None:
        """The bdSeq of the last CONNECT (None: never connected)."""
        ...

    def save(self, bd_seq: int) -> None:
        """Keep ``bd_seq`` (on disk before the CONNECT that carries it)."""
        ...


class MemoryBdSeq:
    """A bdSeq kept only by this process (a bench without retained state, the tests)."""

    def __init__(self, last: int | None = None) -> None:
        self.last = last

    def load(self) -> int | None:
        return self.last

    def save(self, bd_seq: int) -> None:
        self.last = bd_seq


class RetainedBdSeq:
    """The bdSeq in the bench's retained-state store (``<state_dir>/state.sqlite``)."""

    def __init__(self, store: RetainStore, flush_s: float = 2.0) -> None:
        self.store = store
        self.flush_s = flush_s

    def load(self) -> int | None:
        doc = self.store.read().get(BD_SEQ_KEY) or {}
        value = doc.get("bd_seq") if isinstance(doc, dict) else None
        return value if isinstance(value, int) and 0 <= value < SEQ_MODULO else None

    def save(self, bd_seq: int) -> None:
        self.store.put(BD_SEQ_KEY, {"bd_seq": bd_seq})
        if not self.store.flush(self.flush_s):  # a SIGKILL right after must not reuse it
            log.warning("Sparkplug bdSeq %d not yet on disk (%s)", bd_seq, self.store.error)


def _status_tags() -> list[TagSpec]:
    return [
        TagSpec("sparkplug.connected", "bool", description="Connected to the MQTT broker"),
        TagSpec("sparkplug.bd_seq", "int", description="bdSeq of the current MQTT session"),
        TagSpec("sparkplug.messages", "int", description="Sparkplug messages sent"),
        TagSpec(
            "sparkplug.dropped",
            "int",
            description="Changes not sent: the queue folded, or no spool",
        ),
        TagSpec("sparkplug.spool_depth", "int", description="Samples waiting in the spool"),
        TagSpec(
            "sparkplug.spool_dropped",
            "int",
            description="Samples dropped by the spool's bound (the oldest)",
        ),
        TagSpec("sparkplug.replayed", "int", description="Spooled samples sent (historical)"),
        TagSpec(
            "sparkplug.host_online",
            "bool",
            description="The primary host application's STATE says online",
        ),
        TagSpec(
            "sparkplug.commands_accepted",
            "int",
            description="DCMD commands the command path accepted",
        ),
        TagSpec(
            "sparkplug.commands_refused",
            "int",
            description="DCMD commands refused (disabled, host not online, unknown, or by"
            " the command path)",
        ),
    ]


class RecentlySent:
    """Data handed to MQTT in the last ``horizon_s``. Data is QoS 0 (Sparkplug): what was
    handed over just before a connection was found lost may never have reached the
    broker, and nothing says which. What was sent within the time a loss can take to be
    noticed (1.5 keep-alives, MQTT's bound for a silent connection) is kept and, on a
    loss, spooled: replayed as history after the next births (a receiver may see some
    twice, with the same timestamp)."""

    def __init__(self, horizon_s: float, max_samples: int = RESEND_MAX_SAMPLES) -> None:
        self.horizon_s = horizon_s
        self.max_samples = max_samples
        self._sent: deque[tuple[float, list[tuple[str, Metric]]]] = deque()
        self._n = 0

    def add(self, now: float, group: list[tuple[str, Metric]]) -> None:
        sent = self._sent
        sent.append((now, group))
        self._n += len(group)
        horizon = now - self.horizon_s
        while sent and (sent[0][0] < horizon or self._n > self.max_samples):
            self._n -= len(sent.popleft()[1])

    def take(self) -> list[tuple[str, Metric]]:
        """Everything kept, oldest first; none kept after."""
        out = [c for _, group in self._sent for c in group]
        self._sent.clear()
        self._n = 0
        return out


class SparkplugPublisher:
    """Publishes a bench's tags as a Sparkplug B edge node."""

    name = "sparkplug"

    def __init__(
        self,
        db: TagDB,
        clock: Clock,
        settings: SparkplugSettings,
        *,
        channels: Sequence[str],
        devices: Sequence[str],
        bd_seq: BdSeqStore | None = None,
        changes: ChangeSource | None = None,
        transport: Callable[[], Transport] | None = None,
        alarm: AlarmHook | None = None,
        active_alarms: Callable[[], int] | None = None,
    ) -> None:
        self.settings = settings
        self.active_alarms = active_alarms
        """The bench's annunciated alarms, counted on the scan's side (``alarms.active``)."""
        self.hmi_url: str | None = None
        """The bench's own screens (``hmi.url``): set before ``start`` when the HMI runs."""
        self.alarm = alarm
        self.spool: SampleSpool | None = (
            SampleSpool(settings.spool_path, settings.spool_max_bytes)
            if settings.spool_max_bytes > 0
            else None
        )
        self.replayed = 0
        self._recent = RecentlySent(RESEND_KEEPALIVES * settings.keepalive_s)
        self._lost_session = False
        self._down_since: float | None = None
        self._alarms: dict[str, bool] = {}
        self.db = db
        self.clock = clock
        self.source: ChangeSource = changes if changes is not None else ChangeSnapshots(db, clock)
        self.bd_seq_store: BdSeqStore = bd_seq or MemoryBdSeq()
        self.session = Session(
            settings.group, settings.edge_node, Layout(tuple(channels), tuple(devices))
        )
        self._make_transport = transport or self._paho
        self._init_commands(settings.commands, channels)
        self.transport: Transport | None = None
        self._cond = threading.Condition()
        self._queue: deque[ChangeBatch] = deque()
        self._queued = 0  # changes in the queue
        self._idle = False
        self._stopping = False
        self._connected = False
        self._need_birth = False
        self._thread: threading.Thread | None = None
        self.metrics: dict[str, Metric] = {}  # the thread's: each tag's latest state
        self._primed = False  # the metrics hold every tag (the source's first batch came)
        self.bd_seq = 0
        self.sent = 0
        self.dropped = 0
        self._tags: dict[str, Tag] = {}
        self._add_tags(db)
        self._status_t = float("-inf")
        self.gate: ScanGate | None = None
        """Encode only while the scan is not running (``core/gate.py``; set by the bench)."""

    def _init_commands(self, cmd: CommandSettings | None, channels: Sequence[str]) -> None:
        self.commander: CommandHandler | None = None
        """Runs a DCMD's command through the one command path (set by the bench)."""
        self.host: HostState | None = (
            HostState(cmd.primary_host) if cmd is not None and cmd.primary_host else None
        )
        self.commands_accepted = 0
        self.commands_refused = 0
        self._results: list[tuple[str, Metric]] = []
        self._born = False  # births sent on this connection
        self._cycle = False  # the primary host went offline: NDEATH, reconnect
        self._recycling = False
        self._command_metrics: dict[str, Metric] = (
            command_metrics(channels, round(self.clock.wall() * 1000))
            if cmd is not None and cmd.enabled
            else {}
        )

    def _add_tags(self, db: TagDB) -> None:
        """The edge node's status tags, and ``alarms.active`` when it counts them."""
        initial = {"int": 0, "bool": False}
        for spec in _status_tags():
            tag = self._tags[spec.name] = db.get(spec.name) or db.add(spec)
            db.update(tag, initial[spec.dtype])
        if self.active_alarms is not None:
            self._tags[ALARMS_ACTIVE] = db.get(ALARMS_ACTIVE) or db.add(
                TagSpec(ALARMS_ACTIVE, "int", description="Alarms annunciated now (not shelved)")
            )
            db.update(self._tags[ALARMS_ACTIVE], self.active_alarms())

    def _paho(self) -> Transport:
        s = self.settings
        return PahoTransport(
            s.host,
            s.port,
            client_id=f"{s.group}:{s.edge_node}",
            keepalive_s=s.keepalive_s,
        )

    # --- lifecycle --------------------------------------------------------------------
    def start(self, *, threaded: bool = True) -> None:
        """Take the next bdSeq (kept before connecting), connect in the background and
        start the edge node's thread. Never raises for a broker that is away.
        ``threaded=False``: no thread, the caller runs each round (``drain``)."""
        if self.transport is not None:
            return
        if self.spool is not None:
            try:
                self.spool.open()  # what a previous run left is replayed after the births
            except (OSError, sqlite3.Error) as exc:
                # A state folder that cannot be written: publish anyway, without a spool.
                log.error("Sparkplug spool %s cannot be opened (%s): none", self.spool.path, exc)
                self.spool = None
        if self.hmi_url:
            # Before the scan runs (``Bench.start``): a node metric the fleet links to.
            tag = self.db.get(HMI_URL) or self.db.add(
                TagSpec(HMI_URL, "str", description="The bench's operator screens (URL)")
            )
            self.db.update(tag, self.hmi_url)
        self._next_bd_seq()
        self._stopping = False
        self._down_since = self.clock.now()  # until the first connection
        self._queue_every_tag()
        if threaded:
            self._thread = threading.Thread(target=self._thread_main, name="sparkplug", daemon=True)
            self._thread.start()
        self.transport = self._make_transport()
        cmd = self.settings.commands
        if cmd is None:
            self.transport.start(self._will(), self.session.ncmd_topic, self)
            return
        also = [self.session.topic("DCMD") + "/+"]
        if cmd.primary_host:
            also.append(state_topic(cmd.primary_host))
        self.transport.start(self._will(), self.session.ncmd_topic, self, also=also)

    def close(self, timeout_s: float = 5.0) -> None:
        """Send what is queued, publish the NDEATH (a clean stop) and disconnect."""
        if self.transport is None:
            return
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
            self._thread = None
        else:
            self.drain()
        if self.transport is not None:
            self.transport.stop(self._will())
            self.transport = None
        self._connected = False
        if self.spool is not None:
            self.spool.close()  # what it holds waits for the next run

    def _queue_every_tag(self) -> None:
        """Every tag as it is now, as the first batch: what the births carry, whatever
        scans ran before the start (their batches were not kept)."""
        clock = self.clock
        every = [(t, t.value, t.quality, t.reason, t.source_t, t.server_t) for t in self.db]
        batch = ChangeBatch(every, clock.now(), clock.to_wall(0.0), True)
        with self._cond:
            self._queue.clear()
            self._queue.append(batch)
            self._queued = len(every)

    def _host_ready(self) -> bool:
        """No primary host, or its STATE says online (under the lock)."""
        return self.host is None or self.host.online

    def _end_session(self) -> None:
        """The primary host went offline (Sparkplug 3.0, "Edge Node Session Establishment"):
        publish the NDEATH, disconnect, connect again (next bdSeq) and wait for its STATE
        online before the next births. The edge node's thread: the scan never waits."""
        transport = self.transport
        if transport is None:
            return
        log.warning("Sparkplug: primary host offline: NDEATH, reconnecting")
        with self._cond:
            self._connected = False
            self._recycling = True
            if self._down_since is None:
                self._down_since = self.clock.now()
        try:
            death = self._will()
            self._next_bd_seq()
            transport.reconnect(death, self._will())
        finally:
            with self._cond:
                self._recycling = False

    def _next_bd_seq(self) -> None:
        last = self.bd_seq_store.load()
        self.bd_seq = 0 if last is None else (last + 1) % SEQ_MODULO
        self.bd_seq_store.save(self.bd_seq)

    def _will(self) -> Message:
        return self.session.death(self.bd_seq, self._now_ms())

    def _now_ms(self) -> int:
        return round(self.clock.wall() * 1000)

    # --- the transport's callbacks (its thread) ---------------------------------------
    def connected(self) -> None:
        with self._cond:
            self._connected = True
            self._need_birth = True
            self._down_since = None
            self._born = False
            if self.host is not None:
                self.host.online = False  # its retained STATE comes after the SUBSCRIBE
            self._cond.notify_all()

    def disconnected(self) -> None:
        with self._cond:
            self._connected = False
            self._lost_session = True
            stopping = self._stopping or self._recycling
            if self._down_since is None:
                self._down_since = self.clock.now()
        if stopping:
            return
        # The next CONNECT (paho reconnects by itself) carries the next bdSeq in its will.
        self._next_bd_seq()
        if self.transport is not None:
            self.transport.set_will(self._will())

    def command(self, payload: bytes) -> None:
        try:
            ncmd = decode(payload)
        except DecodeError as exc:
            log.warning("Sparkplug NCMD on %s: not a payload (%s)", self.session.ncmd_topic, exc)
            return
        if is_rebirth(ncmd):
            log.info("Sparkplug: rebirth requested on %s", self.session.ncmd_topic)
            with self._cond:
                self._need_birth = True
                self._cond.notify_all()

    def message(self, topic: str, payload: bytes) -> None:
        """A DCMD (``.../DCMD/<edge node>/<device>``) or the primary host's STATE."""
        if self.host is not None and topic == state_topic(self.host.host_id):
            self.state(payload)
        elif topic.startswith(self.session.topic("DCMD") + "/"):
            self.device_command(topic.rsplit("/", 1)[1], payload)

    def state(self, payload: bytes) -> None:
        """The primary host's STATE: online lets the births go (and commands in); offline
        after the births of this connection ends the session (Sparkplug 3.0: NDEATH,
        disconnect, connect again and wait for online)."""
        host = self.host
        if host is None:
            return
        with self._cond:
            online = host.update(payload)
            if online is None:
                return
            log.info("Sparkplug: primary host %s online: %s", host.host_id, online)
            if not online and self._born and self._connected:
                self._cycle = True
            self._cond.notify_all()

    def device_command(self, device: str, payload: bytes) -> None:
        """A DCMD: each ``Command/<verb>`` set to true → the command path (or refused)."""
        try:
            dcmd = decode(payload)
        except DecodeError as exc:
            self._refuse(device, "?", f"not a Sparkplug payload ({exc})")
            return
        for name, verb in requested(dcmd):
            why = self._refusal(device, verb)
            if why:
                self._refuse(device, verb or name, why)
                continue
            assert verb is not None and self.commander is not None and self.host is not None
            actor = ACTOR_PREFIX + self.host.host_id
            log.info("Sparkplug DCMD %s on %s by %s", verb, device, actor)
            self.commander(device, verb, actor, self._replier(device, verb))

    def _refusal(self, device: str, verb: str | None) -> str:
        cmd = self.settings.commands
        if cmd is None or not cmd.enabled or self.commander is None:
            return "commands over Sparkplug are disabled (sparkplug.commands.enabled)"
        if device not in self.session.layout.channels:
            return f"{device} is not a channel"
        if verb is None:
            return "unknown command"
        host = self.host
        if host is None or not host.online:
            return f"the primary host application {cmd.primary_host} is not online (its STATE)"
        return ""

    def _refuse(self, device: str, what: str, why: str) -> None:
        log.warning("Sparkplug DCMD %s on %s refused: %s", what, device, why)
        self._answer(device, what.removeprefix(COMMAND_PREFIX), False, why)

    def _replier(self, device: str, verb: str) -> Callable[[bool, str], None]:
        def reply(accepted: bool, reason: str) -> None:
            if not accepted:
                log.warning("Sparkplug DCMD %s on %s refused: %s", verb, device, reason)
            self._answer(device, verb, accepted, reason)

        return reply

    def _answer(self, device: str, what: str, accepted: bool, reason: str) -> None:
        """Count the answer; publish it as the channel's ``Command/last_result``."""
        text = f"{what}: accepted" if accepted else f"{what}: refused: {reason}"
        cmd = self.settings.commands
        with self._cond:
            if accepted:
                self.commands_accepted += 1
            else:
                self.commands_refused += 1
            if cmd is not None and cmd.enabled and device in self.session.layout.channels:
                m = Metric("str", "", text, Quality.GOOD, self._now_ms())
                self._results.append((f"{device}.{LAST_RESULT}", m))
            self._cond.notify_all()

    # --- the scan's side --------------------------------------------------------------
    def on_scan(self, db: TagDB, t: float) -> None:
        """At scan end: this scan's changes to the queue; the status tags."""
        batches = self.source.batches()  # taken in any case: a shared feed keeps them else
        if self.transport is None:
            return  # not started (or stopped): ``start`` queues every tag
        for batch in batches:
            if not batch.changes and not batch.first:
                continue
            with self._cond:
                self._queue.append(batch)
                self._queued += len(batch.changes)
                if self._queued > self.settings.queue_max_changes:
                    self._fold()
                if self._idle:
                    self._cond.notify_all()
        if self.clock.virtual or t - self._status_t > STATUS_PERIOD_S - 1e-9 or t < self._status_t:
            self._status_t = t
            self._publish_status(db)

    def _fold(self) -> None:
        """The queue as one batch: each tag's latest change (under the lock)."""
        latest: dict[int, RawChange] = {}
        first = False
        for b in self._queue:
            first = first or b.first
            for change in b.changes:
                latest[change[0].index] = change
        last = self._queue[-1]
        self.dropped += self._queued - len(latest)
        self._queue.clear()
        self._queue.append(ChangeBatch(list(latest.values()), last.now, last.wall_offset, first))
        self._queued = len(latest)

    def _publish_status(self, db: TagDB) -> None:
        tags = self._tags
        db.update(tags["sparkplug.connected"], self._connected)
        db.update(tags["sparkplug.bd_seq"], self.bd_seq)
        db.update(tags["sparkplug.messages"], self.sent)
        db.update(tags["sparkplug.dropped"], self.dropped)
        spool = self.spool
        db.update(tags["sparkplug.spool_depth"], spool.waiting if spool else 0)
        db.update(tags["sparkplug.spool_dropped"], spool.dropped if spool else 0)
        db.update(tags["sparkplug.replayed"], self.replayed)
        db.update(tags["sparkplug.host_online"], self.host is not None and self.host.online)
        db.update(tags["sparkplug.commands_accepted"], self.commands_accepted)
        db.update(tags["sparkplug.commands_refused"], self.commands_refused)
        if self.active_alarms is not None:
            db.update(tags[ALARMS_ACTIVE], self.active_alarms())
        if self.alarm is not None:
            self._publish_alarms(self.clock.now())

    def _publish_alarms(self, t: float) -> None:
        """``sparkplug.disconnected`` once the broker has been away ``disconnected_alarm_s``
        (since the start, for a broker never reached); ``sparkplug.spool_full`` while the
        bound drops samples (until the spool is back under 90 %)."""
        s = self.settings
        down_since = self._down_since
        active = {
            ALARM_DISCONNECTED: (
                down_since is not None and t - down_since >= s.disconnected_alarm_s,
                f"MQTT broker {s.host}:{s.port} unreachable for {s.disconnected_alarm_s:g} s:"
                " Sparkplug data is spooled",
            ),
            ALARM_SPOOL_FULL: (
                self.spool is not None and self.spool.overflowing,
                f"Sparkplug spool full ({s.spool_max_bytes} bytes): the oldest samples are dropped",
            ),
        }
        assert self.alarm is not None
        for alarm_id, (on, message) in active.items():
            if self._alarms.get(alarm_id, False) == on:
                continue
            self._alarms[alarm_id] = on
            try:
                self.alarm(alarm_id, on, message)
            except Exception:  # the alarm model's fault must not stop the publisher
                log.exception("Sparkplug: alarm %s could not be set", alarm_id)

    # --- the edge node's thread -------------------------------------------------------
    def _thread_main(self) -> None:
        run_restarting(
            f"Sparkplug edge node {self.session.edge_node}",
            self._run,
            self._crashed,
            lambda: self._stopping,
            self._sleep,
            RETRY_S,
        )

    def _crashed(self, exc: Exception) -> None:
        with self._cond:
            self._need_birth = True  # what the failed round held is in no message: resync

    def _sleep(self, delay_s: float) -> None:
        with self._cond:
            if not self._stopping:
                self._cond.wait(delay_s)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not (
                    self._queue
                    or (self._need_birth and self._host_ready())
                    or self._results
                    or self._cycle
                    or self._stopping
                ):
                    self._idle = True
                    self._cond.wait()
                self._idle = False
                stopping = self._stopping
            self.drain()
            if stopping:
                return

    def drain(self) -> None:
        """One round with what is queued now (the edge node's thread; a test or a tool
        without the thread calls it itself)."""
        with self._cond:
            batches = list(self._queue)
            self._queue.clear()
            self._queued = 0
            cycle, self._cycle = self._cycle and not self._stopping, False
        if cycle:
            self._end_session()
        if self.gate is not None:
            self.gate.wait()  # the scan first: encoding takes the interpreter lock
        self.step(batches)

    def step(self, batches: Sequence[ChangeBatch]) -> None:
        """One round: the batches into the metrics, then the births (and the spool's
        replay after them) or the data; what cannot be sent goes to the spool."""
        changes, fresh = self._apply(batches)
        with self._cond:
            connected, birth = self._connected and self._host_ready(), self._need_birth
            results, self._results = self._results, []
            lost, self._lost_session = self._lost_session, False
        if lost:
            self._keep_recent()
        for name, m in results:
            self._command_metrics[name] = m  # what the next births carry
        if not connected:
            self._keep(fresh)  # a first batch is every tag: what the next births carry
            return
        changes.extend(results)
        if not self._primed:
            return  # no first batch yet: a birth would announce nothing
        if not birth and self.session.needs_birth(name for name, _ in changes):
            birth = True  # a tag added since the births: announce it
        if not birth:
            if changes:
                self._send_data(changes)
            return
        with self._cond:
            self._need_birth = False
        births = self.session.births(
            self.bd_seq, {**self.metrics, **self._command_metrics}, self._now_ms()
        )
        if not self._send(births):
            self._keep(fresh)
            return
        with self._cond:
            self._born = True
        # A change of this round that a later one superseded is not in the births: it
        # is history, replayed after what waited before it.
        metrics = self.metrics
        self._keep([(name, m) for name, m in fresh if metrics.get(name) is not m])
        self._replay()

    def _apply(
        self, batches: Sequence[ChangeBatch]
    ) -> tuple[list[tuple[str, Metric]], list[tuple[str, Metric]]]:
        """Every change (into the metrics), and those that are not a first batch's."""
        metrics = self.metrics
        place = self.session.layout.place
        out: list[tuple[str, Metric]] = []
        fresh: list[tuple[str, Metric]] = []
        for b in batches:
            if b.first:
                metrics.clear()
                self._primed = True
            offset = b.wall_offset
            for tag, value, quality, _, t, server_t in b.changes:
                spec = tag.spec
                if place(spec.name) is None:
                    continue  # not published (the edge node's own status)
                wall_ms = round(((t or server_t) + offset) * 1000)
                m = Metric(spec.dtype, spec.unit, value, quality, wall_ms)
                metrics[spec.name] = m
                out.append((spec.name, m))
                if not b.first:
                    fresh.append((spec.name, m))
        return out, fresh

    def _keep(self, changes: Sequence[tuple[str, Metric]]) -> None:
        """Changes not sent: to the spool (dropped and counted without one)."""
        if not changes:
            return
        if self.spool is None:
            self.dropped += len(changes)
            return
        try:
            self.spool.append(changes)
        except Exception:  # a disk that fails: the changes are lost, the node goes on
            log.exception("Sparkplug spool %s: %d samples lost", self.spool.path, len(changes))
            self.dropped += len(changes)

    def _replay(self) -> None:
        """The spool, oldest first, flagged historical, after the births (same session)."""
        spool = self.spool
        while spool is not None and spool.waiting:
            rows = spool.oldest(REPLAY_CHUNK)
            if not rows:
                return
            if self.gate is not None:
                self.gate.wait()
            samples = [(tag, m) for _, tag, m in rows]
            parts = self.session.data_parts(samples, self._now_ms(), historical=True)
            if not self._send([message for message, _ in parts]):
                # Not removed: replayed again after the next births (a device's message
                # that went out before the failure may then come twice).
                return
            spool.remove(rows[-1][0])
            self.replayed += len(rows)
            log.info("Sparkplug: %d spooled samples replayed, %d wait", len(rows), spool.waiting)

    def _send_data(self, changes: Sequence[tuple[str, Metric]]) -> None:
        parts = self.session.data_parts(changes, self._now_ms())
        for k, (message, group) in enumerate(parts):
            if not self._send([message]):
                self._keep([c for _, group in parts[k:] for c in group])
                return
            self._recent.add(self.clock.now(), list(group))

    def _keep_recent(self) -> None:
        """A connection lost: what was sent within its noticing time goes to the spool."""
        self._keep(self._recent.take())

    def _send(self, messages: list[Message]) -> bool:
        """Hand ``messages`` over in order; False at the first that cannot be (a gap: the
        next round is a birth)."""
        transport = self.transport
        for message in messages:
            if transport is not None and transport.publish(message):
                self.sent += 1
            else:
                with self._cond:
                    self._need_birth = self._connected
                return False
        return True
