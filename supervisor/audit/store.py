"""The audit log's file: ``<state_dir>/audit.sqlite``, append-only, written off the caller's
thread (docs/adr/0047-audit-log.md).

``AuditLog.append`` never blocks and never raises: it takes the time, makes the details
canonical JSON and queues the entry (a list append under a lock); one writer thread
numbers, chains and inserts what is queued, in one transaction per batch. The numbering
and the chain are made inside that transaction from the file's last entry, not from a
number kept in memory: two processes appending to one bench's log (the running
supervisor, ``supervisor opcua add-user`` in a shell) serialize on SQLite's write lock and
keep one chain. A failed write (disk full, a read-only file system) keeps the entries,
is logged and counted (``failures``, ``error``) and retried every ``retry_s``; past
``max_pending`` entries waiting, new ones are dropped, counted (``dropped``) and logged,
never silently.

SQLite in WAL mode with ``synchronous=FULL``: an entry committed survives a power cut
(appends are few: a person's actions). Triggers refuse an UPDATE or a DELETE of an entry,
so that no tool changes one by mistake; they stop no one who means to (a trigger can be
dropped): the chain is what shows a change (``verify_file``).
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from supervisor.audit.chain import (
    GENESIS,
    Broken,
    ChainCheck,
    Entry,
    canonical_json,
    entry_hash,
    utc_text,
)
from supervisor.core.encoding import storable_text
from supervisor.core.gate import ScanGate

log = logging.getLogger(__name__)

AUDIT_NAME: Final = "audit.sqlite"
FORMAT: Final = "1"
RETRY_S: Final = 1.0
MAX_PENDING: Final = 10_000
"""Entries waiting for the disk at most (a person's actions: hours of a full disk)."""

_SCHEMA: Final = (
    "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS entries ("
    " seq INTEGER PRIMARY KEY, time TEXT NOT NULL, actor TEXT NOT NULL, kind TEXT NOT NULL,"
    " target TEXT NOT NULL, details TEXT NOT NULL, prev_hash TEXT NOT NULL,"
    " hash TEXT NOT NULL)",
    "CREATE INDEX IF NOT EXISTS entries_time ON entries (time)",
    "CREATE TRIGGER IF NOT EXISTS entries_no_update BEFORE UPDATE ON entries"
    " BEGIN SELECT RAISE(ABORT, 'the audit log is append-only'); END",
    "CREATE TRIGGER IF NOT EXISTS entries_no_delete BEFORE DELETE ON entries"
    " BEGIN SELECT RAISE(ABORT, 'the audit log is append-only'); END",
)
_COLUMNS: Final = "seq, time, actor, kind, target, details, prev_hash, hash"


def audit_path(state_dir: str | Path) -> Path:
    """The audit log of the bench whose state folder is ``state_dir``."""
    return Path(state_dir) / AUDIT_NAME


@dataclass(frozen=True, slots=True)
class _Draft:
    time: str
    actor: str
    kind: str
    target: str
    details: str


class AuditLog:
    """Appends to one audit file, from any thread, without waiting for the disk."""

    def __init__(
        self,
        path: str | Path,
        *,
        wall: Callable[[], float] = time.time,
        retry_s: float = RETRY_S,
        max_pending: int = MAX_PENDING,
    ) -> None:
        self.path = Path(path)
        self._wall = wall
        self.retry_s = retry_s
        self.max_pending = max_pending
        self._cond = threading.Condition()
        self._pending: list[_Draft] = []
        self._stopping = False
        self._retry_now = False
        self._thread: threading.Thread | None = None
        self.gate: ScanGate | None = None
        """Real clock: the writer waits here while a scan runs (``core/gate.py``)."""
        self.appended = 0
        """Entries handed to ``append`` and queued."""
        self.written = 0
        """Entries committed to the file by this process."""
        self.failures = 0
        """Appends refused (details that cannot be encoded) and batches that failed to write."""
        self.dropped = 0
        """Entries dropped because ``max_pending`` were waiting already."""
        self.error: str | None = None
        """The last write's failure; None once a write succeeds."""
        self.head: str = ""
        """The hash of the last entry this process wrote."""

    # --- any thread -------------------------------------------------------------------
    def append(self, actor: str, kind: str, target: str = "", details: Any = None) -> None:
        """Queue one entry (its time is now); returns at once, never raises."""
        try:
            draft = _Draft(
                utc_text(self._wall()),
                storable_text(str(actor)),
                storable_text(str(kind)),
                storable_text(str(target)),
                canonical_json({} if details is None else details),
            )
        except Exception:  # a bug in a caller's details must not reach its command
            with self._cond:
                self.failures += 1
            log.exception("audit %s: entry %s by %s not recorded", self.path, kind, actor)
            return
        with self._cond:
            if len(self._pending) >= self.max_pending:
                self.dropped += 1
                dropped = self.dropped
            else:
                self._pending.append(draft)
                self.appended += 1
                dropped = 0
        if dropped:
            if dropped == 1 or dropped % 1000 == 0:
                log.error(
                    "audit %s: %d entries waiting for the disk; %s by %s dropped (%d so far)",
                    self.path,
                    self.max_pending,
                    kind,
                    actor,
                    dropped,
                )
            return
        if self.gate is not None:
            self.gate.after_scan(self._kick)
        else:
            self._kick()

    def _kick(self) -> None:
        with self._cond:
            self._cond.notify_all()

    @property
    def pending(self) -> int:
        with self._cond:
            return len(self._pending)

    # --- life -------------------------------------------------------------------------
    def open(self) -> AuditLog:
        """Start the writer (the file and its folder are made at the first write)."""
        if self._thread is None:
            self._stopping = False
            self._thread = threading.Thread(
                target=self._run, name=f"audit:{self.path}", daemon=True
            )
            self._thread.start()
        return self

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until every entry queued so far is written (True), or a write failed or
        ``timeout_s`` passed (False). For shutdown, tools and tests."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            target = self.appended
            failures = self.failures
            self._retry_now = True
            self._cond.notify_all()
            while self.written < target:
                if self._thread is None or self.failures > failures:
                    return False
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def close(self, timeout_s: float = 10.0) -> bool:
        """Write what is queued (one last attempt), stop the writer. True when nothing
        queued was left unwritten."""
        thread = self._thread
        if thread is None:
            return self.pending == 0
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        thread.join(timeout_s)
        if thread.is_alive():
            log.error("audit %s: writer did not stop in %g s", self.path, timeout_s)
        self._thread = None
        left = self.pending
        if left:
            log.error("audit %s: %d entries could not be written", self.path, left)
        return left == 0

    def __enter__(self) -> AuditLog:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the writer -------------------------------------------------------------------
    def _run(self) -> None:
        conn: sqlite3.Connection | None = None
        try:
            while True:
                with self._cond:
                    while not self._pending and not self._stopping:
                        self._cond.wait()
                    if not self._pending:
                        return  # stopping, nothing left
                if self.gate is not None:
                    self.gate.wait()  # not against the scan (ADR 0021)
                with self._cond:
                    batch, self._pending = self._pending, []
                try:
                    if conn is None:
                        conn = _connect(self.path)
                    head = _insert(conn, batch)
                except Exception as exc:  # disk full, read-only, locked: keep, retry
                    if conn is not None:
                        with contextlib.suppress(sqlite3.Error):
                            conn.close()
                        conn = None
                    if not self._failed(exc, batch):
                        return
                    continue
                with self._cond:
                    self.written += len(batch)
                    self.head = head
                    if self.error is not None:
                        log.warning("audit %s: writing again", self.path)
                    self.error = None
                    self._cond.notify_all()
        finally:
            if conn is not None:
                with contextlib.suppress(sqlite3.Error):
                    conn.close()

    def _failed(self, exc: Exception, batch: list[_Draft]) -> bool:
        """Keep ``batch`` (first in line), count, log; wait ``retry_s``. False: stop now."""
        why = f"{type(exc).__name__}: {exc}"
        with self._cond:
            self._pending[:0] = batch
            first = self.error != why
            self.error = why
            self.failures += 1
            self._cond.notify_all()
        if first:
            log.error("audit %s: %d entries not written (%s); retrying", self.path, len(batch), why)
        with self._cond:
            if self._stopping:
                return False
            self._retry_now = False
            deadline = time.monotonic() + self.retry_s
            while not (self._retry_now or self._stopping):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
        return True


def _connect(path: Path) -> sqlite3.Connection:
    path.parent.mkdir(parents=True, exist_ok=True)
    conn = sqlite3.connect(path, isolation_level=None, timeout=10.0)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA synchronous=FULL")
    for stmt in _SCHEMA:
        conn.execute(stmt)
    conn.execute("INSERT OR IGNORE INTO meta (key, value) VALUES ('format', ?)", (FORMAT,))
    return conn


def _insert(conn: sqlite3.Connection, batch: list[_Draft]) -> str:
    """Number, chain and insert ``batch`` in one transaction; the new head's hash."""
    conn.execute("BEGIN IMMEDIATE")  # the write lock first: the last entry cannot move
    try:
        row = conn.execute("SELECT seq, hash FROM entries ORDER BY seq DESC LIMIT 1").fetchone()
        seq, head = (int(row[0]), str(row[1])) if row is not None else (0, GENESIS)
        rows = []
        for d in batch:
            seq += 1
            h = entry_hash(seq, d.time, d.actor, d.kind, d.target, d.details, head)
            rows.append((seq, d.time, d.actor, d.kind, d.target, d.details, head, h))
            head = h
        conn.executemany(f"INSERT INTO entries ({_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?, ?)", rows)
        conn.execute("COMMIT")
    except BaseException:
        with contextlib.suppress(sqlite3.Error):
            conn.execute("ROLLBACK")
        raise
    return head


def append_now(
    path: str | Path, actor: str, kind: str, target: str = "", details: Any = None
) -> str | None:
    """One entry written before returning (a command-line tool's action): None when it is
    on disk, else why not (the tool says so; its action is done either way)."""
    audit = AuditLog(path).open()
    audit.append(actor, kind, target, details)
    ok = audit.flush()
    why = audit.error
    audit.close()
    if ok:
        return None
    return why or "not written"


# --- reading ---------------------------------------------------------------------------
class AuditFileError(Exception):
    """The audit file is missing, or is not an audit log this supervisor can read."""


@contextlib.contextmanager
def _reader(path: Path) -> Iterator[sqlite3.Connection]:
    if not path.exists():
        raise AuditFileError(f"{path}: no audit log there (no action recorded yet?)")
    try:
        conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise AuditFileError(f"{path}: cannot open: {exc}") from None
    # A damaged text is read as it is (its bytes escaped), so that the check names the
    # entry rather than failing on its decoding.
    conn.text_factory = lambda b: b.decode("utf-8", "surrogateescape")
    try:
        try:
            conn.execute("SELECT count(*) FROM meta").fetchone()
            fmt = conn.execute("SELECT value FROM meta WHERE key = 'format'").fetchone()
            conn.execute("SELECT seq FROM entries LIMIT 1").fetchall()
        except sqlite3.DatabaseError as exc:
            raise AuditFileError(f"{path}: not an audit log ({exc})") from None
        if fmt is None or fmt[0] != FORMAT:
            found = "none" if fmt is None else fmt[0]
            raise AuditFileError(f"{path}: audit format {found}; this supervisor reads {FORMAT}")
        yield conn
    finally:
        conn.close()


def _entry(row: tuple[Any, ...]) -> Entry:
    return Entry(*row)


@dataclass
class Verification:
    """What ``verify_file`` found."""

    entries: int
    head: str
    """The hash of the last good entry (``GENESIS`` for an empty log)."""
    broken: Broken | None = None
    anchor_found: bool | None = None
    """With an anchor: was it the hash of an entry of the unbroken chain."""
    last_time: str = ""

    @property
    def ok(self) -> bool:
        return self.broken is None and self.anchor_found is not False

    def as_json(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "entries": self.entries,
            "head": self.head,
            "first_broken": self.broken.as_json() if self.broken is not None else None,
        }


def verify_file(path: str | Path, anchor: str | None = None) -> Verification:
    """Check the whole chain of ``path`` in sequence order. ``anchor``: a head hash kept
    elsewhere (exported, published); the log must still hold it. ``AuditFileError`` when
    the file is missing or no audit log."""
    check = ChainCheck()
    if anchor:
        check.hashes_seen = set()
    with _reader(Path(path)) as conn:
        try:
            for row in conn.execute(f"SELECT {_COLUMNS} FROM entries ORDER BY seq"):
                if not check.feed(_entry(row)):
                    break
        except sqlite3.DatabaseError as exc:  # a damaged page: the entries past it unread
            check.unreadable(str(exc))
    v = Verification(check.entries, check.head, check.broken, last_time=check.last_time)
    if anchor and check.hashes_seen is not None:
        v.anchor_found = anchor in check.hashes_seen
    return v


@dataclass(frozen=True)
class Query:
    """Which entries to read: times as ``utc_text`` (or shorter ISO texts), inclusive."""

    since: str = ""
    until: str = ""
    actor: str = ""
    kind: str = ""
    """A kind, or a family of kinds: ``command`` matches ``command.start`` too."""
    channel: str = ""
    """Entries whose target is the channel, or whose details name it (``channel``)."""
    before_seq: int | None = None
    limit: int | None = None
    newest_first: bool = False

    def sql(self) -> tuple[str, list[Any]]:
        where: list[str] = []
        args: list[Any] = []
        if self.since:
            where.append("time >= ?")
            args.append(self.since)
        if self.until:
            where.append("time <= ?")
            args.append(self.until)
        if self.actor:
            where.append("actor = ?")
            args.append(self.actor)
        if self.kind:
            where.append("(kind = ? OR substr(kind, 1, ?) = ?)")
            args += [self.kind, len(self.kind) + 1, self.kind + "."]
        if self.channel:
            where.append(
                "(target = ? OR (json_valid(details) AND json_extract(details, '$.channel') = ?))"
            )
            args += [self.channel, self.channel]
        if self.before_seq is not None:
            where.append("seq < ?")
            args.append(self.before_seq)
        text = f"SELECT {_COLUMNS} FROM entries"
        if where:
            text += " WHERE " + " AND ".join(where)
        text += " ORDER BY seq DESC" if self.newest_first else " ORDER BY seq"
        if self.limit is not None:
            text += " LIMIT ?"
            args.append(self.limit)
        return text, args


def read_entries(path: str | Path, query: Query | None = None) -> list[Entry]:
    """The entries of ``path`` that ``query`` selects (as stored: not verified)."""
    text, args = (query or Query()).sql()
    with _reader(Path(path)) as conn:
        try:
            return [_entry(row) for row in conn.execute(text, args)]
        except sqlite3.DatabaseError as exc:
            raise AuditFileError(f"{path}: cannot read: {exc}") from None
