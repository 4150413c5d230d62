"""A Sparkplug B edge node (Eclipse Sparkplug 3.0; docs/sparkplug.md, ADR 0051).

``SparkplugPublisher`` is a scan publisher: the bench's tag changes become NDATA (the
bench-level tags) and DDATA (one Sparkplug device per channel and per device), sent by its
own thread over MQTT (``PahoTransport``), after the NBIRTH and DBIRTHs of each connection
and of each rebirth request; the NDEATH is the will of each CONNECT, its ``bdSeq`` kept
across restarts (``RetainedBdSeq``). The composition root (``supervisor.app.sparkplug``)
builds it from the I/O map's ``sparkplug:`` section.
"""

from supervisor.publish.sparkplug.mqtt import PahoTransport, Transport
from supervisor.publish.sparkplug.node import BD_SEQ, NAMESPACE, REBIRTH, Layout, Message, Session
from supervisor.publish.sparkplug.payload import MetricValue, decode, encode, quality_code
from supervisor.publish.sparkplug.publisher import (
    BD_SEQ_KEY,
    BdSeqStore,
    MemoryBdSeq,
    RetainedBdSeq,
    SparkplugPublisher,
    SparkplugSettings,
)

__all__ = [
    "BD_SEQ",
    "BD_SEQ_KEY",
    "NAMESPACE",
    "REBIRTH",
    "BdSeqStore",
    "Layout",
    "MemoryBdSeq",
    "Message",
    "MetricValue",
    "PahoTransport",
    "RetainedBdSeq",
    "Session",
    "SparkplugPublisher",
    "SparkplugSettings",
    "Transport",
    "decode",
    "encode",
    "quality_code",
]
