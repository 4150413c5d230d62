"""The fleet's picture of a Sparkplug B group, without the network (Eclipse Sparkplug 3.0,
chapter 7 "host applications"; docs/fleet.md).

``Fleet.receive`` takes each message of ``spBv1.0/<group>/#`` as it arrives and keeps, per
edge node (a bench), its last NBIRTH and each device's last DBIRTH (a channel or a device
of the bench: docs/adr/0052), with the NDATA/DDATA applied by metric name onto them. It
answers the edge nodes a rebirth must be asked of:

- a message whose ``seq`` is not the one after the node's previous message (0–255, then 0):
  something was lost between the node and us, the picture is wrong until a new birth;
- data or a DBIRTH from a node whose NBIRTH we never saw (the fleet started after it), a
  DDATA of a device without its DBIRTH, a metric the birth did not announce.

A rebirth is asked once per node until its NBIRTH comes (again after ``REBIRTH_RETRY_MS``
if none does). An NDEATH marks its node offline only when its ``bdSeq`` is the one of the
NBIRTH we hold: the late will of an older session (a bench restarted before the broker
noticed the old connection was gone) says nothing of the current one.

The clock is the caller's (``now_ms``, Unix ms): the tests run without one.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Final

from google.protobuf.message import DecodeError

from supervisor.publish.sparkplug.node import BD_SEQ, NAMESPACE, SEQ_MODULO
from supervisor.publish.sparkplug.payload import decode

__all__ = ["REBIRTH_RETRY_MS", "Device", "Fleet", "Node"]

log = logging.getLogger(__name__)

REBIRTH_RETRY_MS: Final = 10_000
"""A rebirth asked and no NBIRTH since: ask again after this long (the NCMD was lost, or
the node was busy reconnecting)."""

# Sparkplug integer datatypes (Int8…Int64): sent as two's complement in an unsigned field.
_SIGNED_BITS: Final = {1: 8, 2: 16, 3: 32, 4: 64}
URL_METRIC: Final = "hmi.url"
"""A node metric (String) with the URL of the bench's own screens, if the bench publishes one."""
ALARMS_METRIC: Final = "alarms.active"
"""A node metric (integer) with the bench's active alarms, if the bench publishes one."""


@dataclass(slots=True)
class Device:
    """A Sparkplug device of a node (a channel or a device of the bench)."""

    online: bool
    since_ms: int
    metrics: dict[str, Any] = field(default_factory=dict)
    datatypes: dict[str, int] = field(default_factory=dict)


@dataclass(slots=True)
class Node:
    """An edge node (a bench) as its births, data and death told it."""

    online: bool
    since_ms: int
    bd_seq: int | None = None
    next_seq: int | None = None
    """The ``seq`` the next message must have (None: no birth held)."""
    metrics: dict[str, Any] = field(default_factory=dict)
    datatypes: dict[str, int] = field(default_factory=dict)
    devices: dict[str, Device] = field(default_factory=dict)
    rebirth_asked_ms: int | None = None
    """When a rebirth was asked and no NBIRTH came since (None: none outstanding)."""
    rebirths: int = 0
    seq_gaps: int = 0
    born: bool = True
    """False for a node heard of only by its data (a rebirth asked, no NBIRTH seen yet)."""


def _value(metric: Any, datatype: int | None) -> Any:
    if metric.is_null:
        return None
    which = metric.WhichOneof("value")
    if which is None:
        return None
    value = getattr(metric, which)
    bits = _SIGNED_BITS.get(datatype or 0)
    if bits is not None and isinstance(value, int) and value >= 1 << (bits - 1):
        value -= 1 << bits  # two's complement (chapter 6)
    return value


