"""A writer's thread that a crash does not end (issue 28, finding 1).

A writer thread ends when an exception escapes its loop, and nothing else notices: its
queue fills, its counters freeze (the historian's writer died on one refused value's
event, with ``write_errors 0`` and ``last_error ''``). Each writer's loop already handles
the failures it expects (a full disk, a lost server); ``run_restarting`` is the net for
the rest: the exception is logged with its traceback, handed to the writer (which counts
it, says it in its ``error``, and lets its owner raise an alarm), and the loop starts
again after ``retry_s``, unless the writer is stopping.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

log = logging.getLogger(__name__)


def run_restarting(
    name: str,
    loop: Callable[[], None],
    crashed: Callable[[Exception], None],
    stopping: Callable[[], bool],
    wait: Callable[[float], None],
    retry_s: float = 1.0,
) -> None:
    """Run ``loop`` until it returns; after an exception escapes it, ``crashed(exc)``,
    then ``wait(retry_s)`` (which returns early at a stop) and run it again, unless
    ``stopping()``."""
    while True:
        try:
            loop()
            return
        except Exception as exc:
            log.error("%s: thread crashed (%s: %s); started again", name, type(exc).__name__, exc)
            log.debug("%s: the crash", name, exc_info=exc)
            try:
                crashed(exc)
            except Exception:  # the net itself must hold
                log.exception("%s: reporting the crash failed", name)
        if stopping():
            return
        wait(retry_s)
