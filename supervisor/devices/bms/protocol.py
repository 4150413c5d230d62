"""BMS CAN frames (seed 002 §2.1, annex IV): DBC codecs shared by the driver and the simulator.

The frames are described by ``bms.dbc`` (package data next to this module, text from
reference/devices.md) and decoded with cantools only, never by hand-written byte slicing:

- 0x1B0 ``PackVoltages`` (8 bytes, every 1000 ms): pack voltage (32 bit) and min/max cell
  voltage (16 bit each), unsigned big-endian, 1 mV per bit.
- 0x2B0 ``PackCurrent`` (4 bytes, every 100 ms): pack current, IEEE float32 big-endian, A.
- 0x3B0 ``PackTemperatures`` (6 bytes, every 1000 ms): min/max/average temperature, signed
  16 bit big-endian, 0.1 °C per bit.

Length policy: a frame shorter than its DBC length cannot be decoded; a LONGER frame is
decoded by cantools as if the extra bytes were not there, but here it is rejected too
(:class:`~supervisor.core.errors.ProtocolError`): a length that disagrees with the DBC means
the DBC or the device is not what we think, and a silently truncated decode would hide it.
``allow_extra_bytes=True`` accepts padded frames (see the note on ``decode``).

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


def decode(frame_id: int, data: bytes, *, allow_extra_bytes: bool = False) -> dict[str, float]:
    """Physical values of one frame, by DBC signal name (``PackVoltage``: V, ...).

    Raises :class:`UnknownFrameError` for an identifier not in the DBC and
    :class:`ProtocolError` (raw bytes kept) for a frame whose length differs from the DBC
    length or that decodes to a non-finite value (float32 NaN/inf current). Never raises
    anything else. ``allow_extra_bytes``: accept frames longer than the DBC length and ignore
    the extra bytes (cantools' own behaviour); off by default, see the module docstring. Note
    that the seed's illustrative frames for 0x2B0 and 0x3B0 are 8 bytes long (padded), so a
    BMS that always sends DLC 8 needs it.
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
