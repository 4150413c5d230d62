"""The registers a Modbus client reads: an image of the tags, encoded on the server's side.

The scan never encodes a register: it keeps its copy of its changes by reference
(``ModbusFeed.on_scan``, ADR 0032) and the server's thread applies them here when a
request comes in (or at its drain period), so a client that polls a thousand registers
every 10 ms costs the scan the append of a batch, whatever it reads.

Quality without a status code (Modbus has none): a BAD value's registers keep the last
value and its channel's STATUS register sets bit 0 (``regmap.STATUS_BITS``); never a
silent stale number. The STATUS, HEARTBEAT and REFUSAL registers are computed at the read.
"""

from __future__ import annotations

import math
import struct
from array import array
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from supervisor.core.driver import Value
from supervisor.core.quality import Quality, Reason
from supervisor.publish.changes import ChangeBatch
from supervisor.publish.modbus.regmap import STATUS_BITS, Kind, Point, RegisterMap, Table

__all__ = ["Decoded", "RegisterImage", "decode", "encode"]

SPACE = 65536
"""Addresses in each table (the PDU's 16-bit address)."""
NOT_A_CODE = 0xFFFF
"""A CODE register whose text is not in the point's table (documented in the CSV)."""

_BAD = Quality.BAD
_UNCERTAIN = Quality.UNCERTAIN
_NOT_FITTED = Reason.NOT_FITTED
BIT = {name: 1 << i for i, name in enumerate(STATUS_BITS)}


class Decoded(ValueError):
    """A written raw value that is not a value of its point (exception 03)."""


def encode(point: Point, value: Value | None, word_order: str) -> tuple[int, ...] | None:
    """The register words (or the bit, 0/1) of ``value`` at ``point``; None when it has no
    encoding (None, a text where a number is wanted): the registers keep what they hold."""
    kind = point.kind
    if value is None:
        return None
    if kind is Kind.BOOL:
        return (1 if value else 0,)
    if kind is Kind.CODE:
        if isinstance(value, int) and not isinstance(value, bool):
            # A tag that holds its code already (``chain.state_code``: the PackML number).
            return (value,) if 0 <= value < len(point.codes) else (NOT_A_CODE,)
        text = str(value)
        try:
            return (point.codes.index(text),)
        except ValueError:
            return (NOT_A_CODE,)
    if isinstance(value, str):
        return None
    x = float(value)
    if kind is Kind.FLOAT32:
        hi, lo = struct.unpack(">HH", struct.pack(">f", x))
        return (hi, lo) if word_order == "big" else (lo, hi)
    if kind is Kind.INT16 or kind is Kind.UINT16:
        if math.isnan(x):
            return None
        raw = round(x * point.scale) if math.isfinite(x) else (1 << 20 if x > 0 else -(1 << 20))
        if kind is Kind.INT16:
            return (max(-32768, min(32767, raw)) & 0xFFFF,)
        return (max(0, min(65535, raw)),)
    return None


def decode(point: Point, words: tuple[int, ...], word_order: str) -> Value:
    """The value a client wrote as ``words`` at ``point`` (``Decoded`` when it is none)."""
    kind = point.kind
    if kind is Kind.BOOL:
        return bool(words[0])
    if kind is Kind.CODE:
        if words[0] >= len(point.codes):
            raise Decoded(f"{point.tag}: code {words[0]} is not in its table")
        return point.codes[words[0]]
    if kind is Kind.FLOAT32:
        hi, lo = words if word_order == "big" else (words[1], words[0])
        x: float = struct.unpack(">f", struct.pack(">HH", hi, lo))[0]
        if not math.isfinite(x):
            raise Decoded(f"{point.tag}: {x} is not a number it takes")
        return x
    if kind is Kind.INT16:
        raw = words[0] - 0x10000 if words[0] & 0x8000 else words[0]
        return raw / point.scale
    if kind is Kind.UINT16:
        return words[0] / point.scale
    raise Decoded(f"{point.tag}: a {kind.value} register is not written")


def _blank(table: Table) -> array:  # type: ignore[type-arg]
    """A table's values, all 0: bytes for the bits, 16-bit words for the registers."""
    if table in (Table.COIL, Table.DISCRETE_INPUT):
        return array("B", bytes(SPACE))
    return array("H", bytes(2 * SPACE))


@dataclass
class _Table:
    values: array  # type: ignore[type-arg]  # 'H' for registers, 'B' for bits
    served: bytearray = field(default_factory=lambda: bytearray(SPACE))
    """1 where an address belongs to a point: a read beyond is exception 02."""
    start: dict[int, Point] = field(default_factory=dict)  # a point by its first address
    owner: dict[int, Point] = field(default_factory=dict)  # a point by any of its addresses


