"""EA-PSB 10000 bidirectional supply over SCPI/TCP (seed 002 §2.2). Registration for
:mod:`supervisor.devices.registry`."""

from __future__ import annotations

from supervisor.core.driver import Driver
from supervisor.devices.ea.config import EaDevice
from supervisor.devices.ea.driver import EaDriver
from supervisor.devices.ea.sim import EaSimulator, EaTcpSimulator
from supervisor.devices.kind import (
    LINK,
    DeviceKind,
    DeviceRole,
    DeviceSimulator,
    DriverWiring,
    Shown,
    SimWiring,
)
from supervisor.fieldbus.scpi_transport import (
    InProcessScpiTransport,
    ScpiConnection,
    ScpiTransport,
    TcpScpiTransport,
)


def _driver(name: str, dev: EaDevice, wiring: DriverWiring) -> Driver:
    owner = wiring.owner(name)
    if owner is None:  # refused by the bench checks: an EA supply takes its limits from it
        raise ValueError(f"device {name!r} drives no channel")
    transport: ScpiTransport
    if wiring.simulator is None:
        transport = TcpScpiTransport(dev.host, dev.port)
    elif isinstance(wiring.simulator, EaSimulator):
        # Dry runs and virtual-clock benches: the simulator's interpreter, no socket.
        transport = InProcessScpiTransport(wiring.simulator, wiring.clock)
    else:
        raise TypeError(f"device {name!r}: {wiring.simulator!r} is not an EA simulator")
    lo, hi = owner.limits.current_a
    return EaDriver(
        name,
        wiring.clock,
        transport,
        v_min=owner.limits.voltage_v[0],
        v_max=owner.limits.voltage_v[1],
        i_charge_max_a=hi,
        i_discharge_max_a=-lo,
        expected_model=dev.expected_model,
        poll_period_s=dev.poll_period_s,
        watchdog_s=dev.watchdog_s,
        timeout_s=dev.timeout_s,
    )


def _simulator(name: str, dev: EaDevice, wiring: SimWiring) -> DeviceSimulator:
    if wiring.in_process:  # nothing served, nothing sleeping on its own
        return EaSimulator(
            wiring.plant,
            dev.sim_model,
            dev.sim_nominal_v,
            dev.sim_nominal_a,
            dev.sim_nominal_w,
            name=name,
        )
    return EaTcpSimulator(
        wiring.plant,
        dev.sim_model,
        dev.sim_nominal_v,
        dev.sim_nominal_a,
        dev.sim_nominal_w,
        host=dev.host,
        port=dev.port,
        name=name,
    )


KIND = DeviceKind(
    EaDevice,
    _driver,
    _simulator,
    role=DeviceRole.SUPPLY,
    shows=(Shown("voltage", "voltage", "n2"), Shown("link", LINK, "link")),
)

__all__ = [
    "KIND",
    "EaDevice",
    "EaDriver",
    "EaSimulator",
    "EaTcpSimulator",
    "InProcessScpiTransport",
    "ScpiConnection",
    "ScpiTransport",
    "TcpScpiTransport",
]
