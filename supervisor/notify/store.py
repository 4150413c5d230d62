"""The notification queue: ``<state_dir>/notify.sqlite`` (docs/adr/0049-notification-queue.md).

A message is committed here before any attempt to send it and marked sent only once the
server took it: a restart (a SIGKILL too) loses none, and sends again at most the one that
was in flight, with the same idempotency key (the primary key: a message enqueued twice is
stored once). A message is never deleted by the supervisor: it stays ``queued``, its
attempts and last error counted, until it is delivered.

SQLite in WAL mode with ``synchronous=FULL``, like the audit log: messages are few (the
flood window makes one of fifty). Every method blocks on the disk: the notifier calls
them off the event loop (``asyncio.to_thread``), one at a time.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from supervisor.notify.router import Notice, Outgoing

__all__ = ["NOTIFY_NAME", "Counts", "NotifyStore", "Queued", "notify_path"]

NOTIFY_NAME: Final = "notify.sqlite"
FORMAT: Final = "1"

_SCHEMA: Final = (
    "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS messages ("
    " key TEXT PRIMARY KEY, route TEXT NOT NULL, created REAL NOT NULL,"
    " message TEXT NOT NULL, state TEXT NOT NULL DEFAULT 'queued',"
    " attempts INTEGER NOT NULL DEFAULT 0, next_at REAL NOT NULL,"
    " last_error TEXT NOT NULL DEFAULT '', sent_at REAL)",
    "CREATE INDEX IF NOT EXISTS messages_due ON messages (state, next_at)",
    # Events routed but not yet in a message (an open flood window, quiet hours, an
    # escalation's wait): kept so that a SIGKILL loses none of them either.
    "CREATE TABLE IF NOT EXISTS notices ("
    " id TEXT PRIMARY KEY, wall REAL NOT NULL, kind TEXT NOT NULL, source TEXT NOT NULL,"
    " channel TEXT NOT NULL, priority TEXT NOT NULL, text TEXT NOT NULL)",
)


def notify_path(state_dir: str | Path) -> Path:
    """The notification queue of the bench whose state folder is ``state_dir``."""
    return Path(state_dir) / NOTIFY_NAME


@dataclass(frozen=True, slots=True)
class Queued:
    """A message waiting in the queue, with its attempts so far."""

    message: Outgoing
    created: float
    attempts: int
    last_error: str


@dataclass(frozen=True, slots=True)
class Counts:
    queued: int  # waiting (never sent yet, retrying included)
    retrying: int  # waiting after at least one failed attempt
    sent: int  # delivered (the file's total)
    oldest_wait_created: float | None  # when the oldest waiting message was enqueued
    queued_by_route: tuple[tuple[str, int], ...] = ()  # (route, waiting) for routes with any


def _encode(m: Outgoing) -> str:
    return json.dumps(
        {
            "kind": m.kind,
            "priority": m.priority,
            "subject": m.subject,
            "text": m.text,
            "escalation": m.escalation,
            "notices": [
                [n.wall, n.kind, n.source, n.channel, n.priority, n.text] for n in m.notices
            ],
        },
        ensure_ascii=False,
    )


def _decode(route: str, key: str, text: str) -> Outgoing:
    d: dict[str, Any] = json.loads(text)
    notices = tuple(Notice(float(w), k, s, c, p, t) for w, k, s, c, p, t in d["notices"])
    return Outgoing(
        route,
        key,
        d["kind"],
        d["priority"],
        d["subject"],
        d["text"],
        notices,
        escalation=bool(d["escalation"]),
    )


class NotifyStore:
    """One bench's notification queue (see the module's docstring)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._conn: sqlite3.Connection | None = None

    def open(self) -> NotifyStore:
        with self._lock:
            if self._conn is None:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                conn = sqlite3.connect(
                    self.path, isolation_level=None, timeout=10.0, check_same_thread=False
                )
                conn.execute("PRAGMA journal_mode=WAL")
                conn.execute("PRAGMA synchronous=FULL")
                for stmt in _SCHEMA:
                    conn.execute(stmt)
                conn.execute(
                    "INSERT OR IGNORE INTO meta (key, value) VALUES ('format', ?)", (FORMAT,)
                )
                self._conn = conn
        return self

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                with contextlib.suppress(sqlite3.Error):
                    self._conn.close()
                self._conn = None

    def _db(self) -> sqlite3.Connection:
        if self._conn is None:
            raise RuntimeError(f"notification queue {self.path} is not open")
        return self._conn

    # --- writes -----------------------------------------------------------------------
    def keep(self, notices: list[Notice]) -> None:
        """Commit events the router now holds (before they are in a message)."""
        rows = [
            (n.identity(), n.wall, n.kind, n.source, n.channel, n.priority, n.text) for n in notices
        ]
        with self._lock, self._transaction() as db:
            db.executemany("INSERT OR IGNORE INTO notices VALUES (?, ?, ?, ?, ?, ?, ?)", rows)

    def enqueue(self, messages: list[Outgoing], now: float, released: Iterable[str] = ()) -> int:
        """Commit ``messages`` and forget the kept events ``released`` (their identities:
        now in a message, or no longer waited for), in one transaction; how many messages
        were new (a key already stored is the same message: kept once)."""
        rows = [(m.key, m.route, now, _encode(m), now) for m in messages]
        with self._lock, self._transaction() as db:
            before = db.total_changes
            db.executemany(
                "INSERT OR IGNORE INTO messages (key, route, created, message, next_at)"
                " VALUES (?, ?, ?, ?, ?)",
                rows,
            )
            new = db.total_changes - before
            db.executemany("DELETE FROM notices WHERE id = ?", [(i,) for i in released])
            return new

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        db = self._db()
        db.execute("BEGIN IMMEDIATE")
        try:
            yield db
            db.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                db.execute("ROLLBACK")
            raise

    def sent(self, key: str, now: float) -> None:
        with self._lock:
            self._db().execute(
                "UPDATE messages SET state = 'sent', sent_at = ?, attempts = attempts + 1"
                " WHERE key = ?",
                (now, key),
            )

    def failed(self, m: Outgoing, error: str, next_at: float) -> int:
        """One more failed attempt of ``m``; its route's waiting messages not before
        ``next_at`` (the route's backoff); the attempts of ``m`` so far."""
        with self._lock, self._transaction() as db:
            db.execute(
                "UPDATE messages SET attempts = attempts + 1, last_error = ? WHERE key = ?",
                (error[:1000], m.key),
            )
            db.execute(
                "UPDATE messages SET next_at = max(next_at, ?)"
                " WHERE route = ? AND state = 'queued'",
                (next_at, m.route),
            )
            row = db.execute("SELECT attempts FROM messages WHERE key = ?", (m.key,)).fetchone()
            return int(row[0]) if row else 0

    # --- reads ------------------------------------------------------------------------
    def kept(self) -> list[Notice]:
        """The events kept by the last run, oldest first (a start offers them again)."""
        with self._lock:
            rows = (
                self._db()
                .execute(
                    "SELECT wall, kind, source, channel, priority, text FROM notices"
                    " ORDER BY wall, id"
                )
                .fetchall()
            )
        return [Notice(float(r[0]), r[1], r[2], r[3], r[4], r[5]) for r in rows]

    def due(self, now: float, limit: int = 100) -> list[Queued]:
        """Waiting messages whose next attempt is due, oldest first."""
        with self._lock:
            rows = (
                self._db()
                .execute(
                    "SELECT key, route, created, message, attempts, last_error FROM messages"
                    " WHERE state = 'queued' AND next_at <= ? ORDER BY created, key LIMIT ?",
                    (now, limit),
                )
                .fetchall()
            )
        return [Queued(_decode(r[1], r[0], r[3]), float(r[2]), int(r[4]), r[5]) for r in rows]

    def next_at(self) -> float | None:
        with self._lock:
            row = (
                self._db()
                .execute("SELECT min(next_at) FROM messages WHERE state = 'queued'")
                .fetchone()
            )
        return None if row is None or row[0] is None else float(row[0])

    def counts(self) -> Counts:
        with self._lock:
            row = (
                self._db()
                .execute(
                    "SELECT"
                    " coalesce(sum(state = 'queued'), 0),"
                    " coalesce(sum(state = 'queued' AND attempts > 0), 0),"
                    " coalesce(sum(state = 'sent'), 0),"
                    " min(CASE WHEN state = 'queued' THEN created END)"
                    " FROM messages"
                )
                .fetchone()
            )
            by_route = self._db().execute(
                "SELECT route, count(*) FROM messages WHERE state = 'queued'"
                " GROUP BY route ORDER BY route"
            )
            routes = tuple((str(r), int(n)) for r, n in by_route)
        return Counts(int(row[0]), int(row[1]), int(row[2]), row[3], routes)

    def rows(self) -> list[dict[str, Any]]:
        """Every message with its state (tests, diagnostics)."""
        with self._lock:
            cur = self._db().execute(
                "SELECT key, route, created, state, attempts, last_error, sent_at FROM messages"
                " ORDER BY created, key"
            )
            names = [d[0] for d in cur.description]
            return [dict(zip(names, r, strict=True)) for r in cur.fetchall()]
