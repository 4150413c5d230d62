"""The embedded historian: every tag's changes and the bench's events in one SQLite file.

The default store of history when no InfluxDB is configured (docs/design.md "Publishing";
docs/adr/0013-historian.md). ``Historian`` is the scan publisher and event sink (it only
queues); one writer thread owns the file (WAL, one transaction per commit interval,
retention by age and size in bounded chunks); ``HistoryQuery`` reads it for the HTTP API,
OPC UA HistoryRead and the screens' trends.
"""

from supervisor.publish.historian.publisher import (
    ALARMS,
    CORRUPT_ALARM,
    CRASH_ALARM,
    OVERFLOW_ALARM,
    WRITE_ALARM,
    AlarmHook,
    Historian,
    writer_settings,
)
from supervisor.publish.historian.query import (
    EVENT_KINDS,
    MAX_BUCKETS,
    MAX_RAW_ROWS,
    Aggregate,
    BadRange,
    Bucket,
    HistoryQuery,
    Series,
    StoredEvent,
    StoredSample,
    UnknownTag,
    bucket_count,
    check_interval,
    check_range,
)
from supervisor.publish.historian.store import HISTORY_NAME, SetAside, TagInfo
from supervisor.publish.historian.writer import HistoryWriter, OpenReport, WriterSettings

__all__ = [
    "ALARMS",
    "CORRUPT_ALARM",
    "CRASH_ALARM",
    "EVENT_KINDS",
    "HISTORY_NAME",
    "MAX_BUCKETS",
    "MAX_RAW_ROWS",
    "OVERFLOW_ALARM",
    "WRITE_ALARM",
    "Aggregate",
    "AlarmHook",
    "BadRange",
    "Bucket",
    "Historian",
    "HistoryQuery",
    "HistoryWriter",
    "OpenReport",
    "Series",
    "SetAside",
    "StoredEvent",
    "StoredSample",
    "TagInfo",
    "UnknownTag",
    "WriterSettings",
    "bucket_count",
    "check_interval",
    "check_range",
    "writer_settings",
]
