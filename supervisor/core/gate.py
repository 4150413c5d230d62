"""The scan's right of way over the process's other threads (issue 13, ADR 0021).

CPython runs one thread at a time. A publisher's thread (the OPC UA server, the InfluxDB
spool's encoder, the historian's writer) that is busy when a scan runs takes the
interpreter lock from it every switch interval: in the load case a scan of 1.6 ms of CPU
took up to 6 ms of wall time. A PLC's scan has priority over its communication tasks;
Python threads have none, so the others give way by themselves: the scan engine *closes*
the gate as it approaches its deadline and *opens* it when the scan is done, and a
thread that calls :meth:`ScanGate.wait` between two pieces of its work waits while the
gate is closed, without the lock. The wait is bounded (``max_wait_s``): a scan that runs
long, or an engine that stopped with the gate closed, delays the others, never stops them.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Final

log = logging.getLogger(__name__)

MAX_WAIT_S: Final = 0.02
"""The longest a thread waits at a closed gate: two periods of a 10 ms scan. A scan
closes it for the last 2 ms before its deadline and its own duration (1–4 ms in the load
case), so a thread at the gate normally waits a few milliseconds."""


class ScanGate:
    """Closed while the scan runs (or is about to); other threads wait for it to open."""

    def __init__(self, max_wait_s: float = MAX_WAIT_S) -> None:
        self.max_wait_s = max_wait_s
        self._open = threading.Event()
        self._open.set()
        self._wakes: list[Callable[[], None]] = []
        self.waits = 0
        """Times a thread found the gate closed (diagnostics)."""

    @property
    def is_open(self) -> bool:
        return self._open.is_set()

    def close(self) -> None:
        """The scan is about to run: threads that come to the gate wait."""
        self._open.clear()

    def open(self) -> None:
        """The scan is done: the threads waiting go on, and those handed work during the
        scan are woken (each once)."""
        self._open.set()
        if self._wakes:
            wakes, self._wakes = self._wakes, []
            for wake in dict.fromkeys(wakes):  # a bound method equals itself: once each
                try:
                    wake()
                except Exception:  # one writer's fault must not keep the others asleep
                    log.exception("scan gate: a wake-up failed")

    @property
    def pending_wakes(self) -> int:
        """Wake-ups waiting for the scan to end (diagnostics)."""
        return len(self._wakes)

    def after_scan(self, wake: Callable[[], None]) -> None:
        """``wake()`` (a thread's wake-up after a hand-over) now if no scan runs, else when
        the scan is done. Woken during the scan, a thread takes the interpreter lock from
        it to reach the gate, and the wake-up itself is a system call on the scan's thread
        (a futex, a pipe write); after the scan it costs the scan nothing."""
        if self._open.is_set():
            wake()
        else:
            self._wakes.append(wake)  # open() swaps the list: a late one waits a period

    def wait(self, timeout_s: float | None = None) -> None:
        """Between two pieces of a thread's work: go on at once if the gate is open, else
        wait (without the interpreter lock) until it opens or ``max_wait_s`` (or the
        shorter ``timeout_s``) passed."""
        if self._open.is_set():
            return
        self.waits += 1
        limit_s = self.max_wait_s if timeout_s is None else min(timeout_s, self.max_wait_s)
        self._open.wait(limit_s)
