"""A simulated device with many analog inputs (sine waves): load for scan benchmarks."""

from __future__ import annotations

import math
from collections.abc import Mapping

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.devices.base import PolledDriver


class SignalGenerator(PolledDriver):
    """``n`` float inputs ``ai{k}`` (sines of different periods) and ``n_out`` outputs."""

    def __init__(self, name: str, clock: Clock, n: int, n_out: int = 0, poll_period_s: float = 0.1):
        self._n = n
        self._points = {f"ai{k}": PointInfo(f"ai{k}", "in", "float", "V") for k in range(n)}
        self._points.update(
            {f"ao{k}": PointInfo(f"ao{k}", "out", "float", "V") for k in range(n_out)}
        )
        self.written: dict[str, Value] = {}
        super().__init__(name, clock, poll_period_s)

    def points(self) -> Mapping[str, PointInfo]:
        return self._points

    async def _connect(self) -> None:
        return None

    async def _read(self) -> dict[str, Sample]:
        t = self.clock.now()
        return {f"ai{k}": Sample(math.sin(t * (1 + k % 17) * 0.1), t=t) for k in range(self._n)}

    async def _write(self, point: str, value: Value) -> None:
        self.written[point] = value

    async def _safe(self) -> None:
        for p in self.written:
            self.written[p] = 0.0
