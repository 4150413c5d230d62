"""The retained state of a bench on disk: ``<state_dir>/state.sqlite``.

docs/design.md "Safety": per channel, the state that matters (recipe, step, step time, cycle,
Ah/Wh counters, test id) is persisted, so that after a restart a channel comes back Held
with its test resumable (seed 001 saves its context to EEPROM before every alarm, so an
interrupted test resumes later).

The store is a key → JSON document table; it knows nothing of chains or alarms (the
composition root decides what a document holds). Writing never blocks the scan: the scan
hands over plain documents with ``put`` (a dict assignment under a lock); one worker
thread writes them in a transaction. The queue is bounded by its keys: a newer document
for a key replaces the one not yet written (latest per channel wins). A failed write
(disk full, read-only file system) is kept, reported in ``error`` (the owner raises an
alarm from it) and retried every ``retry_s``; nothing raises into the caller.

SQLite in WAL mode with ``synchronous=NORMAL``: a committed save survives the process
being killed at any point (the case this store is for); a power cut may lose the last
saves, never corrupt the file. A file that cannot be read — corrupt, not SQLite, or of
another ``FORMAT`` — is moved aside (``state.sqlite.corrupt-<time>``) by ``open`` and the
bench starts from nothing, never crashes.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from supervisor.core.encoding import storable_text
from supervisor.core.gate import ScanGate

log = logging.getLogger(__name__)

STATE_NAME = "state.sqlite"
FORMAT = 1
"""Version of the file's layout and of its documents' meaning. A file of another version
is moved aside, not migrated: it is a restart aid, not an archive (the result files are)."""

RETRY_S = 1.0
"""Time between two attempts at a failed write."""

_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS retained ("
    " key TEXT PRIMARY KEY, saved_wall REAL NOT NULL, document TEXT NOT NULL)",
)

Document = dict[str, Any]


@dataclass
class Loaded:
    """What ``open`` found: the documents, or why there are none."""

    documents: dict[str, Document] = field(default_factory=dict)
    problem: str = ""  # "" when the file was fine or absent
    moved_to: Path | None = None  # where an unreadable file went


class RetainStore:
    """Documents by key in one SQLite file, written off the caller's thread."""

    def __init__(
        self,
        path: str | Path,
        *,
        retry_s: float = RETRY_S,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.path = Path(path)
        self.retry_s = retry_s
        self._wall = wall
        self._cond = threading.Condition()
        self._pending: dict[str, tuple[float, Document]] = {}
        self._submitted = 0  # puts so far
        self._written = 0  # puts whose document (or a newer one) is on disk
        self._attempts = 0
        self._busy = False
        self._stopping = False
        self._retry_now = False
        self._thread: threading.Thread | None = None
        self.gate: ScanGate | None = None
        """Real clock: the writer waits here while a scan runs (``core/gate.py``)."""
        self.error: str | None = None  # the last write's failure; None once one succeeds
        self.writes = 0  # transactions committed
        self.failures = 0  # transactions that failed

    # --- startup (caller's thread, before the worker runs) ------------------------------
    def open(self) -> Loaded:
        """Read what the last run left; move an unreadable file aside. Then start the
        worker. Never raises for the file's content."""
        loaded = Loaded()
        if self.path.exists():
            try:
                loaded.documents = self._read()
            except (sqlite3.Error, ValueError) as exc:
                loaded.problem = str(exc) or type(exc).__name__
                try:
                    loaded.moved_to = self._move_aside()
                except OSError as move_exc:
                    loaded.problem += f"; could not move it aside: {move_exc}"
                log.error(
                    "retained state %s unreadable (%s): moved to %s; every channel starts Idle",
                    self.path,
                    loaded.problem,
                    loaded.moved_to,
                )
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:  # the writer reports it (and retries) at its first write
            log.error("retained state %s: cannot create its folder: %s", self.path, exc)
        self._start()
        return loaded

    def _read(self) -> dict[str, Document]:
        conn = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True)
        try:
            row = conn.execute("PRAGMA quick_check").fetchone()
            if row is None or row[0] != "ok":
                raise ValueError(f"integrity check: {row[0] if row else 'no answer'}")
            try:
                fmt = conn.execute("SELECT value FROM meta WHERE key = 'format'").fetchone()
            except sqlite3.OperationalError as exc:
                raise ValueError(f"not a state file of this supervisor ({exc})") from None
            if fmt is None or fmt[0] != str(FORMAT):
                found = "none" if fmt is None else fmt[0]
                raise ValueError(f"format {found}, this supervisor reads format {FORMAT}")
            out: dict[str, Document] = {}
            for key, text in conn.execute("SELECT key, document FROM retained"):
                doc = json.loads(text)
                if not isinstance(doc, dict):
                    raise ValueError(f"document {key!r} is not a mapping")
                out[str(key)] = doc
            return out
        finally:
            conn.close()

    def copy_aside(self) -> Path:
        """Keep a copy of the file as it is now beside it (``state.sqlite.corrupt-<time>``):
        a document the owner refused (a field it does not know) is overwritten by the next
        saves, while the others stay in use; the copy is what a person looks at. SQLite's
        backup, so that what the WAL holds is in the copy. OSError when it cannot be made."""
        target = self._aside_name()
        try:
            src = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True)
            try:
                dst = sqlite3.connect(target)
                try:
                    src.backup(dst)
                finally:
                    dst.close()
            finally:
                src.close()
        except sqlite3.Error as exc:
            raise OSError(f"cannot copy {self.path} to {target}: {exc}") from None
        return target

    def _aside_name(self) -> Path:
        stamp = time.strftime("%Y%m%dT%H%M%S", time.localtime(self._wall()))
        target = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
        n = 1
        while target.exists():
            n += 1
            target = self.path.with_name(f"{self.path.name}.corrupt-{stamp}-{n}")
        return target

    def _move_aside(self) -> Path:
        target = self._aside_name()
        self.path.replace(target)
        for suffix in ("-wal", "-shm"):
            side = self.path.with_name(self.path.name + suffix)
            if side.exists():
                side.replace(target.with_name(target.name + suffix))
        return target

    # --- the scan's side ------------------------------------------------------------------
    def put(self, key: str, document: Document) -> None:
        """Queue ``document`` (plain JSON data) for ``key``; replaces one not yet written.
        Returns at once; the caller must not mutate the document afterwards."""
        wall = self._wall()
        with self._cond:
            self._pending[key] = (wall, document)
            self._submitted += 1
        if self.gate is not None:
            self.gate.after_scan(self._kick)  # woken once the scan is done
        else:
            self._kick()

    def _kick(self) -> None:
        with self._cond:
            self._cond.notify_all()

    @property
    def pending(self) -> int:
        with self._cond:
            return len(self._pending)

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until every document put so far is on disk (True), or until a write of
        them failed or ``timeout_s`` passed (False). For shutdown and tests."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            target = self._submitted
            attempts = self._attempts
            self._retry_now = True  # a worker waiting to retry tries now
            self._cond.notify_all()
            while self._written < target:
                if self._thread is None:
                    return False
                if self.error is not None and self._attempts > attempts and not self._busy:
                    return False
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def read(self) -> dict[str, Document]:
        """The documents on disk now (for checks and tools; not for the scan)."""
        if not self.path.exists():
            return {}
        return self._read()

    # --- the worker -------------------------------------------------------------------
    def _start(self) -> None:
        if self._thread is not None:
            return
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=f"retain:{self.path}", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what is pending (one last attempt), then stop the worker."""
        thread = self._thread
        if thread is None:
            return
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        thread.join(timeout_s)
        if thread.is_alive():
            log.error("retained state %s: writer did not stop in %g s", self.path, timeout_s)
        self._thread = None

    def _run(self) -> None:
        conn: sqlite3.Connection | None = None
        try:
            while True:
                with self._cond:
                    while not self._pending and not self._stopping:
                        self._cond.wait()
                if self.gate is not None:
                    # Woken by a put of the scan: the documents are dumped once it is done
                    # (and those of the same scan come along), not against it (ADR 0021).
                    self.gate.wait()
                with self._cond:
                    if not self._pending:
                        return  # stopping, nothing left
                    batch, self._pending = self._pending, {}
                    upto = self._submitted
                    self._busy = True
                ok = False
                try:
                    if conn is None:
                        conn = self._connect()
                    self._write(conn, batch)
                    ok = True
                except Exception as exc:  # disk full, read-only, locked: report, retry
                    self._failed(exc, batch)
                    if conn is not None:
                        with contextlib.suppress(sqlite3.Error):
                            conn.close()
                        conn = None
                with self._cond:
                    self._busy = False
                    self._attempts += 1
                    if ok:
                        self.writes += 1
                        if self.error is not None:
                            log.warning("retained state %s: writing again", self.path)
                        self.error = None
                        # The batch held every document put up to ``upto`` (or a newer one).
                        self._written = upto
                    self._cond.notify_all()
                    if not ok:
                        if self._stopping:
                            return
                        # New puts do not shorten the wait (a full disk is not retried at
                        # the scan rate); flush() and close() do.
                        self._retry_now = False
                        deadline = time.monotonic() + self.retry_s
                        while not (self._retry_now or self._stopping):
                            left = deadline - time.monotonic()
                            if left <= 0:
                                break
                            self._cond.wait(left)
        finally:
            if conn is not None:
                with contextlib.suppress(sqlite3.Error):
                    conn.close()

    def _failed(self, exc: Exception, batch: dict[str, tuple[float, Document]]) -> None:
        why = f"{type(exc).__name__}: {exc}"
        with self._cond:
            for key, item in batch.items():
                self._pending.setdefault(key, item)  # a newer document wins
            first = self.error != why
            self.error = why
            self.failures += 1
        if first:
            log.error("retained state %s: write failed (%s); retrying", self.path, why)

    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.path, isolation_level=None, timeout=5.0)
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=NORMAL")
        for stmt in _SCHEMA:
            conn.execute(stmt)
        conn.execute("INSERT OR IGNORE INTO meta (key, value) VALUES ('format', ?)", (str(FORMAT),))
        return conn

    def _write(self, conn: sqlite3.Connection, batch: dict[str, tuple[float, Document]]) -> None:
        """One transaction: every document of a batch, or none."""
        # json.dumps writes ASCII (a lone surrogate as \\udXXX); a key is escaped like any
        # other text a writer stores (``core/encoding.py``).
        rows = [(storable_text(key), wall, json.dumps(doc)) for key, (wall, doc) in batch.items()]
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.executemany(
                "INSERT OR REPLACE INTO retained (key, saved_wall, document) VALUES (?, ?, ?)",
                rows,
            )
            conn.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                conn.execute("ROLLBACK")
            raise
