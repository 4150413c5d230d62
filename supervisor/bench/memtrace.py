"""A debugging switch: where a long-running process's memory goes (issue 13's RSS figure).

Off unless ``$SUPERVISOR_TRACEMALLOC`` names a folder: then :func:`start_from_env` starts
``tracemalloc`` (which costs memory and CPU on every allocation, so never in production)
and a daemon thread dumps a snapshot into that folder every
``$SUPERVISOR_TRACEMALLOC_EVERY_S`` seconds (default 60), named by the seconds since the
start (``snap-000120.000s.tracemalloc``), and a line of ``summary.tsv`` (RSS, SQLite's
memory, glibc's heap: what tracemalloc cannot see). :func:`compare` tells what grew
between two snapshots, by source line: ``supervisor bench memory --trace DIR`` prints it
for the snapshots after the warm-up and at the end. ``$SUPERVISOR_TRACEMALLOC_FRAMES=0``:
no tracemalloc, only the summary lines (the process runs at its normal size and speed).
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import threading
import time
import tracemalloc
from collections.abc import Mapping
from pathlib import Path
from typing import Final

log = logging.getLogger(__name__)

ENV: Final = "SUPERVISOR_TRACEMALLOC"
"""Folder the snapshots are written to; unset or empty: tracing off."""
EVERY_ENV: Final = "SUPERVISOR_TRACEMALLOC_EVERY_S"
FRAMES_ENV: Final = "SUPERVISOR_TRACEMALLOC_FRAMES"
DEFAULT_EVERY_S: Final = 60.0
DEFAULT_FRAMES: Final = 1
"""Frames kept per allocation: one is enough to group by source line and costs least."""
SUFFIX: Final = ".tracemalloc"
SUMMARY: Final = "summary.tsv"
COLUMNS: Final = (
    "elapsed_s",
    "rss_b",
    "traced_b",
    "sqlite_b",
    "malloc_used_b",
    "malloc_free_b",
    "py_blocks",
)
"""Of ``summary.tsv``: ``py_blocks`` is ``sys.getallocatedblocks()`` (Python's objects
alive, counted without tracemalloc)."""

IGNORED: Final = (tracemalloc.Filter(False, tracemalloc.__file__),)
"""Only the tracer's own memory; the imports' (``<frozen importlib._bootstrap_external>``:
code objects) are part of what the process holds."""


class MemTrace:
    """``tracemalloc`` on, a snapshot into ``folder`` every ``every_s`` seconds; with
    ``frames=0`` no tracemalloc at all, only the lines of ``summary.tsv`` (what the
    process's memory is made of, at no cost to it)."""

    def __init__(self, folder: Path, every_s: float = DEFAULT_EVERY_S, frames: int = 1) -> None:
        self.folder = folder
        self.every_s = every_s
        self.frames = frames
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        if self.frames > 0:
            tracemalloc.start(self.frames)
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._loop, name="memtrace", daemon=True)
        self._thread.start()
        log.warning(
            "memory tracing on (%s=%s): every %g s %s",
            ENV,
            self.folder,
            self.every_s,
            "a summary line" if self.frames <= 0 else "a snapshot, slower and bigger than usual",
        )

    def dump(self) -> Path | None:
        """A snapshot now, into the folder; returns its path (None: not tracing). A line
        of ``summary.tsv`` says what tracemalloc cannot see: the RSS, SQLite's own memory
        (its page caches) and glibc's heap (C allocations, and what it keeps free)."""
        elapsed_s = time.monotonic() - self._t0
        path: Path | None = None
        if tracemalloc.is_tracing():
            path = self.folder / f"snap-{elapsed_s:010.3f}s{SUFFIX}"
            tracemalloc.take_snapshot().filter_traces(IGNORED).dump(str(path))
        traced_b, _ = tracemalloc.get_traced_memory()
        summary = self.folder / SUMMARY
        new = not summary.exists()
        with summary.open("a", encoding="utf-8") as f:
            if new:
                f.write("\t".join(COLUMNS) + "\n")
            used_b, free_b = malloc_b()
            row = (rss_b(), traced_b, sqlite_memory_b(), used_b, free_b, sys.getallocatedblocks())
            f.write(f"{elapsed_s:.1f}\t" + "\t".join(str(v) for v in row) + "\n")
        return path

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30.0)
            self._thread = None
        tracemalloc.stop()

    def _loop(self) -> None:
        while not self._stop.wait(self.every_s):
            try:
                self.dump()
            except Exception:  # a full disk must not stop the supervisor
                log.exception("memory tracing: snapshot not written")


def rss_b() -> int:
    """This process's resident memory (``VmRSS``), in bytes; -1 where there is no /proc."""
    try:
        for line in Path("/proc/self/status").read_text(encoding="ascii").splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return -1


def sqlite_memory_b() -> int:
    """Memory SQLite holds in this process, every connection's page cache included
    (``sqlite3_status64(SQLITE_STATUS_MEMORY_USED)``); -1 when it cannot be asked."""
    try:
        import _sqlite3

        lib = ctypes.CDLL(_sqlite3.__file__)
        current, high = ctypes.c_int64(), ctypes.c_int64()
        if lib.sqlite3_status64(0, ctypes.byref(current), ctypes.byref(high), 0) != 0:
            return -1
    except (OSError, AttributeError, ImportError):
        return -1
    return int(current.value)


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


def malloc_b() -> tuple[int, int]:
    """glibc's heap (every thread's arena): bytes in use (``uordblks`` + ``hblkhd``) and
    bytes free but kept by the process (``fordblks``); (-1, -1) without glibc 2.33+."""
    try:
        libc = ctypes.CDLL(None)
        fn = libc.mallinfo2
    except (OSError, AttributeError):
        return -1, -1
    fn.restype = _MallInfo2
    mi = fn()
    return int(mi.uordblks + mi.hblkhd), int(mi.fordblks)


def start_from_env(env: Mapping[str, str] | None = None) -> MemTrace | None:
    """The trace the environment asks for, started; None (nothing done) when it does not."""
    env = os.environ if env is None else env
    folder = env.get(ENV, "")
    if not folder:
        return None
    trace = MemTrace(
        Path(folder),
        float(env.get(EVERY_ENV) or DEFAULT_EVERY_S),
        int(env.get(FRAMES_ENV) or DEFAULT_FRAMES),
    )
    trace.start()
    return trace


def snapshots(folder: Path) -> list[tuple[float, Path]]:
    """The snapshots in ``folder``, as (seconds since the trace started, path), in order."""
    out = []
    for p in folder.glob(f"snap-*s{SUFFIX}"):
        try:
            out.append((float(p.name[len("snap-") : -len("s" + SUFFIX)]), p))
        except ValueError:
            continue
    return sorted(out)


def compare(before: Path, after: Path, top: int = 15, key: str = "lineno") -> list[str]:
    """What grew from ``before`` to ``after`` (two snapshot files), biggest first."""
    old = tracemalloc.Snapshot.load(str(before))
    new = tracemalloc.Snapshot.load(str(after))
    stats = new.compare_to(old, key)
    total_b = sum(s.size_diff for s in stats)
    lines = [f"traced: {total_b / 1e6:+.2f} MB from {before.name} to {after.name}"]
    for s in stats[:top]:
        frame = s.traceback[0]
        lines.append(
            f"  {s.size_diff / 1e3:+9.1f} kB {s.count_diff:+7d} blocks"
            f"  ({s.size / 1e3:9.1f} kB now)  {frame.filename}:{frame.lineno}"
        )
    return lines
