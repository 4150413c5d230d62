"""What the scan hands the OPC UA server: changed tags, events and alarm transitions.

The scan never waits on OPC UA (docs/design.md "One scan"): ``on_scan`` keeps the scan's
copy of its changes (``publish/changes.py``, made once a scan for every publisher), hands
what it kept over under a lock held for microseconds, wakes the server and returns; the
server's side makes them into updates (``take``), one per tag at its latest value: a tag
that changes again before the server wrote it replaces its pending update, and the
replaced one is counted (``opcua.replaced``: by design, nothing is lost — the value it
carried was superseded). So the queue is bounded
by the number of tags whatever happens to the server, and the latest value always gets
through — a client never ends on a value older than the tag's. Events are not conflated:
they wait in a bounded queue (``EVENT_QUEUE``), and one that does not fit is lost and
counted as dropped (``opcua.dropped``: abnormal, the Diagnostics screen shows it red).

The server side (another thread or the same loop, docs/adr/0014-opcua-server.md) calls
``take()`` / ``take_events()`` when woken.

The scan hands over its changes every ``sampling_interval_s`` (the server's sampling
interval, ``opcua.sampling_interval_s``), not every scan: the tags changed since the last
hand-over are copied once, at their latest value, and the server is woken once. At a 10 ms
scan and a 50 ms interval that is a fifth of the copies and of the server's writes, and
a fifth of the wake-ups of the server's thread (each costs a system call on the scan's
thread and a turn of the interpreter lock between the two threads, issue 13). Events and
alarm transitions are not sampled: the first event the server has not taken wakes it.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final, NamedTuple

from supervisor.core.driver import Value
from supervisor.core.encoding import storable, storable_text
from supervisor.core.quality import Quality, Reason
from supervisor.core.records import BenchEvent, storable_event
from supervisor.publish.changes import ChangeBatch, ChangeSnapshots, ChangeSource, RawChange
from supervisor.tags import Tag, TagDB, TagSpec

SAMPLING_TOLERANCE: Final = 0.1
"""A scan up to a tenth of the interval before a grid point hands over for it (scan times
carry their start jitter; deadlines are exact)."""
EVENT_QUEUE: Final = 10_000
"""Events waiting for the server at most (a burst of alarms at an e-stop is tens)."""


class Update(NamedTuple):
    """One tag's value as the scan left it (copied: the tag changes on). A named tuple:
    a hand-over copies every tag changed in the sampling interval, hundreds in one scan
    (a frozen dataclass took five times as long to make)."""

    tag_index: int  # the tag's index in the tag database
    name: str
    value: Value | None
    quality: Quality
    reason: Reason
    source_t: float
    server_t: float


@dataclass(frozen=True, slots=True)
class AlarmView:
    """One alarm as OPC UA shows it (built from ``supervisor.safety.Alarm`` by the app,
    which this layer may not import)."""

    id: str
    group: str  # the channel, or "" for the bench
    severity: int  # 1..1000 (supervisor.safety.Severity)
    message: str
    state: str  # "normal", "active, unacknowledged", …
    active: bool
    acked: bool
    latched: bool = False
    tripped: bool = False
    transition: str = ""  # what just happened ("activated", "acknowledged", …; "" at start)
    actor: str = ""
    wall: float = 0.0  # Unix time of the transition
    shelved: bool = False  # shelved for a time (ISA-18.2), not annunciated meanwhile
    unshelve_s: float = 0.0  # seconds until the shelving expires (0 when not shelved)

    @property
    def retained(self) -> bool:
        """ISA-18.2 / Part 9 Retain: worth showing until it is back to normal, and while it
        is shelved (so that ConditionRefresh shows a client what is shelved)."""
        return self.state != "normal" or self.shelved


class OpcUaFeed:
    """The publisher the scan calls, and the queues the OPC UA server empties."""

    name = "opcua"

    def __init__(self, db: TagDB, changes: ChangeSource | None = None) -> None:
        self._lock = threading.Lock()
        # The scan's copies of its changes: a reader of those the bench shares between its
        # publishers, or copies of its own (from now: the server starts with every tag).
        self._source: ChangeSource = (
            changes if changes is not None else ChangeSnapshots(db, None, since=db.version)
        )
        self._held: list[ChangeBatch] = []  # since the last hand-over (the scan's side)
        self._handovers: list[list[ChangeBatch]] = []  # not taken by the server yet
        self._queued = 0  # changes in the hand-overs
        self._events: deque[BenchEvent | AlarmView] = deque()
        self._started = False
        self.dropped = 0  # events lost (the queue full): abnormal
        self.replaced = 0  # updates superseded by a newer value of their tag: by design
        self.clients = 0  # set by the server (an int: read atomically by the scan)
        self.restarts = 0  # set by the server's process supervisor (process.py)
        self.wake: Callable[[], None] | None = None  # set by the server once it serves
        self.sampling_interval_s = 0.0
        """Hand changes over at most this often (0: every scan); set by the server."""
        self._t0: float | None = None  # the scan time of the first hand-over
        self._k = -1  # the grid point of the last one
        self._dropped_tag = _declare(
            db, "opcua.dropped", "int", "Events lost: the server's event queue was full"
        )
        self._replaced_tag = _declare(
            db,
            "opcua.replaced",
            "int",
            "Updates superseded by a newer value before the server wrote them (by design:"
            " the latest value always gets through)",
        )
        self._depth_tag = _declare(db, "opcua.queue_depth", "int", "Updates waiting for OPC UA")
        self._clients_tag = _declare(db, "opcua.clients", "int", "OPC UA clients connected")
        self._restarts_tag = _declare(
            db, "opcua.restarts", "int", "OPC UA server's process started again (died or hung)"
        )

    # --- the scan side (never blocks) ---------------------------------------------------
    def on_scan(self, db: TagDB, t: float) -> None:
        # The scan's copy of its changes, made once for every publisher that reads it (the
        # historian's and InfluxDB's, ``publish/changes.py``): kept by reference here, made
        # into updates by the server's side. The scan copies no tag for OPC UA (issue 30:
        # a hand-over of every tag changed in the interval was the scan's longest publisher
        # call, a tenth of a millisecond in the load case).
        batches = self._source.batches()
        if self.wake is None:
            return  # not serving yet: the server reads every tag when it starts
        held = self._held
        for b in batches:
            if b.changes:
                held.append(b)
        interval = self.sampling_interval_s
        if interval > 0.0:
            # On a grid of the interval from the first hand-over. A scan starts at its
            # deadline or a little after (its jitter): the tolerance keeps a scan a little
            # earlier on the grid than the first one from missing its grid point (at a
            # 50 ms scan and interval, a grid drawn from the scans' own times handed over
            # every other scan).
            if self._t0 is None:
                self._t0 = t
            k = int((t - self._t0) / interval + SAMPLING_TOLERANCE)
            if k <= self._k:
                return  # sampled at the server's interval: the changes wait here
            self._k = k
        with self._lock:
            depth, dropped, replaced = self._queued + len(self._events), self.dropped, self.replaced
        db.update(self._dropped_tag, dropped)
        db.update(self._replaced_tag, replaced)
        db.update(self._depth_tag, depth)
        db.update(self._clients_tag, self.clients)
        db.update(self._restarts_tag, self.restarts)
        wake = self.wake
        if wake is None or not held:
            return
        n = 0
        for b in held:
            n += len(b.changes)
        self._held = []
        with self._lock:
            self._handovers.append(held)
            self._queued += n
        wake()

    def on_event(self, event: BenchEvent) -> None:
        """An ``EventSink``: chain steps and operator commands (from the scan or a command)."""
        if event.kind == "alarm":
            return  # alarms come as conditions, with their state (``on_alarm``)
        self._put_event(storable_event(event))

    def on_alarm(self, alarm: AlarmView) -> None:
        # asyncua encodes every string as strict UTF-8: a message it cannot encode would
        # raise in the server's thread (``core/encoding.py``).
        message = storable_text(alarm.message)
        if message is not alarm.message:
            alarm = dataclasses.replace(alarm, message=message)
        self._put_event(alarm)

    def _put_event(self, item: BenchEvent | AlarmView) -> None:
        wake = self.wake
        if wake is None:
            return
        with self._lock:
            if len(self._events) >= EVENT_QUEUE:
                self.dropped += 1
                return
            first = not self._events
            self._events.append(item)
        if first:
            # The server is woken by the first event it has not taken: 16 channels changing
            # step in one scan wake it once or twice, not 16 times (each wake-up is a system
            # call and a turn of the interpreter lock on the scan's thread).
            wake()

    # --- the server side -------------------------------------------------------------------
    def start(self, db: TagDB, wake: Callable[[], None]) -> list[Update]:
        """Every tag as it is now (the server's first values); from now on changes are
        queued. Called on the bench's loop (or thread), between two scans."""
        self._source.batches()  # changes before now are in the first values
        self._held = []
        self.wake = wake
        return [_copy(t) for t in db]

    def stop(self) -> None:
        self.wake = None
        self._held = []
        with self._lock:
            self._handovers.clear()
            self._queued = 0
            self._events.clear()

    def take(self) -> list[Update]:
        """The pending updates, oldest first, one per tag at its latest value; a tag
        handed over again before the server took it counts as replaced once."""
        with self._lock:
            handovers, self._handovers = self._handovers, []
            self._queued = 0
        latest: dict[int, RawChange] = {}
        replaced = 0
        for batches in handovers:
            mine: dict[int, RawChange] = {}
            for b in batches:
                for change in b.changes:
                    mine[change[0].index] = change
            if latest:
                replaced += sum(1 for index in mine if index in latest)
            latest.update(mine)
        if replaced:
            with self._lock:
                self.replaced += replaced
        return [_update(c) for c in latest.values()]

    def empty(self) -> bool:
        with self._lock:
            return not self._handovers and not self._events

    def take_events(self) -> list[BenchEvent | AlarmView]:
        with self._lock:
            out = list(self._events)
            self._events.clear()
        return out


def _update(change: RawChange) -> Update:
    tag, value, quality, reason, source_t, server_t = change
    # A text value UTF-8 cannot encode is served escaped (``core/encoding.py``).
    return _new_update(
        Update, (tag.index, tag.spec.name, storable(value), quality, reason, source_t, server_t)
    )


def _copy(tag: Tag) -> Update:
    return _new_update(
        Update,
        # A text value UTF-8 cannot encode is served escaped (``core/encoding.py``).
        (
            tag.index,
            tag.spec.name,
            storable(tag.value),
            tag.quality,
            tag.reason,
            tag.source_t,
            tag.server_t,
        ),
    )


_new_update = tuple.__new__
"""``Update(...)`` without its generated ``__new__`` (a named tuple is a tuple)."""


def _declare(db: TagDB, name: str, dtype: str, description: str) -> Tag:
    existing = db.get(name)
    if existing is not None:
        return existing
    tag = db.add(TagSpec(name, dtype=dtype, description=description, initial=0))  # type: ignore[arg-type]
    db.update(tag, 0)
    return tag
