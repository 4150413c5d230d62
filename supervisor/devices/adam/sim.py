"""A Modbus TCP server laid out like an ADAM-5000/TCP with I/O modules in its slots.

Real pymodbus server (``ModbusTcpServer`` with a ``SimDevice``), so the driver is tested over
real sockets. The register map is :mod:`supervisor.devices.adam.protocol`:

- analog inputs of 5017/5018 slots are served both as holding registers (FC03) and as input
  registers (FC04); every read request samples the callables again (live values);
- relays of 5060/5069 slots are coils: FC05/FC15 call the relay callbacks with the new
  state, FC01 reads back the stored state;
- addresses outside the configured modules answer exception 0x02 (illegal address), as does
  any write to the analog registers.

``stop()`` then ``start()`` models a network outage: relay states are kept. Only bind
127.0.0.1 in tests.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Mapping
from typing import Final

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from supervisor.config.models import SimPoint, SimulationConfig
from supervisor.devices.adam.config import MODULE_KINDS, SLOTS, AdamDevice
from supervisor.devices.adam.protocol import (
    COILS_PER_SLOT,
    DEFAULT_RAW_FORMAT,
    FC_READ_HOLDING_REGISTERS,
    FC_READ_INPUT_REGISTERS,
    RAW_FORMATS,
    REGISTERS_PER_SLOT,
    TC_OPEN_WIRE_RAW,
    value_to_raw,
)
from supervisor.sim.plant import BenchPlant

log = logging.getLogger(__name__)

AnalogSource = Callable[[], float | None]
RelaySink = Callable[[bool], None]

_READ_FUNCTIONS: Final = frozenset({1, 2, 3, 4})
_COIL_FUNCTIONS: Final = frozenset({1, 5, 15})
_REGISTER_FUNCTIONS: Final = frozenset({3, 4, 6, 16, 22, 23})
_N_REGISTERS: Final = REGISTERS_PER_SLOT * len(SLOTS)
_N_COILS: Final = COILS_PER_SLOT * len(SLOTS)


class AdamSimulator:
    """ADAM-5000/TCP on Modbus TCP: ``modules`` maps slot → module kind (``"5017"`` …).

    ``analog[(slot, ch)]`` returns volts (5017) or °C (5018), or ``None`` for an open
    thermocouple; channels without a callable read 0 V (5017) or open wire (5018).
    ``relays[(slot, ch)]`` is called with the new state on every write of that relay.
    ``raw_format`` maps slot → ``"offset"``/``"twos"`` (default offset binary).
    """

    def __init__(
        self,
        modules: dict[int, str],
        analog: dict[tuple[int, int], Callable[[], float | None]] | None = None,
        relays: dict[tuple[int, int], Callable[[bool], None]] | None = None,
        raw_format: dict[int, str] | None = None,
        host: str = "127.0.0.1",
        port: int = 0,
        unit_id: int = 1,
        name: str = "adam",
    ) -> None:
        analog = analog or {}
        relays = relays or {}
        raw_format = raw_format or {}
        for slot, kind in modules.items():
            if isinstance(slot, bool) or slot not in SLOTS:
                raise ValueError(f"ADAM slot must be 0..{SLOTS[-1]}, got {slot!r}")
            if kind not in MODULE_KINDS:
                raise ValueError(f"slot {slot}: unknown ADAM module {kind!r}")
        for slot, fmt in raw_format.items():
            if slot not in modules or MODULE_KINDS[modules[slot]].family == "relay":
                raise ValueError(f"raw_format given for slot {slot}, not an analog module")
            if fmt not in RAW_FORMATS:
                raise ValueError(f"slot {slot}: unknown raw format {fmt!r}")
        for key in analog:
            self._check_point(modules, key, ("analog", "thermocouple"))
        for key in relays:
            self._check_point(modules, key, ("relay",))
        if not 0 <= unit_id <= 255:
            raise ValueError(f"unit_id must be 0..255, got {unit_id!r}")
        self.modules: Mapping[int, str] = dict(modules)
        self.name = name
        self.host = host
        self._port = port
        self.unit_id = unit_id
        self._analog: dict[tuple[int, int], AnalogSource] = dict(analog)
        self._relays: dict[tuple[int, int], RelaySink] = dict(relays)
        self._formats = {
            s: raw_format.get(s, DEFAULT_RAW_FORMAT)
            for s, k in modules.items()
            if MODULE_KINDS[k].family != "relay"
        }
        self._coils: dict[tuple[int, int], bool] = {
            (s, ch): False
            for s, k in modules.items()
            if MODULE_KINDS[k].family == "relay"
            for ch in range(MODULE_KINDS[k].points)
        }
        self._stuck: dict[tuple[int, int], bool] = {}
        self._fail_reads = 0
        self._fail_code = ExcCodes.DEVICE_FAILURE
        self._fail_slot: int | None = None
        self._short_reads = 0
        self._short_slot: int | None = None
        self._truncate_next = False
        self._server: ModbusTcpServer | None = None

    @staticmethod
    def _check_point(
        modules: Mapping[int, str], key: tuple[int, int], families: tuple[str, ...]
    ) -> None:
        slot, ch = key
        kind = modules.get(slot)
        if kind is None or MODULE_KINDS[kind].family not in families:
            raise ValueError(f"no {'/'.join(families)} module in slot {slot} for point {key}")
        if not 0 <= ch < MODULE_KINDS[kind].points:
            raise ValueError(f"slot {slot} ({kind}) has no channel {ch}")

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
        blocks: tuple[list[SimData], list[SimData], list[SimData], list[SimData]] = (
            # Coils of all 8 slots, discrete inputs (none simulated: placeholder, every
            # FC02 is refused), holding and input registers of all 8 slots. The action
            # below refuses addresses outside the configured modules.
            [SimData(0, values=[False] * _N_COILS, datatype=DataType.BITS)],
            [SimData(0, values=[False] * COILS_PER_SLOT, datatype=DataType.BITS)],
            [SimData(0, count=_N_REGISTERS, values=0, datatype=DataType.REGISTERS)],
            [SimData(0, count=_N_REGISTERS, values=0, datatype=DataType.REGISTERS)],
        )
        device = SimDevice(self.unit_id, simdata=blocks, action=self._action)
        server = ModbusTcpServer(device, address=(self.host, self._port), trace_pdu=self._trace)
        await server.serve_forever(background=True)
        sockets = getattr(server.transport, "sockets", None)
        if sockets:
            self._port = int(sockets[0].getsockname()[1])
        self._server = server
        log.info("ADAM simulator listening on %s:%d", self.host, self._port)

    async def stop(self) -> None:
        """Close the listener and every client connection."""
        server, self._server = self._server, None
        if server is None:
            return
        await server.shutdown()  # type: ignore[no-untyped-call]
        # Let the transports deliver their connection_lost callbacks.
        await asyncio.sleep(0)
        log.info("ADAM simulator on port %d stopped", self._port)

    async def __aenter__(self) -> AdamSimulator:
        await self.start()
        return self

    async def __aexit__(self, *_exc: object) -> None:
        await self.stop()

    # --- test hooks ----------------------------------------------------------------
    def fail_next_reads(
        self, n: int, exception_code: int = ExcCodes.DEVICE_FAILURE, slot: int | None = None
    ) -> None:
        """Answer the next ``n`` read requests (FC01–FC04) with a Modbus exception.

        With ``slot``, only reads touching that slot count and fail.
        """
        self._fail_reads = n
        self._fail_code = ExcCodes(exception_code)
        self._fail_slot = slot

    def short_next_reads(self, n: int, slot: int | None = None) -> None:
        """Answer the next ``n`` read requests with one register (or every coil) missing."""
        self._short_reads = n
        self._short_slot = slot

    def relay_state(self, slot: int, ch: int) -> bool:
        """Stored state of a relay (what FC01 reads back)."""
        return self._coils[(slot, ch)]

    def stick_relay(self, slot: int, ch: int, state: bool | None) -> None:
        """Fault: the relay stays in ``state`` whatever is written (``None`` heals it).

        Writes are still acknowledged; the read-back shows the stuck state.
        """
        key = (slot, ch)
        if key not in self._coils:
            raise ValueError(f"no relay at slot {slot} channel {ch}")
        if state is None:
            self._stuck.pop(key, None)
        else:
            self._stuck[key] = state
            self._coils[key] = state

    # --- pymodbus hooks ------------------------------------------------------------
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
        """Called by pymodbus on every access, before it reads or writes ``registers``.

        ``count`` is in registers: for coils, 16-bit words of packed bits.
        """
        if function_code in _COIL_FUNCTIONS:
            if set_values is not None:
                slots = self._coil_write_slots(address, len(set_values))
            else:
                slots = self._coil_read_slots(address, count)
        elif function_code in _REGISTER_FUNCTIONS:
            if set_values is not None:
                return ExcCodes.ILLEGAL_ADDRESS  # analog inputs are read-only
            slots = self._register_slots(address, count)
        else:
            return ExcCodes.ILLEGAL_ADDRESS  # no discrete-input module simulated
        if slots is None:
            return ExcCodes.ILLEGAL_ADDRESS

        if function_code in _READ_FUNCTIONS:
            if self._fail_reads > 0 and (self._fail_slot is None or self._fail_slot in slots):
                self._fail_reads -= 1
                return self._fail_code
            if self._short_reads > 0 and (self._short_slot is None or self._short_slot in slots):
                self._short_reads -= 1
                self._truncate_next = True

        try:
            if function_code in (FC_READ_HOLDING_REGISTERS, FC_READ_INPUT_REGISTERS):
                for reg in range(address, address + count):
                    registers[reg - start_address] = self._sample(*divmod(reg, REGISTERS_PER_SLOT))
            elif function_code in _COIL_FUNCTIONS:
                if set_values is not None:
                    self._apply_coils(address, [bool(v) for v in set_values])
                self._refresh_coils(start_address, address, count, registers)
        except Exception:
            self._truncate_next = False
            log.exception("ADAM simulator: callable failed (FC%02d @%d)", function_code, address)
            return ExcCodes.DEVICE_FAILURE
        return None

    # --- internals -----------------------------------------------------------------
    def _register_slots(self, address: int, count: int) -> set[int] | None:
        slots: set[int] = set()
        for reg in range(address, address + count):
            slot, ch = divmod(reg, REGISTERS_PER_SLOT)
            kind = self.modules.get(slot)
            if kind is None or MODULE_KINDS[kind].family == "relay":
                return None
            if ch >= MODULE_KINDS[kind].points:
                return None
            slots.add(slot)
        return slots

    def _coil_write_slots(self, address: int, n: int) -> set[int] | None:
        slots: set[int] = set()
        for coil in range(address, address + n):
            if divmod(coil, COILS_PER_SLOT) not in self._coils:
                return None
            slots.add(coil // COILS_PER_SLOT)
        return slots

    def _coil_read_slots(self, address: int, words: int) -> set[int] | None:
        # One 16-bit word of coils is one slot; pymodbus does not pass the coil count, so
        # coils past a module's last relay read False rather than being refused.
        first = address // COILS_PER_SLOT
        slots = set(range(first, first + words))
        for slot in slots:
            kind = self.modules.get(slot)
            if kind is None or MODULE_KINDS[kind].family != "relay":
                return None
        return slots

    def _sample(self, slot: int, ch: int) -> int:
        kind = self.modules[slot]
        source = self._analog.get((slot, ch))
        # No source: nothing wired, 0 V on a 5017, an open thermocouple on a 5018.
        value = (None if kind == "5018" else 0.0) if source is None else source()
        if value is None:
            return TC_OPEN_WIRE_RAW
        return value_to_raw(float(value), kind, self._formats[slot])

    def _apply_coils(self, address: int, values: list[bool]) -> None:
        for i, state in enumerate(values):
            key = divmod(address + i, COILS_PER_SLOT)
            state = self._stuck.get(key, state)
            self._coils[key] = state
            sink = self._relays.get(key)
            if sink is not None:
                sink(state)

    def _refresh_coils(
        self, start_address: int, address: int, words: int, registers: list[int]
    ) -> None:
        """Write the stored relay states into pymodbus's packed coil words."""
        first = address // COILS_PER_SLOT
        for slot in range(first, first + words):
            word = 0
            for ch in range(COILS_PER_SLOT):
                if self._coils.get((slot, ch), False):
                    word |= 1 << ch
            registers[slot - start_address] = word


