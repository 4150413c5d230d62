"""SCPI text as any instrument speaks it: pure codecs shared by drivers and simulators.

Line framing (IEEE 488.2 "message terminator" ``\\n``), several commands on one line,
command headers with their long and short forms, numbers with units, ``ON``/``OFF``, status
registers, ``*IDN?`` and the ``SYST:ERR?`` error queue. No sockets here (the line transports
are :mod:`supervisor.fieldbus.scpi_transport`) and nothing of one brand: a unit's command
tree, its status bits and its replies beyond these live in its kind's ``protocol.py``
(e.g. :mod:`supervisor.devices.ea.protocol`).

Everything that parses device text raises :class:`ProtocolError` (naming the device, what
was expected and the raw bytes) and nothing else, whatever it is fed.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final, NamedTuple

from supervisor.core.errors import ProtocolError

DEVICE: Final = "scpi"
"""Device name used in errors when the caller gives none."""

# --- framing constants ---------------------------------------------------------------------
LINE_END: Final = b"\n"
"""Commands and replies end with LF; a CR before it is tolerated."""
MAX_LINE_BYTES: Final = 4096
"""Longest line accepted; a longer one is garbage (a power supply's reply is well under
200 bytes)."""
COMMAND_SEPARATOR: Final = "; "
"""Joins several commands on one line (SCPI's message unit separator). How a unit resolves
the headers after the first (from the root, or from the previous one's node as strict SCPI
says) is the unit's: see its kind's protocol module."""
REPLY_SEPARATOR: Final = ";"
"""Joins the replies to several queries of one line."""

# --- status registers (IEEE 488.2 / SCPI conventions) -----------------------------------------
STB_ERROR_QUEUE_BIT: Final = 2
"""*STB? error/event queue not empty (IEEE 488.2 / SCPI convention)."""
STB_QUES_BIT: Final = 3
"""*STB? questionable summary (SCPI convention)."""
REGISTER_MAX: Final = 0xFFFF_FFFF
"""Largest status register value accepted (SCPI registers are 16-bit; 32 leaves room)."""

# --- error queue (SCPI-99 standard codes) ---------------------------------------------------
ERR_NONE: Final = 0
ERR_COMMAND: Final = -100
"""``-100,"Command error"``: unknown command."""
ERR_PARAMETER: Final = -220
"""``-220,"Parameter error"``."""
ERR_DATA_OUT_OF_RANGE: Final = -222
"""``-222,"Data out of range"``."""
ERR_INVALID_IN_LOCAL: Final = -201
"""``-201,"Invalid while in local"``: a setting without remote control."""
ERROR_MESSAGES: Final = {
    ERR_NONE: "No error",
    ERR_COMMAND: "Command error",
    ERR_PARAMETER: "Parameter error",
    ERR_DATA_OUT_OF_RANGE: "Data out of range",
    ERR_INVALID_IN_LOCAL: "Invalid while in local",
}
ERROR_CODE_LIMIT: Final = 100_000
"""|code| above this is not an SCPI error code."""

LONG_FORMS: Final[Mapping[str, str]] = MappingProxyType(
    {
        "SYSTEM": "SYST",
        "OUTPUT": "OUTP",
        "VOLTAGE": "VOLT",
        "CURRENT": "CURR",
        "POWER": "POW",
        "PROTECTION": "PROT",
        "MEASURE": "MEAS",
        "SCALAR": "SCAL",
        "ARRAY": "ARR",
        "ERROR": "ERR",
        "STATUS": "STAT",
        "QUESTIONABLE": "QUES",
        "OPERATION": "OPER",
        "CONDITION": "COND",
        "COMMUNICATE": "COMM",
        "TIME": "TIM",
        "STATE": "STAT",
    }
)
"""Short forms of the common long mnemonics (SCPI: long or short, any case). A unit's own
nodes are added by its kind (``{**LONG_FORMS, ...}``)."""

_NUMBER = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_NUMBER_WITH_UNIT_RE: Final = re.compile(rf"({_NUMBER})\s*([A-Za-z]*)", re.ASCII)
_INT_RE: Final = re.compile(r"\+?\d{1,12}", re.ASCII)
_ERROR_RE: Final = re.compile(r'([+-]?\d{1,6})\s*,\s*(?:"(.*)"|(.*))', re.DOTALL | re.ASCII)
_NOT_PRINTABLE_RE: Final = re.compile(rb"[^\t\x20-\x7e]")
"""A byte that is neither printable ASCII nor a tab."""
_HEADER_RE: Final = re.compile(
    r":?(\*[A-Za-z]+|[A-Za-z][A-Za-z0-9]*(?::[A-Za-z][A-Za-z0-9]*)*)(\?)?(?:\s+(.*))?",
    re.DOTALL | re.ASCII,
)


# --- framing -----------------------------------------------------------------------------------
def decode_line(raw: bytes, device: str = DEVICE) -> str:
    """One received line (with or without its ``\\n``/``\\r\\n``) as text, stripped.

    Only printable ASCII (and tabs) is accepted: anything else is line noise or binary.
    """
    if len(raw) > MAX_LINE_BYTES:
        raise ProtocolError(device, f"a line of at most {MAX_LINE_BYTES} bytes", raw[:64])
    body = raw
    if body.endswith(b"\n"):
        body = body[:-1]
    if body.endswith(b"\r"):
        body = body[:-1]
    if _NOT_PRINTABLE_RE.search(body) is not None:
        raise ProtocolError(device, "a line of printable ASCII text", raw)
    return body.decode("ascii").strip()


def encode_line(text: str) -> bytes:
    """A command line ready to send: ASCII, no line break inside, ``\\n`` at the end.

    Raises ValueError (a caller bug, not a device fault) on a bad command text.
    """
    if "\n" in text or "\r" in text:
        raise ValueError(f"command text must be one line: {text!r}")
    if not text.isascii():
        raise ValueError(f"command text must be ASCII: {text!r}")
    return text.encode("ascii") + LINE_END


class LineFramer:
    """Cut a byte stream into lines (``\\n``, tolerating ``\\r\\n``)."""

    def __init__(self, device: str = DEVICE) -> None:
        self._device = device
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[str]:
        """Add received bytes; return the complete lines now available, decoded."""
        self._buf += data
        lines: list[str] = []
        while True:
            end = self._buf.find(LINE_END)
            if end < 0:
                break
            raw = bytes(self._buf[: end + 1])
            del self._buf[: end + 1]
            lines.append(decode_line(raw, self._device))
        if len(self._buf) > MAX_LINE_BYTES:
            raw = bytes(self._buf[:64])
            self._buf.clear()
            raise ProtocolError(self._device, f"a line end within {MAX_LINE_BYTES} bytes", raw)
        return lines

    @property
    def pending(self) -> bytes:
        """Bytes received after the last complete line."""
        return bytes(self._buf)


def join_commands(commands: Iterable[str]) -> str:
    """Several commands on one line (see :data:`COMMAND_SEPARATOR`)."""
    parts = [c.strip() for c in commands]
    if not parts or any(not p or ";" in p for p in parts):
        raise ValueError(f"commands must be non-empty and free of ';': {parts!r}")
    return COMMAND_SEPARATOR.join(parts)


def split_commands(line: str) -> list[str]:
    """The commands of one received command line (empty pieces dropped)."""
    return [c.strip() for c in line.split(";") if c.strip()]


def split_reply(text: str, count: int, device: str = DEVICE) -> list[str]:
    """A ``;``-joined reply line cut into exactly ``count`` replies."""
    parts = [p.strip() for p in text.split(REPLY_SEPARATOR)]
    if len(parts) != count or (count and any(not p for p in parts)):
        raise ProtocolError(
            device, f"{count} non-empty ';'-separated replies", text.encode("ascii", "replace")
        )
    return parts


# --- commands (a simulated unit's side) ------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Command:
    """One parsed command: canonical short-form ``header`` (upper case), query flag, argument."""

    header: str
    query: bool
    argument: str | None


def normalize_header(header: str, long_forms: Mapping[str, str] = LONG_FORMS) -> str:
    """Upper-case short form of a header (``volt:prot`` and ``VOLTage:PROTection`` →
    ``VOLT:PROT``). Only the long forms in ``long_forms`` are known: a unit's command tree
    adds its own nodes to :data:`LONG_FORMS`."""
    nodes = header.lstrip(":").upper().split(":")
    return ":".join(long_forms.get(n, n) for n in nodes)


def parse_command(
    text: str, device: str = DEVICE, long_forms: Mapping[str, str] = LONG_FORMS
) -> Command:
    """Parse one command as received (``VOLT 12.00 V``, ``MEAS:ARR?``, ``*IDN?``)."""
    m = _HEADER_RE.fullmatch(text.strip())
    if m is None:
        raise ProtocolError(device, "an SCPI command", text.encode("ascii", "replace"))
    argument = m.group(3)
    if argument is not None:
        argument = argument.strip() or None
    return Command(normalize_header(m.group(1), long_forms), m.group(2) is not None, argument)


# --- numbers and words ------------------------------------------------------------------------
def parse_number(text: str, device: str = DEVICE, unit: str | None = None) -> float:
    """``"48.00 V"``, ``"-1.50 A"``, ``"72.00 W"``, ``"48"``, ``"4.8E+01"`` → float.

    With ``unit``, a unit in the text must be that one (case-insensitive); a bare number is
    accepted. Without ``unit``, any alphabetic unit is accepted. NaN and infinities (and SCPI's
    9.91E37 not-a-number) are refused.
    """
    raw = text.encode("ascii", "replace")
    m = _NUMBER_WITH_UNIT_RE.fullmatch(text.strip())
    what = f"a number in {unit}" if unit else "a number"
    if m is None:
        raise ProtocolError(device, what, raw)
    suffix = m.group(2)
    if unit is not None and suffix and suffix.upper() != unit.upper():
        raise ProtocolError(device, what, raw)
    try:
        value = float(m.group(1))
    except ValueError:  # pragma: no cover - the regex admits only float syntax
        raise ProtocolError(device, what, raw) from None
    if not math.isfinite(value) or abs(value) >= 9.9e37:
        raise ProtocolError(device, f"a finite {what[2:]}", raw)
    return value


def format_number(value: float, decimals: int = 4) -> str:
    """A set value for a command (fixed point, no exponent). ValueError on NaN/inf."""
    if isinstance(value, bool) or not math.isfinite(value):
        raise ValueError(f"set value must be a finite number, got {value!r}")
    text = f"{value:.{decimals}f}"
    if float(text) == 0.0:
        return f"{0.0:.{decimals}f}"  # no "-0.0000"
    return text


def format_setting(header: str, value: float, decimals: int = 4) -> str:
    """``VOLT 14.2000``."""
    return f"{header} {format_number(value, decimals)}"


def parse_on_off(text: str, device: str = DEVICE) -> bool:
    """``ON``/``OFF`` (also ``1``/``0``) → bool."""
    word = text.strip().upper()
    if word in ("ON", "1"):
        return True
    if word in ("OFF", "0"):
        return False
    raise ProtocolError(device, "ON or OFF", text.encode("ascii", "replace"))


def parse_register(text: str, device: str = DEVICE) -> int:
    """An integer status register (``STAT:QUES:COND?``, ``*STB?``): 0..REGISTER_MAX."""
    t = text.strip()
    if _INT_RE.fullmatch(t) is None or int(t) > REGISTER_MAX:
        raise ProtocolError(
            device, f"an integer register 0..{REGISTER_MAX}", text.encode("ascii", "replace")
        )
    return int(t)


def bit_set(register: int, bit: int) -> bool:
    return bool(register >> bit & 1)


# --- identification and error queue -------------------------------------------------
class Identity(NamedTuple):
    manufacturer: str
    model: str
    serial: str
    firmware: str

    def made_by(self, manufacturer: str) -> bool:
        """The manufacturer field starts with ``manufacturer`` (units append a legal form)."""
        return self.manufacturer.startswith(manufacturer)


def parse_idn(text: str, device: str = DEVICE) -> Identity:
    """``*IDN?`` reply → manufacturer, model, serial, firmware (all firmware versions, as sent).

    Tolerates a trailing comma (EA units send one) and extra comma-separated firmware fields.
    """
    fields = [f.strip() for f in text.split(",")]
    while fields and not fields[-1]:
        fields.pop()
    if len(fields) < 4 or not all(fields[:3]):
        raise ProtocolError(
            device,
            "'<manufacturer>, <model>, <serial>, <firmware>'",
            text.encode("ascii", "replace"),
        )
    return Identity(fields[0], fields[1], fields[2], ", ".join(fields[3:]))


def format_idn(identity: Identity) -> str:
    return ", ".join(identity)


class ScpiError(NamedTuple):
    """One error queue entry; ``code == 0`` means the queue is empty."""

    code: int
    message: str

    def __str__(self) -> str:
        return f'{self.code},"{self.message}"'


def parse_error(text: str, device: str = DEVICE) -> ScpiError:
    """``SYST:ERR?`` reply: ``-201,"Invalid while in local"`` → ScpiError(-201, ...)."""
    m = _ERROR_RE.fullmatch(text.strip())
    if m is None:
        raise ProtocolError(device, '<code>,"<message>"', text.encode("ascii", "replace"))
    code = int(m.group(1))
    if abs(code) >= ERROR_CODE_LIMIT:  # pragma: no cover - the regex limits digits
        raise ProtocolError(device, "an SCPI error code", text.encode("ascii", "replace"))
    message = m.group(2) if m.group(2) is not None else m.group(3).strip()
    return ScpiError(code, message)


def format_error(code: int, message: str | None = None) -> str:
    return str(ScpiError(code, message if message is not None else ERROR_MESSAGES[code]))
