"""The interpreter's policy for a process that scans for days: the garbage collector and
the interpreter lock (docs/adr/0018-scan-performance.md, 0021-interpreter-lock.md).

CPython's full (oldest-generation) collections walk every container object alive and stop
the event loop while they do: 30–80 ms on the simulated bench (issue 13), several
deadlines of a 10 ms scan. Almost all of those objects are made at start-up (modules,
the bench, the compiled recipes, the OPC UA address space) and live as long as the
process, so once the bench is built and its first scans ran, what is alive is collected
once and frozen (``gc.freeze``): later full passes never walk it again. Young collections
stay short (CPython's default size: each holds the interpreter lock while it runs) and
middle ones rare, so that objects living a few scans (an asyncio handle, a driver's image)
die before they are promoted, which is what makes full passes due in the first place.

The scan shares the interpreter lock with the publishers' threads (OPC UA server,
historian and InfluxDB writers). A thread that wants the lock waits for the holder to
release it, at the latest after the switch interval (CPython: 5 ms): a scan waking up
while the OPC UA thread writes values waited up to 5 ms to start, and a scan under way
lost the lock to it for as long. The interval is 1 ms here (``SWITCH_INTERVAL_S``): the
scan waits at most about that long each time, the threads switch a little more often.
"""

from __future__ import annotations

import gc
import logging
import sys
import time
from typing import Final

log = logging.getLogger(__name__)

YOUNG_THRESHOLD: Final = 700
"""Allocations (net of frees) of container objects between two young collections:
CPython's default. A young collection holds the interpreter lock while it walks the young
objects still alive, whichever thread runs it: at 5000 (ADR 0018's first choice) each took
3–6 ms in issue 13's load case and a scan that met one lost that long; at 700 they take
about 0.4 ms (load case, back to back: scan duration p99 11–16 → 8–12 ms, jitter p99 6–13
→ 5–9 ms on the loaded machine)."""
MIDDLE_THRESHOLD: Final = 1000
"""Young collections between two middle ones (default 10): about 700 000 allocations. A
middle collection walks every container object allocated since the last one that is
still alive, whatever the threshold (the others were freed by their reference counts):
in issue 13's load case the samples queued for the historian and InfluxDB, 10–13 ms a
pass. At 140 (about 100 000 allocations) that came 28 times a minute, each a late scan,
and 3 full passes followed (24–82 ms); at 1000, 4 times a minute and no full pass in the
minute (load case, back to back). At 10 they came every 7000 allocations and promoted
more to the old generation. Cyclic garbage waits longer to be collected: a few seconds'
worth more, bounded."""
SWITCH_INTERVAL_S: Final = 0.001
"""How long a thread may hold the interpreter lock while another waits for it (CPython's
default 5 ms; issue 13's load case, 16 channels at 10 ms with every publisher on: scan
duration p99 44–46 ms → 16–20 ms and start jitter p99 46–68 ms → 16–19 ms on the loaded
machine, back to back)."""
OLD_THRESHOLD: Final = 20
"""Middle collections between two full ones (default 10); CPython also waits until the
objects promoted since the last full pass are a quarter of those it kept, which after a
freeze counts every frozen object too."""


def settle_after_start() -> int:
    """Collect what start-up left, freeze what is alive, set the thresholds above and the
    interpreter lock's switch interval.

    Call it once the process is built and its first scans ran, before the scan matters
    (one full collection: tens of milliseconds). Returns how many objects were frozen.
    """
    t0 = time.perf_counter()
    gc.collect()
    gc.freeze()
    gc.set_threshold(YOUNG_THRESHOLD, MIDDLE_THRESHOLD, OLD_THRESHOLD)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    frozen = gc.get_freeze_count()
    log.info(
        "heap: %d objects frozen after start-up in %.1f ms; collector thresholds %s;"
        " switch interval %g ms",
        frozen,
        (time.perf_counter() - t0) * 1000,
        gc.get_threshold(),
        sys.getswitchinterval() * 1000,
    )
    return frozen


IDLE_YOUNG: Final = YOUNG_THRESHOLD // 2
"""In the scan's idle time (:func:`collect_when_idle`) the young generation is collected
once it holds half what would set off an automatic collection: the automatic one, which
runs in whichever thread allocates (a scan under way, the OPC UA thread holding the lock
the scan waits for), then rarely comes."""
IDLE_MIDDLE: Final = MIDDLE_THRESHOLD // 2
IDLE_OLD: Final = OLD_THRESHOLD // 2
IDLE_MIDDLE_NEEDS_S: Final = 0.005
"""Idle time a middle or full collection needs to be started (a few ms each in issue
13's load case)..."""
IDLE_YOUNG_NEEDS_S: Final = 0.001
"""...and a young one (~0.4 ms): a late scan's next one is not delayed further."""


def collect_when_idle(left_s: float) -> int:
    """Collect what is due now that the scan is done, ``left_s`` before the next one
    (``ScanEngine.idle``). Returns the generation collected, or -1.

    CPython collects when an allocation crosses a threshold, in the thread that allocates:
    at a 10 ms scan, young and middle collections (0.4 and 3–16 ms) landed in scans and in
    the publishers' threads while the scan waited for the interpreter lock (issue 13).
    Collected here, between scans, they cost the scan nothing; the thresholds stay as the
    backstop for a burst of allocations."""
    young, middle, old = gc.get_count()
    if left_s >= IDLE_MIDDLE_NEEDS_S:
        if old >= IDLE_OLD and middle >= IDLE_MIDDLE:
            gc.collect(2)
            return 2
        if middle >= IDLE_MIDDLE:
            gc.collect(1)
            return 1
    if young >= IDLE_YOUNG and left_s >= IDLE_YOUNG_NEEDS_S:
        gc.collect(0)
        return 0
    return -1
