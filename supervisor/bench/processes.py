"""Child processes that do not outlive the process that started them.

A test run or a benchmark that is killed (SIGKILL, a CI timeout) runs no teardown, so the
servers it started (an InfluxDB for the tests) would keep running and holding their ports.
On Linux the kernel can send the child a signal when its parent dies
(``prctl(PR_SET_PDEATHSIG)``, prctl(2)); elsewhere this does nothing and teardown alone
stops the child.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import signal
import sys
from collections.abc import Callable

_PR_SET_PDEATHSIG = 1


def _set_parent_death_signal(sig: int) -> None:
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, sig, 0, 0, 0)


def stop_with_parent(sig: int = signal.SIGTERM) -> Callable[[], None] | None:
    """A ``preexec_fn`` for ``subprocess.Popen``: the child gets ``sig`` when its parent
    dies (Linux; None elsewhere, which ``Popen`` takes as no ``preexec_fn``)."""
    if not sys.platform.startswith("linux"):
        return None
    return lambda: _set_parent_death_signal(sig)
