"""The historian's file: its layout, how it is opened, and what happens to a corrupt one.

One SQLite file in WAL mode (docs/adr/0013-historian.md):

- ``tags``: the tag dictionary (id, name, unit, dtype, description), so a sample row
  stores a small integer instead of the name and an answer carries the unit;
- ``samples``: (tag id, wall time, value, quality), ``WITHOUT ROWID`` with the primary key
  (tag id, t): the rows of one tag lie together in time order, so a query by tag and time
  range reads consecutive pages (the index *is* the table), and a second sample of a tag
  at the same instant replaces the first (as InfluxDB does: a replay never duplicates).
  ``value`` has no declared type: a float is stored as REAL, a text as TEXT, a boolean as
  0/1, a BAD sample as NULL;
- ``events``: the bench's events (``BenchEvent``) with indexes by time and by channel and
  time.

``auto_vacuum = INCREMENTAL`` is set when the file is created (it cannot be switched on
later without a full VACUUM): pages freed by retention go to the free list and
``PRAGMA incremental_vacuum`` gives them back to the file system, so the file really
shrinks.

A file that is not a database, is truncated, fails ``PRAGMA quick_check``, or is another
program's SQLite file or another format is renamed aside
(``history.sqlite.corrupt-<UTC time>``, with its ``-wal``/``-shm``) and a new one is
started: history is valuable but never worth a bench that does not start.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

HISTORY_NAME = "history.sqlite"
FORMAT = 1
"""Version of the file's layout. Another version is set aside, not migrated."""

APPLICATION_ID = 0x48535452  # "HSTR": tells our file from any other SQLite file
CACHE_KIB = 16 * 1024
"""Page cache of the writer (KiB), at most: one hot page per tag at the end of its range."""
CACHE_MIN_KIB = 2 * 1024
"""At least SQLite's own default (2000 KiB)."""
CACHE_KIB_PER_TAG = 8
"""Two 4 KiB pages per recorded tag: the leaf at the end of the tag's range that its rows
are appended to, and the one a split has just made. A cache fills to its size as the file
grows and then stays there; sized for the worst case (16 MiB) it grew by 2 MB per 10
minutes for the first hour on the simulated bench (272 tags: now 2.1 MiB, full within
minutes; issue 13's memory figure)."""


def cache_kib(tags: int) -> int:
    """The writer's page cache (KiB) for ``tags`` recorded tags."""
    return max(CACHE_MIN_KIB, min(CACHE_KIB, tags * CACHE_KIB_PER_TAG))


def size_cache(conn: sqlite3.Connection, tags: int) -> None:
    """Size the writer's page cache for ``tags`` recorded tags (``PRAGMA cache_size``)."""
    conn.execute(f"PRAGMA cache_size = -{cache_kib(tags)}")


JOURNAL_SIZE_LIMIT_BYTES = 16 * 1024 * 1024
"""The ``-wal`` file is truncated to this after a checkpoint (it is reused, not grown)."""
BUSY_TIMEOUT_S = 5.0

_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS tags ("
    " id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, unit TEXT NOT NULL,"
    " dtype TEXT NOT NULL, description TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS samples ("
    " tag_id INTEGER NOT NULL, t REAL NOT NULL, value, quality INTEGER NOT NULL,"
    " PRIMARY KEY (tag_id, t)) WITHOUT ROWID",
    "CREATE TABLE IF NOT EXISTS events ("
    " id INTEGER PRIMARY KEY, wall REAL NOT NULL, kind TEXT NOT NULL, channel TEXT NOT NULL,"
    " source TEXT NOT NULL, text TEXT NOT NULL, actor TEXT NOT NULL,"
    " severity INTEGER NOT NULL, test_id TEXT NOT NULL, recipe TEXT NOT NULL)",
    "CREATE INDEX IF NOT EXISTS events_wall ON events (wall)",
    "CREATE INDEX IF NOT EXISTS events_channel_wall ON events (channel, wall)",
)

CORRUPT_ERRORS = frozenset({"SQLITE_CORRUPT", "SQLITE_NOTADB", "SQLITE_CORRUPT_INDEX"})
"""sqlite3 error names that mean the file itself is damaged (not the disk or a lock)."""


@dataclass(frozen=True, slots=True)
class TagInfo:
    """A tag as the dictionary keeps it (the unit and type of its stored values)."""

    name: str
    unit: str = ""
    dtype: str = "float"  # "float" | "int" | "bool" | "str"
    description: str = ""


@dataclass(frozen=True)
class SetAside:
    """A file that could not be used and was renamed aside."""

    path: Path
    moved_to: Path | None  # None when even the rename failed
    problem: str
    wall: float

    def text(self) -> str:
        where = f"moved to {self.moved_to}" if self.moved_to else "could NOT be moved aside"
        return f"history file {self.path} unusable ({self.problem}): {where}; a new one started"


