"""Quality of a value: how bad (severity) is kept apart from why (reason).

Follows the OPC UA / Ignition convention (see docs/adr/0001-quality-model.md):
GOOD, UNCERTAIN, BAD, each with a reason such as comm failure or stale.
"""

from __future__ import annotations

from enum import IntEnum, StrEnum


class Quality(IntEnum):
    """Severity, ordered so that ``max()`` of inputs gives the worst one."""

    GOOD = 0
    UNCERTAIN = 1
    BAD = 2


class Reason(StrEnum):
    """Why a value has the quality it has."""

    NONE = "none"
    INITIAL = "initial value"
    NOT_CONNECTED = "not connected"
    COMM_FAILURE = "comm failure"
    STALE = "stale"
    OUT_OF_RANGE = "out of range"
    SENSOR_FAILURE = "sensor failure"
    FORCED = "forced"
    CLAMPED = "clamped to limit"
    CONFIG_ERROR = "configuration error"
    DEVICE_ERROR = "device error"
    LAST_KNOWN = "last known value"
    DERIVED_FROM_BAD = "derived from bad input"
    NOT_FITTED = "not fitted"
    """The bench has no sensor for it (a Chadèche board measures no temperature unless the
    I/O map names a tag read elsewhere): BAD for every reader, but nothing is wrong —
    OPC UA Bad_OutOfService, shown grey as "n/a" by the screens, never an alarm colour."""
