"""The InfluxDB writer as the bench sees it: a scan publisher and an event sink.

Three parts, so that the scan never waits (docs/design.md "Publishing"):

1. the scan's side (``InfluxWriter.on_scan``, ``on_event``): the change feed's samples and
   the bench events go to a bounded in-memory queue; the influx.* status tags and alarms
   are updated from the other two parts;
2. the spool writer thread (``SpoolWriter``): every ``commit_interval_s`` it turns what the
   queue holds into line protocol (``lineproto``; on this thread, not the scan's: at a
   10 ms scan with every change stored the encoding was the scan's largest cost, issue 13)
   and appends it to the spool on disk (``spool``) in one transaction, BEFORE anything is
   sent. A SIGKILL loses at most the points of the last commit interval (still in memory);
3. the forwarder thread (``forward``): sends the spool's oldest chunks, deletes them after
   a 2xx.

A full in-memory queue (the disk stalls) drops its oldest points, counted in
``influx.dropped`` like the spool's own drops past ``max_bytes``; a failing disk raises
``influx.spool`` and is retried every second.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from operator import attrgetter
from pathlib import Path

from supervisor.core.clock import Clock
from supervisor.core.driver import Value
from supervisor.core.gate import ScanGate
from supervisor.core.quality import Quality
from supervisor.core.records import BenchEvent
from supervisor.core.threads import run_restarting
from supervisor.publish.changes import (
    ChangeBatch,
    ChangeFilter,
    ChangeReader,
    ChangeSnapshots,
    ChangeSource,
    Sample,
)
from supervisor.publish.influx.client import CONFIGURATION, TRANSIENT, WriteClient
from supervisor.publish.influx.forward import Forwarder, ForwarderStatus
from supervisor.publish.influx.lineproto import EVENT, LineEncoder
from supervisor.publish.influx.spool import Spool, SpoolCounts
from supervisor.tags import Tag, TagDB, TagSpec

__all__ = [
    "ALARMS",
    "ALARM_CONFIG",
    "ALARM_DEAD_LETTERS",
    "ALARM_SPOOL",
    "ALARM_SPOOL_FULL",
    "ALARM_UNREACHABLE",
    "AlarmHook",
    "AlarmSpec",
    "InfluxSettings",
    "InfluxStatus",
    "InfluxWriter",
    "SpoolWriter",
]

log = logging.getLogger(__name__)

AlarmHook = Callable[[str, bool, str], None]
"""``(alarm id, active, message)``: the composition root puts it on the alarm model."""

SPOOL_RETRY_S = 1.0
"""Time between two attempts at a failed spool write (disk full, read-only)."""
STATUS_PERIOD_S = 0.1
"""On a real clock the ``influx.*`` status tags and alarms are brought up to date at most
this often (the scan's clock); an alarm's own delay (``alarm_after_s``) is seconds."""


@dataclass(frozen=True, slots=True)
class AlarmSpec:
    id: str
    severity: str  # "low" | "medium" | "high" | "critical" (the alarm model's names)
    description: str


ALARM_CONFIG = "influx.config"
ALARM_UNREACHABLE = "influx.unreachable"
ALARM_DEAD_LETTERS = "influx.dead_letters"
ALARM_SPOOL_FULL = "influx.spool_full"
ALARM_SPOOL = "influx.spool"
ALARMS = (
    AlarmSpec(
        ALARM_CONFIG,
        "medium",
        "InfluxDB refuses every write (token, bucket or URL): points are kept, not sent",
    ),
    AlarmSpec(
        ALARM_UNREACHABLE,
        "low",
        "InfluxDB has not accepted a write for alarm_after_s: points wait in the spool",
    ),
    AlarmSpec(
        ALARM_DEAD_LETTERS,
        "low",
        "InfluxDB refused points for good: they are in the spool's dead-letter table",
    ),
    AlarmSpec(ALARM_SPOOL_FULL, "high", "The spool is full: its oldest points are dropped"),
    AlarmSpec(ALARM_SPOOL, "high", "The spool cannot be written: points are not stored"),
)
"""Raised where an operator must act; each clears by itself when the cause is gone."""


@dataclass(frozen=True, slots=True)
class InfluxSettings:
    """What the writer needs (``supervisor.app.influx`` builds it from the I/O map)."""

    url: str
    org: str
    bucket: str
    token: str
    spool_path: Path
    batch_size: int = 5000
    flush_interval_s: float = 1.0
    timeout_s: float = 10.0
    retry_max_s: float = 30.0
    alarm_after_s: float = 60.0
    stop_flush_s: float = 5.0
    spool_max_bytes: int = 256 * 1024 * 1024
    commit_interval_s: float = 0.2
    queue_max_points: int = 200_000


@dataclass(frozen=True, slots=True)
class InfluxStatus:
    """Everything the influx.* tags show, in one snapshot."""

    spool: SpoolCounts
    forwarder: ForwarderStatus
    queued: int  # points in memory, not yet in the spool
    dropped: int  # points dropped, spool bound and full queue (since the spool began)
    spool_error: str  # why the spool cannot be written ("" when it can)


Encode = Callable[[], dict[str, list[str]]]
"""Lines by measurement, made when the spool writer gets to them (``put_deferred``)."""

ENCODE_YIELD_S = 0.0001
"""After encoding one queued scan's samples the spool writer sleeps this long: a sleep
releases the interpreter lock, so a scan waiting for it gets it between two scans' worth
of encoding instead of after the interpreter's switch interval (5 ms)."""


@dataclass(frozen=True, slots=True)
class _Deferred:
    points: int
    encode: Encode


class SpoolWriter:
    """The thread that moves queued lines into the spool, one transaction per interval."""

    def __init__(
        self,
        spool: Spool,
        *,
        commit_interval_s: float,
        chunk_points: int,
        max_queue_points: int,
        on_commit: Callable[[], None] = lambda: None,
    ) -> None:
        self.spool = spool
        self.commit_interval_s = commit_interval_s
        self.chunk_points = chunk_points
        self.max_queue_points = max_queue_points
        self.on_commit = on_commit
        self._cond = threading.Condition()
        # (measurement, lines), or (points, encode) to be encoded on this thread.
        self._items: deque[tuple[str, list[str]] | _Deferred] = deque()
        self._queued = 0
        self._unspooled_drops = 0  # dropped from the queue, not yet counted in the spool
        self._stopping = False
        # The thread waits for a first item (idle) or for the commit interval to pass: only
        # an idle thread is woken by a put. A wake-up per scan costs the scan's thread a
        # system call and an exchange of the interpreter lock, 100 times a second (issue 13).
        self._idle = False
        self._thread: threading.Thread | None = None
        self._in_flight = 0  # points taken from the queue, not spooled or put back yet
        self.gate: ScanGate | None = None
        """Encode only while the scan is not running (``core/gate.py``; set by the bench)."""
        self.error: str | None = None
        self.commits = 0
        self.crashes = 0  # exceptions that escaped the thread's loop (it started again)

    @property
    def queued(self) -> int:
        return self._queued

    @property
    def unspooled_drops(self) -> int:
        return self._unspooled_drops

    def put(self, measurement: str, lines: list[str]) -> None:
        """Queue lines; returns at once. A full queue drops its oldest lines (counted)."""
        if not lines:
            return
        with self._cond:
            self._items.append((measurement, lines))
            self._queued += len(lines)
            if self._queued > self.max_queue_points:
                self._shed()
            if self._idle:
                self._cond.notify_all()

    def put_deferred(self, points: int, encode: Encode) -> None:
        """Queue ``points`` points that ``encode()`` will make, on the writer's thread, in
        the order queued; returns at once. ``encode`` must only read what the caller will
        not change (this scan's samples)."""
        if points <= 0:
            return
        with self._cond:
            self._items.append(_Deferred(points, encode))
            self._queued += points
            if self._queued > self.max_queue_points:
                self._shed()
            idle = self._idle
        if idle:
            if self.gate is not None:
                self.gate.after_scan(self._kick)  # woken once the scan is done
            else:
                self._kick()

    def _kick(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def _shed(self) -> None:
        dropped = 0
        # Points, or samples for those not encoded yet (a line carries one or more: an
        # upper bound). Oldest first; a single scan larger than the bound goes too.
        while self._queued > self.max_queue_points and self._items:
            item = self._items.popleft()
            n = item.points if isinstance(item, _Deferred) else len(item[1])
            self._queued -= n
            dropped += n
        if dropped:
            first = self._unspooled_drops == 0
            self._unspooled_drops += dropped
            if first:
                log.error(
                    "InfluxDB spool %s: the in-memory queue is full (%d points; the spool"
                    " is not keeping up: %s); its oldest points are dropped",
                    self.spool.path,
                    self.max_queue_points,
                    self.error or "disk too slow",
                )

    def open_spool(self) -> bool:
        """Open the spool if it is not; a failure is reported once (``error``) and left
        for the next attempt."""
        if self.spool.is_open:
            return True
        try:
            self.spool.open()
        except (sqlite3.Error, OSError, ValueError) as exc:
            self._failed(exc)
            return False
        return True

    def _failed(self, exc: BaseException) -> None:
        why = f"{type(exc).__name__}: {exc}"
        with self._cond:
            first = self.error != why
            self.error = why
        if first:
            log.error("InfluxDB spool %s: cannot write (%s); retrying", self.spool.path, why)

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stopping = False
        self._thread = threading.Thread(target=self._thread_main, name="influx-spool", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Commit what is queued (one last attempt), then stop."""
        thread = self._thread
        if thread is None:
            return
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        thread.join(timeout_s)
        if thread.is_alive():
            log.error("InfluxDB spool writer did not stop within %g s", timeout_s)
        self._thread = None

    def _thread_main(self) -> None:
        run_restarting(
            f"InfluxDB spool {self.spool.path}",
            self._run,
            self._crashed,
            lambda: self._stopping,
            self._sleep,
            SPOOL_RETRY_S,
        )

    def _crashed(self, exc: Exception) -> None:
        """A crash: counted, said in ``error`` (``influx.last_error``, the spool alarm);
        the lines it was handling are lost, counted as dropped."""
        with self._cond:
            self.crashes += 1
            self._unspooled_drops += self._in_flight
            self._in_flight = 0
        self._failed(RuntimeError(f"writer thread crashed ({type(exc).__name__}: {exc})"))

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._items and not self._unspooled_drops and not self._stopping:
                    self._idle = True
                    self._cond.wait()
                self._idle = False
                if not self._items and not self._unspooled_drops and self._stopping:
                    return
                queued = list(self._items)
                self._items.clear()
                self._queued = 0
                extra = self._unspooled_drops
                stopping = self._stopping
                self._in_flight = sum(
                    item.points if isinstance(item, _Deferred) else len(item[1]) for item in queued
                )
            items = self._encode(queued)
            n = sum(len(lines) for _, lines in items)
            try:
                if not self.spool.is_open:
                    self.spool.open()
                self.spool.append(items, self.chunk_points, extra)
            except (sqlite3.Error, OSError, ValueError) as exc:
                self._failed(exc)
                with self._cond:
                    self._in_flight = 0  # put back, or counted as dropped
                    if stopping:
                        self._unspooled_drops += n
                        lost = self._unspooled_drops
                    else:
                        self._items.extendleft(reversed(items))
                        self._queued += n
                        self._shed()
                if stopping:
                    log.error(
                        "InfluxDB spool %s: %d points could not be spooled at stop (%s)",
                        self.spool.path,
                        lost,
                        self.error,
                    )
                    return
                self._sleep(SPOOL_RETRY_S)
                continue
            with self._cond:
                self._in_flight = 0
                self._unspooled_drops -= extra
                self.commits += 1
                if self.error is not None:
                    log.warning("InfluxDB spool %s: writing again", self.spool.path)
                self.error = None
            self.on_commit()
            if not stopping:
                self._sleep(self.commit_interval_s)

    def _encode(
        self, queued: list[tuple[str, list[str]] | _Deferred]
    ) -> list[tuple[str, list[str]]]:
        items: list[tuple[str, list[str]]] = []
        for item in queued:
            if not isinstance(item, _Deferred):
                items.append(item)
                continue
            self._give_way()
            try:
                lines_by = item.encode()
            except Exception:  # a bug in one scan's encoding must not stop the spool
                log.exception("InfluxDB spool: %d points could not be encoded", item.points)
                continue
            items.extend(lines_by.items())
            time.sleep(ENCODE_YIELD_S)
        return items

    def _give_way(self) -> None:
        if self.gate is not None:
            self.gate.wait()

    def _sleep(self, delay_s: float) -> None:
        end = time.monotonic() + delay_s
        with self._cond:
            while not self._stopping:
                left = end - time.monotonic()
                if left <= 0:
                    return
                self._cond.wait(left)


_version = attrgetter("version")


def _status_tags() -> list[TagSpec]:
    return [
        TagSpec("influx.spool_depth", "int", description="Points waiting in the spool"),
        TagSpec("influx.spool_bytes", "int", description="Bytes of line protocol in the spool"),
        TagSpec(
            "influx.drain_rate",
            "float",
            unit="1/s",
            description="Points delivered to InfluxDB per second (last 10 s)",
        ),
        TagSpec("influx.sent", "int", description="Points InfluxDB acknowledged (spool total)"),
        TagSpec("influx.dead_letters", "int", description="Points refused for good (dead letters)"),
        TagSpec("influx.dropped", "int", description="Points dropped: spool or queue full"),
        TagSpec(
            "influx.last_error",
            "str",
            initial="",
            description="The last failure's cause ('' before any)",
        ),
        TagSpec("influx.connected", "bool", description="The last write was accepted"),
        TagSpec("influx.failed_writes", "int", description="Failed write requests"),
        TagSpec("influx.timeouts", "int", description="Write requests that timed out"),
    ]


class InfluxWriter:
    """Publishes a bench's tag changes and events into InfluxDB, through the spool."""

    name = "influx"

    def __init__(
        self,
        db: TagDB,
        clock: Clock,
        settings: InfluxSettings,
        *,
        bench: str,
        channels: Sequence[str],
        alarm: AlarmHook | None = None,
        client: WriteClient | None = None,
        changes: ChangeReader | None = None,
    ) -> None:
        self.settings = settings
        self.db = db
        self.clock = clock
        self.alarm = alarm
        # Its own copies of the changes, or its reader of those it shares with the
        # historian; filtered on the spool writer's thread (its alone), off the scan.
        self.source: ChangeSource = changes if changes is not None else ChangeSnapshots(db, clock)
        self._filter = ChangeFilter()
        self.encoder = LineEncoder(bench, channels, dtype_of=self._dtype_of)
        self.spool = Spool(settings.spool_path, settings.spool_max_bytes)
        self.client = client or WriteClient(
            settings.url, settings.org, settings.bucket, settings.token, settings.timeout_s
        )
        self.forwarder = Forwarder(
            self.spool,
            self.client,
            batch_size=settings.batch_size,
            flush_interval_s=settings.flush_interval_s,
            retry_max_s=settings.retry_max_s,
        )
        self.writer = SpoolWriter(
            self.spool,
            commit_interval_s=settings.commit_interval_s,
            chunk_points=settings.batch_size,
            max_queue_points=settings.queue_max_points,
            on_commit=self.forwarder.notify,
        )
        self._tags: dict[str, Tag] = {}
        initial: dict[str, Value] = {"int": 0, "float": 0.0, "bool": False, "str": ""}
        for spec in _status_tags():
            tag = self._tags[spec.name] = db.get(spec.name) or db.add(spec)
            db.update(tag, initial[spec.dtype])  # never None, before the first scan too
        self._watch_tests(db, channels)
        self._alarms: dict[str, tuple[bool, str]] = {}
        self._alarms_active: tuple[bool, ...] = (False,) * 5  # as the last scan saw them
        self._status_t = float("-inf")  # the scan time the status tags were last set
        self._spool_problem = ""
        self._started = False
        self._floor_t = clock.now()
        self._floor_wall = clock.to_wall(self._floor_t)

    def _watch_tests(self, db: TagDB, channels: Sequence[str]) -> None:
        """Each channel's (test id, recipe, cell id) tags: the tags of its points."""
        self._tests = {
            ch: (
                db.get(f"{ch}.chain.test_id"),
                db.get(f"{ch}.chain.recipe"),
                db.get(f"{ch}.chain.cell_id"),
            )
            for ch in channels
        }
        # Each channel's (test id, recipe) as its points were last tagged: a change starts
        # new series, which get every field of the channel once (``_new_test_samples``).
        self._tagged: dict[str, tuple[str, ...]] = self._current_tests()
        # Those tags' versions, summed: the scan rebuilds the tests only when one changed
        # (their text 16 times a scan was a tenth of this publisher's time, issue 30).
        self._test_tags = [tag for tags in self._tests.values() for tag in tags if tag is not None]
        self._tests_version = self._test_tags_version()

    def _dtype_of(self, name: str) -> str | None:
        tag = self.db.get(name)
        return None if tag is None else tag.spec.dtype

    # --- lifecycle --------------------------------------------------------------------
    def start(self) -> None:
        """Open the spool (a restart resumes draining what it holds) and start both
        threads. A spool that cannot be opened is reported and retried, never raised."""
        if self._started:
            return
        self.writer.open_spool()
        self._spool_problem = self.spool.problem
        counts = self.spool.counts()
        if counts.waiting:
            log.info(
                "InfluxDB spool %s: %d points waiting from the last run; sending them first",
                self.spool.path,
                counts.waiting,
            )
        self.writer.start()
        self.forwarder.start()
        self._started = True

    def close(self, flush_s: float | None = None) -> None:
        """Spool what is queued, send what can be sent within ``flush_s`` (default
        ``stop_flush_s``), leave the rest in the spool. Blocks: call it off the loop."""
        if not self._started:
            return
        self.writer.stop()
        budget = self.settings.stop_flush_s if flush_s is None else flush_s
        self.forwarder.stop(budget)
        counts = self.spool.counts()
        if self.spool.is_open:
            try:
                self.spool.purge()
            except sqlite3.Error as exc:  # the next start deletes them
                log.warning("InfluxDB spool %s: acknowledged chunks kept: %s", self.spool.path, exc)
        self.spool.close()
        self._started = False
        if counts.waiting:
            log.info(
                "InfluxDB spool %s: %d points left for the next run",
                self.spool.path,
                counts.waiting,
            )

    # --- the scan's side --------------------------------------------------------------
    def on_scan(self, db: TagDB, t: float) -> None:
        """At scan end: this scan's changes to the queue; the status tags and alarms."""
        batches = self.source.batches()
        tests = self._tagged
        version = self._test_tags_version()
        fields: list[Sample] = []
        if version != self._tests_version:
            self._tests_version = version
            tests = self._current_tests()
            if tests != self._tagged:
                fields = self._new_test_samples(db, tests, t)
                self._tagged = tests
        points = len(fields)
        for b in batches:
            points += len(b.changes)
        if points or self._filter.holding:
            # Filtered and encoded on the spool writer's thread, in the order queued.
            self.writer.put_deferred(max(points, 1), lambda: self._encode(batches, fields, tests))
        if self.clock.virtual or t - self._status_t > STATUS_PERIOD_S - 1e-9 or t < self._status_t:
            # Diagnostics (spool depth, drain rate, failures): every STATUS_PERIOD_S on a
            # real clock, not 100 times a second (two locks, two status objects and ten
            # updates a scan); every scan on a virtual one (dry runs, tests).
            self._status_t = t
            self._publish_status(db)

    def _encode(
        self, batches: list[ChangeBatch], fields: list[Sample], tests: dict[str, tuple[str, ...]]
    ) -> dict[str, list[str]]:
        """A scan's batches as line protocol (the spool writer's thread): the changes worth
        storing, then the fields of a new test that did not change in that scan."""
        apply = self._filter.apply
        samples: list[Sample] = []
        for b in batches:
            samples += apply(b)
        floor = self._floor_t
        if any(x.t < floor for x in samples):
            # Set before this writer existed, at time 0 of the clock (on a real clock the
            # boot: every run would write its initial values at the same instant, over the
            # last run's): stored as known since the recording began, before any scan.
            samples = [
                x if x.t >= floor else Sample(x.name, x.value, x.quality, floor, self._floor_wall)
                for x in samples
            ]
        if fields:
            present = {s.name for s in samples}
            samples += [f for f in fields if f.name not in present]
        return self.encoder.encode(samples, tests)

    def _test_tags_version(self) -> int:
        return sum(map(_version, self._test_tags))

    def _current_tests(self) -> dict[str, tuple[str, ...]]:
        """Per channel (test id, recipe, cell id): the tags of its points."""
        return {
            ch: tuple(str(t.value) if t is not None and t.value else "" for t in tags)
            for ch, tags in self._tests.items()
        }

    def _new_test_samples(
        self, db: TagDB, tests: dict[str, tuple[str, ...]], t: float
    ) -> list[Sample]:
        """Every current field of each channel whose test id or recipe changed, at this
        scan's time: the change feed only carries what changed, so a test's series would
        lack the fields that kept their value (a test starting at the cycle number the last
        one ended at has no ``chain_cycle`` point, and the dashboards' per-cycle panels
        find no cycle). A field whose change this scan is stored goes as that change
        (``_encode``); a BAD or unset (None) value writes no field, as everywhere."""
        changed = [ch for ch, test in tests.items() if self._tagged.get(ch) != test]
        prefixes = tuple(f"{ch}." for ch in changed)
        wall = self.clock.to_wall(t)
        return [
            Sample(tag.name, tag.value, tag.quality, t, wall)
            for tag in db
            if tag.name.startswith(prefixes)
            and tag.spec.history.enabled
            and tag.quality is not Quality.BAD
            and tag.value is not None
        ]

    def on_event(self, event: BenchEvent) -> None:
        """A bench event → one ``event`` line (Grafana annotations); returns at once."""
        # Encoded on the spool writer's thread like the samples: the encoder is that
        # thread's alone (it remembers each series' recent timestamps).
        event_line = self.encoder.event
        self.writer.put_deferred(1, lambda: {EVENT: [event_line(event)]})

    # --- status -----------------------------------------------------------------------
    def status(self) -> InfluxStatus:
        counts = self.spool.counts()
        return InfluxStatus(
            spool=counts,
            forwarder=self.forwarder.status(),
            queued=self.writer.queued,
            dropped=counts.dropped + self.writer.unspooled_drops,
            spool_error=self.writer.error or "",
        )

    def _publish_status(self, db: TagDB) -> None:
        st = self.status()
        fs = st.forwarder
        tags = self._tags
        db.update(tags["influx.spool_depth"], st.spool.waiting)
        db.update(tags["influx.spool_bytes"], st.spool.waiting_bytes)
        db.update(tags["influx.drain_rate"], fs.drain_rate)
        db.update(tags["influx.sent"], st.spool.sent)
        db.update(tags["influx.dead_letters"], st.spool.dead)
        db.update(tags["influx.dropped"], st.dropped)
        db.update(tags["influx.last_error"], st.spool_error or fs.last_error)
        db.update(tags["influx.connected"], fs.connected)
        db.update(tags["influx.failed_writes"], fs.failed_writes)
        db.update(tags["influx.timeouts"], fs.timeouts)
        if self.alarm is not None:
            self._publish_alarms(st)

    def _publish_alarms(self, st: InfluxStatus) -> None:
        fs = st.forwarder
        s = self.settings
        failure = fs.failure
        if self._spool_problem and self.writer.commits:
            self._spool_problem = ""  # the new spool works: the alarm returns to normal
        active = (
            failure in CONFIGURATION,
            failure in TRANSIENT and fs.failing_s >= s.alarm_after_s,
            bool(fs.dead_alarm),
            self.spool.overflowing or self.writer.unspooled_drops > 0,
            bool(st.spool_error or self._spool_problem),
        )
        if active == self._alarms_active:
            return  # every scan: the messages are made only for a change
        self._alarms_active = active
        messages: dict[str, Callable[[], str]] = {
            ALARM_CONFIG: lambda: (
                f"InfluxDB {s.url} bucket {s.bucket!r} refuses every write ({fs.last_error});"
                " points are kept in the spool"
            ),
            ALARM_UNREACHABLE: lambda: (
                f"InfluxDB {s.url} has not accepted a write for {s.alarm_after_s:g} s"
                f" ({fs.last_error}); points wait in the spool"
            ),
            ALARM_DEAD_LETTERS: lambda: (
                f"InfluxDB refused points for good ({fs.dead_alarm}); they are in the"
                f" dead-letter table of {s.spool_path}"
            ),
            ALARM_SPOOL_FULL: lambda: (
                f"spool {s.spool_path} full ({s.spool_max_bytes} bytes) or not keeping up:"
                " the oldest points are dropped"
            ),
            ALARM_SPOOL: lambda: (
                f"spool {s.spool_path}: "
                + (
                    st.spool_error
                    or f"unreadable ({self._spool_problem}), moved to {self.spool.moved_to};"
                    " a new spool started"
                )
            ),
        }
        assert self.alarm is not None
        for (alarm_id, message), on in zip(messages.items(), active, strict=True):
            previous = self._alarms.get(alarm_id)
            if previous is None and not on:
                continue
            if previous is None or previous[0] != on:
                self._alarms[alarm_id] = (on, message())
                try:
                    self.alarm(alarm_id, on, self._alarms[alarm_id][1])
                except Exception:  # the alarm model's fault must not stop the publisher
                    log.exception("InfluxDB writer: alarm %s could not be set", alarm_id)
