"""ADAM-5000/TCP remote I/O over Modbus TCP (seed 002 §1.1): analog inputs, thermocouples,
relays. Registration for :mod:`supervisor.devices.registry`."""

from __future__ import annotations

from supervisor.config.models import SimulationConfig
from supervisor.core.driver import Driver
from supervisor.devices.adam.config import AdamDevice
from supervisor.devices.adam.driver import AdamDriver
from supervisor.devices.adam.protocol import AdamModule
from supervisor.devices.adam.sim import AdamSimulator, plant_simulator
from supervisor.devices.kind import DeviceKind, DeviceSimulator, DriverWiring, SimWiring


def _driver(name: str, dev: AdamDevice, wiring: DriverWiring) -> Driver:
    return AdamDriver(
        name,
        wiring.clock,
        dev.host,
        dev.port,
        {slot: AdamModule(m.kind, m.raw_format) for slot, m in sorted(dev.modules.items())},
        unit_id=dev.unit_id,
        poll_period_s=dev.poll_period_s,
        timeout_s=dev.timeout_s,
    )


def _simulator(name: str, dev: AdamDevice, wiring: SimWiring) -> DeviceSimulator:
    return plant_simulator(name, dev, wiring.bench.simulation or SimulationConfig(), wiring.plant)


KIND = DeviceKind(AdamDevice, _driver, _simulator)

__all__ = ["KIND", "AdamDevice", "AdamDriver", "AdamModule", "AdamSimulator"]
