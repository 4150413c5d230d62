"""An ideal bidirectional supply acting directly on the plant, for dry runs.

It has the EA driver's points (``voltage``, ``current``, ``power``, ``output_on``;
outputs ``output``, ``current_set``, ``voltage_set``) and the same regulation (CV at
the voltage set value bounded by the source and sink current limits, via
``BenchPlant``), but no socket: a dry run on the virtual clock stays deterministic and
fast. Real benches use ``supervisor.devices.ea.driver.EaDriver`` over SCPI.
"""

from __future__ import annotations

from collections.abc import Mapping

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.devices.base import PolledDriver
from supervisor.devices.sim_supply.config import POINTS
from supervisor.sim.plant import BenchPlant


class PlantSupplyDriver(PolledDriver):
    def __init__(
        self,
        name: str,
        clock: Clock,
        plant: BenchPlant,
        *,
        v_min: float,
        v_max: float,
        poll_period_s: float = 0.1,
    ) -> None:
        self.plant = plant
        self.v_min = v_min
        self.v_max = v_max
        self._cv_v: float | None = None
        self._current = 0.0
        super().__init__(name, clock, poll_period_s)

    def points(self) -> Mapping[str, PointInfo]:
        return POINTS

    async def _connect(self) -> None:
        self.plant.set_contactor(True)
        self.plant.set_supply(remote=True, output_on=False, curr_set_a=0.0, sink_curr_set_a=0.0)

    async def _read(self) -> dict[str, Sample]:
        p, t = self.plant, self.clock.now()
        i = p.pack_current_a
        v = p.supply_voltage_v
        return {
            "voltage": Sample(v, t=t),
            "current": Sample(i, t=t),
            "power": Sample(v * i, t=t),
            "output_on": Sample(p.supply.output_on, t=t),
        }

    async def _write(self, point: str, value: Value) -> None:
        if point == "output":
            self.plant.set_supply(output_on=bool(value))
            return
        assert not isinstance(value, str)
        if point == "voltage_set":
            self._cv_v = min(max(float(value), self.v_min), self.v_max)
        else:
            self._current = float(value)
        self._apply()

    def _apply(self) -> None:
        i = self._current
        if i > 0:
            v = self.v_max if self._cv_v is None else self._cv_v
            self.plant.set_supply(curr_set_a=i, volt_set_v=v, sink_curr_set_a=0.0)
        elif i < 0:
            self.plant.set_supply(sink_curr_set_a=-i, volt_set_v=self.v_min, curr_set_a=0.0)
        else:
            self.plant.set_supply(curr_set_a=0.0, sink_curr_set_a=0.0)

    async def _safe(self) -> None:
        self._current = 0.0
        self.plant.set_supply(curr_set_a=0.0, sink_curr_set_a=0.0, output_on=False)