class Fleet:
    """Every edge node of one group (thread-safe: the MQTT thread writes, the server reads)."""

    def __init__(self, group: str) -> None:
        self.group = group
        self.nodes: dict[str, Node] = {}
        self.lock = threading.Lock()
        self.undecodable = 0

    # --- messages ---------------------------------------------------------------------
    def receive(self, topic: str, payload: bytes, now_ms: int) -> list[str]:
        """Apply one message; the edge nodes to ask for a rebirth now."""
        parts = topic.split("/")
        if len(parts) not in (4, 5) or parts[0] != NAMESPACE or parts[1] != self.group:
            return []  # STATE, another group: not ours
        verb, edge = parts[2], parts[3]
        device = parts[4] if len(parts) == 5 else None
        if verb in ("NCMD", "DCMD"):
            return []  # a host application's commands (ours among them)
        try:
            p = decode(payload)
        except DecodeError as exc:
            self.undecodable += 1
            log.warning("fleet: %s: not a Sparkplug payload (%s)", topic, exc)
            return []
        with self.lock:
            ok = self._apply(verb, edge, device, p, now_ms)
            return [] if ok else self._ask_rebirth(edge, now_ms)

    def _apply(self, verb: str, edge: str, device: str | None, p: Any, now_ms: int) -> bool:
        """False: the picture of ``edge`` is wrong until its next birth."""
        if verb == "NBIRTH":
            self._nbirth(edge, p, now_ms)
            return True
        if verb == "NDEATH":
            self._ndeath(edge, p, now_ms)
            return True
        node = self.nodes.get(edge)
        if node is None or node.next_seq is None or not node.online:
            return False  # data of a node we have no birth of
        if not self._in_sequence(edge, node, p):
            return False
        if verb == "NDATA":
            return _merge(node.metrics, node.datatypes, p.metrics)
        if device is None:
            return True  # an unknown verb without a device: nothing to keep
        if verb == "DBIRTH":
            dev = node.devices[device] = Device(True, now_ms)
            _birth_metrics(dev.metrics, dev.datatypes, p.metrics)
            return True
        dev_or_none = node.devices.get(device)
        if verb == "DDEATH":
            if dev_or_none is not None:
                dev_or_none.online, dev_or_none.since_ms = False, now_ms
            return True
        if verb == "DDATA":
            if dev_or_none is None or not dev_or_none.online:
                return False
            return _merge(dev_or_none.metrics, dev_or_none.datatypes, p.metrics)
        return True

    def _in_sequence(self, edge: str, node: Node, p: Any) -> bool:
        expected = node.next_seq
        seq = p.seq if p.HasField("seq") else None
        if seq is None or seq != expected:
            node.seq_gaps += 1
            node.next_seq = None  # nothing after a gap is applied before the next birth
            log.warning("fleet: %s: seq %s where %s was due: rebirth", edge, seq, expected)
            return False
        node.next_seq = (seq + 1) % SEQ_MODULO
        return True

    def _nbirth(self, edge: str, p: Any, now_ms: int) -> None:
        metrics: dict[str, Any] = {}
        datatypes: dict[str, int] = {}
        _birth_metrics(metrics, datatypes, p.metrics)
        bd_seq = metrics.get(BD_SEQ)
        seq = p.seq if p.HasField("seq") else 0
        old = self.nodes.get(edge)
        since = old.since_ms if old is not None and old.online else now_ms
        node = Node(True, since, bd_seq if isinstance(bd_seq, int) else None)
        node.next_seq = (seq + 1) % SEQ_MODULO
        node.metrics, node.datatypes = metrics, datatypes
        if old is not None:
            node.rebirths, node.seq_gaps = old.rebirths, old.seq_gaps
        self.nodes[edge] = node
        log.info("fleet: %s born (bdSeq %s)", edge, node.bd_seq)

    def _ndeath(self, edge: str, p: Any, now_ms: int) -> None:
        node = self.nodes.get(edge)
        bd_seq = next((_value(m, m.datatype) for m in p.metrics if m.name == BD_SEQ), None)
        if node is None or not node.online:
            return
        if node.bd_seq is not None and bd_seq != node.bd_seq:
            log.info("fleet: %s: NDEATH of bdSeq %s ignored (born %s)", edge, bd_seq, node.bd_seq)
            return
        node.online, node.since_ms, node.next_seq = False, now_ms, None
        node.rebirth_asked_ms = None
        for dev in node.devices.values():
            if dev.online:
                dev.online, dev.since_ms = False, now_ms
        log.info("fleet: %s dead (bdSeq %s)", edge, bd_seq)

    def _ask_rebirth(self, edge: str, now_ms: int) -> list[str]:
        node = self.nodes.setdefault(edge, Node(False, now_ms, born=False))
        asked = node.rebirth_asked_ms
        if asked is not None and now_ms - asked < REBIRTH_RETRY_MS:
            return []
        node.rebirth_asked_ms = now_ms
        node.rebirths += 1
        return [edge]

    def all_nodes(self) -> list[str]:
        """Every node known (a reconnected fleet asks them all for a rebirth)."""
        with self.lock:
            return list(self.nodes)


def _birth_metrics(
    values: dict[str, Any], datatypes: dict[str, int], metrics: Iterable[Any]
) -> None:
    for m in metrics:
        datatypes[m.name] = m.datatype
        values[m.name] = _value(m, m.datatype)


def _merge(values: dict[str, Any], datatypes: dict[str, int], metrics: Iterable[Any]) -> bool:
    """Data by name onto the birth's metrics; False for a metric the birth did not have."""
    known = True
    for m in metrics:
        if m.name not in datatypes:
            known = False
            continue
        values[m.name] = _value(m, datatypes[m.name])
    return known
