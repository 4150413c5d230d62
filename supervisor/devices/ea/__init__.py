"""EA-PSB 10000 bidirectional supply over SCPI/TCP (seed 002 §2.2). Registration for
:mod:`supervisor.devices.registry`."""

from __future__ import annotations

from supervisor.core.driver import Driver
from supervisor.devices.ea.config import EaDevice
from supervisor.devices.ea.driver import EaDriver
from supervisor.devices.ea.sim import EaSimulator
from supervisor.devices.kind import DeviceKind, DeviceSimulator, DriverWiring, SimWiring


def _driver(name: str, dev: EaDevice, wiring: DriverWiring) -> Driver:
    owner = wiring.owner(name)
    if owner is None:  # refused by the bench checks: an EA supply takes its limits from it
        raise ValueError(f"device {name!r} drives no channel")
    lo, hi = owner.limits.current_a
    return EaDriver(
        name,
        wiring.clock,
        dev.host,
        dev.port,
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
    return EaSimulator(
        wiring.plant,
        model=dev.sim_model,
        nominal_v=dev.sim_nominal_v,
        nominal_a=dev.sim_nominal_a,
        nominal_w=dev.sim_nominal_w,
        host=dev.host,
        port=dev.port,
        name=name,
    )


KIND = DeviceKind(EaDevice, _driver, _simulator)

__all__ = ["KIND", "EaDevice", "EaDriver", "EaSimulator"]
