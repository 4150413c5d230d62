"""Chadèche board SPI words: pure codecs shared by the driver and the simulator.

One Chadèche board (seed 000 §II.C) carries an MCP4922 dual 12-bit DAC (channel A sets the
constant current, channel B the LED blink duty), an MCP3201 12-bit ADC (cell voltage) and a
74HC74 D latch driving the charge/discharge relay. Up to four boards share one SPI bus; the
Raspberry Pi selects a board with two address lines and a chip with three GPIO chip selects.

No I/O here. The board rating and addresses come from the catalog
(:mod:`supervisor.devices.chadeche.config`); every other device fact the seed leaves open is
one named constant marked UNVERIFIED.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum
from types import MappingProxyType
from typing import Final, NamedTuple

from supervisor.core.errors import ProtocolError
from supervisor.devices.chadeche.config import BOARD_ADDRESSES

DEVICE: Final = "chadeche"

# --- analog scale (seed §II.C.4 and §II.C.5) -------------------------------------------
VREF_V: Final = 4.096
"""MAX6241 reference shared by the DAC and the ADC."""
DAC_MAX_CODE: Final = 4095
ADC_MAX_CODE: Final = 4095
DAC_LSB_V: Final = 0.001
"""4.096 V / 4096 codes: 1 mV per DAC step (gain 1)."""
ADC_LSB_V: Final = 0.001
"""4.096 V / 4096 codes: 1 mV per ADC step."""
SENSE_RESISTOR_OHM: Final = 10.0
"""Foot resistor RL of the current source: I = V_dac / RL (seed §II.C.3, Figure 6)."""
DAC_LSB_MA: Final = DAC_LSB_V / SENSE_RESISTOR_OHM * 1000.0
"""0.1 mA per DAC step."""
MAX_CURRENT_CODE: Final = 4000
"""DAC A code for 400 mA: the hardware last line, whatever the calibration says."""

# --- board and chip selection (seed §II.C.2, §II.F) --------------------------------------
A0_GPIO: Final = 17
A1_GPIO: Final = 27


class Chip(IntEnum):
    """Chip on a board, by chip-select line (CS0, CS1, CS2)."""

    DAC = 0
    ADC = 1
    LATCH = 2

    @property
    def gpio(self) -> int:
        """BCM number of the Raspberry Pi GPIO that drives this chip select."""
        return CHIP_SELECT_GPIO[self]


CHIP_SELECT_GPIO: Final[Mapping[Chip, int]] = MappingProxyType(
    # Seed §II.C.2: "CS0, CS1 et CS2 reliés respectivement aux signaux GPIO3, GPIO6 et
    # GPIO5". UNVERIFIED: a later sentence of the same section says "GPIO3 (CS0) et GPIO5
    # (CS1)"; we follow the explicit list (also reference/devices.md). Check on the PCB.
    {Chip.DAC: 3, Chip.ADC: 6, Chip.LATCH: 5}
)

CHIP_SELECT_ACTIVE_HIGH: Final = True
"""UNVERIFIED (inferred): each CSx meets the active-high board-select (output of U6F)
in a NAND (U5B/C/D) whose output is the chip's active-low /CS, so the Pi asserts a chip
select by driving its GPIO high (seed §II.C.2)."""


def address_lines(board: int) -> tuple[bool, bool]:
    """Levels of (A0, A1) that select ``board`` (A0 = bit 0, A1 = bit 1)."""
    if board not in BOARD_ADDRESSES:
        raise ValueError(f"Chadèche board address must be 0..3, got {board!r}")
    return bool(board & 1), bool(board & 2)


DIP_SWITCHES: Final[Mapping[int, tuple[bool, bool, bool, bool]]] = MappingProxyType(
    # Seed Tableau 1: (SW1, SW2, SW3, SW4) for each address, True = ON.
    {
        0: (False, True, False, True),
        1: (True, False, False, True),
        2: (False, True, True, False),
        3: (True, False, True, False),
    }
)


def dip_switch_text(board: int) -> str:
    """Operator text for the address DIP switch, e.g. ``"SW1 OFF, SW2 ON, SW3 OFF, SW4 ON"``."""
    if board not in DIP_SWITCHES:
        raise ValueError(f"Chadèche board address must be 0..3, got {board!r}")
    return ", ".join(
        f"SW{i} {'ON' if on else 'OFF'}" for i, on in enumerate(DIP_SWITCHES[board], 1)
    )


# --- MCP4922 DAC --------------------------------------------------------------------------
DAC_CHANNEL_B_BIT: Final = 1 << 15
DAC_BUF_BIT: Final = 1 << 14
DAC_GAIN_1X_BIT: Final = 1 << 13
"""/GA: 1 = gain 1 (Vout = VREF·code/4096), 0 = gain 2."""
DAC_ACTIVE_BIT: Final = 1 << 12
"""/SHDN: 1 = output active, 0 = channel shut down (output high impedance)."""
DAC_CODE_MASK: Final = 0x0FFF


class DacChannel(IntEnum):
    A = 0
    """Current setpoint."""
    B = 1
    """LED blink duty (NE555 control)."""


@dataclass(frozen=True, slots=True)
class DacWord:
    """A decoded MCP4922 command word."""

    channel: DacChannel
    code: int
    buffered: bool = False
    gain_1x: bool = True
    active: bool = True


def encode_dac_word(
    channel: DacChannel,
    code: int,
    *,
    buffered: bool = False,
    gain_1x: bool = True,
    active: bool = True,
) -> int:
    """16-bit MCP4922 word: bit 15 channel, 14 BUF, 13 /GA, 12 /SHDN, 11–0 code."""
    if not 0 <= code <= DAC_MAX_CODE:
        raise ValueError(f"DAC code must be 0..{DAC_MAX_CODE}, got {code}")
    word = code
    if channel == DacChannel.B:
        word |= DAC_CHANNEL_B_BIT
    if buffered:
        word |= DAC_BUF_BIT
    if gain_1x:
        word |= DAC_GAIN_1X_BIT
    if active:
        word |= DAC_ACTIVE_BIT
    return word


def decode_dac_word(word: int) -> DacWord:
    """Inverse of :func:`encode_dac_word`; every 16-bit value is a valid word."""
    if not 0 <= word <= 0xFFFF:
        raise ValueError(f"DAC word must be 16 bits, got {word}")
    return DacWord(
        channel=DacChannel.B if word & DAC_CHANNEL_B_BIT else DacChannel.A,
        code=word & DAC_CODE_MASK,
        buffered=bool(word & DAC_BUF_BIT),
        gain_1x=bool(word & DAC_GAIN_1X_BIT),
        active=bool(word & DAC_ACTIVE_BIT),
    )


def dac_word_to_bytes(word: int) -> bytes:
    """The two bytes to shift out, most significant first (MCP4922 expects MSB first)."""
    return word.to_bytes(2, "big")


def dac_word_from_bytes(data: bytes) -> int:
    """The word carried by a DAC transfer; raises ProtocolError unless exactly 2 bytes."""
    if len(data) != 2:
        raise ProtocolError(DEVICE, f"DAC transfer must be 2 bytes, got {len(data)}", data)
    return int.from_bytes(data, "big")


def dac_transfer(channel: DacChannel, code: int) -> bytes:
    """Bytes for the usual command: unbuffered, gain 1, active."""
    return dac_word_to_bytes(encode_dac_word(channel, code))


# --- MCP3201 ADC --------------------------------------------------------------------------
ADC_READ: Final = b"\x00\x00"
"""The MCP3201 takes no command: clock two bytes out, whatever is sent."""


def decode_adc_reply(data: bytes) -> int:
    """12-bit code from the 2 bytes read: ``((b0 & 0x1F) << 7) | (b1 >> 1)``.

    Bit layout (16 clocks): b0 = 2 sample clocks, a null bit, B11..B7; b1 = B6..B0 then
    the first bit of the LSB-first repeat. Leading and trailing bits are ignored.
    """
    if len(data) != 2:
        raise ProtocolError(DEVICE, f"ADC reply must be 2 bytes, got {len(data)}", data)
    b0, b1 = data[0], data[1]
    return ((b0 & 0x1F) << 7) | (b1 >> 1)


def encode_adc_reply(code: int) -> bytes:
    """The 2 bytes an MCP3201 shifts out for ``code`` (sample bits and null bit read 0)."""
    if not 0 <= code <= ADC_MAX_CODE:
        raise ValueError(f"ADC code must be 0..{ADC_MAX_CODE}, got {code}")
    b0 = (code >> 7) & 0x1F
    # After B0 the chip starts repeating the word LSB first: the 16th bit is B1.
    b1 = ((code & 0x7F) << 1) | ((code >> 1) & 1)
    return bytes((b0, b1))


_ADC_FULL_SCALE_V: Final = (ADC_MAX_CODE + 1) * ADC_LSB_V


def voltage_to_adc_code(voltage_v: float) -> int:
    """Uncalibrated ADC code for an input voltage, clamped to 0..4095 (simulator side)."""
    # Once per simulated ADC read (a dry run: 87 000): a float that is not equal to itself
    # is NaN (math.isnan's answer without the call); the clamp without min().
    if voltage_v != voltage_v or (type(voltage_v) is not float and math.isnan(voltage_v)):
        raise ValueError("voltage is NaN")
    if voltage_v <= 0.0:
        return 0
    if voltage_v >= _ADC_FULL_SCALE_V:
        return ADC_MAX_CODE
    code: int = round(voltage_v / ADC_LSB_V)
    return code if code < ADC_MAX_CODE else ADC_MAX_CODE


def adc_code_span_v(code: int) -> tuple[float, float]:
    """The lowest and the highest input voltage :func:`voltage_to_adc_code` maps to
    ``code`` (``-inf`` for code 0, ``inf`` for full scale), found by asking it.

    That code never falls as the voltage rises (a division by a positive constant and a
    rounding, both monotonic, between clamps), so every voltage between the two gets
    ``code`` and every other voltage another code: the simulator keeps its last code
    while its ADC input stays in this span (a cell moves by one code every few minutes
    of a slow charge; test_chadeche_protocol.py).
    """
    if not 0 <= code <= ADC_MAX_CODE:
        raise ValueError(f"ADC code must be 0..{ADC_MAX_CODE}, got {code}")
    low = -math.inf if code == 0 else math.nextafter(_highest_adc_input_v(code - 1), math.inf)
    high = math.inf if code == ADC_MAX_CODE else _highest_adc_input_v(code)
    return low, high


def _highest_adc_input_v(code: int) -> float:
    """The highest voltage :func:`voltage_to_adc_code` maps to ``code`` or below (``code``
    below full scale): the rounding's edge, searched from its nominal value one float at
    a time (it is within a few)."""
    v = (code + 0.5) * ADC_LSB_V
    while voltage_to_adc_code(v) > code:
        v = math.nextafter(v, -math.inf)
    while voltage_to_adc_code(up := math.nextafter(v, math.inf)) <= code:
        v = up
    return v


# --- relay latch (74HC74) -----------------------------------------------------------------
LATCH_CHARGE_LEVEL: Final = 1
"""UNVERIFIED. The seed (§II.C.2) says the relay is driven by a 74HC74 D flip-flop clocked
through CS2, but not how its D input is fed nor which output level means charge. Assumed
here: D follows MOSI, and D = 1 means charge (relay energized, bicolour LED red). Only this
constant and the two functions below encode that assumption; correct them here if the
board says otherwise."""


def encode_latch(charging: bool) -> bytes:
    """One byte for the latch transfer.

    Every bit carries the same level so the result does not depend on which bit the
    flip-flop samples (it is clocked at deselect, when MOSI may still hold the last bit).
    """
    level = LATCH_CHARGE_LEVEL if charging else 1 - LATCH_CHARGE_LEVEL
    return b"\xff" if level else b"\x00"


def decode_latch(data: bytes) -> bool:
    """Charging (True) or discharging, as the flip-flop would latch it: bit 0 of the last
    byte (the level left on MOSI at the deselect edge)."""
    if not data:
        raise ProtocolError(DEVICE, "latch transfer carries no byte", data)
    return (data[-1] & 0x01) == LATCH_CHARGE_LEVEL


# --- calibration (seed §III.F, chadecheN.prm) ---------------------------------------------
@dataclass(frozen=True, slots=True)
class Calibration:
    """Per-board linear calibration, the ``-1 -2 -s -o`` parameters of ``chadecheN.prm``.

    §III.F.1 fits *setpoint current as a function of measured current*, so the command for
    a wanted true current I is ``cmd_mA = current_slope·I_mA + current_offset_ma``.
    §III.F.2 fits *voltmeter V as a function of the ADC V*, so
    ``V_true = voltage_slope·V_adc + voltage_offset_v``.

    UNVERIFIED unit of ``-2``: the seed's example (``-2 0.0008`` for a 0–250 mA staircase)
    reads as amperes at least as plausibly as mA; whoever parses a ``.prm`` file must decide.
    Here the field is in mA.
    """

    current_slope: float = 1.0
    current_offset_ma: float = 0.0
    voltage_slope: float = 1.0
    voltage_offset_v: float = 0.0

    def __post_init__(self) -> None:
        for name in ("current_slope", "current_offset_ma", "voltage_slope", "voltage_offset_v"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"calibration {name} must be finite")
        if self.current_slope <= 0 or self.voltage_slope <= 0:
            raise ValueError("calibration slopes must be > 0")


DEFAULT_CALIBRATION: Final = Calibration()


class DacCommand(NamedTuple):
    code: int
    clamped: bool
    """True when the calibrated command exceeded 400 mA and was cut to MAX_CURRENT_CODE."""


def current_to_dac_command(current_a: float, cal: Calibration = DEFAULT_CALIBRATION) -> DacCommand:
    """DAC A code for a wanted true current magnitude (the sign is the relay's business).

    The code is clamped to 0..MAX_CURRENT_CODE (400 mA); ``clamped`` tells if the upper
    limit was hit. A command below zero (negative offset near 0 A) becomes 0 silently.
    """
    if not math.isfinite(current_a):
        raise ValueError(f"current must be finite, got {current_a}")
    cmd_ma = cal.current_slope * abs(current_a) * 1000.0 + cal.current_offset_ma
    code = round(cmd_ma / DAC_LSB_MA)
    if code > MAX_CURRENT_CODE:
        return DacCommand(MAX_CURRENT_CODE, True)
    return DacCommand(max(code, 0), False)


def current_to_dac_code(current_a: float, cal: Calibration = DEFAULT_CALIBRATION) -> int:
    """Like :func:`current_to_dac_command`, code only."""
    return current_to_dac_command(current_a, cal).code


def dac_code_to_current_a(code: int, cal: Calibration = DEFAULT_CALIBRATION) -> float:
    """True current magnitude the calibration predicts for a DAC A code (0 at code 0)."""
    if not 0 <= code <= DAC_MAX_CODE:
        raise ValueError(f"DAC code must be 0..{DAC_MAX_CODE}, got {code}")
    if code == 0:
        return 0.0
    i_ma = (code * DAC_LSB_MA - cal.current_offset_ma) / cal.current_slope
    return max(i_ma, 0.0) / 1000.0


def adc_code_to_voltage_v(code: int, cal: Calibration = DEFAULT_CALIBRATION) -> float:
    """Calibrated cell voltage for an ADC code."""
    if not 0 <= code <= ADC_MAX_CODE:
        raise ValueError(f"ADC code must be 0..{ADC_MAX_CODE}, got {code}")
    return cal.voltage_slope * (code * ADC_LSB_V) + cal.voltage_offset_v
