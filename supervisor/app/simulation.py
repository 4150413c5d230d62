"""The simulated seed-002 bench: one battery (the plant) behind protocol-level simulators.

Built from an I/O map's ``simulation:`` section and the devices marked ``sim: true``:
an ADAM-5000/TCP Modbus server, an EA SCPI server, and a BMS sending its frames through a
socketcand server (or on python-can's virtual bus), all on loopback, all fed by one
``BenchPlant`` so that the physics agree between them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import can

from supervisor.config.models import (
    AdamDevice,
    BenchConfig,
    BmsDevice,
    EaDevice,
    SimCell,
    SimPoint,
    SimulationConfig,
)
from supervisor.core.clock import Clock
from supervisor.devices.adam.sim import AdamSimulator
from supervisor.devices.bms.protocol import BmsValues
from supervisor.devices.bms.sim import BmsSimulator, SocketcandServer
from supervisor.devices.ea.sim import EaSimulator
from supervisor.sim.battery import BatteryModel, make_model
from supervisor.sim.plant import BenchPlant

log = logging.getLogger(__name__)

ESTOP_SENSE_HEALTHY_V = 5.0  # seed 002 §1.5: 5 V while the e-stop circuit is closed
CELL_SPREAD_V = 0.004  # simulated spread between the lowest and highest cell


def _split(point: str) -> tuple[int, str, int]:
    """``slot3.do0`` → (3, "do", 0)."""
    slot, rest = point.split(".", 1)
    prefix = rest.rstrip("0123456789")
    return int(slot.removeprefix("slot")), prefix, int(rest[len(prefix) :])


@dataclass
class SimulatedBench:
    plant: BenchPlant
    adam: dict[str, AdamSimulator] = field(default_factory=dict)
    ea: dict[str, EaSimulator] = field(default_factory=dict)
    bms: dict[str, BmsSimulator] = field(default_factory=dict)
    socketcand: dict[str, SocketcandServer] = field(default_factory=dict)
    virtual_buses: list[can.BusABC] = field(default_factory=list)
    cells_series: int = 1

    async def start(self) -> None:
        for sim in self.adam.values():
            await sim.start()
        for ea in self.ea.values():
            await ea.start()
        for srv in self.socketcand.values():
            await srv.start()
        for bms in self.bms.values():
            await bms.start()

    async def stop(self) -> None:
        for bms in self.bms.values():
            await bms.stop()
        for srv in self.socketcand.values():
            await srv.stop()
        for ea in self.ea.values():
            await ea.stop()
        for sim in self.adam.values():
            await sim.stop()
        for bus in self.virtual_buses:
            bus.shutdown()

    def addresses(self) -> list[str]:
        out = [f"ADAM-5000/TCP {n}: modbus tcp 127.0.0.1:{s.port}" for n, s in self.adam.items()]
        out += [f"EA supply {n}: scpi tcp 127.0.0.1:{s.port}" for n, s in self.ea.items()]
        out += [f"BMS {n}: socketcand 127.0.0.1:{s.port}" for n, s in self.socketcand.items()]
        return out

    def press_estop(self, pressed: bool = True) -> None:
        self.plant.set_estop(pressed)

    def bms_values(self) -> BmsValues:
        p = self.plant
        v = p.pack_voltage_v
        cell = v / self.cells_series
        t = p.pack_temperature_c
        return BmsValues(
            pack_voltage_v=v,
            min_cell_v=cell - CELL_SPREAD_V / 2,
            max_cell_v=cell + CELL_SPREAD_V / 2,
            pack_current_a=p.pack_current_a,
            min_temp_c=t - 0.5,
            max_temp_c=t + 0.5,
            avg_temp_c=t,
        )


def cell_model(cell: SimCell) -> BatteryModel:
    """The battery model an I/O map's ``sim:`` entry describes."""
    params: dict[str, float] = {
        "capacity_ah": cell.capacity_ah,
        "soc": cell.soc,
        "temperature_c": cell.temperature_c,
    }
    if cell.cells_series is not None:
        params["cells_series"] = cell.cells_series
    return make_model(cell.model, **params)


