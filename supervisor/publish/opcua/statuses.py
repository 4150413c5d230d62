"""Status codes: a tag's quality as OPC UA shows it, and a refused command as a client
gets it back (docs/adr/0014-opcua-server.md has both tables with their reasons).

A value never travels without its quality (ADR 0001): each (quality, reason) pair has one
status code, chosen from OPC UA Part 8 "DataAccess" where it has one (Bad_SensorFailure,
Bad_OutOfService, Uncertain_LastUsableValue, …) and from Part 4's generic codes otherwise.
A pair not in the table takes its quality's generic code (Good / Uncertain / Bad), so a
reason added later is never shown better than it is.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Final

from asyncua import ua

from supervisor.core.quality import Quality, Reason

S = ua.StatusCodes

QUALITY_STATUS: Final[Mapping[tuple[Quality, Reason], int]] = {
    (Quality.GOOD, Reason.NONE): S.Good,
    # ADR 0001: a forced tag stays GOOD and says so (Part 8 Good_LocalOverride).
    (Quality.GOOD, Reason.FORCED): S.GoodLocalOverride,
    (Quality.GOOD, Reason.CLAMPED): S.GoodClamped,
    (Quality.UNCERTAIN, Reason.INITIAL): S.UncertainInitialValue,
    (Quality.UNCERTAIN, Reason.LAST_KNOWN): S.UncertainLastUsableValue,
    (Quality.UNCERTAIN, Reason.STALE): S.UncertainLastUsableValue,
    (Quality.UNCERTAIN, Reason.NOT_CONNECTED): S.UncertainNoCommunicationLastUsableValue,
    (Quality.UNCERTAIN, Reason.COMM_FAILURE): S.UncertainNoCommunicationLastUsableValue,
    (Quality.UNCERTAIN, Reason.OUT_OF_RANGE): S.UncertainEngineeringUnitsExceeded,
    (Quality.UNCERTAIN, Reason.SENSOR_FAILURE): S.UncertainSensorNotAccurate,
    (Quality.UNCERTAIN, Reason.CLAMPED): S.UncertainEngineeringUnitsExceeded,
    (Quality.UNCERTAIN, Reason.DERIVED_FROM_BAD): S.UncertainSubNormal,
    (Quality.UNCERTAIN, Reason.FORCED): S.UncertainSubstituteValue,
    (Quality.UNCERTAIN, Reason.CONFIG_ERROR): S.UncertainConfigurationError,
    # Bad: the server publishes a null value with these (Part 4 §7.7.1).
    (Quality.BAD, Reason.INITIAL): S.BadWaitingForInitialData,
    (Quality.BAD, Reason.NOT_CONNECTED): S.BadNoCommunication,
    (Quality.BAD, Reason.COMM_FAILURE): S.BadCommunicationError,
    (Quality.BAD, Reason.STALE): S.Bad,
    (Quality.BAD, Reason.SENSOR_FAILURE): S.BadSensorFailure,
    (Quality.BAD, Reason.DEVICE_ERROR): S.BadDeviceFailure,
    (Quality.BAD, Reason.CONFIG_ERROR): S.BadConfigurationError,
    (Quality.BAD, Reason.OUT_OF_RANGE): S.BadOutOfRange,
    (Quality.BAD, Reason.LAST_KNOWN): S.BadNoCommunication,
    (Quality.BAD, Reason.DERIVED_FROM_BAD): S.Bad,
    (Quality.BAD, Reason.NOT_FITTED): S.BadOutOfService,
}

OUT_OF_SERVICE_REASONS: Final = frozenset({"disabled", "out of service"})
"""Reasons (by their text) that mean the source is switched off on purpose: Part 8
Bad_OutOfService, beside ``Reason.NOT_FITTED`` (no sensor on this bench) in the table."""

GENERIC: Final[Mapping[Quality, int]] = {
    Quality.GOOD: S.Good,
    Quality.UNCERTAIN: S.Uncertain,
    Quality.BAD: S.Bad,
}

NO_VALUE: Final = S.BadWaitingForInitialData
"""A GOOD or UNCERTAIN tag without a value (an ETA not estimated yet, an internal
resistance not measured yet): OPC UA refuses a null of a typed variable with a Good code."""


def quality_status(quality: Quality, reason: Reason) -> int:
    """The status code of a value of this quality and reason."""
    code = QUALITY_STATUS.get((quality, reason))
    if code is not None:
        return code
    if quality is Quality.BAD and str(reason) in OUT_OF_SERVICE_REASONS:
        return int(S.BadOutOfService)
    return GENERIC[quality]


REFUSAL_STATUS: Final[Mapping[str, int]] = {
    # Keyed by the command path's ``ResultKind`` values (supervisor/commands/model.py),
    # which this layer may not import (ADR 0003); tests check that every kind is here.
    "bad argument": S.BadInvalidArgument,
    "forbidden": S.BadUserAccessDenied,
    "not found": S.BadNotFound,
    "refused": S.BadInvalidState,
    "out of range": S.BadOutOfRange,  # beyond a channel's hard limits
    "invalid recipe": S.BadConfigurationError,
    "timeout": S.BadTimeout,
    "internal error": S.BadInternalError,
}
"""What a method call answers when the command path refuses it (with the reason as text in
its ``Result`` output argument)."""


def refusal_status(kind: str) -> int:
    return REFUSAL_STATUS.get(kind, S.Bad)
