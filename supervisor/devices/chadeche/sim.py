"""Simulated Chadèche boards answering SPI transfers, decoded with the driver's own codecs.

``SimChadecheBus`` has the same surface as the real bus (``transfer(board, chip, data)``,
``close()``), so the driver cannot tell them apart. Cells are integrated lazily: on each
transfer (or ``advance()``) a board first steps its cell from its last update to
``clock.now()`` with the current that was flowing, then applies the new command. Fast and
deterministic on a virtual clock.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable, Mapping
from typing import NamedTuple, Protocol, runtime_checkable

from supervisor.core.clock import Clock
from supervisor.core.errors import DeviceIOError, ProtocolError
from supervisor.devices.chadeche.protocol import (
    ADC_READ,
    DAC_LSB_MA,
    Chip,
    DacChannel,
    DacWord,
    adc_code_span_v,
    dac_word_from_bytes,
    decode_dac_word,
    decode_latch,
    encode_adc_reply,
    voltage_to_adc_code,
)

log = logging.getLogger(__name__)
_DAC, _ADC = Chip.DAC, Chip.ADC
"""The chips as module constants: an enum member is a class attribute lookup per use."""

NO_BOARD_BYTE = 0xFF
"""What MISO reads when no board answers (assumed pulled up / floating high)."""


class Cell(Protocol):
    """What a board needs from a battery model (supervisor/sim/battery.py).

    A model may also offer ``step_then_voltage_v(current_a, dt_s) -> float``: ``step``
    then ``voltage_at(current_a)`` in one call (``NiMHCell``); an ADC read after time
    passed then asks it that instead (``SimChadecheBus.transfer``).
    """

    def step(self, current_a: float, dt_s: float) -> None:
        """Advance by ``dt_s`` at ``current_a`` (positive current CHARGES)."""
        ...

    def voltage_at(self, current_a: float) -> float: ...

    @property
    def terminal_voltage_v(self) -> float: ...


@runtime_checkable
class ThermalCell(Cell, Protocol):
    """A cell model with a thermal state and fault reporting (supervisor/sim/battery.py):
    what the simulation-only temperature point reads."""

    @property
    def temperature_c(self) -> float: ...

    @property
    def fault(self) -> str | None: ...


class SimTransfer(NamedTuple):
    """One transfer seen by the simulated bus, for tests and diagnostics (immutable; a
    named tuple, not a frozen dataclass: one is made per transfer, and a frozen dataclass
    takes about five times as long to build — issue 13)."""

    t: float
    board: int
    chip: Chip
    data: bytes
    reply: bytes


class SimBoard:
    """One board: DAC A/B, the relay latch and the cell it is wired to.

    ``true_current_*`` make the current source differ from nominal (what calibration
    §III.F.1 corrects); ``adc_*`` do the same for the voltage chain (§III.F.2).
    """

    def __init__(
        self,
        cell: Cell,
        true_current_gain: float = 1.0,
        true_current_offset_ma: float = 0.0,
        adc_gain: float = 1.0,
        adc_offset_v: float = 0.0,
    ) -> None:
        self.cell = cell
        # The current source's inputs (properties: the current it drives is computed again
        # whenever one of them is set, and read as a plain attribute by every transfer).
        self._true_current_gain = true_current_gain
        self._true_current_offset_ma = true_current_offset_ma
        self.adc_gain = adc_gain
        self.adc_offset_v = adc_offset_v
        # Power-up: both channels shut down (MCP4922 POR), latch state unknown -> discharge.
        self._dac_a = DacWord(DacChannel.A, 0, active=False)
        self.dac_b = DacWord(DacChannel.B, 0, active=False)
        self._charging = False
        self._current = self._current_now()
        self.transfers = 0
        self.hot_switches = 0
        """Relay flips made while current was flowing (the driver must keep this at 0)."""
        self._last_t: float | None = None
        # Checked once: isinstance() on a runtime protocol is too slow for every transfer.
        self._thermal: ThermalCell | None = cell if isinstance(cell, ThermalCell) else None
        self._step_then_voltage_v: Callable[[float, float], float] | None = getattr(
            cell, "step_then_voltage_v", None
        )
        """The cell's step and voltage in one call, if it offers that (see ``Cell``)."""
        self._fault_watch: ThermalCell | None = self._thermal
        """The thermal cell while its fault is not reported yet (logged once, then None)."""
        # The last ADC reply, kept with the code it encodes and the span of ADC input
        # voltages that give that code (``adc_code_span_v``: nothing yet): a cell's
        # voltage moves by one ADC step every few minutes of a slow charge, its code need
        # not be computed again while it stays in the span, nor its reply encoded anew.
        self._adc_code = -1
        self._adc_reply = b""
        self._adc_low_v = math.inf
        self._adc_high_v = -math.inf
        self.label = "Chadèche board"
        """How the log names it (the bus sets the address)."""

    # The current source's inputs: each set computes the current again (a few times per
    # test; the current is read twice per transfer, issue 13).
    @property
    def dac_a(self) -> DacWord:
        return self._dac_a

    @dac_a.setter
    def dac_a(self, word: DacWord) -> None:
        self._dac_a = word
        self._current = self._current_now()

    @property
    def charging(self) -> bool:
        return self._charging

    @charging.setter
    def charging(self, charging: bool) -> None:
        self._charging = charging
        self._current = self._current_now()

    @property
    def true_current_gain(self) -> float:
        return self._true_current_gain

    @true_current_gain.setter
    def true_current_gain(self, gain: float) -> None:
        self._true_current_gain = gain
        self._current = self._current_now()

    @property
    def true_current_offset_ma(self) -> float:
        return self._true_current_offset_ma

    @true_current_offset_ma.setter
    def true_current_offset_ma(self, offset_ma: float) -> None:
        self._true_current_offset_ma = offset_ma
        self._current = self._current_now()

    @property
    def current_a(self) -> float:
        """Current through the cell now, + charging, − discharging."""
        return self._current

    def _current_now(self) -> float:
        word = self._dac_a
        if not word.active or word.code == 0:
            return 0.0
        gain = 1.0 if word.gain_1x else 2.0
        i_ma = (
            word.code * gain * DAC_LSB_MA * self._true_current_gain + self._true_current_offset_ma
        )
        # The current source cannot reverse: below zero it simply turns off.
        i_a = max(i_ma, 0.0) / 1000.0
        return i_a if self._charging else -i_a

    @property
    def led_duty(self) -> float:
        word = self.dac_b
        return word.code / 4095 if word.active else 0.0

    @property
    def temperature_c(self) -> float | None:
        """The cell model's temperature (None: a model without a thermal state). No board
        measures it: this is what the simulation-only ``b{n}.temperature`` point reads
        (devices/chadeche/config.py)."""
        return None if self._thermal is None else self._thermal.temperature_c

    def advance(self, now: float) -> None:
        """Step the cell from the last update to ``now`` at the current that was flowing."""
        last_t = self._last_t
        if last_t is None:
            self._last_t = now
        elif now > last_t:
            self.cell.step(self._current, now - last_t)
            watch = self._fault_watch
            if watch is not None and watch.fault is not None:
                self._log_fault(now, watch.fault)
            self._last_t = now

    def _log_fault(self, now: float, fault: str) -> None:
        # Once: a dry run would otherwise log it every poll for hours.
        log.warning("simulated %s at t=%.0f s: %s", self.label, now, fault)
        self._fault_watch = None

    def adc_code(self) -> int:
        v = self.cell.voltage_at(self._current)
        return voltage_to_adc_code(self.adc_gain * v + self.adc_offset_v)

    def adc_reply(self) -> bytes:
        """``encode_adc_reply(self.adc_code())``, computed again only when the ADC input
        left the span of the last code."""
        v = self.cell.voltage_at(self._current)
        adc_input_v = self.adc_gain * v + self.adc_offset_v
        if not self._adc_low_v <= adc_input_v <= self._adc_high_v:  # also for a NaN
            self._adc_moved(adc_input_v)
        return self._adc_reply

    def _adc_moved(self, adc_input_v: float) -> None:
        """The code, reply and span of an ADC input out of the last code's span (a NaN
        raises as ``voltage_to_adc_code`` does)."""
        code = voltage_to_adc_code(adc_input_v)
        self._adc_reply = encode_adc_reply(code)
        self._adc_code = code
        self._adc_low_v, self._adc_high_v = adc_code_span_v(code)

    def handle(self, chip: Chip, data: bytes) -> bytes:
        """Apply one transfer (after :meth:`advance`) and return what MISO carried."""
        self.transfers += 1
        if chip == _DAC:
            word = decode_dac_word(dac_word_from_bytes(data))
            if word.channel == DacChannel.A:
                self.dac_a = word
            else:
                self.dac_b = word
            return bytes(len(data))  # the MCP4922 has no data output
        if chip == _ADC:
            if len(data) != 2:  # the driver must clock exactly 16 bits
                raise ProtocolError("chadeche-sim", "ADC read must be 2 bytes", data)
            return self.adc_reply()
        charging = decode_latch(data)
        if charging != self._charging and self._current != 0.0:
            self.hot_switches += 1
        self.charging = charging
        return bytes(len(data))


