"""A debugging switch: where a long-running process's memory goes (issue 13's RSS figure).

Off unless ``$SUPERVISOR_TRACEMALLOC`` names a folder: then :func:`start_from_env` starts
``tracemalloc`` (which costs memory and CPU on every allocation, so never in production)
and a daemon thread dumps a snapshot into that folder every
``$SUPERVISOR_TRACEMALLOC_EVERY_S`` seconds (default 60), named by the seconds since the
start (``snap-000120.000s.tracemalloc``). :func:`compare` tells what grew between two of them,
by source line: ``supervisor bench memory --trace DIR`` prints it for the snapshots after
the warm-up and at the end.
"""

from __future__ import annotations

import logging
import os
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

_IGNORED: Final = (tracemalloc.Filter(False, tracemalloc.__file__),)
"""Only the tracer's own memory; the imports' (``<frozen importlib._bootstrap_external>``:
code objects) are part of what the process holds."""


class MemTrace:
    """``tracemalloc`` on, a snapshot into ``folder`` every ``every_s`` seconds."""

    def __init__(self, folder: Path, every_s: float = DEFAULT_EVERY_S, frames: int = 1) -> None:
        self.folder = folder
        self.every_s = every_s
        self.frames = frames
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        tracemalloc.start(self.frames)
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._loop, name="memtrace", daemon=True)
        self._thread.start()
        log.warning(
            "memory tracing on (%s=%s): a snapshot every %g s, slower and bigger than usual",
            ENV,
            self.folder,
            self.every_s,
        )

    def dump(self) -> Path:
        """A snapshot now, into the folder; returns its path."""
        elapsed_s = time.monotonic() - self._t0
        path = self.folder / f"snap-{elapsed_s:010.3f}s{SUFFIX}"
        tracemalloc.take_snapshot().filter_traces(_IGNORED).dump(str(path))
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
