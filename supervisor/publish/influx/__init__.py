"""InfluxDB with store and forward (docs/adr/0012-influx-spool.md).

``InfluxWriter`` is a scan publisher and an event sink: the bench's tag changes
(``supervisor.publish.changes.ChangeFeed``) and events become line protocol
(``LineEncoder``, the schema in ``lineproto``), are appended to an on-disk spool
(``Spool``, ``<state_dir>/influx-spool.sqlite``) before anything is sent, and are deleted
from it only once InfluxDB acknowledged them (``Forwarder``). The composition root
(``supervisor.app.influx``) builds it from the I/O map's ``influxdb:`` section and puts its
``ALARMS`` on the alarm model.
"""

from supervisor.publish.influx.client import Failure, Reply, WriteClient
from supervisor.publish.influx.forward import Delivery, Forwarder, ForwarderStatus
from supervisor.publish.influx.lineproto import MEASUREMENTS, LineEncoder
from supervisor.publish.influx.spool import SPOOL_NAME, Batch, DeadLetter, Spool, SpoolCounts
from supervisor.publish.influx.writer import (
    ALARMS,
    AlarmHook,
    AlarmSpec,
    InfluxSettings,
    InfluxStatus,
    InfluxWriter,
)

__all__ = [
    "ALARMS",
    "MEASUREMENTS",
    "SPOOL_NAME",
    "AlarmHook",
    "AlarmSpec",
    "Batch",
    "DeadLetter",
    "Delivery",
    "Failure",
    "Forwarder",
    "ForwarderStatus",
    "InfluxSettings",
    "InfluxStatus",
    "InfluxWriter",
    "LineEncoder",
    "Reply",
    "Spool",
    "SpoolCounts",
    "WriteClient",
]
