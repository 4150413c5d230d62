"""BMS over CAN (seed 002 §2.1), listened to and decoded with its DBC. Registration for
:mod:`supervisor.devices.registry`."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from supervisor.config.models import SimulationConfig
from supervisor.core.driver import Driver
from supervisor.devices.bms.config import BmsDevice
from supervisor.devices.kind import (
    LINK,
    DeviceKind,
    DeviceRole,
    DeviceSimulator,
    DriverWiring,
    Shown,
    SimWiring,
)

if TYPE_CHECKING:
    import can

    from supervisor.devices.bms.driver import BmsDriver
    from supervisor.devices.bms.sim import BmsSimulator, SimulatedBms

# The driver and the simulator speak CAN through python-can and decode with cantools: both
# imported when a driver or a simulator is built, not with the kind's registration
# (``supervisor check`` of an I/O map; issue 30).


def bus_factory(dev: BmsDevice) -> Callable[[], can.BusABC]:
    """How the driver opens its bus, from the I/O map entry."""
    import can

    from supervisor.devices.bms.driver import socketcand_bus_factory

    if dev.interface == "socketcand":
        # The product's own client: reads the daemon's TCP stream element by element.
        return socketcand_bus_factory(dev.host, dev.port, dev.channel)
    return lambda: can.Bus(interface=dev.interface, channel=dev.channel)


def _driver(name: str, dev: BmsDevice, wiring: DriverWiring) -> Driver:
    from supervisor.devices.bms.driver import BmsDriver
    from supervisor.devices.bms.sim import SimulatedBms

    factory = bus_factory(dev)
    sim = wiring.simulator
    if isinstance(sim, SimulatedBms):  # in process: no socket, frames pumped on the clock
        factory = sim.link
    return BmsDriver(
        name,
        wiring.clock,
        factory,
        poll_period_s=dev.poll_period_s,
        stale_factor=dev.stale_factor,
        allow_extra_bytes=dev.allow_extra_bytes,
    )


def _simulator(name: str, dev: BmsDevice, wiring: SimWiring) -> DeviceSimulator:
    from supervisor.devices.bms.sim import SimulatedBms, plant_values

    sc = wiring.bench.simulation or SimulationConfig()
    cells = sc.pack.cells_series or 1
    return SimulatedBms(
        name,
        wiring.clock,
        plant_values(wiring.plant, cells),
        interface=dev.interface,
        channel=dev.channel,
        host=dev.host,
        port=dev.port,
        in_process=wiring.in_process,
    )


KIND = DeviceKind(
    BmsDevice,
    _driver,
    _simulator,
    role=DeviceRole.BMS,
    shows=(
        Shown("link", LINK, "link"),
        Shown("pack", "pack_voltage", "n2"),
        Shown("cell min", "min_cell_voltage", "n3"),
        Shown("cell max", "max_cell_voltage", "n3"),
        Shown("temp max", "max_temp", "n1"),
    ),
)

__all__ = ["KIND", "BmsDevice", "BmsDriver", "BmsSimulator", "SimulatedBms"]


def __getattr__(name: str) -> Any:
    if name == "BmsDriver":
        from supervisor.devices.bms import driver

        return driver.BmsDriver
    if name in ("BmsSimulator", "SimulatedBms"):
        from supervisor.devices.bms import sim

        return getattr(sim, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
