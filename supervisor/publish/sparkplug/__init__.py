"""A Sparkplug B edge node (Eclipse Sparkplug 3.0; docs/sparkplug.md, ADR 0051).

``SparkplugPublisher`` is a scan publisher: the bench's tag changes become NDATA (the
bench-level tags) and DDATA (one Sparkplug device per channel and per device), sent by its
own thread over MQTT (``PahoTransport``), after the NBIRTH and DBIRTHs of each connection
and of each rebirth request; what could not be sent waits on disk (``SampleSpool``) and is
replayed after the next births, flagged historical; the NDEATH is the will of each CONNECT,
its ``bdSeq`` kept across restarts (``RetainedBdSeq``). The composition root
(``supervisor.app.sparkplug``) builds it from the I/O map's ``sparkplug:`` section.
"""

from supervisor.publish.sparkplug.commands import (
    CommandHandler,
    CommandSettings,
    Reply,
)
from supervisor.publish.sparkplug.mqtt import PahoTransport, Transport
from supervisor.publish.sparkplug.node import BD_SEQ, NAMESPACE, REBIRTH, Layout, Message, Session
from supervisor.publish.sparkplug.payload import MetricValue, decode, encode, quality_code
from supervisor.publish.sparkplug.publisher import (
    ALARM_DISCONNECTED,
    ALARM_SPOOL_FULL,
    ALARMS,
    BD_SEQ_KEY,
    AlarmHook,
    AlarmSpec,
    BdSeqStore,
    MemoryBdSeq,
    RetainedBdSeq,
    SparkplugPublisher,
    SparkplugSettings,
)
from supervisor.publish.sparkplug.spool import SPOOL_NAME, SampleSpool

__all__ = [
    "ALARMS",
    "ALARM_DISCONNECTED",
    "ALARM_SPOOL_FULL",
    "BD_SEQ",
    "BD_SEQ_KEY",
    "NAMESPACE",
    "REBIRTH",
    "SPOOL_NAME",
    "AlarmHook",
    "AlarmSpec",
    "BdSeqStore",
    "CommandHandler",
    "CommandSettings",
    "Layout",
    "MemoryBdSeq",
    "Message",
    "MetricValue",
    "PahoTransport",
    "Reply",
    "RetainedBdSeq",
    "SampleSpool",
    "Session",
    "SparkplugPublisher",
    "SparkplugSettings",
    "Transport",
    "decode",
    "encode",
    "quality_code",
]