# --- wiring from an I/O map --------------------------------------------------------------
ESTOP_SENSE_HEALTHY_V: Final = 5.0
"""Seed 002 §1.5: the e-stop sense input reads 5 V while the e-stop circuit is closed."""


def _split(point: str) -> tuple[int, int]:
    """``slot3.do0`` → (3, 0)."""
    slot, rest = point.split(".", 1)
    prefix = rest.rstrip("0123456789")
    return int(slot.removeprefix("slot")), int(rest[len(prefix) :])


def plant_simulator(
    name: str, dev: AdamDevice, sc: SimulationConfig, plant: BenchPlant
) -> AdamSimulator:
    """The simulated unit ``name``, its inputs and relays wired to the plant as the I/O map's
    ``simulation:`` section says (LEM sensor, voltage board, e-stop sense, thermocouples,
    battery contactor)."""
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
    if (k := mine(sc.contactor)) is not None:
        relays[k] = plant.set_contactor
    return AdamSimulator(
        {slot: m.kind for slot, m in dev.modules.items()},
        analog,
        relays,
        raw_format={
            slot: m.raw_format
            for slot, m in dev.modules.items()
            if MODULE_KINDS[m.kind].family != "relay"
        },
        host=dev.host,
        port=dev.port,
        unit_id=dev.unit_id,
        name=name,
    )