def problem_of(path: Path) -> str:
    """Why ``path`` cannot be used as our history file ("" when it can, or is absent or
    empty). Opens it read-write so that a ``-wal`` left by a killed process is replayed."""
    if not path.exists() or path.stat().st_size == 0:
        return ""
    try:
        conn = sqlite3.connect(f"file:{path}?mode=rw", uri=True, timeout=BUSY_TIMEOUT_S)
    except sqlite3.Error as exc:
        return f"cannot open: {exc}"
    try:
        rows = conn.execute("PRAGMA quick_check").fetchall()
        if [r[0] for r in rows] != ["ok"]:
            # One line for the log and the alarm: the first findings, not hundreds.
            lines = [ln for r in rows for ln in str(r[0]).splitlines() if "***" not in ln]
            first = "; ".join(lines[:2])[:200] if lines else "no answer"
            more = f" (and {len(lines) - 2} more)" if len(lines) > 2 else ""
            return f"integrity check failed: {first}{more}"
        app_id = conn.execute("PRAGMA application_id").fetchone()[0]
        if app_id != APPLICATION_ID:
            return f"not a history file of this supervisor (application id {app_id:#x})"
        fmt = conn.execute("SELECT value FROM meta WHERE key = 'format'").fetchone()
        if fmt is None or fmt[0] != str(FORMAT):
            found = "none" if fmt is None else fmt[0]
            return f"format {found}, this supervisor writes format {FORMAT}"
        return ""
    except sqlite3.Error as exc:  # "file is not a database", "malformed", no meta table
        return f"{type(exc).__name__}: {exc}"
    finally:
        conn.close()


def set_aside(path: Path, problem: str, wall: float) -> SetAside:
    """Rename ``path`` (and its ``-wal``/``-shm``) to ``<name>.corrupt-<UTC time>``."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(wall))
    target = path.with_name(f"{path.name}.corrupt-{stamp}")
    n = 1
    while target.exists():
        n += 1
        target = path.with_name(f"{path.name}.corrupt-{stamp}-{n}")
    try:
        path.replace(target)
    except OSError as exc:
        log.error("history file %s unusable (%s); cannot move it aside: %s", path, problem, exc)
        return SetAside(path, None, f"{problem}; cannot move it aside: {exc}", wall)
    for suffix in ("-wal", "-shm"):
        side = path.with_name(path.name + suffix)
        with contextlib.suppress(FileNotFoundError):
            side.replace(target.with_name(target.name + suffix))
    log.error(
        "history file %s unusable (%s): moved to %s; a new one started", path, problem, target
    )
    return SetAside(path, target, problem, wall)


def check(path: Path, wall: float) -> SetAside | None:
    """Set ``path`` aside when it is unusable (what was done, or None when it is fine)."""
    problem = problem_of(path)
    return set_aside(path, problem, wall) if problem else None


def connect(path: Path) -> sqlite3.Connection:
    """The writer's connection: WAL, ``synchronous=NORMAL`` (a committed transaction
    survives the process being killed; a power cut may lose the last ones, never corrupt
    the file), the layout created if absent. Autocommit mode: transactions are explicit."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # Opened by ``open`` on the owner's thread, then used by the writer thread alone.
    conn = sqlite3.connect(
        path, isolation_level=None, timeout=BUSY_TIMEOUT_S, check_same_thread=False
    )
    try:
        new = conn.execute("PRAGMA page_count").fetchone()[0] == 0
        if new:  # only before the first table: an existing file keeps its mode
            conn.execute("PRAGMA auto_vacuum = INCREMENTAL")
            conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
        conn.execute("PRAGMA journal_mode = WAL")
        conn.execute("PRAGMA synchronous = NORMAL")
        size_cache(conn, 0)  # grown as the writer meets tags (``size_cache``)
        conn.execute(f"PRAGMA journal_size_limit = {JOURNAL_SIZE_LIMIT_BYTES}")
        for stmt in _SCHEMA:
            conn.execute(stmt)
        conn.execute("INSERT OR IGNORE INTO meta (key, value) VALUES ('format', ?)", (str(FORMAT),))
    except BaseException:
        conn.close()
        raise
    return conn


def on_disk_bytes(path: Path) -> int:
    """The file and its ``-wal`` (what the history takes on the disk now)."""
    total = 0
    for p in (path, path.with_name(path.name + "-wal")):
        with contextlib.suppress(OSError):
            total += p.stat().st_size
    return total


def used_bytes(conn: sqlite3.Connection) -> int:
    """Bytes of the pages in use (the file minus its free list): what retention bounds."""
    page_size = conn.execute("PRAGMA page_size").fetchone()[0]
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    free = conn.execute("PRAGMA freelist_count").fetchone()[0]
    return int((pages - free) * page_size)


def error_name(exc: BaseException) -> str:
    """The SQLite error name of ``exc`` (``SQLITE_FULL``…), "" for anything else."""
    return str(getattr(exc, "sqlite_errorname", "") or "")
