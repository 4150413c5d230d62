"""The store-and-forward spool: line protocol on disk until InfluxDB acknowledged it.

``<state_dir>/influx-spool.sqlite``, SQLite in WAL mode (docs/adr/0012-influx-spool.md):

- ``chunk``: one row per measurement per writer commit (at most ``batch_size`` lines each,
  joined by line breaks), with an ``AUTOINCREMENT`` id: ids only grow, also across
  restarts and after the table was emptied, so "oldest first" is "smallest id first";
- ``meta.acked_id``: every chunk up to this id was acknowledged by InfluxDB (a 2xx). An
  acknowledgement commits only this watermark and the counters (a small transaction on
  the forwarder's path); the rows behind it are deleted by the writer thread in its next
  transaction, and at open;
- ``dead_letter``: lines InfluxDB refused for good (a 400 isolated to that one line), with
  the status and the server's reason; at most ``DEAD_LETTER_ROWS`` rows, the oldest go;
- ``counter``: points produced, sent, dropped and dead-lettered, per measurement, kept in
  the same transactions as the rows they count: in every committed state
  ``produced = sent + dropped + dead + waiting``.

The bound is on the waiting lines' bytes (``max_bytes``): past it the oldest chunks that are
not being sent are dropped and counted. ``synchronous=NORMAL``: a committed chunk survives
the process being killed at any point; a power cut may lose the last commits, never corrupt
the file. A file that cannot be read (corrupt, not SQLite, another format) is moved aside
and a new spool started.

One connection, shared by the writer thread and the forwarder thread under a lock: every
operation is a short local transaction (the network is never waited for under it). The
bodies of the chunks this process appended are also kept in memory (at most
``CACHE_BYTES``), so that sending what was just spooled does not read it back from disk.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from supervisor.publish.influx.lineproto import line_measurement

__all__ = [
    "CACHE_BYTES",
    "DEAD_LETTER_ROWS",
    "SPOOL_NAME",
    "Batch",
    "Chunk",
    "DeadLetter",
    "Spool",
    "SpoolCounts",
]

log = logging.getLogger(__name__)

SPOOL_NAME = "influx-spool.sqlite"
FORMAT = 1
"""Layout version; a file of another version is moved aside, not migrated."""
DEAD_LETTER_ROWS = 100_000
"""Dead letters kept at most (the oldest are deleted past it, with a log line)."""
CACHE_BYTES = 32 * 1024 * 1024
"""Bodies of freshly spooled chunks kept in memory for the forwarder."""

_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS chunk ("
    " id INTEGER PRIMARY KEY AUTOINCREMENT, measurement TEXT NOT NULL,"
    " points INTEGER NOT NULL, bytes INTEGER NOT NULL, spooled_wall REAL NOT NULL,"
    " body BLOB NOT NULL)",
    "CREATE TABLE IF NOT EXISTS dead_letter ("
    " id INTEGER PRIMARY KEY AUTOINCREMENT, wall REAL NOT NULL, measurement TEXT NOT NULL,"
    " status INTEGER NOT NULL, reason TEXT NOT NULL, line TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS counter (name TEXT PRIMARY KEY, value INTEGER NOT NULL)",
)


@dataclass(frozen=True, slots=True)
class Chunk:
    id: int
    measurement: str
    points: int
    bytes: int


@dataclass(frozen=True, slots=True)
class Batch:
    """The oldest waiting chunks, as one request body."""

    chunks: tuple[Chunk, ...]
    body: bytes
    oldest_wall: float

    @property
    def ids(self) -> tuple[int, ...]:
        return tuple(c.id for c in self.chunks)

    @property
    def points(self) -> int:
        return sum(c.points for c in self.chunks)

    def lines(self) -> list[bytes]:
        return self.body.split(b"\n")


@dataclass(frozen=True, slots=True)
class DeadLetter:
    line: bytes
    status: int
    reason: str


@dataclass(frozen=True, slots=True)
class SpoolCounts:
    """Points waiting now, and totals since the spool file was created (they survive
    restarts)."""

    waiting: int = 0  # points in the spool, not yet acknowledged
    waiting_bytes: int = 0
    chunks: int = 0
    produced: int = 0
    sent: int = 0
    dropped: int = 0
    dead: int = 0
    dead_letters: int = 0  # rows in the dead-letter table now
    by_measurement: dict[str, dict[str, int]] = field(default_factory=dict)


@dataclass
class _Txn:
    """What one transaction changes, applied to the in-memory totals after its commit."""

    chunks: int = 0
    points: int = 0
    nbytes: int = 0
    dead_rows: int = 0
    acked_id: int | None = None
    overflowing: bool | None = None
    counters: dict[str, int] = field(default_factory=dict)
    cached: list[tuple[int, bytes]] = field(default_factory=list)
    uncached: list[int] = field(default_factory=list)

    def add(self, key: str, n: int) -> None:
        self.counters[key] = self.counters.get(key, 0) + n


class Spool:
    """Line-protocol chunks on disk, oldest first."""

    def __init__(
        self,
        path: str | Path,
        max_bytes: int,
        *,
        wall: Callable[[], float] = time.time,
        cache_bytes: int = CACHE_BYTES,
    ) -> None:
        if max_bytes <= 0:
            raise ValueError("max_bytes must be > 0")
        self.path = Path(path)
        self.max_bytes = max_bytes
        self.cache_bytes = cache_bytes
        self._wall = wall
        self._lock = threading.Lock()  # the connection and its transactions
        # The in-memory totals, for readers that must not wait for a transaction (the
        # scan's status tags): held only while the totals are copied or changed.
        self._stats = threading.Lock()
        self._conn: sqlite3.Connection | None = None
        self._acked_id = 0
        self._purged_id = 0  # rows up to here are deleted
        self._waiting = 0
        self._waiting_bytes = 0
        self._chunks = 0
        self._dead_rows = 0
        self._counters: dict[str, int] = {}
        self._inflight: set[int] = set()
        self._cache: OrderedDict[int, bytes] = OrderedDict()
        self._cached_bytes = 0
        self.overflowing = False  # dropped since the spool was last below 90 % of its bound
        self.problem = ""  # what open() found wrong with the file ("" when fine)
        self.moved_to: Path | None = None

    # --- lifecycle --------------------------------------------------------------------
    def open(self) -> None:
        """Open (or create) the file; one that cannot be read is moved aside and a new one
        started (``problem`` and ``moved_to`` say so). Raises OSError or sqlite3.Error when
        the file cannot be opened at all (permissions, a full disk)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            conn = self._connect()
        except sqlite3.OperationalError:
            raise  # cannot open it (permissions, locked, read-only): not the file's content
        except (sqlite3.DatabaseError, ValueError) as exc:
            self.problem = str(exc) or type(exc).__name__
            self.moved_to = self._move_aside()
            log.error(
                "InfluxDB spool %s unreadable (%s): moved to %s; a new spool starts",
                self.path,
                self.problem,
                self.moved_to,
            )
            conn = self._connect()
        with self._lock:
            self._conn = conn
            self._load(conn)
            txn = _Txn()

            def tidy(c: sqlite3.Connection) -> int:
                self._purge(c)  # what the last run acknowledged but did not delete yet
                return self._enforce_bound(c, txn)  # e.g. the bound was lowered

            self._run(tidy, txn)

    @property
    def is_open(self) -> bool:
        return self._conn is not None

    def close(self) -> None:
        with self._lock:
            conn, self._conn = self._conn, None
            self._cache.clear()
            self._cached_bytes = 0
        if conn is not None:
            with contextlib.suppress(sqlite3.Error):
                conn.close()

    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(
            self.path, isolation_level=None, timeout=10.0, check_same_thread=False
        )
        try:
            row = conn.execute("PRAGMA quick_check").fetchone()
            if row is None or row[0] != "ok":
                raise ValueError(f"integrity check: {row[0] if row else 'no answer'}")
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
            # The WAL file is truncated back to this after a checkpoint (the bound on the
            # lines is max_bytes; this keeps the file next to it from staying large).
            conn.execute("PRAGMA journal_size_limit=67108864")
            tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
            if tables and "meta" not in tables:
                raise ValueError("not an InfluxDB spool of this supervisor")
            for stmt in _SCHEMA:
                conn.execute(stmt)
            fmt = conn.execute("SELECT value FROM meta WHERE key = 'format'").fetchone()
            if fmt is None:
                conn.execute("INSERT INTO meta (key, value) VALUES ('format', ?)", (str(FORMAT),))
            elif fmt[0] != str(FORMAT):
                raise ValueError(f"format {fmt[0]}, this supervisor reads format {FORMAT}")
        except BaseException:
            conn.close()
            raise
        return conn

    def _move_aside(self) -> Path:
        stamp = time.strftime("%Y%m%dT%H%M%S", time.localtime(self._wall()))
        target = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
        n = 1
        while target.exists():
            n += 1
            target = self.path.with_name(f"{self.path.name}.corrupt-{stamp}-{n}")
        self.path.replace(target)
        for suffix in ("-wal", "-shm"):
            side = self.path.with_name(self.path.name + suffix)
            if side.exists():
                side.replace(target.with_name(target.name + suffix))
        return target

    def _load(self, conn: sqlite3.Connection) -> None:
        row = conn.execute("SELECT value FROM meta WHERE key = 'acked_id'").fetchone()
        self._acked_id = int(row[0]) if row is not None else 0
        self._purged_id = 0  # unknown: the first purge deletes whatever is behind acked_id
        n, points, size = conn.execute(
            "SELECT COUNT(*), COALESCE(SUM(points), 0), COALESCE(SUM(bytes), 0)"
            " FROM chunk WHERE id > ?",
            (self._acked_id,),
        ).fetchone()
        dead_rows = int(conn.execute("SELECT COUNT(*) FROM dead_letter").fetchone()[0])
        counters = {k: int(v) for k, v in conn.execute("SELECT name, value FROM counter")}
        with self._stats:
            self._chunks, self._waiting, self._waiting_bytes = int(n), int(points), int(size)
            self._dead_rows = dead_rows
            self._counters = counters

    # --- the writer's side --------------------------------------------------------------
    def append(
        self, items: Iterable[tuple[str, Sequence[str]]], max_chunk_points: int, extra: int = 0
    ) -> tuple[int, int]:
        """Spool lines (``(measurement, lines)`` items) in one transaction, in chunks of at
        most ``max_chunk_points`` lines, after deleting the acknowledged chunks; then drop
        the oldest past the bound. ``extra``: points dropped before they reached the spool
        (a full in-memory queue), counted here. Returns (points spooled, points dropped
        by the bound)."""
        wall = self._wall()
        rows: list[tuple[str, int, int, float, bytes]] = []
        for measurement, lines in items:
            for k in range(0, len(lines), max_chunk_points):
                part = lines[k : k + max_chunk_points]
                body = "\n".join(part).encode("utf-8")
                rows.append((measurement, len(part), len(body), wall, body))
        inserted = sum(r[1] for r in rows)
        if not rows and not extra:
            return 0, 0
        txn = _Txn()
        if extra:
            txn.add("produced:queue", extra)
            txn.add("dropped:queue", extra)

        def work(conn: sqlite3.Connection) -> int:
            self._purge(conn)
            for row in rows:
                cursor = conn.execute(
                    "INSERT INTO chunk (measurement, points, bytes, spooled_wall, body)"
                    " VALUES (?, ?, ?, ?, ?)",
                    row,
                )
                assert cursor.lastrowid is not None
                measurement, n, size, _, body = row
                txn.add(f"produced:{measurement}", n)
                txn.chunks += 1
                txn.points += n
                txn.nbytes += size
                txn.cached.append((cursor.lastrowid, body))
            return self._enforce_bound(conn, txn)

        with self._lock:
            dropped = self._run(work, txn)
        return inserted, dropped

    def purge(self) -> None:
        """Delete the acknowledged chunks now (``append`` does it too)."""
        with self._lock:
            self._run(self._purge, _Txn())

    def _purge(self, conn: sqlite3.Connection) -> int:
        if self._acked_id > self._purged_id:
            conn.execute("DELETE FROM chunk WHERE id <= ?", (self._acked_id,))
            self._purged_id = self._acked_id
        return 0

    def _enforce_bound(self, conn: sqlite3.Connection, txn: _Txn) -> int:
        """Delete the oldest waiting chunks not being sent until the lines fit
        ``max_bytes`` (inside the caller's transaction, recorded in ``txn``). Returns the
        points dropped."""
        size = self._waiting_bytes + txn.nbytes
        dropped = 0
        last_id = self._acked_id
        while size > self.max_bytes:
            rows = conn.execute(
                "SELECT id, measurement, points, bytes FROM chunk WHERE id > ?"
                " ORDER BY id LIMIT 256",
                (last_id,),
            ).fetchall()
            if not rows:
                break
            gone: list[tuple[int]] = []
            for cid, measurement, points, nbytes in rows:
                last_id = int(cid)
                if size <= self.max_bytes:
                    break
                if cid in self._inflight:
                    continue
                gone.append((int(cid),))
                size -= int(nbytes)
                dropped += int(points)
                txn.add(f"dropped:{measurement}", int(points))
                txn.chunks -= 1
                txn.points -= int(points)
                txn.nbytes -= int(nbytes)
                txn.uncached.append(int(cid))
            conn.executemany("DELETE FROM chunk WHERE id = ?", gone)
        if dropped:
            txn.overflowing = True
        elif self.overflowing and size <= 0.9 * self.max_bytes:
            txn.overflowing = False
        return dropped

    # --- the forwarder's side -----------------------------------------------------------
    @property
    def waiting(self) -> int:
        """Points in the spool, not yet acknowledged."""
        return self._waiting

    def oldest_wall(self) -> float | None:
        """When the oldest waiting chunk was spooled (Unix s); None when there is none."""
        with self._lock:
            row = (
                self._need()
                .execute(
                    "SELECT spooled_wall FROM chunk WHERE id > ? ORDER BY id LIMIT 1",
                    (self._acked_id,),
                )
                .fetchone()
            )
        return None if row is None else float(row[0])

    def next_batch(self, max_points: int) -> Batch | None:
        """The oldest waiting chunks, together at most ``max_points`` lines (at least one
        chunk); they are not dropped by the bound until ``ack`` or ``release``."""
        chunks: list[Chunk] = []
        points = 0
        oldest = 0.0
        with self._lock:
            conn = self._need()
            cursor = conn.execute(
                "SELECT id, measurement, points, bytes, spooled_wall FROM chunk"
                " WHERE id > ? ORDER BY id",
                (self._acked_id,),
            )
            try:
                for cid, measurement, n, size, wall in cursor:
                    if chunks and points + n > max_points:
                        break
                    if not chunks:
                        oldest = float(wall)
                    chunks.append(Chunk(int(cid), str(measurement), int(n), int(size)))
                    points += int(n)
            finally:
                cursor.close()
            if not chunks:
                return None
            bodies = {c.id: self._cache.get(c.id) for c in chunks}
            missing = [cid for cid, body in bodies.items() if body is None]
            for k in range(0, len(missing), 500):
                part = missing[k : k + 500]
                for cid, body in conn.execute(
                    f"SELECT id, body FROM chunk WHERE id IN ({','.join('?' * len(part))})",
                    part,
                ):
                    bodies[int(cid)] = bytes(body)
            self._inflight = {c.id for c in chunks}
        body = b"\n".join(bodies[c.id] or b"" for c in chunks)
        return Batch(tuple(chunks), body, oldest)

    def release(self) -> None:
        """The batch is not being sent any more (a failure: it stays, oldest first)."""
        with self._lock:
            self._inflight = set()

    def ack(self, batch: Batch, dead: Sequence[DeadLetter] = ()) -> None:
        """InfluxDB accepted ``batch`` (except the ``dead`` lines, refused for good): move
        the watermark past it and record the dead letters, in one transaction."""
        wall = self._wall()
        txn = _Txn(acked_id=max(batch.ids))
        for c in batch.chunks:
            txn.add(f"sent:{c.measurement}", c.points)
            txn.chunks -= 1
            txn.points -= c.points
            txn.nbytes -= c.bytes
            txn.uncached.append(c.id)
        rows = []
        for d in dead:
            m = line_measurement(d.line)
            rows.append((wall, m, d.status, d.reason, d.line.decode("utf-8", "replace")))
            txn.add(f"sent:{m}", -1)
            txn.add(f"dead:{m}", 1)

        def work(conn: sqlite3.Connection) -> int:
            conn.execute(
                "INSERT INTO meta (key, value) VALUES ('acked_id', ?)"
                " ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (str(txn.acked_id),),
            )
            if rows:
                conn.executemany(
                    "INSERT INTO dead_letter (wall, measurement, status, reason, line)"
                    " VALUES (?, ?, ?, ?, ?)",
                    rows,
                )
                txn.dead_rows += len(rows)
                excess = self._dead_rows + txn.dead_rows - DEAD_LETTER_ROWS
                if excess > 0:
                    conn.execute(
                        "DELETE FROM dead_letter WHERE id IN"
                        " (SELECT id FROM dead_letter ORDER BY id LIMIT ?)",
                        (excess,),
                    )
                    txn.dead_rows -= excess
                    log.warning(
                        "InfluxDB spool %s: %d oldest dead letters deleted (at most %d kept)",
                        self.path,
                        excess,
                        DEAD_LETTER_ROWS,
                    )
            if self.overflowing and self._waiting_bytes + txn.nbytes <= 0.9 * self.max_bytes:
                txn.overflowing = False
            return 0

        with self._lock:
            try:
                self._run(work, txn)
            finally:
                self._inflight = set()

    # --- views ------------------------------------------------------------------------
    def counts(self) -> SpoolCounts:
        """Never waits for a transaction (the scan's thread calls it)."""
        with self._stats:
            counters = dict(self._counters)
            waiting, size, chunks = self._waiting, self._waiting_bytes, self._chunks
            dead_rows = self._dead_rows
        by: dict[str, dict[str, int]] = {}
        totals = {"produced": 0, "sent": 0, "dropped": 0, "dead": 0}
        for key, value in counters.items():
            what, _, measurement = key.partition(":")
            if what in totals:
                totals[what] += value
                by.setdefault(measurement, {})[what] = value
        return SpoolCounts(
            waiting=waiting,
            waiting_bytes=size,
            chunks=chunks,
            produced=totals["produced"],
            sent=totals["sent"],
            dropped=totals["dropped"],
            dead=totals["dead"],
            dead_letters=dead_rows,
            by_measurement=by,
        )

    def dead_letters(self, limit: int = 100) -> list[tuple[float, int, str, str]]:
        """The newest dead letters: (wall, status, reason, line)."""
        with self._lock:
            rows = (
                self._need()
                .execute(
                    "SELECT wall, status, reason, line FROM dead_letter ORDER BY id DESC LIMIT ?",
                    (limit,),
                )
                .fetchall()
            )
        return [(float(w), int(s), str(r), str(line)) for w, s, r, line in rows]

    def waiting_ids(self) -> list[int]:
        """Ids of the waiting chunks, oldest first (for checks and tools)."""
        with self._lock:
            rows = (
                self._need()
                .execute("SELECT id FROM chunk WHERE id > ? ORDER BY id", (self._acked_id,))
                .fetchall()
            )
        return [int(r[0]) for r in rows]

    # --- helpers ----------------------------------------------------------------------
    def _need(self) -> sqlite3.Connection:
        if self._conn is None:
            raise sqlite3.ProgrammingError(f"InfluxDB spool {self.path} is not open")
        return self._conn

    def _run(self, work: Callable[[sqlite3.Connection], int], txn: _Txn) -> int:
        """``work`` and ``txn``'s counters in one transaction (the caller holds the lock);
        the in-memory state follows only after the commit."""
        conn = self._need()
        purged = self._purged_id
        conn.execute("BEGIN IMMEDIATE")
        try:
            result = work(conn)
            conn.executemany(
                "INSERT INTO counter (name, value) VALUES (?, ?)"
                " ON CONFLICT(name) DO UPDATE SET value = value + excluded.value",
                [(k, v) for k, v in txn.counters.items() if v],
            )
            conn.execute("COMMIT")
        except BaseException:
            self._purged_id = purged
            with contextlib.suppress(sqlite3.Error):
                conn.execute("ROLLBACK")
            raise
        with self._stats:
            self._chunks += txn.chunks
            self._waiting += txn.points
            self._waiting_bytes += txn.nbytes
            self._dead_rows += txn.dead_rows
            for k, v in txn.counters.items():
                self._counters[k] = self._counters.get(k, 0) + v
        if txn.acked_id is not None:
            self._acked_id = txn.acked_id
        if txn.overflowing is not None:
            self.overflowing = txn.overflowing
        cache = self._cache
        for cid in txn.uncached:
            body = cache.pop(cid, None)
            if body is not None:
                self._cached_bytes -= len(body)
        for cid, body in txn.cached:
            cache[cid] = body
            self._cached_bytes += len(body)
        while self._cached_bytes > self.cache_bytes and cache:
            _, body = cache.popitem(last=False)
            self._cached_bytes -= len(body)
        return result
