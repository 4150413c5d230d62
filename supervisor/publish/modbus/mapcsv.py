"""The register map as CSV (``supervisor modbus map IOMAP``): what panel-HMI and SCADA
tools import (ADR 0031).

One row per point, sorted by table then address::

    address,reference,function,type,word_order,tag,unit,scale,access,codes

``address`` is the PDU's, 0-based; ``reference`` the 6-digit form panels show (coil
000001, discrete input 100001, input register 300001, holding register 400001, each + the
address); ``function`` the codes that read (and write) it; ``type`` the point's kind;
``word_order`` a float's (big: high word first); ``access`` r or rw (rw only while
``modbus_server.writes`` is on); ``codes`` a code's table (``0=off; 1=idle …``) or a
status register's bits (``bit0=bad …``). A status,
heartbeat or refusal register has a name of its own in ``tag`` (``ch0.status``,
``bench.heartbeat``: names no tag can have).
"""

from __future__ import annotations

import csv
import io
from typing import Final

from supervisor.publish.modbus.regmap import STATUS_BITS, Kind, Point, RegisterMap, Table

__all__ = ["COLUMNS", "map_csv", "point_name"]

COLUMNS: Final = (
    "address",
    "reference",
    "function",
    "type",
    "word_order",
    "tag",
    "unit",
    "scale",
    "access",
    "codes",
)

REFERENCE_BASE: Final = {
    Table.COIL: 0,
    Table.DISCRETE_INPUT: 100001,
    Table.INPUT_REGISTER: 300001,
    Table.HOLDING_REGISTER: 400001,
}
"""The 6-digit references panels use (coils from 000001)."""
READ_FC: Final = {
    Table.COIL: "01",
    Table.DISCRETE_INPUT: "02",
    Table.HOLDING_REGISTER: "03",
    Table.INPUT_REGISTER: "04",
}
WRITE_FC: Final = {Table.COIL: "05 15", Table.HOLDING_REGISTER: "06 16"}
TABLE_ORDER: Final = (
    Table.COIL,
    Table.DISCRETE_INPUT,
    Table.INPUT_REGISTER,
    Table.HOLDING_REGISTER,
)
OWN_NAMES: Final = {Kind.STATUS: "status", Kind.HEARTBEAT: "heartbeat", Kind.REFUSAL: "refusal"}


def point_name(p: Point) -> str:
    """The tag's name, or the register's own (``ch0.status``, ``bench.heartbeat``)."""
    if p.tag:
        return p.tag
    return f"{p.channel or 'bench'}.{OWN_NAMES.get(p.kind, p.kind.value)}"


def _reference(p: Point) -> str:
    base = REFERENCE_BASE[p.table] or 1
    return f"{base + p.address:06d}"


def _codes(p: Point) -> str:
    if p.kind is Kind.STATUS:
        return "; ".join(f"bit{i}={b}" for i, b in enumerate(STATUS_BITS))
    return "; ".join(f"{n}={c or '(none)'}" for n, c in enumerate(p.codes) if c or n == 0)


def _row(p: Point, word_order: str, writes: bool) -> list[str]:
    numeric = p.kind in (Kind.FLOAT32, Kind.INT16, Kind.UINT16)
    writable = p.writable and writes
    function = READ_FC[p.table] + (f" {WRITE_FC[p.table]}" if writable else "")
    return [
        str(p.address),
        _reference(p),
        function,
        p.kind.value,
        word_order if p.kind is Kind.FLOAT32 else "",
        point_name(p),
        p.unit,
        f"{p.scale:g}" if numeric else "",
        "rw" if writable else "r",
        _codes(p),
    ]


def map_csv(m: RegisterMap, writes: bool = True) -> str:
    """The map as CSV text (a header row, then one row per point). ``writes``: the server
    takes writes (``modbus_server.writes``); off, every point reads ``r`` (a write would
    answer an exception), though the addresses stay the same."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(COLUMNS)
    for table in TABLE_ORDER:
        for p in sorted(m.in_table(table), key=lambda p: p.address):
            w.writerow(_row(p, m.word_order, writes))
    return out.getvalue()
