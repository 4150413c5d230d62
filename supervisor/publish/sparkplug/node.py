"""An edge node's Sparkplug session, without the network: which messages, on which topics,
with which sequence numbers (Sparkplug 3.0, chapters 4 and 5).

The bench is one edge node (``spBv1.0/<group>/NBIRTH/<edge node>``): its bench-level tags
(``scan.*``, ``bench.*``, ``alarms.*``…) are the node's metrics, beside ``bdSeq`` and
``Node Control/Rebirth``. Each channel and each device is a Sparkplug device
(``.../DBIRTH/<edge node>/<channel or device>``) whose metrics are its tags, named without
the ``<channel>.`` or ``<device>.`` prefix. ``seq`` counts every message of a session but
the death, 0 to 255 and round again; a birth sequence starts it at 0. ``bdSeq`` is given
by the caller (it survives restarts: ``publisher``).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Final, NamedTuple

from supervisor.core.driver import DType, Value
from supervisor.core.quality import Quality
from supervisor.publish.sparkplug.payload import (
    BOOLEAN,
    INT64,
    SPARKPLUG_TYPES,
    MetricValue,
    encode,
    quality_code,
)

__all__ = [
    "BD_SEQ",
    "NAMESPACE",
    "REBIRTH",
    "Layout",
    "Message",
    "Metric",
    "Session",
    "is_rebirth",
]

NAMESPACE: Final = "spBv1.0"
BD_SEQ: Final = "bdSeq"
REBIRTH: Final = "Node Control/Rebirth"
SEQ_MODULO: Final = 256


class Message(NamedTuple):
    topic: str
    payload: bytes
    qos: int  # births and data 0, the death (the will) 1: chapter 5


class Metric(NamedTuple):
    """A tag's latest state, as the edge node keeps it for its births."""

    dtype: DType
    unit: str
    value: Value | None
    quality: Quality
    wall_ms: int  # acquisition time, Unix ms


@dataclass(frozen=True, slots=True)
class Layout:
    """Where a tag goes: the node (``device`` None) or a device, and its metric name."""

    channels: tuple[str, ...]
    devices: tuple[str, ...]
    excluded_prefixes: tuple[str, ...] = ("sparkplug.",)
    """The edge node's own diagnostics: they change with every message it sends, so
    publishing them would publish forever."""

    def place(self, tag: str) -> tuple[str | None, str] | None:
        """(device id or None for the node, metric name); None: not published."""
        if tag.startswith(self.excluded_prefixes):
            return None
        head, dot, rest = tag.partition(".")
        if dot and (head in self.channels or head in self.devices):
            return head, rest
        return None, tag

    @property
    def device_ids(self) -> tuple[str, ...]:
        """Every device, channels first (a name both would be is the channel)."""
        return self.channels + tuple(d for d in self.devices if d not in self.channels)


def _metric(name: str, m: Metric, *, unit: bool, historical: bool = False) -> MetricValue:
    return MetricValue(
        name,
        SPARKPLUG_TYPES[m.dtype],
        None if m.quality is Quality.BAD else m.value,
        m.wall_ms,
        quality_code(m.quality),
        m.unit if unit else "",
        historical,
    )


class Session:
    """The messages of one edge node: births, data, death."""

    def __init__(self, group: str, edge_node: str, layout: Layout) -> None:
        self.group = group
        self.edge_node = edge_node
        self.layout = layout
        self.seq = 0
        self.born: set[str] = set()
        """The tags announced by the last birth sequence: a tag outside it needs a rebirth."""

    def topic(self, verb: str, device: str | None = None) -> str:
        base = f"{NAMESPACE}/{self.group}/{verb}/{self.edge_node}"
        return base if device is None else f"{base}/{device}"

    @property
    def ncmd_topic(self) -> str:
        return self.topic("NCMD")

    def _next_seq(self) -> int:
        seq = self.seq
        self.seq = (seq + 1) % SEQ_MODULO
        return seq

    def death(self, bd_seq: int, now_ms: int) -> Message:
        """NDEATH: the will of a connection (and what a clean stop publishes itself)."""
        bd = MetricValue(BD_SEQ, INT64, bd_seq, now_ms)
        return Message(self.topic("NDEATH"), encode(now_ms, [bd], None), 1)

    def births(self, bd_seq: int, metrics: dict[str, Metric], now_ms: int) -> list[Message]:
        """NBIRTH then one DBIRTH per device, every metric with its current value, type,
        unit and quality; ``seq`` starts again at 0."""
        self.seq = 0
        node: list[MetricValue] = [
            MetricValue(BD_SEQ, INT64, bd_seq, now_ms),
            MetricValue(REBIRTH, BOOLEAN, False, now_ms),
        ]
        devices: dict[str, list[MetricValue]] = {d: [] for d in self.layout.device_ids}
        born: set[str] = set()
        for tag, m in metrics.items():
            where = self.layout.place(tag)
            if where is None:
                continue
            device, name = where
            born.add(tag)
            (node if device is None else devices[device]).append(_metric(name, m, unit=True))
        self.born = born
        out = [Message(self.topic("NBIRTH"), encode(now_ms, node, self._next_seq()), 0)]
        for device, device_metrics in devices.items():
            payload = encode(now_ms, device_metrics, self._next_seq())
            out.append(Message(self.topic("DBIRTH", device), payload, 0))
        return out

    def needs_birth(self, tags: Iterable[str]) -> bool:
        """Some tag that is published was not in the last birth (added since)."""
        born, place = self.born, self.layout.place
        return any(t not in born and place(t) is not None for t in tags)

    def data(self, changes: Sequence[tuple[str, Metric]], now_ms: int) -> list[Message]:
        """NDATA and one DDATA per device that changed: every change in ``changes`` (in
        order: a tag that changed twice is in twice, each with its own timestamp)."""
        return [message for message, _ in self.data_parts(changes, now_ms)]

    def data_parts(
        self, changes: Sequence[tuple[str, Metric]], now_ms: int, *, historical: bool = False
    ) -> list[tuple[Message, list[tuple[str, Metric]]]]:
        """``data``, each message with the changes it carries (what to keep when it cannot
        be sent). ``historical``: each metric flagged ``is_historical`` (Sparkplug 3.0: data
        that is not the current value, a store-and-forward replay)."""
        node: list[tuple[str, Metric]] = []
        devices: dict[str, list[tuple[str, Metric]]] = {}
        place = self.layout.place
        for tag, m in changes:
            where = place(tag)
            if where is None:
                continue
            device = where[0]
            (node if device is None else devices.setdefault(device, [])).append((tag, m))
        groups: list[tuple[str | None, list[tuple[str, Metric]]]] = [(None, node)] if node else []
        groups.extend(devices.items())
        out: list[tuple[Message, list[tuple[str, Metric]]]] = []
        for device, group in groups:
            metrics = [
                _metric(self._name(tag), m, unit=False, historical=historical) for tag, m in group
            ]
            payload = encode(now_ms, metrics, self._next_seq())
            verb = "NDATA" if device is None else "DDATA"
            out.append((Message(self.topic(verb, device), payload, 0), group))
        return out

    def _name(self, tag: str) -> str:
        where = self.layout.place(tag)
        assert where is not None
        return where[1]


def is_rebirth(payload: Any) -> bool:
    """An NCMD payload asks for a rebirth: a 'Node Control/Rebirth' metric set to true."""
    return any(m.name == REBIRTH and m.boolean_value for m in payload.metrics)