class SimChadecheBus:
    """A simulated SPI bus with up to four boards; same surface as the real ``ChadecheBus``."""

    blocking = False  # fast and deterministic on a virtual clock: called directly

    def __init__(
        self, clock: Clock, boards: Mapping[int, SimBoard], history_len: int = 256
    ) -> None:
        for address in boards:
            if address not in range(4):
                raise ValueError(f"Chadèche board address must be 0..3, got {address!r}")
        self.clock = clock
        self.boards: dict[int, SimBoard] = dict(boards)
        for address, sim in self.boards.items():
            sim.label = f"Chadèche board {address}"
        # The last transfers as plain tuples (a named tuple is built by a Python call:
        # once per transfer was more than the rest of a dry run's ADC read, issue 13).
        self._history: deque[tuple[float, int, Chip, bytes, bytes]] = deque(maxlen=history_len)
        self.closed = False
        self.fault: Exception | None = None
        """Fault injection: while set, every transfer raises it (cable pulled, bus error)."""
        self._lock = threading.Lock()

    def transfer(self, board: int, chip: Chip, data: bytes) -> bytes:
        # The lock taken and given back by hand, as ``with self._lock`` would: without
        # ``with``'s two bound methods and its exit call's arguments (issue 13: a dry run
        # takes it twice a poll; ``with`` measured about 1 900 CPU instructions, this 700).
        self._lock.acquire()
        try:
            if self.closed:
                raise DeviceIOError("chadeche-sim", "bus closed")
            if self.fault is not None:
                raise self.fault
            now = self.clock.now()
            sim = self.boards.get(board)
            if data is ADC_READ and chip is _ADC and sim is not None:
                # The driver's ADC read (every poll, issue 13): ``sim.advance(now)`` and
                # ``sim.handle(chip, data)`` in this one call, the same steps without the
                # other chips' tests. A cell that offers it is stepped and read in one
                # call (``Cell``): the voltage the step leaves is the one read next.
                last_t = sim._last_t
                fused = sim._step_then_voltage_v
                if fused is not None and last_t is not None and now > last_t:
                    v = fused(sim._current, now - last_t)
                    # ``advance``'s fault report, after the step as there.
                    watch = sim._fault_watch
                    if watch is not None and watch.fault is not None:
                        sim._log_fault(now, watch.fault)
                    sim._last_t = now
                else:
                    sim.advance(now)
                    v = sim.cell.voltage_at(sim._current)
                sim.transfers += 1
                # ``sim.adc_reply()`` after the voltage, the same steps without the call.
                adc_input_v = sim.adc_gain * v + sim.adc_offset_v
                if not sim._adc_low_v <= adc_input_v <= sim._adc_high_v:
                    sim._adc_moved(adc_input_v)
                reply = sim._adc_reply
                self._history.append((now, board, chip, data, reply))
                return reply
            sent = data if type(data) is bytes else bytes(data)  # bytes(b) is b itself
            if sim is None:
                reply = bytes([NO_BOARD_BYTE]) * len(data)
            else:
                sim.advance(now)
                reply = sim.handle(chip, sent)
            self._history.append((now, board, chip, sent, reply))
            return reply
        finally:
            self._lock.release()

    @property
    def history(self) -> deque[SimTransfer]:
        """The last transfers in order (bounded: dry runs last hours); a copy."""
        return deque(map(SimTransfer._make, self._history), maxlen=self._history.maxlen)

    def cell_temperature_c(self, board: int) -> float | None:
        """The temperature of board ``board``'s simulated cell now (None: no such board, or
        a cell model without a thermal state). Not an SPI transfer: a Chadèche board has
        no temperature sensor; this is the simulator's thermometer on the cell, read by
        the driver for the simulation-only ``b{n}.temperature`` points."""
        self._lock.acquire()  # ``with self._lock``, as in ``transfer``
        try:
            sim = self.boards.get(board)
            if sim is None:
                return None
            now = self.clock.now()
            if sim._last_t != now:  # else advance(now) would do nothing (None: it starts)
                sim.advance(now)
            thermal = sim._thermal  # ``sim.temperature_c``, without the call
            return None if thermal is None else thermal.temperature_c
        finally:
            self._lock.release()

    def advance(self) -> None:
        """Bring every cell up to ``clock.now()`` without a transfer."""
        with self._lock:
            now = self.clock.now()
            for sim in self.boards.values():
                sim.advance(now)

    def close(self) -> None:
        self.closed = True


__all__ = ["Cell", "SimBoard", "SimChadecheBus", "SimTransfer", "SimulatedBoards", "ThermalCell"]


class SimulatedBoards:
    """The simulated boards of one Chadèche device, as the composition root sees them: an
    SPI bus that only exists in this process (nothing to serve on the network)."""

    def __init__(self, bus: SimChadecheBus) -> None:
        self.bus = bus

    async def start(self) -> None:
        return None

    async def stop(self) -> None:
        self.bus.close()

    def addresses(self) -> list[str]:
        return []
