"""What the scan hands the OPC UA server: changed tags, events and alarm transitions.

The scan never waits on OPC UA (docs/design.md "One scan"): ``on_scan`` copies the tags that
changed since the last scan (``TagDB.changed_since``, O(changes)) into a pending map under
a lock held for microseconds, wakes the server and returns. The map holds at most one
update per tag: a tag that changes again before the server wrote it replaces its pending
update, and the replaced one counts as dropped (``opcua.dropped``). So the queue is bounded
by the number of tags whatever happens to the server, and the latest value always gets
through — a client never ends on a value older than the tag's. Events are not conflated:
they wait in a bounded queue (``EVENT_QUEUE``), and one that does not fit is dropped and
counted too.

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

    def __init__(self, db: TagDB) -> None:
        self._lock = threading.Lock()
        self._pending: dict[int, Update] = {}
        self._events: deque[BenchEvent | AlarmView] = deque()
        self._version = db.version
        self._started = False
        self.dropped = 0
        self.clients = 0  # set by the server (an int: read atomically by the scan)
        self.restarts = 0  # set by the server's process supervisor (process.py)
        self.wake: Callable[[], None] | None = None  # set by the server once it serves
        self.sampling_interval_s = 0.0
        """Hand changes over at most this often (0: every scan); set by the server."""
        self._t0: float | None = None  # the scan time of the first hand-over
        self._k = -1  # the grid point of the last one
        self._dropped_tag = _declare(db, "opcua.dropped", "int", "Updates and events lost")
        self._depth_tag = _declare(db, "opcua.queue_depth", "int", "Updates waiting for OPC UA")
        self._clients_tag = _declare(db, "opcua.clients", "int", "OPC UA clients connected")
        self._restarts_tag = _declare(
            db, "opcua.restarts", "int", "OPC UA server's process started again (died or hung)"
        )

    # --- the scan side (never blocks) ---------------------------------------------------
    def on_scan(self, db: TagDB, t: float) -> None:
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
                return  # sampled at the server's interval: the changes wait in the tag database
            self._k = k
        with self._lock:
            depth, dropped = len(self._pending) + len(self._events), self.dropped
        db.update(self._dropped_tag, dropped)
        db.update(self._depth_tag, depth)
        db.update(self._clients_tag, self.clients)
        db.update(self._restarts_tag, self.restarts)
        wake = self.wake
        changed = db.changed_since(self._version)
        self._version = db.version
        if wake is None or not changed:
            return  # not serving yet: the server reads every tag when it starts
        updates = [_copy(tag) for tag in changed]
        with self._lock:
            pending = self._pending
            for u in updates:
                if u.tag_index in pending:
                    self.dropped += 1
                pending[u.tag_index] = u
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
        self._version = db.version
        self.wake = wake
        return [_copy(t) for t in db]

    def stop(self) -> None:
        self.wake = None
        with self._lock:
            self._pending.clear()
            self._events.clear()

    def take(self) -> list[Update]:
        """The pending updates, oldest first; the map starts empty again."""
        with self._lock:
            out = list(self._pending.values())
            self._pending = {}
        return out

    def empty(self) -> bool:
        with self._lock:
            return not self._pending and not self._events

    def take_events(self) -> list[BenchEvent | AlarmView]:
        with self._lock:
            out = list(self._events)
            self._events.clear()
        return out


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
