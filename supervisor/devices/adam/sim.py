"""The simulated ADAM-5000/TCP served over Modbus TCP, and its wiring to the bench plant.

:class:`AdamSimulator` is a real pymodbus server (``ModbusTcpServer`` with a ``SimDevice``
action hook) around an :class:`~supervisor.devices.adam.unit.AdamUnit`, the register/coil
model, so the pymodbus link and foreign Modbus clients are tested over real sockets: every
request is answered by the unit (its values, its exception answers, its faults); pymodbus
does the framing, the bit packing of coils and the word order. The in-process link calls
the same unit directly.

``stop()`` then ``start()`` models a network outage: same port again, relay states kept
(unless the unit's host watchdog, once armed, switched them off meanwhile: it is checked
by a task every :data:`CHECK_PERIOD_S` while served, on the unit's clock, which must then
be a real clock; and lazily before every request). Only bind 127.0.0.1 in tests.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Final

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from supervisor.config.models import SimPoint, SimulationConfig
from supervisor.devices.adam.catalog import MODULE_KINDS, SLOTS
from supervisor.devices.adam.config import AdamDevice
from supervisor.devices.adam.protocol import (
    COILS_PER_SLOT,
    HOST_WATCHDOG_REGISTERS,
    REGISTERS_PER_SLOT,
)
from supervisor.devices.adam.unit import AdamUnit
from supervisor.fieldbus.modbus import (
    FC_READ_COILS,
    FC_READ_HOLDING_REGISTERS,
    FC_READ_INPUT_REGISTERS,
    FC_WRITE_MULTIPLE_COILS,
    FC_WRITE_MULTIPLE_REGISTERS,
    FC_WRITE_SINGLE_COIL,
    FC_WRITE_SINGLE_REGISTER,
    ModbusExceptionAnswer,
    quiet_pymodbus,
)
from supervisor.sim.plant import BenchPlant

log = logging.getLogger(__name__)

_COIL_FUNCTIONS: Final = frozenset({FC_READ_COILS, FC_WRITE_SINGLE_COIL, FC_WRITE_MULTIPLE_COILS})
_REGISTER_FUNCTIONS: Final = frozenset(
    {
        FC_READ_HOLDING_REGISTERS,
        FC_READ_INPUT_REGISTERS,
        FC_WRITE_SINGLE_REGISTER,
        FC_WRITE_MULTIPLE_REGISTERS,
        22,  # mask write register
        23,  # read/write multiple registers
    }
)
_REGISTER_WRITES: Final = frozenset({FC_WRITE_SINGLE_REGISTER, FC_WRITE_MULTIPLE_REGISTERS})
_N_REGISTERS: Final = REGISTERS_PER_SLOT * len(SLOTS)
_N_COILS: Final = COILS_PER_SLOT * len(SLOTS)

CHECK_PERIOD_S: Final = 0.02
"""How often a served unit enforces its host watchdog between requests (as the EA's)."""


class AdamSimulator:
    """``unit`` served on Modbus TCP at ``host:port`` as device ``unit_id``.

    Port 0 lets the OS choose (see :attr:`port` once started); the same port is taken
    again after :meth:`stop`. Starting the server plugs the unit in, stopping it unplugs
    it. A muted or unplugged unit gets the request but sends no answer.
    """

    def __init__(
        self, unit: AdamUnit, host: str = "127.0.0.1", port: int = 0, unit_id: int = 1
    ) -> None:
        if not 0 <= unit_id <= 255:
            raise ValueError(f"unit_id must be 0..255, got {unit_id!r}")
        self.unit = unit
        self.host = host
        self._port = port
        self.unit_id = unit_id
        self._truncate_next = False
        self._server: ModbusTcpServer | None = None
        self._checker: asyncio.Task[None] | None = None

    @property
    def name(self) -> str:
        return self.unit.name

    # --- lifecycle -----------------------------------------------------------------
    @property
    def port(self) -> int:
        """The bound port (the one the OS chose when 0 was asked, once started)."""
        return self._port

    @property
    def running(self) -> bool:
        return self._server is not None

    def addresses(self) -> list[str]:
        return [f"ADAM-5000/TCP {self.name}: modbus tcp {self.host}:{self._port}"]

    async def start(self) -> None:
        """Listen on ``host:port``; again on the same port after :meth:`stop`."""
        if self._server is not None:
            raise RuntimeError("ADAM simulator already running")
        quiet_pymodbus()
        blocks: tuple[list[SimData], list[SimData], list[SimData], list[SimData]] = (
            # Coils of all 8 slots, discrete inputs (none simulated: placeholder, every
            # FC02 is refused), holding and input registers of all 8 slots. The unit
            # refuses addresses outside the configured modules.
            [SimData(0, values=[False] * _N_COILS, datatype=DataType.BITS)],
            [SimData(0, values=[False] * COILS_PER_SLOT, datatype=DataType.BITS)],
            # The host watchdog's registers are holding registers after the analog block.
            [
                SimData(0, count=_N_REGISTERS, values=0, datatype=DataType.REGISTERS),
                SimData(
                    HOST_WATCHDOG_REGISTERS[0],
                    count=len(HOST_WATCHDOG_REGISTERS),
                    values=0,
                    datatype=DataType.REGISTERS,
                ),
            ],
            [SimData(0, count=_N_REGISTERS, values=0, datatype=DataType.REGISTERS)],
        )
        device = SimDevice(self.unit_id, simdata=blocks, action=self._action)
        server = ModbusTcpServer(
            device,
            address=(self.host, self._port),
            trace_pdu=self._trace,
            trace_packet=self._trace_packet,
        )
        await server.serve_forever(background=True)
        sockets = getattr(server.transport, "sockets", None)
        if sockets:
            self._port = int(sockets[0].getsockname()[1])
        self._server = server
        await self.unit.start()
        if self.unit.clock is not None and not self.unit.clock.virtual:
            name = f"adam-sim-{self._port}-check"
            self._checker = asyncio.create_task(self._check_loop(), name=name)
        log.info("ADAM simulator listening on %s:%d", self.host, self._port)

    async def stop(self) -> None:
        """Close the listener and every client connection."""
        server, self._server = self._server, None
        if server is None:
            return
        checker, self._checker = self._checker, None
        if checker is not None:
            checker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await checker
        await self.unit.stop()
        await server.shutdown()  # type: ignore[no-untyped-call]
        # Let the transports deliver their connection_lost callbacks.
        await asyncio.sleep(0)
        log.info("ADAM simulator on port %d stopped", self._port)

    async def __aenter__(self) -> AdamSimulator:
        await self.start()
        return self

    async def __aexit__(self, *_exc: object) -> None:
        await self.stop()

    async def _check_loop(self) -> None:
        clock = self.unit.clock
        assert clock is not None
        while True:
            self.unit.check()
            await clock.sleep_until(clock.now() + CHECK_PERIOD_S)

    # --- pymodbus hooks ------------------------------------------------------------
    def _silent(self) -> bool:
        return self.unit.muted or not self.unit.running

    def _trace_packet(self, sending: bool, packet: bytes) -> bytes:
        # A silent unit sends nothing: the client waits for its timeout.
        return b"" if sending and self._silent() else packet

    def _trace(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        if sending and self._truncate_next:
            self._truncate_next = False
            if pdu.registers:
                pdu.registers = list(pdu.registers)[:-1]
            elif pdu.bits:
                pdu.bits = []
        return pdu

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """Called by pymodbus on every access, before it reads or writes ``registers``:
        the unit answers, pymodbus packs the answer.

        ``count`` is in registers: for coils, 16-bit words of packed bits (pymodbus does
        not pass the coil count, so whole slots are read).
        """
        if self._silent():
            return ExcCodes.DEVICE_FAILURE  # not acted on; the answer is dropped
        try:
            if function_code in _REGISTER_FUNCTIONS:
                if set_values is not None:
                    # Accepted: pymodbus stores the values and echoes the request.
                    self.unit.write_registers(address, [int(v) for v in set_values])
                    return None
                if function_code in _REGISTER_WRITES:
                    return None  # pymodbus reading back what it stored, for the echo
                values = self.unit.read_registers(function_code, address, count)
                registers[address - start_address : address - start_address + len(values)] = values
                self._truncate_next = len(values) < count
            elif function_code in _COIL_FUNCTIONS:
                if set_values is not None:
                    # The echo of a write carries no coil data: nothing to pack.
                    self.unit.write_coils(address, [bool(v) for v in set_values])
                else:
                    self._pack_coils(start_address, address, count, registers)
            else:
                return ExcCodes.ILLEGAL_ADDRESS  # no discrete-input module simulated
        except ModbusExceptionAnswer as answer:
            self._truncate_next = False
            return ExcCodes(answer.code)
        return None

    def _pack_coils(
        self, start_address: int, address: int, words: int, registers: list[int]
    ) -> None:
        """Read whole slots of relay states from the unit and pack them into pymodbus's
        coil words (bit 0 = channel 0: pymodbus unpacks bit 0 first)."""
        first = address // COILS_PER_SLOT
        states = self.unit.read_coils(first * COILS_PER_SLOT, words * COILS_PER_SLOT)
        self._truncate_next = len(states) < words * COILS_PER_SLOT
        for i in range(words):
            word = 0
            for ch, on in enumerate(states[i * COILS_PER_SLOT : (i + 1) * COILS_PER_SLOT]):
                if on:
                    word |= 1 << ch
            registers[first + i - start_address] = word


# --- wiring from an I/O map --------------------------------------------------------------
ESTOP_SENSE_HEALTHY_V: Final = 5.0
"""Seed 002 §1.5: the e-stop sense input reads 5 V while the e-stop circuit is closed."""
CONTACTOR_AUX_CLOSED_V: Final = 5.0
"""The contactor's auxiliary contact, wired like the e-stop sense: 5 V while the contactor
is really closed, 0 V when open (or unpowered: fail-safe)."""


def _split(point: str) -> tuple[int, int]:
    """``slot3.do0`` → (3, 0)."""
    slot, rest = point.split(".", 1)
    prefix = rest.rstrip("0123456789")
    return int(slot.removeprefix("slot")), int(rest[len(prefix) :])


def plant_simulator(
    name: str, dev: AdamDevice, sc: SimulationConfig, plant: BenchPlant
) -> AdamUnit:
    """The simulated unit ``name``, its inputs and relays wired to the plant as the I/O map's
    ``simulation:`` section says (LEM sensor, voltage board, e-stop sense, thermocouples,
    battery contactor coil, its auxiliary contact, the watchdog relay's heartbeat), on the
    plant's clock (its host watchdog runs on it).

    The unit itself is the server-less simulator (an in-process link calls it); serve it
    with :class:`AdamSimulator` for a driver or a tool on the network."""
    analog: dict[tuple[int, int], Callable[[], float | None]] = {}
    relays: dict[tuple[int, int], Callable[[bool], None]] = {}

    def mine(sp: SimPoint | None) -> tuple[int, int] | None:
        return _split(sp.point) if sp is not None and sp.device == name else None

    if (k := mine(sc.lem_current)) is not None:
        vpa = sc.lem_volts_per_amp
        analog[k] = lambda: plant.pack_current_a * vpa
    if (k := mine(sc.voltage_board)) is not None:
        ratio = sc.voltage_board_ratio
        analog[k] = lambda: plant.pack_voltage_v * ratio
    if (k := mine(sc.estop_sense)) is not None:
        analog[k] = lambda: 0.0 if plant.estop_pressed else ESTOP_SENSE_HEALTHY_V
    for i, tc in enumerate(sc.thermocouples):
        if (k := mine(tc)) is not None:
            # The first thermocouple sits on the pack; the others read the ambient air.
            if i == 0:
                analog[k] = lambda: plant.pack_temperature_c
            else:
                analog[k] = lambda: sc.ambient_c
    # Thermocouple inputs not wired to the pack read the room, not an open circuit.
    for slot, m in dev.modules.items():
        if MODULE_KINDS[m.kind].family == "thermocouple":
            for ch in range(MODULE_KINDS[m.kind].points):
                analog.setdefault((slot, ch), lambda: sc.ambient_c)
    if (k := mine(sc.contactor_feedback)) is not None:
        analog[k] = lambda: CONTACTOR_AUX_CLOSED_V if plant.contactor_closed else 0.0
    if (k := mine(sc.contactor)) is not None:
        relays[k] = plant.set_contactor
    if (k := mine(sc.watchdog_relay)) is not None:
        relays[k] = plant.set_heartbeat
    return AdamUnit(
        {slot: m.kind for slot, m in dev.modules.items()},
        analog,
        relays,
        raw_format={
            slot: m.raw_format
            for slot, m in dev.modules.items()
            if MODULE_KINDS[m.kind].family != "relay"
        },
        name=name,
        clock=plant.clock,
    )
