"""BMS CAN frames (seed 002 §2.1, annex IV): DBC codecs shared by the driver and the simulator.

The frames are described by ``bms.dbc`` (package data next to this module, text from
reference/devices.md) and decoded with cantools only, never by hand-written byte slicing:

- 0x1B0 ``PackVoltages`` (8 bytes, every 1000 ms): pack voltage (32 bit) and min/max cell
  voltage (16 bit each), unsigned big-endian, 1 mV per bit.
- 0x2B0 ``PackCurrent`` (4 bytes, every 100 ms): pack current, IEEE float32 big-endian, A.
- 0x3B0 ``PackTemperatures`` (6 bytes, every 1000 ms): min/max/average temperature, signed
  16 bit big-endian, 0.1 °C per bit.

Length policy: a CAN controller pads a frame to 8 bytes (the seed's own frames for 0x2B0
and 0x3B0 are 8 bytes), so a frame at least as long as its DBC message decodes, its extra
bytes ignored; a SHORTER frame cannot be decoded
(:class:`~supervisor.core.errors.ProtocolError`). ``allow_extra_bytes=False`` refuses longer
frames too (a bench whose BMS is known to send exact lengths, where a longer one means the
DBC is not the device's).

Plausibility (:func:`implausible`): a decoded value is not necessarily a measurement. The
DBC's ``[min|max]`` of each signal is its plausible range (chosen here, UNVERIFIED against
the BMS's data sheet: a pack of at most 1000 V, cells of 0–5 V, ±1000 A, −40…125 °C); a
non-zero subnormal float32 current (the seed's ``00 00 00 64`` is 1.4e-43 A: an integer
written into a float field) is no measurement; the minimum cell voltage and temperature
may not exceed the maximum, and the average temperature lies between them. The seed's
sample frames break three of these rules (12 800.16 V, 1.4e-43 A, a minimum temperature
above the maximum).

No I/O here. Every device fact the seed leaves open is one named constant marked UNVERIFIED.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from importlib import resources
from types import MappingProxyType
from typing import Final

import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage

from supervisor.core.errors import ProtocolError

DEVICE: Final = "bms"

DBC_RESOURCE: Final = "bms.dbc"
"""File name of the DBC inside this package (package data)."""

PACK_VOLTAGES_ID: Final = 0x1B0
PACK_CURRENT_ID: Final = 0x2B0
PACK_TEMPERATURES_ID: Final = 0x3B0
FRAME_IDS: Final = (PACK_VOLTAGES_ID, PACK_CURRENT_ID, PACK_TEMPERATURES_ID)
"""Standard (11-bit) identifiers of the frames the BMS sends."""

PERIODS_MS: Final[Mapping[int, int]] = MappingProxyType(
    {PACK_VOLTAGES_ID: 1000, PACK_CURRENT_ID: 100, PACK_TEMPERATURES_ID: 1000}
)
"""Transmit period of each frame (seed annex IV)."""

BMS_CURRENT_SIGN: Final = +1
"""UNVERIFIED: sign of ``PackCurrent`` on the wire relative to the supervisor's convention
(BDF: positive current CHARGES the pack). Neither the seed nor the reference says which
sign this BMS uses; check on the bench (charge at a known current, look at the frame) and
set to -1 if the BMS reports discharge as positive. Applied on both sides: the driver
multiplies the decoded current by it, the simulator multiplies before encoding."""


@dataclass(frozen=True, slots=True)
class BmsValues:
    """What the BMS reports, in engineering units; current + charges (BDF convention)."""

    pack_voltage_v: float
    min_cell_v: float
    max_cell_v: float
    pack_current_a: float
    min_temp_c: float
    max_temp_c: float
    avg_temp_c: float


class UnknownFrameError(ProtocolError):
    """A frame whose identifier is not in the DBC."""


@cache
def load_database() -> Database:
    """The BMS DBC, parsed once (strict: overlapping or out-of-frame signals are errors)."""
    text = resources.files("supervisor.devices.bms").joinpath(DBC_RESOURCE).read_text("utf-8")
    db = cantools.database.load_string(text, database_format="dbc")
    if not isinstance(db, Database):  # pragma: no cover - a DBC always gives a CAN database
        raise TypeError(f"{DBC_RESOURCE} is not a CAN database")
    return db


@cache
def _messages_by_id() -> Mapping[int, DbcMessage]:
    # Exact standard identifiers: cantools' own lookup masks and ORs the extended flag in.
    return MappingProxyType(
        {m.frame_id: m for m in load_database().messages if not m.is_extended_frame}
    )


def message_for(frame_id: int) -> DbcMessage:
    """DBC message of a standard identifier; :class:`UnknownFrameError` if there is none."""
    message = _messages_by_id().get(frame_id)
    if message is None:
        raise UnknownFrameError(DEVICE, f"unknown frame id {_hex_id(frame_id)}")
    return message


def period_s(frame_id: int) -> float:
    """Transmit period of a known frame, in seconds."""
    return PERIODS_MS[frame_id] / 1000.0


def decode(frame_id: int, data: bytes, *, allow_extra_bytes: bool = True) -> dict[str, float]:
    """Physical values of one frame, by DBC signal name (``PackVoltage``: V, ...).

    Raises :class:`UnknownFrameError` for an identifier not in the DBC and
    :class:`ProtocolError` (raw bytes kept) for a frame shorter than its DBC length (or
    longer, with ``allow_extra_bytes=False``) or that decodes to a non-finite value (float32
    NaN/inf current). Never raises anything else. Values are not judged here: see
    :func:`implausible`.
    """
    raw = bytes(data)
    message = _messages_by_id().get(frame_id)
    if message is None:
        raise UnknownFrameError(DEVICE, f"unknown frame id {_hex_id(frame_id)}", raw=raw)
    expected = message.length
    if len(raw) < expected or (len(raw) > expected and not allow_extra_bytes):
        raise ProtocolError(
            DEVICE,
            f"{message.name} ({_hex_id(frame_id)}) has {len(raw)} bytes, DBC says {expected}",
            raw=raw,
        )
    try:
        decoded = message.decode(raw[:expected], decode_choices=False, scaling=True)
    except (cantools.database.DecodeError, ValueError) as exc:  # pragma: no cover - length checked
        raise ProtocolError(DEVICE, f"{message.name}: {exc}", raw=raw) from exc
    if not isinstance(decoded, dict):  # pragma: no cover - no container frames in the DBC
        raise ProtocolError(DEVICE, f"{message.name}: unexpected container frame", raw=raw)
    values: dict[str, float] = {}
    for signal, value in decoded.items():
        if not isinstance(value, int | float):  # pragma: no cover - no choices in the DBC
            raise ProtocolError(DEVICE, f"{message.name}.{signal}: not a number", raw=raw)
        number = float(value)
        if not math.isfinite(number):
            raise ProtocolError(DEVICE, f"{message.name}.{signal} is {number}", raw=raw)
        values[signal] = number
    return values


FLOAT32_MIN_NORMAL: Final = 1.1754943508222875e-38
"""Smallest normal float32: a non-zero value below it is subnormal, never a measurement."""


def implausible(frame_id: int, signals: Mapping[str, float]) -> dict[str, str]:
    """The signals of one decoded frame that are no plausible measurement, each with why
    (empty: all plausible). See the module docstring for the rules."""
    message = message_for(frame_id)
    why: dict[str, str] = {}
    for sig in message.signals:
        value = signals.get(sig.name)
        if value is None:
            continue
        low, high = sig.minimum, sig.maximum
        if (low is not None and value < low) or (high is not None and value > high):
            why[sig.name] = f"{sig.name} {value:.10g} {sig.unit} outside [{low:g}, {high:g}] (DBC)"
        elif sig.is_float and value != 0.0 and abs(value) < FLOAT32_MIN_NORMAL:
            why[sig.name] = f"{sig.name} {value:g} {sig.unit} is a subnormal float32"
    _ordered(why, signals, "MinCellVoltage", "MaxCellVoltage", "V")
    _ordered(why, signals, "MinTemp", "MaxTemp", "degC")
    avg, low, high = (signals.get(n) for n in ("AvgTemp", "MinTemp", "MaxTemp"))
    if avg is not None and low is not None and high is not None and not low <= avg <= high:
        why.setdefault("AvgTemp", f"AvgTemp {avg:g} degC not within [MinTemp, MaxTemp]")
    return why


def _ordered(
    why: dict[str, str], signals: Mapping[str, float], lo: str, hi: str, unit: str
) -> None:
    """Both of a minimum and a maximum are implausible when the minimum exceeds the maximum
    (which of the two is wrong cannot be told)."""
    low, high = signals.get(lo), signals.get(hi)
    if low is not None and high is not None and low > high:
        text = f"{lo} {low:g} {unit} > {hi} {high:g} {unit}"
        why.setdefault(lo, text)
        why.setdefault(hi, text)


def encode(name_or_id: str | int, signals: Mapping[str, float]) -> bytes:
    """Bytes of one frame from physical values by signal name (every signal required).

    Raises ``ValueError`` for an unknown message or a value outside the DBC range.
    """
    try:
        if isinstance(name_or_id, str):
            message = load_database().get_message_by_name(name_or_id)
        else:
            message = message_for(name_or_id)
    except (KeyError, UnknownFrameError) as exc:
        raise ValueError(f"no BMS message {name_or_id!r}") from exc
    try:
        return bytes(message.encode(dict(signals), scaling=True, strict=True))
    except (cantools.database.EncodeError, OverflowError, ValueError) as exc:
        raise ValueError(f"cannot encode {message.name}: {exc}") from exc


def encode_values(values: BmsValues) -> dict[int, bytes]:
    """The three frames carrying ``values``, by identifier (current sign applied)."""
    return {
        PACK_VOLTAGES_ID: encode(
            PACK_VOLTAGES_ID,
            {
                "PackVoltage": values.pack_voltage_v,
                "MinCellVoltage": values.min_cell_v,
                "MaxCellVoltage": values.max_cell_v,
            },
        ),
        PACK_CURRENT_ID: encode(
            PACK_CURRENT_ID, {"PackCurrent": BMS_CURRENT_SIGN * values.pack_current_a}
        ),
        PACK_TEMPERATURES_ID: encode(
            PACK_TEMPERATURES_ID,
            {
                "MinTemp": values.min_temp_c,
                "MaxTemp": values.max_temp_c,
                "AvgTemp": values.avg_temp_c,
            },
        ),
    }


def _hex_id(frame_id: int) -> str:
    return f"0x{frame_id:03X}" if frame_id >= 0 else str(frame_id)
