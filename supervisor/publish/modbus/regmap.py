"""The Modbus register map: which tag is at which address, in which table and encoding.

A contract with the panels and SCADA configured from it: an address, once given, never
moves (a tag added to the I/O map or a field added to the product goes after the others,
never between them), and an explicit ``address`` in the I/O map overrides. The map is
documented by ``supervisor modbus map IOMAP`` (CSV: address, function, type, tag, unit,
scale, access), which panel-HMI software imports.

Addresses are the PDU's, 0-based (a panel's "40001" is holding register 0).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from enum import StrEnum
from typing import Final, Literal

from supervisor.config import modbusmap
from supervisor.config.models import BenchConfig
from supervisor.tags import Access, TagDB

__all__ = ["REFUSALS", "STATUS_BITS", "Kind", "Point", "RegisterMap", "Table", "WordOrder", "plan"]

WordOrder = Literal["big", "little"]
"""A 32-bit float's two registers: ``big``, the high word first (Modbus's own byte order
within a word is always big-endian); ``little``, the low word first."""


class Table(StrEnum):
    """The four Modbus data tables (and the function codes that read and write them)."""

    COIL = "coil"  # FC 01 read, 05/15 write: booleans a client may write
    DISCRETE_INPUT = "discrete_input"  # FC 02: booleans a client reads
    HOLDING_REGISTER = "holding_register"  # FC 03 read, 06/16 write: setpoints, commands
    INPUT_REGISTER = "input_register"  # FC 04: measurements, states, status


class Kind(StrEnum):
    """How a point's value is encoded."""

    FLOAT32 = "float32"  # IEEE 754 in two registers, in the map's word order
    INT16 = "int16"  # a number × scale, rounded, two's complement
    UINT16 = "uint16"  # a number × scale, rounded
    BOOL = "bool"  # a coil or a discrete input
    CODE = "code"  # a text (a state's name) as its index in ``Point.codes``
    STATUS = "status"  # a channel's (or the bench's) status bits (``STATUS_BITS``)
    HEARTBEAT = "heartbeat"  # a counter that moves every scan (the supervisor alive)
    REFUSAL = "refusal"  # the reason code of the last refused write (``REFUSALS``)


STATUS_BITS: tuple[str, ...] = (
    "bad",  # bit 0: an input of the channel reads BAD (its registers hold the last value)
    "uncertain",  # bit 1: an input of the channel reads UNCERTAIN
    "tripped",  # bit 2: a safety trip is latched
    "unacked",  # bit 3: an alarm waits for its acknowledge
    "alive",  # bit 4: the supervisor scans (cleared when the scan stalls)
)
"""The status register's bits, bit 0 first: Modbus has no quality, so each channel (and the
bench) says it here; a read of a BAD value answers the last value and sets bit 0."""


REFUSALS: tuple[str, ...] = (
    "",  # 0: no write refused since the start
    "forbidden",  # 1: not a writer (modbus_server.writers), or the tag is read-only
    "refused",  # 2: not in this state, Auto/Manual, or an interlock (a trip, an alarm)
    "bad argument",  # 3: a value the tag does not take (a code not in its table, NaN)
    "out of range",  # 4: beyond the channel's hard limits
    "not found",  # 5: no such tag or channel on the command path
    "failed",  # 6: the command path failed (a refusal of any kind not named here)
    "closing",  # 7: the bench is going to its safe state (stopping)
    "timeout",  # 8: the bench's loop did not answer in time
)
"""The REFUSAL register's reason codes (code = index): the last write the command path
refused, as the command path's refusal kinds name them (docs/adr/0032-modbus-server.md)."""


