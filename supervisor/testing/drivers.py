"""A fake driver for scan and logic tests: inputs the test sets, writes it records."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.core.errors import DeviceIOError
from supervisor.devices.base import PolledDriver


class RecordingDriver(PolledDriver):
    """Inputs are whatever the test puts in ``values``; every write lands in ``writes``.

    Set ``fail`` to make connecting and reading fail like a lost device (PolledDriver then
    marks every input BAD and reconnects with its backoff); ``safe_calls`` counts safe-state
    requests.
    """

    def __init__(
        self,
        name: str,
        clock: Clock,
        inputs: Mapping[str, Value],
        outputs: Iterable[str] = (),
        poll_period_s: float = 0.1,
    ) -> None:
        self.values: dict[str, Value] = dict(inputs)
        self.writes: list[tuple[str, Value]] = []
        self.fail = False
        self.safe_calls = 0
        self._points = {p: PointInfo(p, "in") for p in self.values}
        self._points.update({p: PointInfo(p, "out") for p in outputs})
        super().__init__(name, clock, poll_period_s)

    def points(self) -> Mapping[str, PointInfo]:
        return self._points

    async def _connect(self) -> None:
        if self.fail:
            raise DeviceIOError(self.name, "connection refused")

    async def _read(self) -> dict[str, Sample]:
        if self.fail:
            raise DeviceIOError(self.name, "no answer")
        t = self.clock.now()
        return {k: Sample(v, t=t) for k, v in self.values.items()}

    async def _write(self, point: str, value: Value) -> None:
        self.writes.append((point, value))

    async def _safe(self) -> None:
        self.safe_calls += 1
