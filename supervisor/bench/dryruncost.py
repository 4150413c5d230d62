"""What one scan of a dry run costs in Python bytecodes and calls, by function:
``supervisor bench dry-run --bytecodes``.

Issue 13's dry-run figure is a wall-clock ratio, and on the 2-core machine it moved by a
third between runs of the same code. The bytecodes a scan runs do not depend on the
machine, its load or its speed: two dry runs of the same recipe, ``hours`` and twice
``hours`` of virtual time, are traced (``sys.settrace`` with opcode events) after one
untraced run (what a process does once), and their difference divided by the scans between
them leaves one scan's cost, start-up and the run's first scans cancelling out. Tracing
makes the runs some fifty times slower: a profiling aid for the hot paths, never a speed
figure.
"""

from __future__ import annotations

import asyncio
import gc
import sys
from collections import Counter
from collections.abc import Callable, Coroutine, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

from supervisor.app.dryrun import dry_run

PACKAGE_DIR = str(Path(__file__).resolve().parent.parent)


@dataclass(frozen=True)
class ScanCost:
    """Bytecodes and Python calls per scan, in all and by function (``where``: the file
    under ``supervisor/`` or the module path, the first line and the name)."""

    scans: int
    bytecodes: float
    calls: float
    by_function: list[tuple[str, float, float]]  # (where, bytecodes, calls), costliest first


def _where(frame: FrameType) -> str:
    code = frame.f_code
    filename = code.co_filename
    if filename.startswith(PACKAGE_DIR):
        filename = "supervisor" + filename[len(PACKAGE_DIR) :]
    return f"{filename}:{code.co_firstlineno}:{code.co_name}"


class _Collections:
    """Whether the garbage collector is at work: its first callback raises the flag, its
    last lowers it, so every other callback is inside, as the finalizers are."""

    def __init__(self) -> None:
        self.running = False

    def first(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self.running = True

    def last(self, phase: str, info: dict[str, int]) -> None:
        if phase == "stop":
            self.running = False

    @contextmanager
    def watched(self) -> Iterator[_Collections]:
        """The garbage others left collected first, and no automatic collection inside:
        one set off by any thread's allocations would run in the middle of the run."""
        gc.collect()
        enabled = gc.isenabled()
        gc.disable()
        gc.callbacks.insert(0, self.first)
        gc.callbacks.append(self.last)
        try:
            yield self
        finally:
            gc.callbacks.remove(self.first)
            gc.callbacks.remove(self.last)
            if enabled:
                gc.enable()


def _traced(run: Callable[[], Coroutine[Any, Any, Any]]) -> tuple[Counter[str], Counter[str]]:
    """The bytecodes and calls ``run`` executes, by function, on a new event loop.

    Only the run's own code counts, never what the process's history puts in its way
    (issue 29: the same scan cost 3929.14 and 3933.25 bytecodes in one process of the
    full suite): the tracing starts and stops inside the loop, not around ``asyncio.run``,
    whose tear-down walks every task of the process (``asyncio.all_tasks``: other loops'
    too, other threads' or tests' left-overs, as many as there are at that moment); and
    what the garbage collector runs (the finalizers and weakref callbacks of garbage, an
    earlier test's or another thread's) belongs to no scan, also in the collection the run
    asks for itself (``settled_heap``)."""
    ops: Counter[str] = Counter()
    calls: Counter[str] = Counter()
    collections = _Collections()

    def on_call(frame: FrameType, event: str, arg: object) -> Any:
        if collections.running or frame.f_code is _Collections.first.__code__:
            return None
        frame.f_trace_opcodes = True
        where = _where(frame)
        calls[where] += 1

        def on_opcode(frame: FrameType, event: str, arg: object) -> Any:
            if event == "opcode":
                ops[where] += 1
            return on_opcode

        return on_opcode

    async def traced() -> None:
        previous = sys.gettrace()
        sys.settrace(on_call)
        try:
            await run()
        finally:
            sys.settrace(previous)

    with collections.watched():
        asyncio.run(traced())
    return ops, calls


def scan_cost(recipe: str | Path, hours: float = 0.5, period_s: float = 1.0) -> ScanCost:
    """One scan's bytecodes and calls in a dry run of ``recipe`` (from ``soc`` 0, as
    ``supervisor bench dry-run``): a run of ``2 * hours`` less a run of ``hours``."""
    if hours <= 0:
        raise ValueError("hours must be > 0")

    def run(h: float) -> Callable[[], Coroutine[Any, Any, Any]]:
        return lambda: dry_run(recipe, soc=0.0, max_hours=h, period_s=period_s)

    asyncio.run(run(hours)())  # untraced: what a process's first run does once (caches, imports)
    short_ops, short_calls = _traced(run(hours))
    long_ops, long_calls = _traced(run(2 * hours))
    scans = round(hours * 3600 / period_s)
    ops = long_ops - short_ops  # Counter subtraction keeps the positive differences
    calls = long_calls - short_calls
    rows = sorted(((w, n / scans, calls[w] / scans) for w, n in ops.items()), key=lambda r: -r[1])
    return ScanCost(scans, sum(ops.values()) / scans, sum(calls.values()) / scans, rows)
