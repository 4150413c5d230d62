"""Result rows appended on a thread of their own, off the scan's (issue 13).

A live test's record (its logging rule: every second in the load case) was a CSV row and
a Chadèche line formatted, written and flushed on the scan's thread: 16 channels logging
in the same few scans cost each of them 16 × ~25 µs of formatting and 32 write calls,
and every write call lets the interpreter lock go, to a publisher's thread that may keep
it up to the switch interval. Here the scan hands over the row (a frozen record) and
returns; the writer's thread formats, writes and flushes each row at once, in the order
they were handed over. A crash loses at most the rows handed over in the last moments,
not yet written (without it: none); a clean stop, a test's end and ``flush`` write them
all first.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable

from supervisor.core.gate import ScanGate

log = logging.getLogger(__name__)

Job = Callable[[], None]
FLUSH_LOOK_S = 0.001
"""How often a thread at the scan gate looks whether someone waits in ``flush``."""


class ThreadWriter:
    """What the result writers with a thread of their own share: the thread started at the
    first piece of work, ``flush`` (wait until nothing is waiting or being written) and
    ``stop`` (write what waits, end the thread; later work is done on the caller's
    thread). A subclass says what is busy (``_busy``, under ``_cond``) and does the work
    (``_run``, notifying ``_cond`` when a piece is done)."""

    what = "work"
    """What it writes, for its log line."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._cond = threading.Condition()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self.gate: ScanGate | None = None
        """Real clock: the thread waits here while a scan runs (``core/gate.py``)."""
        self._flushing = 0  # callers waiting in flush()

    def _wake(self) -> None:
        """Wake the thread for work handed over (after the scan when one runs)."""
        if self.gate is not None:
            self.gate.after_scan(self._kick)
        else:
            self._kick()

    def _kick(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def _give_way(self) -> None:
        """Before a piece of work, outside ``_cond``: a thread woken by the scan's hand-over
        would otherwise take the interpreter lock from that very scan (ADR 0021). Not while
        someone waits in ``flush``: that may be the scan itself (a test ending in it)."""
        gate = self.gate
        if gate is None:
            return
        end = time.monotonic() + gate.max_wait_s
        # In steps, so that a flush that comes meanwhile is not kept waiting.
        while not gate.is_open and not self._flushing and time.monotonic() < end:
            gate.wait(FLUSH_LOOK_S)

    def _start_thread(self) -> None:
        """The caller holds ``_cond``."""
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._run, name=f"{self.name}-{self.what}", daemon=True
            )
            self._thread.start()

    def _busy(self) -> bool:
        raise NotImplementedError

    def _run(self) -> None:
        raise NotImplementedError

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until everything handed over is on disk; False after ``timeout_s``."""
        end = time.monotonic() + timeout_s
        with self._cond:
            # Woken here, not after the scan (``_wake``), and past the gate: the caller
            # waits for it, and may be the scan.
            self._flushing += 1
            self._cond.notify_all()
            try:
                while self._busy():
                    left = end - time.monotonic()
                    if left <= 0:
                        return False
                    self._cond.wait(left)
            finally:
                self._flushing -= 1
        return True

    def stop(self, timeout_s: float = 10.0) -> None:
        """Write what is waiting, then end the thread; later work is done at once."""
        if not self.flush(timeout_s):
            log.error("%s: %s not written within %g s", self.name, self.what, timeout_s)
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
            thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)


class RowWriter(ThreadWriter):
    """Runs the jobs handed over (appending rows to files), one after the other, in order,
    on a thread started at the first one. After :meth:`stop` a job runs on the caller's
    thread at once (a test ending during the stop)."""

    what = "rows"

    def __init__(self, name: str = "results") -> None:
        super().__init__(name)
        self._jobs: deque[Job] = deque()
        self._running = 0  # jobs taken by the thread and not done yet
        self._waiting = False  # the thread sleeps until the next job
        self.done = 0
        self.failed = 0

    def put(self, job: Job) -> None:
        """Run ``job`` soon, after every job handed over before it; returns at once."""
        with self._cond:
            stopped = self._stopping
            if not stopped:
                self._jobs.append(job)
                wake = self._thread is not None and self._waiting
                if self._thread is None:
                    self._start_thread()
        if stopped:
            self._do(job)
        elif wake:
            self._wake()  # a busy thread takes it without being told

    def _busy(self) -> bool:
        return bool(self._jobs or self._running)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._jobs and not self._stopping:
                    self._waiting = True
                    self._cond.wait()
                    self._waiting = False
            self._give_way()  # the rows of this scan come along
            with self._cond:
                if not self._jobs:
                    return
                jobs = list(self._jobs)
                self._jobs.clear()
                self._running = len(jobs)
            for job in jobs:
                self._do(job)
            with self._cond:
                self._running = 0
                self._cond.notify_all()  # flush() waits for this

    def _do(self, job: Job) -> None:
        try:
            job()
            self.done += 1
        except Exception:  # one bad row must not stop the others (its file says why)
            self.failed += 1
            log.exception("%s: a result row could not be written", self.name)
