"""Work that must not run on the scan's event loop: in a thread of its own, with a time
limit (README "Input limits"; issue 9: a 20 MB recipe parsed on the loop stopped the scan
for 6.8 s, long enough for the EA supply's watchdog to drop remote control).

Each job gets a daemon thread: one that never returns (a named pipe nobody writes to, a
network share that hangs) is abandoned at its time limit, never joined, and neither the
next job nor the end of the process waits for it. Its late result is dropped.

While a job is awaited, CPython's full (oldest-generation) garbage collections are
deferred: they stop every thread, and a parse that makes a million objects triggers
several, each walking the whole heap — half a second on a small machine, during which no
scan runs. Young collections go on as usual. When the last job ends, what is alive is frozen
(``gc.freeze``) before full collections resume: they never walk it again. A megabyte
recipe's compiled program is some 80 000 objects, 0.3 s of every full collection on a
small two-core machine — a stall of the scan each time. Nothing is lost to the collector:
parsing, compiling, loading and replacing a program make no reference cycles, all of it
is freed by reference counting (tests/unit/test_recipe_load_off_the_loop.py).
"""

from __future__ import annotations

import asyncio
import gc
import logging
import threading
from collections.abc import Callable
from typing import Final, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")

__all__ = ["WorkerTimeout", "run_in_worker"]

_NO_FULL_COLLECTION: Final = 2**31 - 1
"""A third-generation threshold no count reaches."""


class WorkerTimeout(Exception):
    """The job did not finish within its time limit (it is abandoned, its result dropped)."""

    def __init__(self, what: str, timeout_s: float) -> None:
        super().__init__(f"{what} took more than {timeout_s:g} s")
        self.what = what
        self.timeout_s = timeout_s


class _FullCollections:
    """Defers full collections while at least one job runs. One per process, like the
    collector it tunes (the one piece of module state here, behind a lock)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._jobs = 0
        self._saved: tuple[int, ...] = ()

    def __enter__(self) -> None:
        with self._lock:
            if self._jobs == 0:
                self._saved = gc.get_threshold()
                first, second = self._saved[0], self._saved[1]
                gc.set_threshold(first, second, _NO_FULL_COLLECTION)
            self._jobs += 1

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            self._jobs -= 1
            if self._jobs == 0 and self._saved:
                gc.freeze()  # before full collections resume: they leave it alone
                gc.set_threshold(*self._saved)


_FULL_COLLECTIONS = _FullCollections()


async def run_in_worker(fn: Callable[[], T], timeout_s: float, what: str) -> T:
    """``fn()`` in a new daemon thread; its result, or its exception re-raised here.

    Raises :class:`WorkerTimeout` after ``timeout_s`` (the thread is left to finish on its
    own; whatever it returns then is dropped, logged at INFO).
    """
    loop = asyncio.get_running_loop()
    done: asyncio.Future[T] = loop.create_future()

    def deliver(result: list[T], error: Exception | None) -> None:
        if done.done():  # the caller gave up (time limit, cancelled)
            log.info("%s: finished after its time limit; result dropped", what)
        elif error is not None:
            done.set_exception(error)
        else:
            done.set_result(result[0])

    def work() -> None:
        result: list[T] = []
        error: Exception | None = None
        try:
            result.append(fn())
        except Exception as exc:  # handed to the awaiting coroutine
            error = exc
        try:
            loop.call_soon_threadsafe(deliver, result, error)
        except RuntimeError:  # the loop is closed: nobody is waiting any more
            log.info("%s: finished after its event loop closed; result dropped", what)

    # Deferred while someone waits for the job, not while its thread lives: an abandoned
    # job that never returns must not keep full collections off for ever.
    with _FULL_COLLECTIONS:
        threading.Thread(target=work, name=what, daemon=True).start()
        try:
            return await asyncio.wait_for(done, timeout_s)
        except TimeoutError:
            log.error("%s: no result within %g s; abandoned", what, timeout_s)
            raise WorkerTimeout(what, timeout_s) from None
