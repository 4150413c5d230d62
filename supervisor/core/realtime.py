"""Real-time scheduling for the scan's thread (``scan.realtime_priority``, ADR 0023).

A soft PLC's cyclic task runs at a real-time priority (SCHED_FIFO on Linux): on a machine
whose cores are shared with the bench's other programs (its InfluxDB, SCADA clients, a
browser), a task of normal priority that wakes for its deadline waits its turn on the
core, and a scan in progress is taken off it for another program's time slice. Issue 13's
load case, back to back: the scan's thread waited for a core p99 3.6 ms per scan at normal
priority, 0.3 ms at SCHED_FIFO 20.

Only the thread that calls :meth:`RealtimePriority.enter` is raised (Linux schedules
threads, not processes), and :meth:`RealtimePriority.leave` puts back what it had. A
refusal (no CAP_SYS_NICE and no ``RLIMIT_RTPRIO``, a seccomp filter, another system) is
logged once with what grants it, and the scan runs at normal priority: a slower scan is
not a reason to leave outputs unattended.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from typing import Any, Final

log = logging.getLogger(__name__)

__all__ = ["GRANT_HINT", "RealtimePriority"]

GRANT_HINT: Final = (
    "grant it with LimitRTPRIO= in the service unit (deploy/bench-supervisor@.service) or"
    " the CAP_SYS_NICE capability"
)

SetScheduler = Callable[[int, int, Any], None]


def _no_setscheduler(_pid: int, _policy: int, _param: Any) -> None:
    raise OSError("this system has no sched_setscheduler")


class RealtimePriority:
    """SCHED_FIFO at ``priority`` (1–99) for the calling thread, while entered.

    ``setscheduler`` / ``getscheduler`` / ``getparam`` are ``os``'s by default (injected
    by the tests that play a refusal)."""

    def __init__(
        self,
        priority: int,
        what: str = "scan",
        setscheduler: SetScheduler | None = None,
        getscheduler: Callable[[int], int] | None = None,
        getparam: Callable[[int], Any] | None = None,
    ) -> None:
        if not 1 <= priority <= 99:
            raise ValueError(f"real-time priority {priority}: expected 1 to 99")
        self.priority = priority
        self.what = what
        sys_os: Any = os  # sched_* exist on Linux only
        self._set: SetScheduler = (
            setscheduler
            if setscheduler is not None
            else getattr(sys_os, "sched_setscheduler", _no_setscheduler)
        )
        self._get: Callable[[int], int] = (
            getscheduler
            if getscheduler is not None
            else getattr(sys_os, "sched_getscheduler", lambda _pid: 0)
        )
        self._param: Callable[[int], Any] = (
            getparam
            if getparam is not None
            else getattr(sys_os, "sched_getparam", lambda _pid: None)
        )
        self._saved: dict[int, tuple[int, Any]] = {}
        self.refused: str | None = None
        """Why the last :meth:`enter` was refused (None when it was not)."""

    def enter(self) -> bool:
        """Raise the calling thread; True when it runs at the real-time priority now."""
        tid = threading.get_native_id()
        try:
            saved = (self._get(0), self._param(0))
            policy = getattr(os, "SCHED_FIFO", 1)
            self._set(0, policy, os.sched_param(self.priority))
        except (OSError, AttributeError) as exc:
            self.refused = str(exc) or type(exc).__name__
            log.warning(
                "%s: real-time priority %d refused (%s): it runs at normal priority, its"
                " start and duration shared with every other program of the machine; %s",
                self.what,
                self.priority,
                self.refused,
                GRANT_HINT,
            )
            return False
        self.refused = None
        self._saved[tid] = saved
        log.info("%s: runs at real-time priority %d (SCHED_FIFO)", self.what, self.priority)
        return True

    def leave(self) -> None:
        """Put the calling thread back to what it had before :meth:`enter` (nothing when
        that was refused)."""
        saved = self._saved.pop(threading.get_native_id(), None)
        if saved is None:
            return
        policy, param = saved
        try:
            self._set(0, policy, param if param is not None else os.sched_param(0))
        except OSError as exc:  # lowering one's own priority is always allowed: a bug
            log.error("%s: could not leave real-time priority: %s", self.what, exc)