def make_plant(cfg: BenchConfig, clock: Clock) -> BenchPlant:
    sc = cfg.simulation or SimulationConfig()
    return BenchPlant(clock, cell_model(sc.pack), ambient_c=sc.ambient_c)


def build_simulation(cfg: BenchConfig, clock: Clock) -> SimulatedBench | None:
    """Simulators for every device marked ``sim: true`` (None if there are none)."""
    simulated = {n: d for n, d in cfg.devices.items() if getattr(d, "sim", False)}
    if not simulated:
        return None
    sc = cfg.simulation or SimulationConfig()
    plant = make_plant(cfg, clock)
    bench = SimulatedBench(plant, cells_series=sc.pack.cells_series or 1)

    for name, dev in simulated.items():
        if isinstance(dev, AdamDevice):
            bench.adam[name] = _adam(name, dev, sc, plant)
        elif isinstance(dev, EaDevice):
            bench.ea[name] = EaSimulator(
                plant,
                model=dev.sim_model,
                nominal_v=dev.sim_nominal_v,
                nominal_a=dev.sim_nominal_a,
                nominal_w=dev.sim_nominal_w,
                host=dev.host,
                port=dev.port,
            )
        elif isinstance(dev, BmsDevice):
            bus: can.BusABC
            if dev.interface == "virtual":
                bus = can.Bus(interface="virtual", channel=dev.channel)
                bench.virtual_buses.append(bus)
            else:
                srv = SocketcandServer(dev.host, dev.port, channel=dev.channel)
                bench.socketcand[name] = srv
                bus = srv.bus
            bench.bms[name] = BmsSimulator(bus, clock, bench.bms_values)
    return bench


def _adam(name: str, dev: AdamDevice, sc: SimulationConfig, plant: BenchPlant) -> AdamSimulator:
    analog: dict[tuple[int, int], Callable[[], float | None]] = {}
    relays: dict[tuple[int, int], Callable[[bool], None]] = {}

    def mine(sp: SimPoint | None) -> tuple[int, str, int] | None:
        return _split(sp.point) if sp is not None and sp.device == name else None

    if (k := mine(sc.lem_current)) is not None:
        vpa = sc.lem_volts_per_amp
        analog[(k[0], k[2])] = lambda: plant.pack_current_a * vpa
    if (k := mine(sc.voltage_board)) is not None:
        ratio = sc.voltage_board_ratio
        analog[(k[0], k[2])] = lambda: plant.pack_voltage_v * ratio
    if (k := mine(sc.estop_sense)) is not None:
        analog[(k[0], k[2])] = lambda: 0.0 if plant.estop_pressed else ESTOP_SENSE_HEALTHY_V
    for i, tc in enumerate(sc.thermocouples):
        if (k := mine(tc)) is not None:
            # The first thermocouple sits on the pack; the others read the ambient air.
            if i == 0:
                analog[(k[0], k[2])] = lambda: plant.pack_temperature_c
            else:
                analog[(k[0], k[2])] = lambda: sc.ambient_c
    # Thermocouple inputs not wired to the pack read the room, not an open circuit.
    for slot, m in dev.modules.items():
        if m.kind == "5018":
            for ch in range(7):
                analog.setdefault((slot, ch), lambda: sc.ambient_c)
    if (k := mine(sc.contactor)) is not None:
        relays[(k[0], k[2])] = plant.set_contactor
    return AdamSimulator(
        {slot: m.kind for slot, m in dev.modules.items()},
        analog,
        relays,
        raw_format={
            slot: m.raw_format for slot, m in dev.modules.items() if m.kind in ("5017", "5018")
        },
        host=dev.host,
        port=dev.port,
        unit_id=dev.unit_id,
    )
