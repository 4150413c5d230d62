"""Waiting for a condition in real-clock loopback tests (a bound, never a timing claim)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

SETTLE_S = 15.0
"""Generous upper bound for a loaded machine: reaching it fails the test, it is not a
claim about how fast anything is."""


async def wait_until(
    condition: Callable[[], bool], what: str, limit_s: float = SETTLE_S, step_s: float = 0.02
) -> None:
    """Poll ``condition`` until true; AssertionError naming ``what`` after ``limit_s``."""
    deadline = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting after {limit_s:g} s: {what}")
        await asyncio.sleep(step_s)
