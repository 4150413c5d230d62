"""The historian's one writer thread: a bounded queue in, one transaction per interval out.

The scan hands over each scan's copied changes (``put_batches``, filtered into samples on
the writer's thread) or samples (``put_samples``) and the bench's events
(``put_event``): a lock, a length check and an append, never the disk. One thread owns
the file: every ``commit_interval_s`` it writes everything queued in one transaction
(SQLite's cost is per transaction, not per row: thousands of rows cost one journal sync),
and between two commits it runs retention in bounded chunks, so a long delete never holds
the write lock for long and never delays a commit by more than one chunk.

Nothing is lost silently (docs/adr/0013-historian.md):

- **A full queue** (the disk slower than the scan for longer than the queue holds) drops
  the newest samples, never blocks the scan: each dropped row is counted
  (``rows_dropped``) and the owner raises an alarm. The rows already queued stay queued
  (a contiguous past is worth more than a scattered one), and the owner resends every
  tag's current value once there is room again, so a trend shows a gap, never a stale
  value. Events have their own queue and count (``events_dropped``).
- **A failed write** (disk full, read-only file system, locked) rolls back, keeps its rows
  queued (they still count in the bound), is reported once per distinct cause
  (``error``, the log), counted (``write_errors``), and retried every ``retry_s`` on a
  new connection; the scan never notices. A file found corrupt while running is set aside
  at the next connection, as at open (``store.check``).
- **A crash of the thread** (an exception no write expects: a bug, a value no writer should
  have been handed) is counted (``crashes``, ``write_errors``), said (``error``,
  ``last_crash``, the log with its traceback; the owner raises ``historian.crashed``) and
  the thread starts again after ``retry_s``. The batch it was writing is dropped and
  counted: written again it would crash again (issue 28: one refused value's event
  stopped the writer for good, with nobody told).
- **A clean stop** (``close``) writes everything queued before the thread ends; a killed
  process loses what was not committed yet: one ``commit_interval_s`` of samples (plus the
  rows of a commit under way), or the whole queue if the disk had fallen behind.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from supervisor.core.encoding import storable, storable_text
from supervisor.core.gate import ScanGate
from supervisor.core.quality import Quality
from supervisor.core.records import BenchEvent, storable_event
from supervisor.publish.changes import ChangeBatch, ChangeFilter, Sample
from supervisor.publish.historian.store import (
    CORRUPT_ERRORS,
    SetAside,
    TagInfo,
    check,
    connect,
    error_name,
    on_disk_bytes,
    size_cache,
    used_bytes,
)

log = logging.getLogger(__name__)

Describe = Callable[[str], TagInfo]
"""What the dictionary stores for a tag name (its unit, dtype, description)."""
ConnectHook = Callable[[sqlite3.Connection], None]

SIZE_TARGET_FRACTION = 0.9
"""Retention by size deletes down to this fraction of ``max_bytes``: a file at its bound
would otherwise run a delete at every pass."""
GATE_ROWS = 500
"""Rows inserted between two looks at the scan gate (``executemany`` takes the interpreter
lock back for every row; a batch of ten thousand rows in one call is milliseconds of it)."""
SIZE_ROUNDS = 20
"""Estimates of the cut-off time per retention pass (each one deletes the slice of time
the file's average rate says is too much; the next one corrects it)."""


@dataclass(frozen=True)
class WriterSettings:
    commit_interval_s: float = 0.5
    queue_max_rows: int = 200_000
    events_max: int = 10_000
    max_age_s: float = 90 * 86400.0
    max_bytes: int = 1024**3
    retention_period_s: float = 60.0
    retry_s: float = 1.0
    chunk_rows: int = 20_000
    """Rows deleted per retention transaction."""
    vacuum_pages: int = 2048
    """Free pages given back to the file system per transaction (8 MiB of 4 KiB pages)."""


@dataclass(frozen=True)
class OpenReport:
    """What ``open`` found."""

    set_aside: SetAside | None = None
    error: str | None = None  # the file could not be opened (the thread keeps trying)


class HistoryWriter:
    """Samples and events into the history file, from one thread of its own."""

    def __init__(
        self,
        path: str | Path,
        settings: WriterSettings,
        describe: Describe,
        *,
        wall: Callable[[], float] = time.time,
        connect_hook: ConnectHook | None = None,
    ) -> None:
        self.path = Path(path)
        self.settings = settings
        self._describe = describe
        self._wall = wall
        self._connect_hook = connect_hook
        self._cond = threading.Condition()
        # Each scan's copied changes (filtered on this thread), or samples put as they are.
        self._samples: deque[Sequence[Sample] | ChangeBatch] = deque()
        self._filter = ChangeFilter()
        self._events: deque[BenchEvent] = deque()
        self._seq = 0  # puts accepted so far
        self._done_seq = 0  # puts written (or given up at stop)
        self._now_wall: float | None = None  # the latest wall time the scan handed in
        self._last_retention_wall: float | None = None
        self._force_retention = False
        # A flush(retention=True) waits for a pass that *starts* after it asks: a pass
        # already running began with an older cut-off and does not answer it.
        self._retention_asked = 0  # requests so far
        self._retention_running = 0  # the requests the running pass answers
        self._retention_answered = 0  # the requests a finished pass answered
        self._flush_req = 0
        self._attempts = 0
        self._stopping = False
        self._stop_deadline = math.inf
        self._thread: threading.Thread | None = None
        self.gate: ScanGate | None = None
        """Write a batch only while the scan is not running (``core/gate.py``; set by the
        bench)."""
        self._conn: sqlite3.Connection | None = None
        self._check_on_connect = False
        self._ids: dict[str, int] = {}  # tag name → id, upserted on this connection
        self._size_warned = False
        # --- status: written under the lock, read from any thread (plain values) ---
        self.queued_rows = 0  # samples accepted and not yet on disk
        self.rows_written = 0
        self.rows_dropped = 0
        self.events_written = 0
        self.events_dropped = 0
        self.rows_deleted = 0  # by retention
        self.events_deleted = 0
        self.write_errors = 0
        self.error: str | None = None  # the last failure; None once a write succeeds
        self.commit_duration_s = 0.0
        self.file_bytes = 0
        self.oldest_wall: float | None = None
        self.retention_runs = 0
        self.set_asides: list[SetAside] = []  # files renamed aside, for the owner's alarm
        self.crashes = 0  # exceptions that escaped the thread's loop (it started again)
        self.last_crash = ""  # the last of them, with its type ("" when none)
        self._in_flight: tuple[int, int, int] | None = None  # rows, events, seq being written

    # --- start and stop (the owner's thread) -----------------------------------------
    def open(self) -> OpenReport:
        """Set an unusable file aside, open (or create) the file, start the thread.
        Blocks for the integrity check (seconds for a file of gigabytes): call it before
        the scan starts, off the event loop."""
        with self._cond:
            known = len(self.set_asides)
        error = None
        try:
            self._conn = self._connect(check_first=True)
            self._measure(self._conn)
        except (sqlite3.Error, OSError) as exc:  # e.g. a folder it may not write in
            error = f"{type(exc).__name__}: {exc}"
            self._failed(exc)
            self._check_on_connect = True  # the thread checks the file when it gets in
        self._stopping = False
        self._stop_deadline = math.inf
        self._thread = threading.Thread(
            target=self._thread_main, name=f"historian:{self.path}", daemon=True
        )
        self._thread.start()
        with self._cond:
            aside = self.set_asides[-1] if len(self.set_asides) > known else None
        return OpenReport(aside, error)

    def close(self, timeout_s: float = 10.0) -> None:
        """Write everything queued (retrying a failed write until ``timeout_s``), then stop
        the thread. What could not be written is counted as dropped and logged."""
        thread = self._thread
        if thread is None:
            return
        with self._cond:
            self._stopping = True
            self._stop_deadline = time.monotonic() + max(0.0, timeout_s - 0.5)
            self._cond.notify_all()
        thread.join(timeout_s)
        if thread.is_alive():
            log.error("history %s: writer did not stop in %g s", self.path, timeout_s)
        self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None

    # --- the scan's side --------------------------------------------------------------
    def put_batches(self, batches: Sequence[ChangeBatch], now_wall: float) -> int:
        """Queue the scan's copied changes (``publish/changes.py``), filtered into samples
        on this writer's thread; returns how many changes had to be dropped (0 unless the
        queue is full). The queue counts a change as a row until it is filtered (at most
        one sample each). Never blocks."""
        n = 0
        for b in batches:
            n += len(b.changes)
        with self._cond:
            self._now_wall = now_wall
            if not n and not self._filter.holding:
                return 0  # nothing to store, nothing held back to release
            room = self.settings.queue_max_rows - self.queued_rows
            dropped = 0
            if room < n:
                dropped = n - max(room, 0)
                self.rows_dropped += dropped
                if room <= 0:
                    return dropped
                kept: list[ChangeBatch] = []
                for b in batches:  # the oldest changes first, as they came
                    if room <= 0:
                        break
                    if len(b.changes) > room:
                        b = b._replace(changes=b.changes[:room])
                    kept.append(b)
                    room -= len(b.changes)
                batches = kept
                n -= dropped
            self._samples.extend(batches)
            self.queued_rows += n
            self._seq += 1
            return dropped

    def put_samples(self, samples: Sequence[Sample], now_wall: float) -> int:
        """Queue one scan's samples (the caller must not change the sequence afterwards);
        returns how many had to be dropped (0 unless the queue is full). Never blocks."""
        n = len(samples)
        with self._cond:
            self._now_wall = now_wall
            if not n:
                return 0
            room = self.settings.queue_max_rows - self.queued_rows
            if room < n:
                dropped = n - max(room, 0)
                self.rows_dropped += dropped
                if room <= 0:
                    return dropped
                samples = samples[:room]  # the oldest of this scan first (take() order)
                n = room
            else:
                dropped = 0
            self._samples.append(samples)
            self.queued_rows += n
            self._seq += 1
            return dropped

    def put_event(self, event: BenchEvent) -> bool:
        """Queue one event; False when it had to be dropped (counted). Never blocks."""
        with self._cond:
            if len(self._events) >= self.settings.events_max:
                self.events_dropped += 1
                return False
            self._events.append(event)
            self._seq += 1
            return True

    # --- waiting (tests, shutdown, tools) ---------------------------------------------
    def flush(self, timeout_s: float = 10.0, *, retention: bool = False) -> bool:
        """Wait until everything put so far is on disk (True); False when a write of it
        failed or ``timeout_s`` passed. ``retention=True`` also runs a retention pass
        now and waits for its end."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            target = self._seq
            asked = 0
            if retention:
                self._retention_asked += 1
                asked = self._retention_asked
                self._force_retention = True
            attempts = self._attempts
            self._flush_req += 1
            self._cond.notify_all()
            while self._done_seq < target or self._retention_answered < asked:
                if self._thread is None:
                    return False
                if self.error is not None and self._attempts > attempts:
                    return False
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    # --- the thread -------------------------------------------------------------------
    def _thread_main(self) -> None:
        """``_run``, started again after an exception escaped it: nothing a writer is
        handed may stop the history for good."""
        while True:
            try:
                self._run()
                return
            except Exception as exc:
                self._crashed(exc)
            with self._cond:
                if self._stopping and time.monotonic() >= self._stop_deadline:
                    self._give_up()
                    return
                if not self._stopping:
                    self._cond.wait(self.settings.retry_s)

    def _crashed(self, exc: Exception) -> None:
        """Count and say a crash; drop the batch it was writing (counted)."""
        why = f"writer thread crashed ({type(exc).__name__}: {exc}); restarted"
        log.error("history %s: %s", self.path, why, exc_info=exc)
        self._drop_connection()
        with self._cond:
            self.crashes += 1
            self.last_crash = why
            self.error = why
            self.write_errors += 1
            self._attempts += 1
            if self._retention_running > self._retention_answered:
                self._force_retention = True  # the pass it was running is run again
            if self._in_flight is not None:
                rows, events, upto = self._in_flight
                self._in_flight = None
                self.rows_dropped += rows
                self.events_dropped += events
                self.queued_rows -= rows
                self._done_seq = max(self._done_seq, upto)
            self._cond.notify_all()

    def _run(self) -> None:
        settings = self.settings
        job: Iterator[None] | None = None
        next_commit = time.monotonic() + settings.commit_interval_s
        flush_seen = 0
        try:
            while True:
                with self._cond:
                    while True:
                        now = time.monotonic()
                        has = bool(self._samples or self._events)
                        urgent = self._stopping or self._flush_req != flush_seen
                        if has and (urgent or now >= next_commit):
                            break
                        if self._stopping or job is not None or self._retention_wanted():
                            break
                        if urgent:
                            flush_seen = self._flush_req  # nothing to write for it
                            continue
                        wait = next_commit - now if has else settings.commit_interval_s
                        self._cond.wait(max(wait, 0.001))
                    flush_seen = self._flush_req
                    stopping = self._stopping
                    take = has and (urgent or now >= next_commit)
                    if take:
                        taken, self._samples = self._samples, deque()
                        events, self._events = self._events, deque()
                        upto = self._seq
                    start_retention = (
                        job is None and not stopping and not take and self._retention_wanted()
                    )
                    if start_retention:
                        self._force_retention = False
                        self._retention_running = self._retention_asked
                        self._last_retention_wall = self._now_wall
                        known = self._now_wall
                        retention_wall = known if known is not None else self._wall()
                if take:
                    ok, samples = self._write_queued(taken, events, upto)
                    if ok:
                        next_commit = time.monotonic() + settings.commit_interval_s
                    else:
                        job = None  # its connection is gone
                        with self._cond:  # back at the front, in order, still counted
                            self._samples.extendleft(reversed(samples))
                            self._events.extendleft(reversed(events))
                            if stopping and time.monotonic() >= self._stop_deadline:
                                self._give_up()
                                return
                        next_commit = time.monotonic() + settings.retry_s
                        self._wait_retry(next_commit)
                    continue
                if stopping:
                    return
                if start_retention:
                    job = self._retention_job(retention_wall)
                if job is not None:
                    try:
                        next(job)
                    except StopIteration:
                        job = None
                        self._retention_done()
                    except (sqlite3.Error, OSError) as exc:
                        job = None
                        self._failed(exc)
                        self._retention_done()
        finally:
            if self._conn is not None:
                with contextlib.suppress(sqlite3.Error):
                    self._conn.close()
                self._conn = None

    def _write_queued(
        self, taken: deque[Sequence[Sample] | ChangeBatch], events: deque[BenchEvent], upto: int
    ) -> tuple[bool, deque[Sequence[Sample]]]:
        """Filter what was taken from the queue and write it: (written, the samples)."""
        if self.gate is not None:
            self.gate.wait()  # the batch's rows are made while no scan runs
        self._in_flight = (_rows_of(taken), len(events), upto)
        samples = self._filtered(taken)
        self._in_flight = (sum(len(b) for b in samples), len(events), upto)
        if not samples and not events:
            self._nothing_to_write(upto)
            ok = True
        else:
            ok = self._write_batch(samples, events, upto)
        self._in_flight = None
        return ok, samples

    def _filtered(self, items: deque[Sequence[Sample] | ChangeBatch]) -> deque[Sequence[Sample]]:
        """The queued batches of changes as samples (``ChangeFilter``, this thread's alone),
        a scan's batch at a time with the scan's turn in between; what the filter does not
        keep leaves the queue's count. Samples put back after a failed write stay as they
        are (filtered once)."""
        out: deque[Sequence[Sample]] = deque()
        unkept = 0
        for item in items:
            if type(item) is ChangeBatch:
                self._give_way()
                samples = self._filter.apply(item)
                unkept += len(item.changes) - len(samples)
                if samples:
                    out.append(samples)
            elif item:
                out.append(item)  # type: ignore[arg-type]
        if unkept:
            with self._cond:
                self.queued_rows -= unkept
        return out

    def _nothing_to_write(self, upto: int) -> None:
        """Every change of the batch was filtered out: the puts so far are done."""
        with self._cond:
            self._done_seq = max(self._done_seq, upto)
            self._cond.notify_all()

    def _retention_wanted(self) -> bool:
        if self._force_retention:
            return True
        if self._now_wall is None:
            return False
        last = self._last_retention_wall
        return last is None or self._now_wall - last >= self.settings.retention_period_s

    def _wait_retry(self, until: float) -> None:
        """After a failure: wait ``retry_s``, or less if a flush asks or the stop comes
        (one attempt at once, then ``retry_s`` again until the stop's deadline)."""
        with self._cond:
            flush, stopping = self._flush_req, self._stopping
            while self._flush_req == flush and self._stopping == stopping:
                left = min(until, self._stop_deadline) - time.monotonic()
                if left <= 0:
                    return
                self._cond.wait(left)

    def _give_up(self) -> None:
        """At stop, after the last attempt failed: what is still queued is lost, said."""
        rows = self.queued_rows
        events = len(self._events)
        self.rows_dropped += rows
        self.events_dropped += events
        self.queued_rows = 0
        self._samples.clear()
        self._events.clear()
        self._done_seq = self._seq
        self._cond.notify_all()
        log.error(
            "history %s: stopped with %d samples and %d events NOT written (%s)",
            self.path,
            rows,
            events,
            self.error,
        )

    # --- connection -------------------------------------------------------------------
    def _connect(self, check_first: bool) -> sqlite3.Connection:
        if check_first:
            aside = check(self.path, self._wall())
            if aside is not None:
                with self._cond:
                    self.set_asides.append(aside)
        conn = connect(self.path)
        try:
            if self._connect_hook is not None:
                self._connect_hook(conn)
        except BaseException:
            conn.close()
            raise
        self._ids = {}
        return conn

    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            check_first, self._check_on_connect = self._check_on_connect, False
            self._conn = self._connect(check_first)
            self._measure(self._conn)
        return self._conn

    def _drop_connection(self) -> None:
        if self._conn is not None:
            with contextlib.suppress(sqlite3.Error):
                self._conn.close()
            self._conn = None

    def _failed(self, exc: BaseException) -> None:
        """Report a failure once per distinct cause; reconnect next time."""
        why = f"{type(exc).__name__}: {exc}"
        if error_name(exc) in CORRUPT_ERRORS:
            self._check_on_connect = True  # set the damaged file aside, start a new one
        self._drop_connection()
        with self._cond:
            first = self.error != why
            self.error = why
            self.write_errors += 1
            self._attempts += 1
            self._cond.notify_all()
        if first:
            log.error("history %s: write failed (%s); retrying", self.path, why)

    # --- writing ----------------------------------------------------------------------
    def _write_batch(
        self, samples: deque[Sequence[Sample]], events: deque[BenchEvent], upto: int
    ) -> bool:
        t0 = time.perf_counter()
        new: dict[str, int] = {}
        n_rows = 0
        try:
            conn = self._connection()
            conn.execute("BEGIN IMMEDIATE")
            try:
                rows = self._rows(conn, samples, new)
                n_rows = len(rows)
                for k in range(0, n_rows, GATE_ROWS):
                    self._give_way()
                    conn.executemany(
                        "INSERT OR REPLACE INTO samples (tag_id, t, value, quality)"
                        " VALUES (?, ?, ?, ?)",
                        rows[k : k + GATE_ROWS],
                    )
                if events:
                    conn.executemany(
                        "INSERT INTO events (wall, kind, channel, source, text, actor,"
                        " severity, test_id, recipe) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        [
                            (
                                e.wall,
                                e.kind,
                                e.channel,
                                e.source,
                                e.text,
                                e.actor,
                                e.severity,
                                e.test_id,
                                e.recipe,
                            )
                            for e in map(storable_event, events)
                        ],
                    )
                conn.execute("COMMIT")
            except BaseException:
                with contextlib.suppress(sqlite3.Error):
                    conn.execute("ROLLBACK")
                raise
        except (sqlite3.Error, OSError) as exc:
            self._failed(exc)
            return False
        if new:
            self._ids.update(new)
            with contextlib.suppress(sqlite3.Error):  # a smaller cache costs reads, no data
                size_cache(conn, len(self._ids))
        duration = time.perf_counter() - t0
        size = on_disk_bytes(self.path)
        oldest = self._batch_oldest(samples, events)
        with self._cond:
            if self.error is not None:
                log.warning("history %s: writing again (%s before)", self.path, self.error)
            self.error = None
            self._attempts += 1
            self.rows_written += n_rows
            self.events_written += len(events)
            self.queued_rows -= n_rows
            self._done_seq = upto
            self.commit_duration_s = duration
            self.file_bytes = size
            if oldest is not None and (self.oldest_wall is None or oldest < self.oldest_wall):
                self.oldest_wall = oldest
            self._cond.notify_all()
        return True

    def _rows(
        self,
        conn: sqlite3.Connection,
        samples: deque[Sequence[Sample]],
        new: dict[str, int],
    ) -> list[tuple[int, float, object, Quality]]:
        """The rows of a batch, a scan's samples at a time; a tag first seen on this
        connection is upserted into the dictionary first. Values are stored as they are:
        the tag database has made a non-finite value BAD, so it arrives here as None
        (``ChangeFeed``)."""
        ids = self._ids
        if any(s.name not in ids for b in samples for s in b):
            for name in {s.name for b in samples for s in b if s.name not in ids}:
                new[name] = self._upsert_tag(conn, name)
            ids = {**ids, **new}
        rows: list[tuple[int, float, object, Quality]] = []
        extend = rows.extend
        for b in samples:
            # A scan's samples at a time, the scan's turn in between: a second of changes
            # in the load case is ten thousand rows, 5 ms of the interpreter lock in one go.
            self._give_way()
            # A text value is stored escaped when UTF-8 cannot encode it (a lone
            # surrogate: ``core/encoding.py``); sqlite3 would raise for the whole batch.
            extend([(ids[s.name], s.wall, storable(s.value), s.quality) for s in b])
        return rows

    def _give_way(self) -> None:
        """Between two pieces of a batch: wait while a scan runs (``core/gate.py``)."""
        if self.gate is not None:
            self.gate.wait()

    def _upsert_tag(self, conn: sqlite3.Connection, name: str) -> int:
        """The tag's id, its unit, dtype and description as this run declares them."""
        info = self._describe(name)
        row = conn.execute(
            "INSERT INTO tags (name, unit, dtype, description) VALUES (?, ?, ?, ?)"
            " ON CONFLICT (name) DO UPDATE SET unit = excluded.unit, dtype = excluded.dtype,"
            " description = excluded.description RETURNING id",
            (
                storable_text(name),
                storable_text(info.unit),
                storable_text(info.dtype),
                storable_text(info.description),
            ),
        ).fetchone()
        return int(row[0])

    @staticmethod
    def _batch_oldest(samples: deque[Sequence[Sample]], events: deque[BenchEvent]) -> float | None:
        first = [b[0].wall for b in samples if b]
        if events:
            first.append(min(e.wall for e in events))
        return min(first) if first else None

    def _measure(self, conn: sqlite3.Connection) -> None:
        """The file's size and its oldest sample or event (after open and retention)."""
        oldest = oldest_wall(conn)
        size = on_disk_bytes(self.path)
        with self._cond:
            self.oldest_wall = oldest
            self.file_bytes = size

    # --- retention --------------------------------------------------------------------
    def _retention_done(self) -> None:
        with self._cond:
            self.retention_runs += 1
            self._retention_answered = max(self._retention_answered, self._retention_running)
            self._cond.notify_all()

    def _retention_job(self, now_wall: float) -> Iterator[None]:
        """One retention pass, one transaction per step (the thread writes due batches
        between steps): by age, then by size (oldest first), then the free pages back
        to the file system."""
        conn = self._connection()
        settings = self.settings
        deleted = yield from self._delete_before(conn, now_wall - settings.max_age_s)
        for _ in range(SIZE_ROUNDS):
            used = used_bytes(conn)
            if used <= settings.max_bytes:
                self._size_warned = False
                break
            oldest = oldest_wall(conn)
            if oldest is None:
                self._warn_size(used)
                break
            # The slice of the oldest history that, at the file's average rate, holds
            # what is above the target (at least a millisecond: always some progress).
            target = SIZE_TARGET_FRACTION * settings.max_bytes
            span = max(now_wall - oldest, 0.0)
            cutoff = oldest + max((used - target) / used * span, 1e-3)
            n = yield from self._delete_before(conn, cutoff)
            deleted += n
            if n == 0 and cutoff > now_wall:
                self._warn_size(used)
                break
        yield from self._vacuum(conn)
        self._measure(conn)
        if deleted:
            log.info(
                "history %s: retention deleted %d rows; %d bytes on disk",
                self.path,
                deleted,
                self.file_bytes,
            )

    def _warn_size(self, used: int) -> None:
        if not self._size_warned:
            self._size_warned = True
            log.warning(
                "history %s: %d bytes in use, above max_bytes %d, with nothing old left to delete",
                self.path,
                used,
                self.settings.max_bytes,
            )

    def _delete_before(self, conn: sqlite3.Connection, cutoff: float) -> Generator[None, None, int]:
        """Delete every sample and event older than ``cutoff`` (wall s), at most
        ``chunk_rows`` per transaction. Returns (as the generator's value) the rows
        deleted."""
        chunk = self.settings.chunk_rows
        ids = [r[0] for r in conn.execute("SELECT id FROM tags ORDER BY id")]
        total = 0
        i = 0
        events_left = True
        while i < len(ids) or events_left:
            budget = chunk
            n_samples = n_events = 0
            conn.execute("BEGIN IMMEDIATE")
            try:
                while i < len(ids) and budget > 0:
                    tag_id = ids[i]
                    # The row ``budget`` places past the tag's oldest: delete before it
                    # (exactly ``budget`` rows), or all the old rows when there is none.
                    row = conn.execute(
                        "SELECT t FROM samples WHERE tag_id = ? AND t < ?"
                        " ORDER BY t LIMIT 1 OFFSET ?",
                        (tag_id, cutoff, budget),
                    ).fetchone()
                    bound = cutoff if row is None else row[0]
                    n = conn.execute(
                        "DELETE FROM samples WHERE tag_id = ? AND t < ?", (tag_id, bound)
                    ).rowcount
                    budget -= n
                    n_samples += n
                    if row is None:
                        i += 1
                if budget > 0 and events_left:
                    n_events = conn.execute(
                        "DELETE FROM events WHERE id IN"
                        " (SELECT id FROM events WHERE wall < ? ORDER BY wall LIMIT ?)",
                        (cutoff, budget),
                    ).rowcount
                    events_left = n_events == budget
                conn.execute("COMMIT")
            except BaseException:
                with contextlib.suppress(sqlite3.Error):
                    conn.execute("ROLLBACK")
                raise
            total += n_samples + n_events
            with self._cond:
                self.rows_deleted += n_samples
                self.events_deleted += n_events
            yield
        return total

    def _vacuum(self, conn: sqlite3.Connection) -> Iterator[None]:
        """Give the free pages back to the file system (``auto_vacuum = INCREMENTAL``), a
        bounded number per step, then checkpoint so that the file itself shrinks (in WAL
        mode the main file is truncated when the WAL is copied back into it)."""
        pages = self.settings.vacuum_pages
        while conn.execute("PRAGMA freelist_count").fetchone()[0] > 0:
            conn.execute(f"PRAGMA incremental_vacuum({pages})").fetchall()
            yield
        # TRUNCATE also empties the -wal; busy (a reader's snapshot) just means later.
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()


def oldest_wall(conn: sqlite3.Connection) -> float | None:
    """The wall time of the oldest sample or event (each tag's first row by its key)."""
    row = conn.execute(
        "SELECT min((SELECT min(t) FROM samples WHERE tag_id = tags.id)) FROM tags"
    ).fetchone()
    ev = conn.execute("SELECT min(wall) FROM events").fetchone()
    found = [v for v in (row[0] if row else None, ev[0] if ev else None) if v is not None]
    return float(min(found)) if found else None


def _rows_of(items: deque[Sequence[Sample] | ChangeBatch]) -> int:
    """The rows queued items count for: a change each until filtered, then a sample each."""
    return sum(len(b.changes) if type(b) is ChangeBatch else len(b) for b in items)
