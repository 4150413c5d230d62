"""The historian as the scan sees it: a publisher and an event sink that only queue.

Each scan ``on_scan`` copies the tag changes (``ChangeSnapshots``, or its reader of the
copy it shares with the InfluxDB writer) and hands them to the writer thread's queue,
where they are filtered into the samples worth storing (``ChangeFilter``: each tag's
deadband and minimum interval, quality changes always) off the scan (issue 30);
``on_event`` does the same for the bench's events. Neither touches the
disk. At the end of the scan it refreshes the ``historian.*`` diagnostic tags and tells the
owner's alarm hook what an operator must know: a file set aside, writes failing, samples
dropped. The alarm model lives in another layer (``supervisor.safety``); the composition
root (``supervisor.app.history``) declares the alarms and passes the hook.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Final

from supervisor.config.models import HistorianConfig
from supervisor.core.clock import Clock
from supervisor.core.records import BenchEvent
from supervisor.publish.changes import ChangeReader, ChangeSnapshots, ChangeSource
from supervisor.publish.historian.query import HistoryQuery
from supervisor.publish.historian.store import TagInfo
from supervisor.publish.historian.writer import (
    ConnectHook,
    HistoryWriter,
    OpenReport,
    WriterSettings,
)
from supervisor.tags import HistorySettings, Tag, TagDB, TagSpec

log = logging.getLogger(__name__)

CORRUPT_ALARM: Final = "historian.corrupt"
"""A history file could not be used and was set aside (a new one started)."""
WRITE_ALARM: Final = "historian.write"
"""Writes fail (disk full, read-only): active until one succeeds."""
OVERFLOW_ALARM: Final = "historian.overflow"
"""Samples or events were dropped because the queue was full: active while it is."""
CRASH_ALARM: Final = "historian.crashed"
"""The writer's thread crashed and was started again (the batch it was writing lost)."""
ALARMS: Final = (CORRUPT_ALARM, WRITE_ALARM, OVERFLOW_ALARM, CRASH_ALARM)

AlarmHook = Callable[[str, bool, str], None]
"""``hook(alarm_id, active, message)``: the owner raises or clears that alarm."""

STATUS_PERIOD_S: Final = 0.1
"""On a real clock the ``historian.*`` tags and alarms are brought up to date at most this
often (the scan's clock), as InfluxDB's are."""
RESYNC_FRACTION: Final = 0.5
"""After an overflow, every tag's value is sent again once the queue is below this
fraction of its bound (a constant tag would otherwise show its last stored value across
the gap)."""

_DIAGNOSTICS: Final = (
    ("queue_rows", "int", "", "Samples waiting for the disk"),
    ("rows_written", "int", "", "Samples written since start"),
    ("rows_dropped", "int", "", "Samples dropped since start (queue full, or lost at stop)"),
    ("events_written", "int", "", "Events written since start"),
    ("events_dropped", "int", "", "Events dropped since start (queue full)"),
    ("rows_deleted", "int", "", "Samples deleted by retention since start"),
    ("write_errors", "int", "", "Failed transactions since start"),
    ("last_error", "str", "", "Why the last write failed ('' once one succeeds)"),
    ("crashes", "int", "", "Times the writer's thread crashed and was started again"),
    ("last_crash", "str", "", "Why the writer's thread last crashed ('' when never)"),
    ("file_bytes", "int", "B", "The history file and its WAL on disk"),
    ("oldest_sample_age_s", "float", "s", "Age of the oldest sample or event kept"),
    ("commit_duration_s", "float", "s", "Duration of the last transaction"),
)
# Counters move every scan at full rate: a trend of them needs no more than one a second.
_DIAG_HISTORY: Final = HistorySettings(min_interval_s=1.0)


def writer_settings(cfg: HistorianConfig) -> WriterSettings:
    return WriterSettings(
        commit_interval_s=cfg.commit_interval_s,
        queue_max_rows=cfg.queue_max_rows,
        max_age_s=cfg.max_age_s,
        max_bytes=cfg.max_bytes,
        retention_period_s=cfg.retention_period_s,
    )