class RegisterImage:
    """The four tables of ``regmap`` with the tags' latest encoded values. Used from the
    server's thread only (the scan hands it batches through ``ModbusFeed``)."""

    def __init__(self, regmap: RegisterMap) -> None:
        self.map = regmap
        self.word_order = regmap.word_order
        self.tables = {t: _Table(_blank(t)) for t in Table}
        self._by_tag: dict[str, list[Point]] = {}
        self._computed: dict[Table, list[Point]] = {t: [] for t in Table}
        self._inputs: dict[str, str] = {}  # tag → its channel, for the quality bits
        self._bad: dict[str, set[str]] = {}  # channel → its tags reading BAD
        self._uncertain: dict[str, set[str]] = {}
        for p in regmap.points:
            table = self.tables[p.table]
            for a in range(p.address, p.address + p.words):
                table.served[a] = 1
                table.owner[a] = p
            table.start[p.address] = p
            if p.kind in (Kind.STATUS, Kind.HEARTBEAT, Kind.REFUSAL):
                self._computed[p.table].append(p)
            else:
                self._by_tag.setdefault(p.tag, []).append(p)
                if not p.writable:  # a measurement: its quality is its channel's
                    self._inputs[p.tag] = p.channel
        self.heartbeat = 0
        self.alive = False
        self.refusal = 0
        self.flags: dict[str, int] = {}  # channel ("" bench) → tripped/unacked bits

    # --- the tags ---------------------------------------------------------------------------
    def apply(self, batches: Iterable[ChangeBatch]) -> None:
        """The changes of ``batches``, oldest first, into the registers."""
        by_tag, order = self._by_tag, self.word_order
        for b in batches:
            for tag, value, quality, reason, _, _ in b.changes:
                name = tag.spec.name
                points = by_tag.get(name)
                if points is None:
                    continue
                self._quality(name, quality, reason)
                if quality is _BAD:
                    continue  # the last value stays, its channel's bit 0 says so
                for p in points:
                    self.put(p, encode(p, value, order))

    def load(self, values: Mapping[str, tuple[Value | None, Quality, Reason]]) -> None:
        """Every tag's value, quality and reason at once (the server's start)."""
        order = self.word_order
        for name, points in self._by_tag.items():
            if name not in values:
                continue
            value, quality, reason = values[name]
            self._quality(name, quality, reason)
            if quality is not _BAD:
                for p in points:
                    self.put(p, encode(p, value, order))

    def put(self, p: Point, words: tuple[int, ...] | None) -> None:
        if words is None:
            return
        values = self.tables[p.table].values
        for i, w in enumerate(words):
            values[p.address + i] = w

    def _quality(self, name: str, quality: Quality, reason: Reason) -> None:
        channel = self._inputs.get(name)
        if channel is None:
            return
        bad = self._bad.setdefault(channel, set())
        uncertain = self._uncertain.setdefault(channel, set())
        bad.discard(name)
        uncertain.discard(name)
        if quality is _BAD:
            # A sensor this bench does not have (a channel without a thermocouple) is no
            # fault: it would hold the bit for good and hide every real BAD input.
            if reason is not _NOT_FITTED:
                bad.add(name)
        elif quality is _UNCERTAIN:
            uncertain.add(name)

    # --- the reads --------------------------------------------------------------------------
    def status(self, channel: str) -> int:
        """A channel's (or, "", the bench's) STATUS register (``regmap.STATUS_BITS``)."""
        bits = self.flags.get(channel, 0)
        if channel:
            bits |= self.flags.get("", 0) & BIT["tripped"]  # a bench trip holds every channel
        if self._bad.get(channel) or (not channel and any(self._bad.values())):
            bits |= BIT["bad"]
        if self._uncertain.get(channel) or (not channel and any(self._uncertain.values())):
            bits |= BIT["uncertain"]
        if self.alive:
            bits |= BIT["alive"]
        return bits

    def served(self, table: Table, address: int, count: int) -> bool:
        """Every address of the range belongs to a point."""
        if address < 0 or address + count > SPACE:
            return False
        return self.tables[table].served.count(0, address, address + count) == 0

    def read(self, table: Table, address: int, count: int) -> list[int]:
        """The range's words (or bits); ``served`` first."""
        t = self.tables[table]
        for p in self._computed[table]:
            if address <= p.address < address + count:
                t.values[p.address] = self._computed_value(p)
        return t.values[address : address + count].tolist()

    def _computed_value(self, p: Point) -> int:
        if p.kind is Kind.STATUS:
            return self.status(p.channel)
        if p.kind is Kind.HEARTBEAT:
            return self.heartbeat & 0xFFFF
        return self.refusal

    def points_in(self, table: Table, address: int, count: int) -> list[Point] | None:
        """The whole points the range covers, in order; None when it cuts one (a write of
        half a float) or covers an address of none."""
        t = self.tables[table]
        out: list[Point] = []
        a, end = address, address + count
        while a < end:
            p = t.start.get(a)
            if p is None or a + p.words > end:
                return None
            out.append(p)
            a += p.words
        return out
