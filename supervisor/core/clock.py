"""Time source injected everywhere: real time in service, virtual time for dry runs.

All internal times are ``float`` seconds on a monotonic axis (``now()``); ``to_wall``
turns such a time into Unix time for timestamps shown to people and databases.
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol


class Clock(Protocol):
    @property
    def virtual(self) -> bool: ...

    def now(self) -> float:
        """Monotonic seconds."""
        ...

    def wall(self) -> float:
        """Unix time in seconds."""
        ...

    def to_wall(self, t: float) -> float:
        """Unix time of the monotonic instant ``t``."""
        ...

    async def sleep_until(self, t: float) -> None: ...


class RealClock:
    """Wall-clock time; sleeps really sleep."""

    virtual = False

    def now(self) -> float:
        return time.monotonic()

    def wall(self) -> float:
        return time.time()

    def to_wall(self, t: float) -> float:
        return time.time() - (time.monotonic() - t)

    async def sleep_until(self, t: float) -> None:
        delay = t - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)


class VirtualClock:
    """Time that only moves when someone sleeps: scans run back to back.

    Used by dry runs and deterministic tests; ten simulated hours take as long as the
    CPU needs to compute them.
    """

    virtual = True

    def __init__(self, start_s: float = 0.0, wall_epoch_s: float = 1_767_225_600.0) -> None:
        # Default epoch 2026-01-01T00:00:00Z keeps result files reproducible.
        self.t_s = start_s
        """The time now (``now()``); the scan engine's lockstep reads and moves it without
        a call (issue 13's dry run). Never moved backwards."""
        self._epoch = wall_epoch_s

    def now(self) -> float:
        return self.t_s

    def wall(self) -> float:
        return self._epoch + self.t_s

    def to_wall(self, t: float) -> float:
        return self._epoch + t

    def advance(self, dt_s: float) -> None:
        if dt_s < 0:
            raise ValueError("virtual time never goes backwards")
        self.t_s += dt_s

    async def sleep_until(self, t: float) -> None:
        if t > self.t_s:
            self.t_s = t
        # Yield once so other tasks get a turn, as a real sleep would allow.
        await asyncio.sleep(0)