class Historian:
    """``Publisher`` (``on_scan``) and ``EventSink`` (``on_event``) of the history file."""

    name = "historian"

    def __init__(
        self,
        db: TagDB,
        clock: Clock,
        path: str | Path,
        settings: WriterSettings | None = None,
        *,
        alarm: AlarmHook | None = None,
        connect_hook: ConnectHook | None = None,
        changes: ChangeReader | None = None,
    ) -> None:
        self.db = db
        self.clock = clock
        self.path = Path(path)
        self.settings = settings or WriterSettings()
        self._alarm = alarm
        # Its own copies of the changes, or its reader of those it shares with the InfluxDB
        # writer.
        self.source: ChangeSource = changes if changes is not None else ChangeSnapshots(db, clock)
        self.writer = HistoryWriter(
            self.path,
            self.settings,
            self._describe,
            wall=clock.wall,
            connect_hook=connect_hook,
        )
        self.query = HistoryQuery(self.path)
        self.diag: dict[str, Tag] = {}
        for key, dtype, unit, text in _DIAGNOSTICS:
            initial: object = "" if dtype == "str" else (0.0 if dtype == "float" else 0)
            spec = TagSpec(
                f"historian.{key}",
                dtype=dtype,  # type: ignore[arg-type]
                unit=unit,
                description=text,
                initial=initial,  # type: ignore[arg-type]
                history=_DIAG_HISTORY,
            )
            self.diag[key] = db.get(spec.name) or db.add(spec)
        self._reported_asides = 0
        self._reported_crashes = 0
        self._write_alarm = False
        self._overflow_alarm = False
        self._dropped_seen = 0
        self._events_dropped_seen = 0
        self._resync = False
        self._status_t = float("-inf")  # the scan time the diagnostics were last set
        self.opened: OpenReport | None = None

    def _describe(self, name: str) -> TagInfo:
        tag = self.db.get(name)  # a read of an immutable spec: safe from the writer's thread
        if tag is None:
            return TagInfo(name)
        s = tag.spec
        return TagInfo(name, s.unit, s.dtype, s.description)

    # --- lifetime ---------------------------------------------------------------------
    def open(self) -> OpenReport:
        """Check the file (set aside if unusable), open it, start the writer. Blocks:
        call it before the first scan, off the event loop (``start``)."""
        self.opened = self.writer.open()
        if self.opened.set_aside is None and self.opened.error is None:
            log.info("history: %s", self.path)
        return self.opened

    async def start(self) -> OpenReport:
        report = await asyncio.to_thread(self.open)
        self._report()  # the alarms of the open, before the first scan
        return report

    def close(self, timeout_s: float = 10.0) -> None:
        """This scan's last changes, then everything queued to disk, then stop."""
        if not self.writer.running:
            return
        self._take()
        self.writer.close(timeout_s)
        self._closed()

    async def stop(self, timeout_s: float = 10.0) -> None:
        """``close`` with the wait for the disk off the event loop."""
        if not self.writer.running:
            return
        self._take()
        await asyncio.to_thread(self.writer.close, timeout_s)
        self._closed()

    def _closed(self) -> None:
        self.query.close()
        # What could not be written at the stop was logged by the writer (not an overflow).
        self._dropped_seen = self.writer.rows_dropped
        self._events_dropped_seen = self.writer.events_dropped
        self._report()

    # --- the scan's side --------------------------------------------------------------
    def on_scan(self, db: TagDB, t: float) -> None:
        """Queue this scan's changes; refresh the diagnostics; raise or clear alarms."""
        self._take()
        if self.clock.virtual or t - self._status_t > STATUS_PERIOD_S - 1e-9 or t < self._status_t:
            # Every STATUS_PERIOD_S on a real clock, not 100 times a second (thirteen
            # updates a scan, issue 30); every scan on a virtual one (dry runs, tests).
            self._status_t = t
            self._report()

    def on_event(self, event: BenchEvent) -> None:
        self.writer.put_event(event)

    def _take(self) -> None:
        writer = self.writer
        if self._resync and writer.queued_rows <= RESYNC_FRACTION * self.settings.queue_max_rows:
            # Room again after an overflow: fresh copies send every tag's current value
            # once (their first batch is every tag, and starts the writer's filter
            # afresh), which closes the gap in each trend.
            self._resync = False
            if isinstance(self.source, ChangeReader):
                self.source.close()  # a shared copy must not wait for this reader
            self.source = ChangeSnapshots(self.db, self.clock)
            log.warning("history %s: queue has room again; every tag's value sent", self.path)
        if writer.put_batches(self.source.batches(), self.clock.wall()):
            self._resync = True

    def _report(self) -> None:
        w = self.writer
        d = self.diag
        db = self.db
        db.update(d["queue_rows"], w.queued_rows)
        db.update(d["rows_written"], w.rows_written)
        db.update(d["rows_dropped"], w.rows_dropped)
        db.update(d["events_written"], w.events_written)
        db.update(d["events_dropped"], w.events_dropped)
        db.update(d["rows_deleted"], w.rows_deleted)
        db.update(d["write_errors"], w.write_errors)
        db.update(d["last_error"], w.error or "")
        db.update(d["crashes"], w.crashes)
        db.update(d["last_crash"], w.last_crash)
        db.update(d["file_bytes"], w.file_bytes)
        oldest = w.oldest_wall
        db.update(d["oldest_sample_age_s"], 0.0 if oldest is None else self.clock.wall() - oldest)
        db.update(d["commit_duration_s"], w.commit_duration_s)
        alarm = self._alarm
        # A file set aside: raised and cleared at once, so it waits for an acknowledge
        # (the event is over; the operator must know the old history is elsewhere).
        asides = w.set_asides
        while self._reported_asides < len(asides):
            aside = asides[self._reported_asides]
            self._reported_asides += 1
            if alarm is not None:
                alarm(CORRUPT_ALARM, True, aside.text())
                alarm(CORRUPT_ALARM, False, "")
        # A crash: raised and cleared at once like a file set aside (the thread runs again;
        # the operator must know a batch was lost, and a bug is there).
        if w.crashes > self._reported_crashes:
            self._reported_crashes = w.crashes
            if alarm is not None:
                alarm(CRASH_ALARM, True, f"history {self.path}: {w.last_crash}")
                alarm(CRASH_ALARM, False, "")
        error = w.error
        if (error is not None) != self._write_alarm:
            self._write_alarm = error is not None
            if alarm is not None:
                alarm(WRITE_ALARM, self._write_alarm, f"history not written ({self.path}): {error}")
        dropping = (
            w.rows_dropped > self._dropped_seen or w.events_dropped > self._events_dropped_seen
        )
        if dropping:
            text = (
                f"history queue full: {w.rows_dropped} samples and {w.events_dropped} events"
                f" dropped so far ({self.path})"
            )
            if not self._overflow_alarm:
                log.error("%s; the disk is slower than the scan", text)
            self._overflow_alarm = True
            if alarm is not None:
                alarm(OVERFLOW_ALARM, True, text)
        elif self._overflow_alarm and not self._resync:
            self._overflow_alarm = False
            if alarm is not None:
                alarm(OVERFLOW_ALARM, False, "")
        self._dropped_seen = w.rows_dropped
        self._events_dropped_seen = w.events_dropped
