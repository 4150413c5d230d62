"""An EA-PSB 10060-60 on a test bench: a 4s Li-ion pack, the simulated unit, its drivers.

One rig for both transports (:mod:`rig_transports`): ``in-process`` hands the driver's lines
to :class:`EaSimulator` through :class:`InProcessScpiTransport` (virtual clock), ``tcp``
serves the same unit with :class:`EaTcpSimulator` on a loopback port the OS picks and
connects with :class:`TcpScpiTransport` (real clock). tests/unit/test_ea_driver.py (both
transports, or in process) and tests/integration/test_ea.py (TCP only) build it here.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Final

from rig_transports import IN_PROCESS, TCP

from supervisor.core.clock import Clock
from supervisor.core.quality import Quality, Reason
from supervisor.devices.ea import EaDriver, EaSimulator, EaTcpSimulator
from supervisor.fieldbus.scpi_transport import (
    InProcessScpiTransport,
    ScpiTransport,
    TcpScpiTransport,
)
from supervisor.sim.battery import make_model
from supervisor.sim.plant import BenchPlant
from supervisor.testing.ports import LOOPBACK

# The pack: 4 Li-ion cells in series, 3.0..4.2 V a cell; ±5 A on the channel.
V_MIN: Final = 12.0
V_MAX: Final = 16.8
I_MAX_A: Final = 5.0
INPUTS: Final = ("voltage", "current", "power", "output_on", "remote", "ques", "error")

DRIVER_DEFAULTS: Final[Mapping[str, Any]] = MappingProxyType(
    {
        "v_min": V_MIN,
        "v_max": V_MAX,
        "i_charge_max_a": I_MAX_A,
        "i_discharge_max_a": I_MAX_A,
        "poll_period_s": 0.1,
        "watchdog_s": 2.0,
        "timeout_s": 1.0,
    }
)
"""The driver settings the tests start from (a test overrides some with ``make_driver``)."""


def make_plant(clock: Clock) -> BenchPlant:
    """The pack half charged, the contactor closed (the supply drives it at once)."""
    battery = make_model("liion-pack", cells_series=4, capacity_ah=10.0, soc=0.5)
    plant = BenchPlant(clock, battery)
    plant.set_contactor(True)
    return plant


@dataclass
class EaRig:
    transport: str
    clock: Clock
    plant: BenchPlant
    sim: EaSimulator
    """The unit (an :class:`EaTcpSimulator`, served, on the ``tcp`` rig)."""
    address: str
    """Where the driver connects, as its messages name it (written out here, not read from
    the transport, so that a test comparing messages with it checks the wording)."""
    drivers: list[EaDriver] = field(default_factory=list)

    def scpi_transport(self) -> ScpiTransport:
        """A new transport to the unit, of the rig's kind."""
        if isinstance(self.sim, EaTcpSimulator):
            return TcpScpiTransport(LOOPBACK, self.sim.port)
        return InProcessScpiTransport(self.sim, self.clock)

    def make_driver(self, **overrides: Any) -> EaDriver:
        """A driver for ``psu`` with :data:`DRIVER_DEFAULTS` but ``overrides`` (not polled
        yet; closed when the rig closes)."""
        driver = EaDriver(
            "psu", self.clock, self.scpi_transport(), **{**DRIVER_DEFAULTS, **overrides}
        )
        self.drivers.append(driver)
        return driver

    async def connected_driver(self) -> EaDriver:
        """A driver with the default settings, polled once: connected."""
        driver = self.make_driver()
        await driver.poll()
        assert driver.connected, driver.last_error
        return driver


@asynccontextmanager
async def open_rig(transport: str, clock: Clock) -> AsyncIterator[EaRig]:
    """The unit reachable over ``transport``; on exit every driver made is closed and the
    unit stopped (served: no port left open, no checker task left running)."""
    plant = make_plant(clock)
    sim: EaSimulator
    if transport == IN_PROCESS:
        sim = EaSimulator(plant)  # plugged in from the start
        address = "in-process simulator ea"
    elif transport == TCP:
        sim = EaTcpSimulator(plant, host=LOOPBACK, port=0)
        await sim.start()
        address = f"{LOOPBACK}:{sim.port}"
    else:
        raise ValueError(f"unknown transport {transport!r}")
    rig = EaRig(transport, clock, plant, sim, address)
    try:
        yield rig
    finally:
        for driver in rig.drivers:
            await driver.close()
        await sim.stop()


def value(driver: EaDriver, point: str) -> Any:
    return driver.image()[point].value


def assert_all_good(driver: EaDriver) -> None:
    for point in INPUTS:
        sample = driver.image()[point]
        assert sample.quality is Quality.GOOD, (point, sample)


def assert_all_bad_comm_failure(driver: EaDriver) -> None:
    for point in INPUTS:
        sample = driver.image()[point]
        assert (sample.quality, sample.reason) == (Quality.BAD, Reason.COMM_FAILURE), point


async def charge(driver: EaDriver, current_a: float) -> None:
    """Set ``current_a`` (negative: discharge), switch the output on, one poll."""
    driver.write("current_set", current_a)
    driver.write("output", True)
    await driver.poll()
    assert driver.connected, driver.last_error


async def poll_connecting_now(driver: EaDriver) -> None:
    """One poll that tries to connect at once, whatever PolledDriver's backoff says."""
    driver._next_connect_t = float("-inf")
    await driver.poll()


async def reconnect_now(driver: EaDriver) -> None:
    """:func:`poll_connecting_now`, which must connect."""
    await poll_connecting_now(driver)
    assert driver.connected, driver.last_error


def ea_only_io_map(bench: str, ea: dict[str, Any]) -> dict[str, Any]:
    """An I/O map with the EA supply ``ea`` alone and one Li-ion channel on it (the pack's
    limits)."""
    return {
        "bench": bench,
        "devices": {"ea": {"driver": "ea-psb", "host": LOOPBACK, **ea}},
        "channels": [
            {
                "name": "ch0",
                "source": {"device": "ea"},
                "chemistry": "liion",
                "capacity_ah": 10.0,
                "limits": {"current_a": [-I_MAX_A, I_MAX_A], "voltage_v": [V_MIN, V_MAX]},
            }
        ],
    }
