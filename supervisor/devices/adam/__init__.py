"""ADAM-5000/TCP remote I/O over Modbus TCP (seed 002 §1.1): analog inputs, thermocouples,
relays. Registration for :mod:`supervisor.devices.registry`."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from supervisor.config.models import SimulationConfig
from supervisor.core.driver import Driver
from supervisor.devices.adam.config import AdamDevice
from supervisor.devices.adam.driver import AdamDriver
from supervisor.devices.adam.protocol import AdamModule
from supervisor.devices.adam.transport import InProcessLink, ModbusLink, PymodbusTcpLink
from supervisor.devices.adam.unit import AdamUnit
from supervisor.devices.kind import (
    LINK,
    DeviceKind,
    DeviceRole,
    DeviceSimulator,
    DriverWiring,
    Shown,
    SimWiring,
)
from supervisor.fieldbus.modbus import ModbusExceptionAnswer

if TYPE_CHECKING:
    from supervisor.devices.adam.sim import AdamSimulator

# The simulator serves Modbus TCP through pymodbus's server, whose package imports its HTTP
# simulator (aiohttp): imported when a simulator is built, not with the kind's registration
# (``supervisor check`` of an I/O map; issue 30).


def unit_of(sim: DeviceSimulator) -> AdamUnit:
    """The simulated unit behind an ADAM simulator (served or not)."""
    if isinstance(sim, AdamUnit):
        return sim
    from supervisor.devices.adam.sim import AdamSimulator

    if isinstance(sim, AdamSimulator):
        return sim.unit
    raise TypeError(f"not an ADAM simulator: {sim!r}")


def _driver(name: str, dev: AdamDevice, wiring: DriverWiring) -> Driver:
    link: ModbusLink
    if wiring.simulator is not None:
        link = InProcessLink(name, wiring.clock, unit_of(wiring.simulator), dev.timeout_s)
    else:
        link = PymodbusTcpLink(name, dev.host, dev.port, dev.unit_id, dev.timeout_s)
    return AdamDriver(
        name,
        wiring.clock,
        link,
        {
            slot: AdamModule(m.kind, m.raw_format, m.poll_period_s)
            for slot, m in sorted(dev.modules.items())
        },
        poll_period_s=dev.poll_period_s,
        host_watchdog_s=dev.host_watchdog_s,
    )


def _simulator(name: str, dev: AdamDevice, wiring: SimWiring) -> DeviceSimulator:
    from supervisor.devices.adam.sim import AdamSimulator, plant_simulator

    unit = plant_simulator(name, dev, wiring.bench.simulation or SimulationConfig(), wiring.plant)
    if wiring.in_process:
        return unit  # nothing served: the driver calls the unit directly
    return AdamSimulator(unit, host=dev.host, port=dev.port, unit_id=dev.unit_id)


KIND = DeviceKind(
    AdamDevice,
    _driver,
    _simulator,
    role=DeviceRole.IO,
    shows=(Shown("link", LINK, "link"),),
)

__all__ = [
    "KIND",
    "AdamDevice",
    "AdamDriver",
    "AdamModule",
    "AdamSimulator",
    "AdamUnit",
    "InProcessLink",
    "ModbusExceptionAnswer",
    "ModbusLink",
    "PymodbusTcpLink",
    "unit_of",
]


def __getattr__(name: str) -> Any:
    if name == "AdamSimulator":
        from supervisor.devices.adam import sim

        return sim.AdamSimulator
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
