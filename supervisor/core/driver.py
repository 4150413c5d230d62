"""What a device driver offers the scan engine: a latest-value image and queued writes.

A driver owns its device (one poller per device). The scan never awaits a driver: at
scan start it copies ``image()`` synchronously; outputs go through ``write()``, which
only queues. The driver's own task (or, on a virtual clock, the engine in lockstep)
calls ``poll()`` to talk to the device.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal, Protocol

from supervisor.core.quality import Quality, Reason

Value = float | int | bool | str
DType = Literal["float", "int", "bool", "str"]
Direction = Literal["in", "out"]


@dataclass(slots=True)
class Sample:
    """One acquired value with its quality and acquisition time (``Clock.now()`` axis)."""

    value: Value | None
    quality: Quality = Quality.GOOD
    reason: Reason = Reason.NONE
    t: float = 0.0


@dataclass(frozen=True, slots=True)
class PointInfo:
    """A point a driver exposes; I/O maps bind tags to points by name."""

    name: str
    direction: Direction
    dtype: DType = "float"
    unit: str = ""
    description: str = ""


class Driver(Protocol):
    name: str
    poll_period_s: float

    @property
    def connected(self) -> bool: ...

    def points(self) -> Mapping[str, PointInfo]: ...

    def image(self) -> Mapping[str, Sample]: ...

    def write(self, point: str, value: Value) -> None: ...

    async def poll(self) -> None: ...

    async def safe_state(self) -> str | None:
        """Drive every output safe; None when confirmed, else why it was not."""
        ...

    async def close(self) -> None: ...
