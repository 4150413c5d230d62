"""Reading the history: raw samples, min/max/mean per interval, events.

For the HTTP API (``supervisor.hmi.history_api``), OPC UA HistoryRead and the screens'
trends. Thread-safe: one read connection of its own (WAL: readers never wait for the
writer, and the writer never waits for them), used under a lock; call it off the event
loop (``asyncio.to_thread``), a long range takes milliseconds to seconds.

Times are Unix seconds (wall). Every answer carries the tag's unit and dtype, and every
value its quality; a BAD sample has no value (None).

Aggregation is one ``GROUP BY`` on the bucket number ``(t - start) // interval_s``: the
rows of a tag are stored by (tag, time), so a week of 1 s samples (604 800 rows) is one
range scan and about a thousand buckets, one request. ``mean`` is the mean of the stored
samples, not weighted by time: with a deadband or a minimum interval, a steady value
weighs less than a moving one. ``first``/``last`` are the first and last values (not BAD)
of the bucket; ``quality`` is the worst of its samples.
"""

from __future__ import annotations

import math
import sqlite3
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from supervisor.core.driver import Value
from supervisor.core.quality import Quality
from supervisor.publish.historian.store import BUSY_TIMEOUT_S, TagInfo

MAX_BUCKETS: Final = 10_000
"""Buckets per aggregate request at most (a trend is about a thousand pixels wide)."""
MAX_RAW_ROWS: Final = 100_000
"""Raw samples per request at most."""
MAX_EVENTS: Final = 100_000
EVENT_KINDS: Final = ("step", "state", "message", "alarm", "command")


class UnknownTag(LookupError):
    """The history holds nothing of this tag."""

    def __init__(self, name: str) -> None:
        super().__init__(f"no history of tag {name!r}")
        self.name = name


class BadRange(ValueError):
    """A time range, interval or limit that cannot be answered (the message says why)."""


@dataclass(frozen=True, slots=True)
class StoredSample:
    t: float  # wall (s)
    value: Value | None  # None when BAD
    quality: Quality


@dataclass(frozen=True)
class Series:
    """Raw samples of one tag in [start, end]; ``before`` is the last sample before
    ``start`` (what a trend draws from its left edge), ``truncated`` that more samples
    than ``limit`` are in the range."""

    tag: TagInfo
    start: float
    end: float
    samples: list[StoredSample]
    truncated: bool
    before: StoredSample | None


@dataclass(frozen=True, slots=True)
class Bucket:
    """One interval [t, t + interval_s) of a tag (the last one also holds ``end``)."""

    t: float
    count: int  # values (samples not BAD)
    samples: int  # every sample, BAD ones included
    min: float | None
    max: float | None
    mean: float | None
    first: Value | None
    last: Value | None
    quality: Quality  # the worst of the bucket


@dataclass(frozen=True)
class Aggregate:
    tag: TagInfo
    start: float
    end: float
    interval_s: float
    buckets: list[Bucket]  # only the buckets that hold samples, in time order


@dataclass(frozen=True, slots=True)
class StoredEvent:
    wall: float
    kind: str
    channel: str
    source: str
    text: str
    actor: str
    severity: int
    test_id: str
    recipe: str


def check_range(start_wall: float, end_wall: float) -> None:
    for name, v in (("start", start_wall), ("end", end_wall)):
        if not math.isfinite(v):
            raise BadRange(f"{name} must be a finite time, got {v}")
    if start_wall > end_wall:
        raise BadRange(f"start ({start_wall:.3f}) is after end ({end_wall:.3f})")


def bucket_count(start_wall: float, end_wall: float, interval_s: float) -> int:
    """Buckets of ``interval_s`` in [start, end] (at least one)."""
    return max(1, math.ceil((end_wall - start_wall) / interval_s))


def check_interval(start_wall: float, end_wall: float, interval_s: float) -> int:
    """The number of buckets; BadRange when the interval is not usable."""
    if not (math.isfinite(interval_s) and interval_s > 0):
        raise BadRange(f"interval_s must be a finite number > 0, got {interval_s}")
    n = bucket_count(start_wall, end_wall, interval_s)
    if n > MAX_BUCKETS:
        least = (end_wall - start_wall) / MAX_BUCKETS
        raise BadRange(
            f"interval_s={interval_s:g} over {end_wall - start_wall:g} s gives {n} buckets,"
            f" at most {MAX_BUCKETS}: use interval_s >= {least:.6g}"
        )
    return n


