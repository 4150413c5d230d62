"""The edge node's store and forward: the samples it could not send, on disk until a new
session replays them (docs/sparkplug.md "Store and forward").

``<state_dir>/sparkplug-spool.sqlite``, SQLite in WAL mode, one table of samples in the
order they happened (an ``AUTOINCREMENT`` id: "oldest first" is "smallest id first", also
across restarts). A sample is kept as what it is (tag, type, unit, value, quality, its own
acquisition time), not as an encoded message: a Sparkplug message carries the ``seq`` of
the session that sends it, which the session that replays it decides.

Why not the InfluxDB spool (``supervisor.publish.influx.spool``): its rows are line
protocol, counted per measurement and joined by line breaks; Sparkplug samples are neither.
What is shared is the rule: bounded in bytes, the oldest dropped past the bound and counted,
``synchronous=NORMAL`` (a committed sample survives the process being killed), a file that
cannot be read moved aside and a new spool started.

Used by the edge node's thread only (one connection, no lock needed beyond it); the
counters are plain ints that the scan's side reads for the status tags.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Final

from supervisor.core.driver import DType
from supervisor.core.quality import Quality
from supervisor.publish.sparkplug.node import Metric

__all__ = ["SPOOL_NAME", "SampleSpool", "Spooled"]

log = logging.getLogger(__name__)

SPOOL_NAME: Final = "sparkplug-spool.sqlite"
FORMAT: Final = 1
"""Layout version; a file of another version is moved aside, not migrated."""
ROW_OVERHEAD_BYTES: Final = 32
"""What a row costs besides its text (the id, the numbers, SQLite's own): the bound is on
an estimate of the file's payload, not on the file's size."""

_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS sample ("
    " id INTEGER PRIMARY KEY AUTOINCREMENT, tag TEXT NOT NULL, dtype TEXT NOT NULL,"
    " unit TEXT NOT NULL, value TEXT NOT NULL, quality INTEGER NOT NULL,"
    " wall_ms INTEGER NOT NULL, bytes INTEGER NOT NULL)",
)

Spooled = tuple[int, str, Metric]
"""(row id, tag name, sample)."""


def _row(tag: str, m: Metric) -> tuple[str, str, str, str, int, int, int]:
    value = json.dumps(m.value)  # None, bool, int, float (NaN too) and str round-trip
    size = len(tag) + len(m.unit) + len(value) + ROW_OVERHEAD_BYTES
    return tag, m.dtype, m.unit, value, int(m.quality), m.wall_ms, size


class SampleSpool:
    """Samples waiting for a connection, oldest first, at most ``max_bytes`` of them.

    ``path`` None: in memory (a bench without a state folder, the tests)."""

    def __init__(self, path: Path | None, max_bytes: int) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self.waiting = 0
        """Samples in the spool."""
        self.waiting_bytes = 0
        self.dropped = 0
        """Samples dropped by the bound since this process opened the spool."""
        self.overflowing = False
        """The bound dropped samples and the spool has not gone below 90 % since."""
        self.moved_to: Path | None = None
        self._conn: sqlite3.Connection | None = None

    # --- lifecycle --------------------------------------------------------------------
    def open(self) -> None:
        """Open (or create) the file; one that cannot be read is moved aside."""
        if self._conn is not None:
            return
        try:
            self._conn = self._connect()
        except sqlite3.DatabaseError as exc:
            assert self.path is not None  # an in-memory database is always readable
            self.moved_to = self.path.with_name(f"{self.path.name}.bad-{int(time.time())}")
            self.path.replace(self.moved_to)
            log.error(
                "Sparkplug spool %s unreadable (%s): moved to %s, a new spool started",
                self.path,
                exc,
                self.moved_to,
            )
            self._conn = self._connect()
        n, size = self._conn.execute(
            "SELECT COUNT(*), COALESCE(SUM(bytes), 0) FROM sample"
        ).fetchone()
        self.waiting, self.waiting_bytes = int(n), int(size)
        if self.waiting:
            log.info("Sparkplug spool %s: %d samples wait from a previous run", self.path, n)

    def _connect(self) -> sqlite3.Connection:
        target = ":memory:" if self.path is None else str(self.path)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        conn = sqlite3.connect(target, check_same_thread=False, isolation_level=None)
        try:
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
            for statement in _SCHEMA:
                conn.execute(statement)
            row = conn.execute("SELECT value FROM meta WHERE key = 'format'").fetchone()
            if row is None:
                conn.execute("INSERT INTO meta (key, value) VALUES ('format', ?)", (str(FORMAT),))
            elif row[0] != str(FORMAT):
                raise sqlite3.DatabaseError(f"format {row[0]}, expected {FORMAT}")
        except sqlite3.DatabaseError:
            conn.close()
            raise
        return conn

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def _need(self) -> sqlite3.Connection:
        if self._conn is None:
            self.open()
        assert self._conn is not None
        return self._conn

    # --- the offline side -------------------------------------------------------------
    def append(self, samples: Sequence[tuple[str, Metric]]) -> int:
        """Keep ``samples`` (in order) in one transaction, then drop the oldest past the
        bound. Returns the samples dropped."""
        if not samples:
            return 0
        rows = [_row(tag, m) for tag, m in samples]
        conn = self._need()
        with conn:
            conn.execute("BEGIN")
            conn.executemany(
                "INSERT INTO sample (tag, dtype, unit, value, quality, wall_ms, bytes)"
                " VALUES (?, ?, ?, ?, ?, ?, ?)",
                rows,
            )
            self.waiting += len(rows)
            self.waiting_bytes += sum(r[-1] for r in rows)
            dropped = self._enforce_bound(conn)
        if dropped:
            if not self.overflowing:
                log.warning(
                    "Sparkplug spool full (%d bytes): its oldest samples are dropped",
                    self.max_bytes,
                )
            self.overflowing = True
            self.dropped += dropped
        return dropped

    def _enforce_bound(self, conn: sqlite3.Connection) -> int:
        dropped = 0
        while self.waiting_bytes > self.max_bytes:
            rows = conn.execute("SELECT id, bytes FROM sample ORDER BY id LIMIT 1024").fetchall()
            if not rows:
                break
            last_id = 0
            for row_id, size in rows:
                if self.waiting_bytes <= self.max_bytes:
                    break
                last_id = int(row_id)
                self.waiting_bytes -= int(size)
                self.waiting -= 1
                dropped += 1
            conn.execute("DELETE FROM sample WHERE id <= ?", (last_id,))
        return dropped

    # --- the replay side --------------------------------------------------------------
    def oldest(self, limit: int) -> list[Spooled]:
        """At most ``limit`` samples, oldest first (they stay until ``remove``)."""
        rows = (
            self._need()
            .execute(
                "SELECT id, tag, dtype, unit, value, quality, wall_ms FROM sample"
                " ORDER BY id LIMIT ?",
                (limit,),
            )
            .fetchall()
        )
        out: list[Spooled] = []
        for row_id, tag, dtype, unit, value, quality, wall_ms in rows:
            dt: DType = dtype
            m = Metric(dt, unit, json.loads(value), Quality(quality), int(wall_ms))
            out.append((int(row_id), str(tag), m))
        return out

    def remove(self, up_to_id: int) -> None:
        """The samples up to ``up_to_id`` were sent."""
        conn = self._need()
        with conn:
            conn.execute("BEGIN")
            size = conn.execute(
                "SELECT COUNT(*), COALESCE(SUM(bytes), 0) FROM sample WHERE id <= ?", (up_to_id,)
            ).fetchone()
            conn.execute("DELETE FROM sample WHERE id <= ?", (up_to_id,))
        self.waiting -= int(size[0])
        self.waiting_bytes -= int(size[1])
        if self.overflowing and self.waiting_bytes <= 0.9 * self.max_bytes:
            self.overflowing = False
