"""SCPI text for the EA-PSB 10000 (and EA-ELR 10000): pure codecs shared by driver and simulator.

What any SCPI unit speaks (framing, headers, numbers, ``*IDN?``, the error queue) is
:mod:`supervisor.fieldbus.scpi`; this module adds the EA's command tree, status bits and
replies. No sockets here. Everything that parses device text raises :class:`ProtocolError`
(naming the device, what was expected and the raw bytes) and nothing else, whatever it is fed.

Facts come from ``devices.md`` (section "EA-PSB 10000") and seed 002 §2.2. Every fact
that is not confirmed by a manufacturer document is ONE named constant below, marked
``[S]`` (one third-party source) or ``[U]`` (not found), so it is easy to correct once
checked on a real unit.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from enum import StrEnum
from types import MappingProxyType
from typing import Final, NamedTuple

from supervisor.core.errors import ProtocolError
from supervisor.fieldbus import scpi
from supervisor.fieldbus.scpi import DEVICE, Command, Identity, parse_number

# --- transport -------------------------------------------------------------------------
SCPI_TCP_PORT: Final = 5025
"""Raw-socket SCPI port of EA units [V]. Lines end with LF [V] (:data:`scpi.LINE_END`)."""
# [S] EA accepts ``;`` lines and answers ``;``-joined replies on one line
# (scpi.join_commands), AND resolves every command of such a line from the root (strict SCPI
# would read ``SINK:CURR 1; VOLT 10`` as ``SINK:VOLT 10``). A real-unit script sends
# ``SINK:CURR <I>; VOLT <Vmin>; CURR 0``, which only works if the latter holds.

# --- identification ------------------------------------------------------------------------
EA_MANUFACTURER: Final = "EA Elektro-Automatik"
"""``*IDN?`` manufacturer field starts with this [V] (seed 002: ``EA Elektro-Automatik GmbH &
Co. KG``)."""

# --- status registers ------------------------------------------------------------------------
QUES_OVP_BIT: Final = 0
"""STAT:QUES:COND? overvoltage protection [V]."""
QUES_OCP_BIT: Final = 1
"""STAT:QUES:COND? overcurrent protection [V] (the sink OCP is assumed to share it [U])."""
QUES_OPP_BIT: Final = 2
"""STAT:QUES:COND? overpower protection [V]."""
QUES_OT_BIT: Final = 3
"""STAT:QUES:COND? overtemperature [V]."""
QUES_POWER_FAIL_BIT: Final = 13
"""STAT:QUES:COND? power fail [V]. Bits 4–8 and 14 exist but their meaning is [S]."""
OPER_CV_BIT: Final = 8
"""STAT:OPER:COND? constant-voltage regulation [V]."""
OPER_CC_BIT: Final = 9
"""STAT:OPER:COND? constant-current regulation [V]."""
OPER_CP_BIT: Final = 10
"""STAT:OPER:COND? constant-power regulation [S]."""
OPER_SINK_BIT: Final = 12
"""STAT:OPER:COND? the unit is sinking [S]."""

# --- measurements ------------------------------------------------------------------------------
SINK_READS_NEGATIVE: Final = True
"""[S] ``MEAS:CURR?``/``MEAS:POW?``/``MEAS:ARR?`` read NEGATIVE while the unit sinks. If a real
unit reads the magnitude instead, set this to False: :func:`parse_meas_array` then signs the
reading from the direction the caller knows it commanded (``sinking``)."""

# --- watchdog ("interface monitoring") -------------------------------------------------------
WATCHDOG_TIME_HEADER: Final = "SYST:COMM:MON:TIM"
"""Interface monitoring timeout in seconds. Two independent drivers agree on the short form
[V-]; the long form (and so whether ``TIM`` is the right abbreviation) [U]; unit = seconds [S]."""
WATCHDOG_ENABLE_HEADER: Final = "SYST:COMM:MON:ACT"
"""``ON`` enables interface monitoring; must be sent on its own line after ``SYST:LOCK ON``
[V-]; long form [U]."""
STATE_AFTER_REMOTE_HEADER: Final = "POW:STAG:AFT:REM"
"""What the output does when remote ends (``OFF``) [S]. Not sent by the driver (it is a unit
setting); the simulator behaves as if it were ``OFF``."""

# Short forms of the EA's own long mnemonics besides SCPI's common ones (SCPI: long or short,
# any case). The EA long forms of the watchdog nodes are [U].
LONG_FORMS: Final = {
    **scpi.LONG_FORMS,
    "LOCK": "LOCK",
    "OWNER": "OWN",
    "NOMINAL": "NOM",
    "MONITORING": "MON",
    "ACTIVE": "ACT",
    "ACTIVATE": "ACT",
    "SOURCE": "SOUR",
    "LEVEL": "LEV",
    "IMMEDIATE": "IMM",
    "AMPLITUDE": "AMPL",
    "NEXT": "NEXT",
}

OPTIONAL_NODES: Final = (
    "OUTP[:STAT]",
    "SYST:LOCK[:STAT]",
    "[SOUR:]VOLT[:LEV][:IMM][:AMPL]",
    "[SOUR:]CURR[:LEV][:IMM][:AMPL]",
    "[SOUR:]POW[:LEV][:IMM][:AMPL]",
    "SINK:CURR[:LEV][:IMM][:AMPL]",
    "SINK:POW[:LEV][:IMM][:AMPL]",
    "[SOUR:]VOLT:PROT[:LEV]",
    "[SOUR:]CURR:PROT[:LEV]",
    "[SOUR:]POW:PROT[:LEV]",
    "SINK:CURR:PROT[:LEV]",
    "MEAS[:SCAL]:VOLT[:DC]",
    "MEAS[:SCAL]:CURR[:DC]",
    "MEAS[:SCAL]:POW[:DC]",
    "MEAS[:SCAL]:ARR",
    "SYST:ERR[:NEXT]",
)
"""The EA commands with optional nodes (SCPI's ``[...]``: a unit accepts the header with or
without them), in short form; each means its header without them (``OUTP:STAT OFF`` is
``OUTP OFF``). ``OUTPut[:STATe]``, ``SYSTem:ERRor[:NEXT]`` and the set values'
``[:LEVel][:IMMediate][:AMPLitude]`` are SCPI-99's own forms; that an EA unit accepts every
one of them (and ``[SOURce:]``, ``MEASure[:SCALar]``, ``[:DC]``) is [S] (seed 002's script
sends ``OUTP:STAT OFF``; EA's programming guide lists its commands in this notation)."""


def _variants(pattern: str) -> list[str]:
    """Every header a pattern of :data:`OPTIONAL_NODES` stands for (``A[:B]`` → ``A``,
    ``A:B``)."""
    parts = re.split(r"(\[[^\]]*\])", pattern)
    headers = [""]
    for part in parts:
        if part.startswith("["):
            headers = [h + extra for h in headers for extra in ("", part[1:-1])]
        else:
            headers = [h + part for h in headers]
    return headers


CANONICAL_HEADERS: Final[Mapping[str, str]] = MappingProxyType(
    {v: _variants(p)[0] for p in OPTIONAL_NODES for v in _variants(p)}
)
"""Each header with optional nodes (short form) → the header without them."""


# --- commands (simulator side) -------------------------------------------------------------
def normalize_header(header: str) -> str:
    """:func:`scpi.normalize_header` with the EA's long forms (``SYSTem:COMMunicate:MONitoring``
    → ``SYST:COMM:MON``) and without its optional nodes (``OUTPut:STATe`` → ``OUTP``)."""
    short = scpi.normalize_header(header, LONG_FORMS)
    return CANONICAL_HEADERS.get(short, short)


def parse_command(text: str, device: str = DEVICE) -> Command:
    """:func:`scpi.parse_command` with the EA's long forms, its optional nodes left out of
    the header (:data:`OPTIONAL_NODES`)."""
    cmd = scpi.parse_command(text, device, LONG_FORMS)
    header = CANONICAL_HEADERS.get(cmd.header)
    if header is None:
        return cmd
    return Command(header, cmd.query, cmd.argument)


# --- words ------------------------------------------------------------------------------------
class LockOwner(StrEnum):
    """``SYST:LOCK:OWN?`` replies [V]. Other owners a real unit may report (e.g. per
    interface) are [U]: they parse as a ProtocolError, so the driver notices loudly."""

    REMOTE = "REMOTE"
    NONE = "NONE"
    LOCAL = "LOCAL"


def parse_lock_owner(text: str, device: str = DEVICE) -> LockOwner:
    word = text.strip().upper()
    try:
        return LockOwner(word)
    except ValueError:
        raise ProtocolError(
            device, "REMOTE, NONE or LOCAL", text.encode("ascii", "replace")
        ) from None


# --- replies ------------------------------------------------------------------------------------
class Measurement(NamedTuple):
    """One ``MEAS:ARR?`` reading; current and power are negative while sinking."""

    voltage_v: float
    current_a: float
    power_w: float


def parse_meas_array(text: str, device: str = DEVICE, *, sinking: bool = False) -> Measurement:
    """``"48.00 V, -1.50 A, -72.00 W"`` → Measurement (V, A, W), sink current negative.

    ``sinking`` (the direction the caller commanded) is used only when
    :data:`SINK_READS_NEGATIVE` is False.
    """
    raw = text.encode("ascii", "replace")
    fields = text.split(",")
    if len(fields) != 3:
        raise ProtocolError(device, "'<V> V, <I> A, <P> W'", raw)
    v = parse_number(fields[0], device, "V")
    i = parse_number(fields[1], device, "A")
    p = parse_number(fields[2], device, "W")
    if not SINK_READS_NEGATIVE and sinking:  # pragma: no cover - depends on the constant
        i, p = -abs(i), -abs(p)
    return Measurement(v, i, p)


def format_meas_array(m: Measurement) -> str:
    return f"{m.voltage_v:.2f} V, {m.current_a:.2f} A, {m.power_w:.2f} W"


def is_ea(identity: Identity) -> bool:
    """An ``*IDN?`` reply of an EA unit."""
    return identity.made_by(EA_MANUFACTURER)


def normalize_model(model: str) -> str:
    """``ea-psb  10060-60`` → ``PSB 10060-60`` (for comparing models)."""
    m = " ".join(model.upper().split())
    return m.removeprefix("EA-").removeprefix("EA ")


def model_matches(expected: str, received: str) -> bool:
    return normalize_model(expected) == normalize_model(received)
