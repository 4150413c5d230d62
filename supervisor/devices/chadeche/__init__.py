"""Chadèche charger/discharger boards on one SPI bus (seed 000). Registration for
:mod:`supervisor.devices.registry`."""

from __future__ import annotations

from supervisor.core.driver import Driver
from supervisor.devices.chadeche.bus import (
    BoardClaim,
    ChadecheBus,
    SpidevBus,
    board_lock_path,
    claim_board,
    default_lock_dir,
)
from supervisor.devices.chadeche.config import ChadecheDevice
from supervisor.devices.chadeche.driver import RELAY_SETTLE_S, ChadecheDriver
from supervisor.devices.chadeche.protocol import Calibration
from supervisor.devices.chadeche.sim import SimBoard, SimChadecheBus, SimulatedBoards
from supervisor.devices.kind import (
    LINK,
    DeviceKind,
    DeviceRole,
    DeviceSimulator,
    DriverWiring,
    Shown,
    SimWiring,
)
from supervisor.sim.plant import make_cell


def _driver(name: str, dev: ChadecheDevice, wiring: DriverWiring) -> Driver:
    cal = {
        b.address: Calibration(
            current_slope=b.calibration.current_slope,
            current_offset_ma=b.calibration.current_offset_ma,
            voltage_slope=b.calibration.voltage_slope,
            voltage_offset_v=b.calibration.voltage_offset_v,
        )
        for b in dev.boards
    }
    bus: ChadecheBus
    probe = None
    if isinstance(wiring.simulator, SimulatedBoards):
        bus, owned = wiring.simulator.bus, False
        # The simulation-only temperature points (config.sim_board_points).
        probe = wiring.simulator.bus.cell_temperature_c
    else:  # opened for this driver: its close() closes it
        bus = SpidevBus(
            spi_bus=dev.spi.bus,
            spi_device=dev.spi.device,
            max_speed_hz=dev.spi.max_speed_hz,
            lock_dir=dev.lock_dir,
        )
        owned = True
    return ChadecheDriver(
        name,
        wiring.clock,
        bus,
        cal,
        poll_period_s=dev.poll_period_s,
        lock_dir=dev.lock_dir,
        owns_bus=owned,
        temperature_probe=probe,
    )


def _simulator(name: str, dev: ChadecheDevice, wiring: SimWiring) -> DeviceSimulator:
    boards = {}
    for b in dev.boards:
        cell = make_cell(b.sim, wiring.plant.ambient_c)
        wiring.cells[f"{name}.b{b.address}"] = cell
        boards[b.address] = SimBoard(cell)
    return SimulatedBoards(SimChadecheBus(wiring.clock, boards))


# A simulated SPI bus cannot be served to another process: the driver always talks to it.
KIND = DeviceKind(
    ChadecheDevice,
    _driver,
    _simulator,
    in_process_only=True,
    role=DeviceRole.CYCLER,
    shows=(Shown("link", LINK, "link"),),
)

__all__ = [
    "KIND",
    "RELAY_SETTLE_S",
    "BoardClaim",
    "ChadecheBus",
    "ChadecheDevice",
    "ChadecheDriver",
    "SimChadecheBus",
    "SpidevBus",
    "board_lock_path",
    "claim_board",
    "default_lock_dir",
]
