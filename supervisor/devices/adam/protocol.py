"""ADAM-5000/TCP over Modbus TCP: register map and raw number codecs (no I/O here).

Module facts (slots, channel counts) come from the point catalog,
:mod:`supervisor.devices.adam.catalog`; Modbus's own codes from
:mod:`supervisor.fieldbus.modbus`. Shared by the driver
(:mod:`supervisor.devices.adam.driver`), its links (:mod:`supervisor.devices.adam.transport`)
and the simulated unit (:mod:`supervisor.devices.adam.unit`, served by
:mod:`supervisor.devices.adam.sim`).
Facts come from ``shared/reference/devices.md`` ("ADAM-5000/TCP"): the address rules are
verified, the raw number format of analog values over Modbus is not. Every uncertain fact is
ONE named constant marked UNVERIFIED, so that a measurement on the real unit corrects it in
one place.

Addresses are 0-based PDU addresses (what goes on the wire):

- analog point ``ch`` of the module in ``slot``: register ``8·slot + ch`` (``40001 + …`` in
  Modicon numbering), read with :data:`ANALOG_READ_FUNCTION`;
- relay ``ch`` of the module in ``slot``: coil ``16·slot + ch`` (``00001 + …``), read FC01,
  written FC05 (one relay) or FC15 (several).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final, Literal

from supervisor.devices.adam.catalog import MODULE_KINDS, SLOTS, ModuleKind
from supervisor.fieldbus.modbus import FC_READ_HOLDING_REGISTERS

DEVICE: Final = "adam"

REGISTERS_PER_SLOT: Final = 8
COILS_PER_SLOT: Final = 16

ANALOG_READ_FUNCTION: Final[int] = FC_READ_HOLDING_REGISTERS
"""Function code used to read analog values. devices.md: "read with FC04 (or FC03)" [V];
the register numbers are given as 4xxxx (holding). The simulator answers both, so switching
to FC04 is this one line."""

RawFormat = Literal["offset", "twos"]
RAW_FORMATS: Final = ("offset", "twos")
DEFAULT_RAW_FORMAT: Final[RawFormat] = "offset"
"""UNVERIFIED: raw format of 5017/5018 values over Modbus on the 5000/TCP. One tested
application reads bipolar ranges as offset binary; the ASCII protocol uses two's complement.
It is a per-module setting (:class:`AdamModule.raw_format`), this is only its default."""

OFFSET_BINARY_SPAN: Final[Mapping[str, tuple[float, float]]] = MappingProxyType(
    {"5017": (-10.0, 10.0), "5018": (-100.0, 400.0)}
)
"""Engineering values of raw 0x0000 and 0xFFFF in offset binary (−FS, +FS), linear between.
UNVERIFIED for the 5000/TCP, in particular for type T: we take the range ends (−100 °C,
+400 °C, as Advantech's ADAM-6000 modules do), not a symmetric ±400 °C scale."""

TWOS_COMPLEMENT_FULL_SCALE: Final[Mapping[str, float]] = MappingProxyType(
    {"5017": 10.0, "5018": 400.0}
)
"""Engineering value of +FS (0x7FFF) in two's complement; −FS (0x8000) is its negative, so
type T reads +400 °C = 0x7FFF and −100 °C = 0xE000 (both sides on the 400 °C scale). From the
ASCII protocol [V there]; UNVERIFIED for Modbus on the 5000/TCP."""

TC_OPEN_WIRE_RAW: Final = 0xFFFF
"""Raw code of an open thermocouple (over-range): the ASCII protocol returns 0xFFFF [V];
UNVERIFIED over Modbus. The simulator serves this code for an open input."""

TC_BURNOUT_RAW: Final[Mapping[str, frozenset[int]]] = MappingProxyType(
    {
        "offset": frozenset({0x0000, 0xFFFF}),
        "twos": frozenset({0x7FFF, 0x8000, TC_OPEN_WIRE_RAW}),
    }
)
"""UNVERIFIED rule: thermocouple raw codes taken as burn-out (open wire) per format: the
full-scale readings and the open-wire code. In offset binary that is the range ends (−100 °C
and +400 °C, never a real battery temperature). In two's complement: ±FS and 0xFFFF, which
costs one valid code (−0.012 °C reads as burn-out) but never lets an open wire look like a
plausible temperature. The ASCII protocol reports *under*-range as 0x0000 in two's
complement; that reads 0 °C and cannot be told from a real 0 °C, so it is not flagged."""


@dataclass(frozen=True)
class AdamModule:
    """One I/O module in a slot: its type, for analog inputs the raw number format, and how
    often the driver reads it (``None``: the driver's default period)."""

    kind: str
    raw_format: str = DEFAULT_RAW_FORMAT
    poll_period_s: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in MODULE_KINDS:
            raise ValueError(f"unknown ADAM module {self.kind!r}; known: {', '.join(MODULE_KINDS)}")
        if self.raw_format not in RAW_FORMATS:
            raise ValueError(
                f"unknown raw format {self.raw_format!r}; known: {', '.join(RAW_FORMATS)}"
            )
        period = self.poll_period_s
        if period is not None and (
            isinstance(period, bool) or not math.isfinite(period) or period <= 0
        ):
            raise ValueError(f"poll_period_s must be a number of seconds > 0, got {period!r}")

    @property
    def spec(self) -> ModuleKind:
        return MODULE_KINDS[self.kind]


# --- addresses ------------------------------------------------------------------------
def _check_slot_channel(slot: int, ch: int, per_slot: int) -> None:
    if isinstance(slot, bool) or slot not in SLOTS:
        raise ValueError(f"ADAM slot must be 0..{SLOTS[-1]}, got {slot!r}")
    if isinstance(ch, bool) or not 0 <= ch < per_slot:
        raise ValueError(f"ADAM channel must be 0..{per_slot - 1}, got {ch!r}")


def analog_register(slot: int, ch: int) -> int:
    """0-based register of analog point ``ch`` in ``slot``: ``8·slot + ch``."""
    _check_slot_channel(slot, ch, REGISTERS_PER_SLOT)
    return REGISTERS_PER_SLOT * slot + ch


def coil_address(slot: int, ch: int) -> int:
    """0-based coil of digital point ``ch`` in ``slot``: ``16·slot + ch``."""
    _check_slot_channel(slot, ch, COILS_PER_SLOT)
    return COILS_PER_SLOT * slot + ch


def register_slot_channel(register: int) -> tuple[int, int]:
    """Inverse of :func:`analog_register`."""
    return divmod(register, REGISTERS_PER_SLOT)


def coil_slot_channel(coil: int) -> tuple[int, int]:
    """Inverse of :func:`coil_address`."""
    return divmod(coil, COILS_PER_SLOT)


# --- raw numbers ----------------------------------------------------------------------
def _analog_kind(kind: str) -> None:
    if kind not in OFFSET_BINARY_SPAN:
        raise ValueError(f"ADAM module {kind!r} has no analog inputs")


def _check_format(fmt: str) -> None:
    if fmt not in RAW_FORMATS:
        raise ValueError(f"unknown raw format {fmt!r}; known: {', '.join(RAW_FORMATS)}")


def _check_raw(raw: int) -> None:
    if isinstance(raw, bool) or not 0 <= raw <= 0xFFFF:
        raise ValueError(f"raw value must be a 16-bit unsigned integer, got {raw!r}")


def lsb(kind: str, fmt: str = DEFAULT_RAW_FORMAT) -> float:
    """Engineering value of one raw step (the largest step where it varies)."""
    _analog_kind(kind)
    _check_format(fmt)
    if fmt == "offset":
        lo, hi = OFFSET_BINARY_SPAN[kind]
        return (hi - lo) / 0xFFFF
    return TWOS_COMPLEMENT_FULL_SCALE[kind] / 0x7FFF


def raw_to_value(raw: int, kind: str, fmt: str = DEFAULT_RAW_FORMAT) -> float:
    """Engineering value (V for a 5017, °C for a 5018) of a 16-bit register."""
    _analog_kind(kind)
    _check_format(fmt)
    _check_raw(raw)
    if fmt == "offset":
        lo, hi = OFFSET_BINARY_SPAN[kind]
        return lo + (hi - lo) * raw / 0xFFFF
    fs = TWOS_COMPLEMENT_FULL_SCALE[kind]
    signed = raw - 0x10000 if raw & 0x8000 else raw
    # +FS is 0x7FFF and −FS 0x8000: each side has its own divisor so both ends are exact.
    return fs * signed / (0x7FFF if signed >= 0 else 0x8000)


def value_to_raw(value: float, kind: str, fmt: str = DEFAULT_RAW_FORMAT) -> int:
    """16-bit register for an engineering value, clamped to the module range (simulator)."""
    _analog_kind(kind)
    _check_format(fmt)
    if math.isnan(value):
        raise ValueError("cannot encode NaN")
    if fmt == "offset":
        lo, hi = OFFSET_BINARY_SPAN[kind]
        v = min(max(value, lo), hi)
        return min(max(round((v - lo) / (hi - lo) * 0xFFFF), 0), 0xFFFF)
    fs = TWOS_COMPLEMENT_FULL_SCALE[kind]
    v = min(max(value, -fs), fs)
    if kind == "5018":
        lo, hi = OFFSET_BINARY_SPAN[kind]
        v = min(max(v, lo), hi)
    signed = round(v / fs * (0x7FFF if v >= 0 else 0x8000))
    signed = min(max(signed, -0x8000), 0x7FFF)
    return signed & 0xFFFF


def is_burnout(raw: int, fmt: str = DEFAULT_RAW_FORMAT) -> bool:
    """True if a thermocouple raw reading means open wire (see :data:`TC_BURNOUT_RAW`)."""
    _check_format(fmt)
    _check_raw(raw)
    return raw in TC_BURNOUT_RAW[fmt]


# --- host (communication) watchdog ----------------------------------------------------
# The ADAM-5000/TCP's own watchdog: when no host talks to it for its timeout, its outputs
# go to their safe values (docs/design.md "Safety": the contactor opens when the supervisor
# dies). devices.md gives no Modbus register for it, and no Advantech document giving them
# was found: EVERY address and value below is UNVERIFIED, a placeholder laid out like the
# host watchdogs of comparable Modbus TCP I/O (a timeout register where 0 disarms, a safe
# value per output, e.g. CREVIS NA-9189 0x1020 in 100 ms units, ICP DAS ET-7000 safe values
# [S]). Read the unit's manual (or the ADAM-5000/TCP utility's Modbus traffic) and correct
# them here; the driver, the simulated unit and the tests all follow.

HOST_WATCHDOG_TIMEOUT_REGISTER: Final = 0x0100
"""UNVERIFIED: holding register of the host watchdog timeout in :data:`HOST_WATCHDOG_UNIT_S`
counts; writing a count arms (and re-arms) it, 0 disarms it. Written FC06, read back FC03."""

HOST_WATCHDOG_REFRESH_REGISTER: Final = 0x0101
"""UNVERIFIED: the "host OK" register: writing :data:`HOST_WATCHDOG_REFRESH_VALUE` restarts
the timer (used only when :data:`HOST_WATCHDOG_NEEDS_REFRESH`)."""

HOST_WATCHDOG_REFRESH_VALUE: Final = 1
"""UNVERIFIED: what a "host OK" write carries."""

HOST_WATCHDOG_SAFE_VALUES_REGISTER: Final = 0x0108
"""UNVERIFIED: holding register ``0x0108 + slot``: the safe value of that relay slot, bit
``ch`` = relay ``ch`` energised after a timeout. The driver writes 0 (every relay off: the
contactor coil de-energised, as after a power cycle)."""

HOST_WATCHDOG_UNIT_S: Final = 0.1
"""UNVERIFIED: one count of the timeout register. The ADAM-4000 ASCII command family counts
its host watchdog in 100 ms units (``~AA2<flag><timeout><safe>``, 01..FF) [S]."""

HOST_WATCHDOG_MAX_COUNTS: Final = 0xFFFF
"""UNVERIFIED: the largest timeout the register holds (a 16-bit register)."""

HOST_WATCHDOG_NEEDS_REFRESH: Final = False
"""UNVERIFIED: False: any Modbus request counts as host communication (as for ICP DAS
ET-7000 and WAGO 750 couplers [S]); every poll then keeps the watchdog alive. True: the unit
wants an explicit "host OK" (as the ASCII ``~**`` command [S]): the driver writes
:data:`HOST_WATCHDOG_REFRESH_REGISTER` on every poll and the simulated unit counts only
those writes."""

HOST_WATCHDOG_REGISTERS: Final = range(
    HOST_WATCHDOG_TIMEOUT_REGISTER, HOST_WATCHDOG_SAFE_VALUES_REGISTER + len(SLOTS)
)
"""Every register of the host watchdog block (outside the analog block ``0..8·8-1``)."""


def host_watchdog_counts(timeout_s: float) -> int:
    """The timeout register value for ``timeout_s`` (ValueError if the register cannot hold
    it: not a whole number of :data:`HOST_WATCHDOG_UNIT_S`, or out of range)."""
    if isinstance(timeout_s, bool) or not math.isfinite(timeout_s):
        raise ValueError(f"host watchdog timeout must be a number of seconds, got {timeout_s!r}")
    counts = round(timeout_s / HOST_WATCHDOG_UNIT_S)
    if abs(counts * HOST_WATCHDOG_UNIT_S - timeout_s) > 1e-6:
        raise ValueError(
            f"host watchdog timeout {timeout_s:g} s is not a multiple of"
            f" {HOST_WATCHDOG_UNIT_S:g} s (the unit's register counts in those)"
        )
    if not 1 <= counts <= HOST_WATCHDOG_MAX_COUNTS:
        top = HOST_WATCHDOG_MAX_COUNTS * HOST_WATCHDOG_UNIT_S
        raise ValueError(
            f"host watchdog timeout {timeout_s:g} s is outside {HOST_WATCHDOG_UNIT_S:g}..{top:g} s"
        )
    return counts


def host_watchdog_seconds(counts: int) -> float:
    """Inverse of :func:`host_watchdog_counts` (0: disarmed)."""
    return counts * HOST_WATCHDOG_UNIT_S
