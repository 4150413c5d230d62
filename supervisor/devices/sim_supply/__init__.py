"""An ideal bidirectional supply acting directly on the simulated pack (dry runs).
Registration for :mod:`supervisor.devices.registry`."""

from __future__ import annotations

from dataclasses import dataclass

from supervisor.core.driver import Driver
from supervisor.devices.kind import DeviceKind, DeviceSimulator, DriverWiring, SimWiring
from supervisor.devices.sim_supply.config import SimSupplyDevice
from supervisor.devices.sim_supply.driver import PlantSupplyDriver
from supervisor.sim.plant import BenchPlant


@dataclass
class _Plant:
    plant: BenchPlant

    async def start(self) -> None:
        return None

    async def stop(self) -> None:
        return None

    def addresses(self) -> list[str]:
        return []


def _driver(name: str, dev: SimSupplyDevice, wiring: DriverWiring) -> Driver:
    owner = wiring.owner(name)
    if owner is None or not isinstance(wiring.simulator, _Plant):
        raise ValueError(f"device {name!r} drives no channel or has no plant")
    return PlantSupplyDriver(
        name,
        wiring.clock,
        wiring.simulator.plant,
        v_min=owner.limits.voltage_v[0],
        v_max=owner.limits.voltage_v[1],
        poll_period_s=dev.poll_period_s,
    )


def _simulator(name: str, dev: SimSupplyDevice, wiring: SimWiring) -> DeviceSimulator:
    return _Plant(wiring.plant)


KIND = DeviceKind(SimSupplyDevice, _driver, _simulator, in_process_only=True)
