"""The simulated devices of a bench: protocol-level simulators around one plant.

Built from an I/O map's ``simulation:`` section and its simulated devices (``sim: true``,
or a Chadèche ``backend: sim``): every registered kind builds its own simulator on its own
codec; the seed-002 devices (ADAM Modbus server, EA SCPI server, BMS frames through a
socketcand server or python-can's virtual bus) all read one ``BenchPlant`` so that the
physics agree between them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from supervisor.config.models import BenchConfig
from supervisor.core.clock import Clock
from supervisor.devices.kind import DeviceSimulator, SimWiring
from supervisor.devices.registry import REGISTRY, Registry
from supervisor.sim.battery import BatteryModel
from supervisor.sim.plant import BenchPlant, make_plant

log = logging.getLogger(__name__)


@dataclass
class SimulatedBench:
    plant: BenchPlant
    devices: dict[str, DeviceSimulator] = field(default_factory=dict)
    cells: dict[str, BatteryModel] = field(default_factory=dict)
    """Battery models of simulators besides the plant (Chadèche boards), by name."""
    served: tuple[str, ...] = ()
    """Devices whose simulator another process can reach (protocol servers on loopback)."""

    async def start(self) -> None:
        for sim in self.devices.values():
            await sim.start()

    async def stop(self) -> None:
        for name, sim in reversed(self.devices.items()):
            try:
                await sim.stop()
            except Exception:
                log.exception("simulator %s: stop failed", name)

    def release(self) -> None:
        """After the last ``stop()``: what a simulator keeps across a stop and a start (an
        unplugged device plugged in again) is let go."""
        for sim in self.devices.values():
            release = getattr(sim, "release", None)
            if release is not None:
                release()

    def addresses(self) -> list[str]:
        return [line for sim in self.devices.values() for line in sim.addresses()]

    def press_estop(self, pressed: bool = True) -> None:
        self.plant.set_estop(pressed)

    def state(self) -> dict[str, Any]:
        """What the plant is doing now, as JSON-ready values (``GET /api/sim/state``): the
        battery contactor (and what holds it), the e-stop, the supply, the pack."""
        p = self.plant
        s = p.supply
        return {
            "contactor_closed": p.contactor_closed,
            "contactor_coil_on": p.contactor_coil_on,
            "watchdog_relay_fitted": p.watchdog_timeout_s is not None,
            "watchdog_relay_closed": p.watchdog_relay_closed,
            "heartbeat_toggles": p.heartbeat_toggles,
            "estop_pressed": p.estop_pressed,
            "supply": {
                "output_on": s.output_on,
                "remote": s.remote,
                "energised": p.supply_energised,
                "volt_set_v": s.volt_set_v,
                "curr_set_a": s.curr_set_a,
                "sink_curr_set_a": s.sink_curr_set_a,
            },
            "pack": {"current_a": p.pack_current_a, "voltage_v": p.pack_voltage_v},
        }


def build_simulation(
    cfg: BenchConfig,
    clock: Clock,
    *,
    in_process_only: bool = False,
    in_process: bool = False,
    registry: Registry = REGISTRY,
) -> SimulatedBench | None:
    """Simulators for the bench's simulated devices (None if it has none).

    ``in_process_only``: only the kinds whose simulator cannot be served to another process
    (a simulated SPI bus); the others are served by ``supervisor sim`` elsewhere.
    ``in_process``: the drivers will talk to every simulator in this process (nothing served).
    """
    wiring = SimWiring(clock, cfg, make_plant(cfg.simulation, clock), in_process=in_process)
    bench = SimulatedBench(wiring.plant, cells=wiring.cells)
    served: list[str] = []
    for name, dev in cfg.devices.items():
        kind = registry.kind_of(dev)
        if not dev.simulated or kind.build_simulator is None:
            continue
        if in_process_only and not kind.in_process_only:
            continue
        bench.devices[name] = kind.build_simulator(name, dev, wiring)
        if not kind.in_process_only:
            served.append(name)
    bench.served = tuple(served)
    return bench if bench.devices else None