@dataclass(frozen=True, slots=True)
class Point:
    """One tag (or one status, heartbeat or refusal register) at one address."""

    table: Table
    address: int  # 0-based PDU address
    kind: Kind
    tag: str  # the tag's name ("" for STATUS, HEARTBEAT and REFUSAL)
    channel: str = ""  # the channel it belongs to ("" for the bench)
    unit: str = ""
    scale: float = 1.0  # INT16/UINT16: raw = round(value × scale)
    writable: bool = False  # a write goes through the command path (``server``)
    codes: tuple[str, ...] = ()  # CODE: the text of each code (code = index)

    @property
    def words(self) -> int:
        """Registers (or bits) it takes."""
        return 2 if self.kind is Kind.FLOAT32 else 1


@dataclass(frozen=True)
class RegisterMap:
    points: tuple[Point, ...]
    word_order: WordOrder = "big"
    unit_id: int = 1

    def in_table(self, table: Table) -> Iterator[Point]:
        return (p for p in self.points if p.table is table)


DRIVE_STATES: Final = ("off", "idle", "charging", "discharging", "faulted")
"""A channel's ``state`` (its power stage, ``channels/channel.py``) by code."""
FAULT_ACTIONS: Final = ("", "hold", "abort")
"""A channel's ``fault_action`` by code ("" while no fault)."""
CHAIN_STATES: Final = (
    "Stopped",
    "",
    "Idle",
    "",
    "Running",
    "",
    "Complete",
    "Aborting",
    "Aborted",
    "Stopping",
    "",
    "",
    "",
    "",
    "Holding",
    "Held",
    "Resuming",
)
"""A channel's ``chain.state`` (a text) by its OPC UA (PackML) number, the number
``chain.state_code`` holds: ``chains/states.py::OPCUA_CODE`` written again (the publishers
may not import the chains; a test holds them equal; "" is no state)."""
FIXED_CODES: Final[dict[str, tuple[str, ...]]] = {
    "state": DRIVE_STATES,
    "fault_action": FAULT_ACTIONS,
    "chain.state": CHAIN_STATES,
}
"""Code tables by a channel field's suffix (the others: the tag's ``choices``)."""


def plan(cfg: BenchConfig, db: TagDB) -> RegisterMap:
    """The bench's register map (ADR 0031): the layout of ``config/modbusmap.py`` (a pure
    function of the I/O map: stable addresses), each point described by its tag in ``db``
    (unit, code table, whether a client may write it). A slot whose tag ``db`` does not
    have (a channel without an output switch has no ``output_cmd``) stays empty: nothing
    else moves. Raises ``ValueError`` when two points overlap (``supervisor check`` refuses
    such a map first)."""
    server = cfg.modbus_server
    points: list[Point] = []
    for s in modbusmap.layout(cfg):
        kind = Kind(s.kind)
        table = Table(s.table)
        if not s.tag:
            points.append(Point(table, s.address, kind, "", s.channel))
            continue
        tag = db.get(s.tag)
        if tag is None:
            continue
        spec = tag.spec
        codes: tuple[str, ...] = ()
        if kind is Kind.CODE:
            suffix = s.tag[len(s.channel) + 1 :] if s.channel else s.tag
            codes = FIXED_CODES.get(suffix) or tuple(spec.choices or ())
        writable = (
            table in (Table.COIL, Table.HOLDING_REGISTER) and spec.access is not Access.READ_ONLY
        )
        points.append(
            Point(table, s.address, kind, s.tag, s.channel, spec.unit, s.scale, writable, codes)
        )
    _refuse_overlaps(points)
    return RegisterMap(
        tuple(points),
        server.word_order if server is not None else "big",
        server.unit_id if server is not None else 1,
    )


def _refuse_overlaps(points: list[Point]) -> None:
    taken: dict[tuple[Table, int], Point] = {}
    for p in points:
        for a in range(p.address, p.address + p.words):
            other = taken.setdefault((p.table, a), p)
            if other is not p:
                raise ValueError(
                    f"Modbus map: {p.tag or p.kind.value} and {other.tag or other.kind.value}"
                    f" overlap at {p.table.value} {a}"
                )