def _typed(value: object, dtype: str) -> Value | None:
    """A stored value as the tag's type (booleans are stored as 0/1; a non-finite number,
    which the tag database never passes as a value, is no value)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return None
    if dtype == "bool":
        return bool(value)
    if dtype == "float" and isinstance(value, int | float):
        return float(value)
    if dtype == "int" and isinstance(value, float) and value.is_integer():
        return int(value)
    return value  # type: ignore[return-value]


def _quality(q: object) -> Quality:
    try:
        return Quality(int(q))  # type: ignore[call-overload]
    except (TypeError, ValueError):
        return Quality.BAD


def _stored(t: float, value: object, quality: object, dtype: str) -> StoredSample:
    """A row as a sample: no value is BAD, whatever was stored with it (SQLite keeps a NaN
    as NULL)."""
    v = _typed(value, dtype)
    return StoredSample(t, v, Quality.BAD if v is None else _quality(quality))


class HistoryQuery:
    """Read access to one history file (it may not exist yet: then nothing is known)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._conn: sqlite3.Connection | None = None
        self._inode: tuple[int, int] | None = None

    # --- connection -------------------------------------------------------------------
    def _connection(self) -> sqlite3.Connection | None:
        """The read connection, reopened when the file was replaced (set aside)."""
        try:
            st = self.path.stat()
        except FileNotFoundError:
            self._close()
            return None
        inode = (st.st_dev, st.st_ino)
        if self._conn is not None and inode == self._inode:
            return self._conn
        self._close()
        # mode=rw: never creates the file; query_only: never writes it.
        conn = sqlite3.connect(
            f"file:{self.path}?mode=rw",
            uri=True,
            timeout=BUSY_TIMEOUT_S,
            check_same_thread=False,
        )
        conn.execute("PRAGMA query_only = ON")
        self._conn, self._inode = conn, inode
        return conn

    def _close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
            self._inode = None

    def close(self) -> None:
        with self._lock:
            self._close()

    # --- tags -------------------------------------------------------------------------
    def tags(self) -> list[TagInfo]:
        """Every tag the history holds, by name."""
        with self._lock:
            conn = self._connection()
            if conn is None:
                return []
            rows = conn.execute(
                "SELECT name, unit, dtype, description FROM tags ORDER BY name"
            ).fetchall()
        return [TagInfo(*r) for r in rows]

    def tag(self, name: str) -> TagInfo | None:
        with self._lock:
            found = self._tag(name)
        return None if found is None else found[1]

    def _tag(self, name: str) -> tuple[int, TagInfo] | None:
        conn = self._connection()
        if conn is None:
            return None
        try:
            row = conn.execute(
                "SELECT id, name, unit, dtype, description FROM tags WHERE name = ?", (name,)
            ).fetchone()
        except sqlite3.OperationalError:  # a file being created: no table yet
            return None
        return None if row is None else (int(row[0]), TagInfo(*row[1:]))

    def _known(self, name: str) -> tuple[sqlite3.Connection, int, TagInfo]:
        found = self._tag(name)
        if found is None or self._conn is None:
            raise UnknownTag(name)
        return self._conn, found[0], found[1]

    # --- samples ----------------------------------------------------------------------
    def samples(self, tag: str, start_wall: float, end_wall: float, limit: int = 10_000) -> Series:
        """Raw samples of ``tag`` with ``start <= t <= end``, oldest first, at most
        ``limit`` (``truncated`` says there were more)."""
        check_range(start_wall, end_wall)
        if not 1 <= limit <= MAX_RAW_ROWS:
            raise BadRange(f"limit must be between 1 and {MAX_RAW_ROWS}, got {limit}")
        with self._lock:
            conn, tag_id, info = self._known(tag)
            rows = conn.execute(
                "SELECT t, value, quality FROM samples WHERE tag_id = ? AND t >= ? AND t <= ?"
                " ORDER BY t LIMIT ?",
                (tag_id, start_wall, end_wall, limit + 1),
            ).fetchall()
            prev = conn.execute(
                "SELECT t, value, quality FROM samples WHERE tag_id = ? AND t < ?"
                " ORDER BY t DESC LIMIT 1",
                (tag_id, start_wall),
            ).fetchone()
        dtype = info.dtype
        out = [_stored(t, v, q, dtype) for t, v, q in rows[:limit]]
        before = None if prev is None else _stored(prev[0], prev[1], prev[2], dtype)
        return Series(info, start_wall, end_wall, out, len(rows) > limit, before)

    def count(self, tag: str, start_wall: float, end_wall: float) -> int:
        """Samples of ``tag`` in [start, end]."""
        check_range(start_wall, end_wall)
        with self._lock:
            conn, tag_id, _ = self._known(tag)
            row = conn.execute(
                "SELECT count(*) FROM samples WHERE tag_id = ? AND t >= ? AND t <= ?",
                (tag_id, start_wall, end_wall),
            ).fetchone()
        return int(row[0])

    def aggregate(
        self, tag: str, start_wall: float, end_wall: float, interval_s: float
    ) -> Aggregate:
        """min/max/mean/count/first/last of ``tag`` per ``interval_s`` over [start, end]."""
        check_range(start_wall, end_wall)
        n = check_interval(start_wall, end_wall, interval_s)
        with self._lock:
            conn, tag_id, info = self._known(tag)
            rows = conn.execute(
                _AGGREGATE,
                {
                    "id": tag_id,
                    "s": start_wall,
                    "e": end_wall,
                    "i": interval_s,
                    "last": n - 1,
                },
            ).fetchall()
        numeric = info.dtype != "str"
        dtype = info.dtype
        buckets = [
            Bucket(
                t=start_wall + k * interval_s,
                count=int(count),
                samples=int(total),
                min=float(mn) if numeric and mn is not None else None,
                max=float(mx) if numeric and mx is not None else None,
                mean=float(av) if numeric and av is not None else None,
                first=_typed(first, dtype),
                last=_typed(last, dtype),
                quality=_quality(q),
            )
            for k, mn, mx, av, count, total, q, first, last in rows
        ]
        return Aggregate(info, start_wall, end_wall, interval_s, buckets)

    # --- events -----------------------------------------------------------------------
    def events(
        self,
        start_wall: float,
        end_wall: float,
        channel: str | None = None,
        kind: str | None = None,
        limit: int = 10_000,
    ) -> list[StoredEvent]:
        """Events with ``start <= wall <= end``, oldest first, optionally of one channel
        ("" = the bench's own) and one kind; at most ``limit``."""
        check_range(start_wall, end_wall)
        if kind is not None and kind not in EVENT_KINDS:
            raise BadRange(f"unknown event kind {kind!r} (one of {', '.join(EVENT_KINDS)})")
        if not 1 <= limit <= MAX_EVENTS:
            raise BadRange(f"limit must be between 1 and {MAX_EVENTS}, got {limit}")
        sql = [
            "SELECT wall, kind, channel, source, text, actor, severity, test_id, recipe"
            " FROM events WHERE wall >= ? AND wall <= ?"
        ]
        args: list[object] = [start_wall, end_wall]
        if channel is not None:
            sql.append("AND channel = ?")
            args.append(channel)
        if kind is not None:
            sql.append("AND kind = ?")
            args.append(kind)
        sql.append("ORDER BY wall, id LIMIT ?")
        args.append(limit)
        with self._lock:
            conn = self._connection()
            if conn is None:
                return []
            try:
                rows: Sequence[tuple[object, ...]] = conn.execute(" ".join(sql), args).fetchall()
            except sqlite3.OperationalError:  # a file being created: no table yet
                return []
        return [StoredEvent(*r) for r in rows]  # type: ignore[arg-type]


# Values of a bucket: min/max/avg skip NULL (BAD) values; ``first``/``last`` are looked up
# by their time through the primary key (tag_id, t), two index seeks per bucket. The last
# bucket also takes the samples at ``end`` itself (the range is closed).
_AGGREGATE = """
WITH b AS (
    SELECT min(CAST((t - :s) / :i AS INTEGER), :last) AS k,
           min(value) AS mn, max(value) AS mx, avg(value) AS av,
           count(value) AS n, count(*) AS total, max(quality) AS q,
           min(t) FILTER (WHERE value IS NOT NULL) AS t0,
           max(t) FILTER (WHERE value IS NOT NULL) AS t1
    FROM samples WHERE tag_id = :id AND t >= :s AND t <= :e
    GROUP BY k
)
SELECT k, mn, mx, av, n, total, q,
       (SELECT value FROM samples WHERE tag_id = :id AND t = b.t0) AS first,
       (SELECT value FROM samples WHERE tag_id = :id AND t = b.t1) AS last
FROM b ORDER BY k
"""
