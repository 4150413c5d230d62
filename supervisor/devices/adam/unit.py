"""A simulated ADAM-5000/TCP unit: its register and coil model, with no I/O of its own.

What a Modbus master can ask of the unit (read coils, read registers, write coils) and what
it answers, laid out as :mod:`supervisor.devices.adam.protocol` says:

- analog inputs of 5017/5018 slots are registers, served both as holding registers (FC03)
  and as input registers (FC04); every read samples the callables again (live values);
- relays of 5060/5069 slots are coils: a write calls the relay callbacks with the new state,
  FC01 reads back the stored state;
- addresses outside the configured modules answer exception 0x02 (illegal address), as does
  any write to the analog registers;
- with a clock, the host (communication) watchdog of
  :mod:`~supervisor.devices.adam.protocol` (its registers are UNVERIFIED placeholders): once
  armed, no request for its timeout sets every relay to its safe value (off, as after a
  power cycle). Checked lazily, like the EA simulator's watchdog: before every request and
  whenever :meth:`AdamUnit.check` is called (a served unit has a checker task calling it on
  a real clock), and acted on the clock at that instant.

Both ends use it: :class:`~supervisor.devices.adam.sim.AdamSimulator` serves it over Modbus
TCP (pymodbus), :class:`~supervisor.devices.adam.transport.InProcessLink` calls it directly
(virtual-clock tests, in-process benches). On its own it is the server-less
:class:`~supervisor.devices.kind.DeviceSimulator`: ``start()`` plugs it in, ``stop()``
unplugs it (a network outage: relay states are kept). Nothing here sleeps or listens.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from typing import Final

from supervisor.core.clock import Clock
from supervisor.devices.adam.catalog import MODULE_KINDS, SLOTS
from supervisor.devices.adam.protocol import (
    COILS_PER_SLOT,
    DEFAULT_RAW_FORMAT,
    HOST_WATCHDOG_MAX_COUNTS,
    HOST_WATCHDOG_NEEDS_REFRESH,
    HOST_WATCHDOG_REFRESH_REGISTER,
    HOST_WATCHDOG_REFRESH_VALUE,
    HOST_WATCHDOG_REGISTERS,
    HOST_WATCHDOG_SAFE_VALUES_REGISTER,
    HOST_WATCHDOG_TIMEOUT_REGISTER,
    RAW_FORMATS,
    TC_OPEN_WIRE_RAW,
    coil_slot_channel,
    host_watchdog_seconds,
    register_slot_channel,
    value_to_raw,
)
from supervisor.fieldbus.modbus import (
    EXC_DEVICE_FAILURE,
    EXC_ILLEGAL_ADDRESS,
    EXC_ILLEGAL_FUNCTION,
    EXC_ILLEGAL_VALUE,
    EXCEPTION_MEANINGS,
    FC_READ_HOLDING_REGISTERS,
    FC_READ_INPUT_REGISTERS,
    FC_WRITE_MULTIPLE_COILS,
    FC_WRITE_SINGLE_COIL,
    ModbusExceptionAnswer,
)

log = logging.getLogger(__name__)

AnalogSource = Callable[[], float | None]
RelaySink = Callable[[bool], None]

_REGISTER_READS: Final = frozenset({FC_READ_HOLDING_REGISTERS, FC_READ_INPUT_REGISTERS})


class AdamUnit:
    """ADAM-5000/TCP ``name`` with ``modules`` (slot → module kind, ``"5017"`` …).

    ``analog[(slot, ch)]`` returns volts (5017) or °C (5018), or ``None`` for an open
    thermocouple; channels without a callable read 0 V (5017) or open wire (5018).
    ``relays[(slot, ch)]`` is called with the new state on every write of that relay.
    ``raw_format`` maps slot → ``"offset"``/``"twos"`` (default offset binary).
    ``clock``: the unit's own time (the plant's); without one it has no host watchdog (its
    registers answer illegal address). ``watchdog_needs_refresh``: only "host OK" writes
    keep the host watchdog alive, not every request (see
    :data:`~supervisor.devices.adam.protocol.HOST_WATCHDOG_NEEDS_REFRESH`).
    """

    def __init__(
        self,
        modules: Mapping[int, str],
        analog: Mapping[tuple[int, int], AnalogSource] | None = None,
        relays: Mapping[tuple[int, int], RelaySink] | None = None,
        raw_format: Mapping[int, str] | None = None,
        name: str = "adam",
        *,
        clock: Clock | None = None,
        watchdog_needs_refresh: bool = HOST_WATCHDOG_NEEDS_REFRESH,
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
        self.modules: Mapping[int, str] = dict(modules)
        self.name = name
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
        self._fail_code = EXC_DEVICE_FAILURE
        self._fail_slot: int | None = None
        self._short_reads = 0
        self._short_slot: int | None = None
        self._muted = False
        self._running = False
        self._outages = 0
        self.clock = clock
        self._wd_needs_refresh = watchdog_needs_refresh
        self._wd_counts = 0  # 0: disarmed
        self._wd_safe = {s: 0 for s, k in modules.items() if MODULE_KINDS[k].family == "relay"}
        self._wd_last_t: float | None = None  # last host request; None: timer stopped
        self.host_watchdog_trips = 0

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

    # --- DeviceSimulator: plugged in or not ---------------------------------------------
    @property
    def running(self) -> bool:
        """Plugged in: a master can connect (and, unless muted, gets answers)."""
        return self._running

    @property
    def outages(self) -> int:
        """How many times it was unplugged: a link opened before the last outage is dead
        even once the unit is back, as a TCP connection would be."""
        return self._outages

    async def start(self) -> None:
        """Plug the unit in (again: relay states are kept across an outage)."""
        self._running = True

    async def stop(self) -> None:
        """Unplug it: connects are refused and every open link drops."""
        if self._running:
            self._outages += 1
        self._running = False

    def addresses(self) -> list[str]:
        """Nothing listens: the driver calls this unit in process."""
        return []

    # --- fault injection --------------------------------------------------------------
    def fail_next_reads(
        self, n: int, exception_code: int = EXC_DEVICE_FAILURE, slot: int | None = None
    ) -> None:
        """Answer the next ``n`` read requests (FC01–FC04) with a Modbus exception.

        With ``slot``, only reads touching that slot count and fail.
        """
        if exception_code not in EXCEPTION_MEANINGS:
            raise ValueError(f"0x{exception_code:02X} is not a Modbus exception code")
        self._fail_reads = n
        self._fail_code = exception_code
        self._fail_slot = slot

    def short_next_reads(self, n: int, slot: int | None = None) -> None:
        """Answer the next ``n`` read requests with one register (or every coil) missing."""
        self._short_reads = n
        self._short_slot = slot

    def mute(self, silent: bool = True) -> None:
        """Fault: the unit accepts connections but answers no request (``False`` heals it).

        A muted unit does not act on what it is sent either: the in-process link and the
        TCP server do not hand it the request, so a relay write is lost.
        """
        self._muted = silent

    @property
    def muted(self) -> bool:
        return self._muted

    # --- host watchdog -------------------------------------------------------------------
    @property
    def host_watchdog_s(self) -> float | None:
        """The armed host watchdog timeout; None while disarmed."""
        return host_watchdog_seconds(self._wd_counts) if self._wd_counts else None

    def check(self) -> None:
        """What the unit did on its own since the last request, at ``clock.now()``: once
        armed, no request for longer than its timeout (at exactly the timeout it still
        holds) sets every relay to its safe value."""
        timeout_s = self.host_watchdog_s
        if timeout_s is None or self._wd_last_t is None or self.clock is None:
            return
        silent_s = self.clock.now() - self._wd_last_t
        if silent_s <= timeout_s:
            return
        self._wd_last_t = None  # tripped: the timer restarts with the next request
        self.host_watchdog_trips += 1
        log.warning(
            "ADAM simulator %s: host watchdog: no request for %.3f s (timeout %g s), every"
            " relay to its safe value",
            self.name,
            silent_s,
            timeout_s,
        )
        for key in self._coils:
            slot, ch = key
            self._set_relay(key, bool(self._wd_safe[slot] >> ch & 1))

    def _host_request(self, refresh: bool = False) -> None:
        """A request reached the unit: first what it did meanwhile, then the timer restarts
        (with ``watchdog_needs_refresh``, only a "host OK" write restarts it)."""
        if self.clock is None:
            return
        self.check()
        if refresh or not self._wd_needs_refresh:
            self._wd_last_t = self.clock.now()

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

    # --- requests (what a Modbus master asks) --------------------------------------------
    # Called by the links and the server once a request has reached the unit: being
    # plugged in and answering (mute) are theirs to check.
    def read_registers(self, function_code: int, address: int, count: int) -> list[int]:
        """FC03/FC04: ``count`` raw 16-bit values from ``address`` (one fewer when a short
        answer is armed). Raises :class:`ModbusExceptionAnswer`."""
        self._host_request()
        if function_code not in _REGISTER_READS:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_FUNCTION)
        if count < 1:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_VALUE)
        if self._in_watchdog_block(address, count):
            if function_code != FC_READ_HOLDING_REGISTERS:
                raise ModbusExceptionAnswer(EXC_ILLEGAL_ADDRESS)  # holding registers only
            return [self._watchdog_register(reg) for reg in range(address, address + count)]
        slots = self._register_slots(address, count)
        short = self._read_faults(slots)
        try:
            values = [
                self._sample(*register_slot_channel(reg)) for reg in range(address, address + count)
            ]
        except Exception as exc:
            log.exception("ADAM simulator: callable failed (FC%02d @%d)", function_code, address)
            raise ModbusExceptionAnswer(EXC_DEVICE_FAILURE) from exc
        return values[:-1] if short else values

    def read_coils(self, address: int, count: int) -> list[bool]:
        """FC01: ``count`` relay states from ``address`` (none when a short answer is armed).

        Coils past a module's last relay (inside its 16-coil slot) read False.
        Raises :class:`ModbusExceptionAnswer`.
        """
        self._host_request()
        slots = self._coil_read_slots(address, count)
        short = self._read_faults(slots)
        states = [
            self._coils.get(coil_slot_channel(coil), False)
            for coil in range(address, address + count)
        ]
        return [] if short else states

    def write_coils(self, address: int, values: Sequence[bool]) -> None:
        """FC05 (one value) or FC15: set relays, calling their callbacks; a stuck relay
        keeps its state. Raises :class:`ModbusExceptionAnswer`."""
        self._host_request()
        if not values:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_VALUE)
        for coil in range(address, address + len(values)):
            if coil_slot_channel(coil) not in self._coils:
                raise ModbusExceptionAnswer(EXC_ILLEGAL_ADDRESS)
        try:
            for i, value in enumerate(values):
                self._set_relay(coil_slot_channel(address + i), bool(value))
        except Exception as exc:
            fc = FC_WRITE_SINGLE_COIL if len(values) == 1 else FC_WRITE_MULTIPLE_COILS
            log.exception("ADAM simulator: callable failed (FC%02d @%d)", fc, address)
            raise ModbusExceptionAnswer(EXC_DEVICE_FAILURE) from exc

    def write_registers(self, address: int, values: Sequence[int]) -> None:
        """FC06/FC16: the host watchdog's registers (with a clock); anything else is
        refused, analog inputs are read-only."""
        refresh = list(values) == [HOST_WATCHDOG_REFRESH_VALUE] and (
            address == HOST_WATCHDOG_REFRESH_REGISTER
        )
        self._host_request(refresh=refresh)
        if not values:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_VALUE)
        if not self._in_watchdog_block(address, len(values)):
            raise ModbusExceptionAnswer(EXC_ILLEGAL_ADDRESS)
        for reg, value in zip(range(address, address + len(values)), values, strict=True):
            self._set_watchdog_register(reg, int(value))

    # --- internals -----------------------------------------------------------------
    def _set_relay(self, key: tuple[int, int], value: bool) -> None:
        """Drive one relay (a stuck one keeps its state) and tell its sink."""
        state = self._stuck.get(key, value)
        self._coils[key] = state
        sink = self._relays.get(key)
        if sink is not None:
            sink(state)

    def _in_watchdog_block(self, address: int, count: int) -> bool:
        if self.clock is None or address not in HOST_WATCHDOG_REGISTERS:
            return False
        if address + count - 1 not in HOST_WATCHDOG_REGISTERS:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_ADDRESS)
        return True

    def _safe_value_slot(self, reg: int) -> int | None:
        slot = reg - HOST_WATCHDOG_SAFE_VALUES_REGISTER
        return slot if slot in self._wd_safe else None

    def _watchdog_register(self, reg: int) -> int:
        if reg == HOST_WATCHDOG_TIMEOUT_REGISTER:
            return self._wd_counts
        if reg == HOST_WATCHDOG_REFRESH_REGISTER:
            return 0
        slot = self._safe_value_slot(reg)
        if slot is None:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_ADDRESS)
        return self._wd_safe[slot]

    def _set_watchdog_register(self, reg: int, value: int) -> None:
        if not 0 <= value <= HOST_WATCHDOG_MAX_COUNTS:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_VALUE)
        if reg == HOST_WATCHDOG_TIMEOUT_REGISTER:
            self._wd_counts = value
            assert self.clock is not None  # no watchdog block without a clock
            self._wd_last_t = self.clock.now() if value else None
            if value:
                log.info(
                    "ADAM simulator %s: host watchdog armed, %g s",
                    self.name,
                    host_watchdog_seconds(value),
                )
            return
        if reg == HOST_WATCHDOG_REFRESH_REGISTER:
            if value != HOST_WATCHDOG_REFRESH_VALUE:
                raise ModbusExceptionAnswer(EXC_ILLEGAL_VALUE)
            return
        slot = self._safe_value_slot(reg)
        if slot is None:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_ADDRESS)
        if value >> MODULE_KINDS[self.modules[slot]].points:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_VALUE)  # a relay the module lacks
        self._wd_safe[slot] = value

    def _read_faults(self, slots: set[int]) -> bool:
        """Apply the armed read faults to a read touching ``slots``: raise the armed
        exception answer, or return True if this answer must be short."""
        if self._fail_reads > 0 and (self._fail_slot is None or self._fail_slot in slots):
            self._fail_reads -= 1
            raise ModbusExceptionAnswer(self._fail_code)
        if self._short_reads > 0 and (self._short_slot is None or self._short_slot in slots):
            self._short_reads -= 1
            return True
        return False

    def _register_slots(self, address: int, count: int) -> set[int]:
        slots: set[int] = set()
        for reg in range(address, address + count):
            slot, ch = register_slot_channel(reg)
            kind = self.modules.get(slot)
            if kind is None or MODULE_KINDS[kind].family == "relay":
                raise ModbusExceptionAnswer(EXC_ILLEGAL_ADDRESS)
            if ch >= MODULE_KINDS[kind].points:
                raise ModbusExceptionAnswer(EXC_ILLEGAL_ADDRESS)
            slots.add(slot)
        return slots

    def _coil_read_slots(self, address: int, count: int) -> set[int]:
        if count < 1:
            raise ModbusExceptionAnswer(EXC_ILLEGAL_VALUE)
        slots = {coil // COILS_PER_SLOT for coil in range(address, address + count)}
        for slot in slots:
            kind = self.modules.get(slot)
            if kind is None or MODULE_KINDS[kind].family != "relay":
                raise ModbusExceptionAnswer(EXC_ILLEGAL_ADDRESS)
        return slots

    def _sample(self, slot: int, ch: int) -> int:
        kind = self.modules[slot]
        source = self._analog.get((slot, ch))
        # No source: nothing wired, 0 V on a 5017, an open thermocouple on a 5018.
        value = (None if kind == "5018" else 0.0) if source is None else source()
        if value is None:
            return TC_OPEN_WIRE_RAW
        return value_to_raw(float(value), kind, self._formats[slot])


__all__ = ["AdamUnit", "AnalogSource", "RelaySink"]
