"""The timestamps of a value as a client gets them (OPC UA Part 4 §7.11, §7.40).

**TimestampsToReturn** (Read, CreateMonitoredItems, ModifyMonitoredItems): Source, Server,
Both or Neither; a timestamp not asked for is not sent (with its picoseconds). asyncua
sends both whatever was asked: ``returned`` makes the answer. A SourceTimestamp belongs
to the Value attribute only (§7.11): other attributes never carry one. Invalid (4) is the
service's fault Bad_TimestampsToReturnInvalid (§5.10.2).

**ServerTimestamp** (§7.11): "the time the Server received a Variable value or knew it to
be accurate" — Part 4's own example is a server that gets a value only when it changes
and, not hearing otherwise, stamps it afresh: its silence means the value still holds. The
bench's server is such a server: the scan reads the devices every scan and hands the
server every change once per sampling interval (feed.py); a tag it did not hand over is
unchanged *as of that hand-over*. So a tag variable's ServerTimestamp is the latest of
its change's time and the last hand-over's (``Freshness``): a value unchanged for minutes
read while the scan runs is seconds old at most, not minutes. The SourceTimestamp stays
the time the value last changed at its source (§7.11: "should indicate the time of the
last change of the value or statusCode"). A BAD value's ServerTimestamp moves the same
way: the scan retried its device at that time (§7.11: "the time the Server last tried to
recover"). Nothing is written into the address space for this: a Read answers with the
fresher stamp, as does the first notification of a monitored item; a newer
ServerTimestamp alone is no data change (§7.10), so the rest of the notifications are
the changes' own.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Container, Sequence
from datetime import UTC, datetime
from typing import Final

from asyncua import ua
from asyncua.common.utils import ServiceError

TTR = ua.TimestampsToReturn
SOURCE: Final = frozenset({TTR.Source, TTR.Both})
SERVER: Final = frozenset({TTR.Server, TTR.Both})
VALUE: Final = ua.AttributeIds.Value


def check(ttr: object) -> ua.TimestampsToReturn:
    """The request's TimestampsToReturn, or the service fault for an invalid one."""
    try:
        wanted = TTR(int(ttr))  # type: ignore[call-overload]
    except (TypeError, ValueError):
        raise ServiceError(ua.StatusCodes.BadTimestampsToReturnInvalid) from None
    if wanted == TTR.Invalid:
        raise ServiceError(ua.StatusCodes.BadTimestampsToReturnInvalid)
    return wanted


def returned(
    dv: ua.DataValue, ttr: ua.TimestampsToReturn, value_attribute: bool = True
) -> ua.DataValue:
    """``dv`` with the timestamps ``ttr`` asks for (a new DataValue: the address space's
    own is shared by every reader)."""
    source = value_attribute and ttr in SOURCE
    server = ttr in SERVER
    drop_source = not source and (dv.SourceTimestamp is not None or dv.SourcePicoseconds)
    drop_server = not server and (dv.ServerTimestamp is not None or dv.ServerPicoseconds)
    if not drop_source and not drop_server:
        return dv
    changes: dict[str, object] = {}
    if drop_source:
        changes.update(SourceTimestamp=None, SourcePicoseconds=None)
    if drop_server:
        changes.update(ServerTimestamp=None, ServerPicoseconds=None)
    return dataclasses.replace(dv, **changes)


class Freshness:
    """When the server last heard from the scan: the ServerTimestamp of every tag variable
    that has not changed since (``stamp``)."""

    def __init__(self, tags: Container[ua.NodeId]) -> None:
        self.tags = tags
        self.known: datetime | None = None

    def heard(self, when: datetime | None) -> None:
        """The scan handed over its changes as of ``when`` (the latest change's time, an
        aware UTC datetime)."""
        if when is not None and (self.known is None or when > self.known):
            self.known = when

    def stamp(self, nid: ua.NodeId, attribute: int, dv: ua.DataValue) -> ua.DataValue:
        """``dv`` of ``nid``'s ``attribute`` with the time its value was last known current."""
        known = self.known
        if known is None or attribute != VALUE or nid not in self.tags:
            return dv
        ts = dv.ServerTimestamp
        if ts is not None and (ts if ts.tzinfo else ts.replace(tzinfo=UTC)) >= known:
            return dv
        return dataclasses.replace(dv, ServerTimestamp=known, ServerPicoseconds=None)


def read(
    params: ua.ReadParameters, results: Sequence[ua.DataValue], fresh: Freshness
) -> list[ua.DataValue]:
    """A Read's answer: each value with its fresh ServerTimestamp, then with the timestamps
    the client asked for."""
    ttr = check(params.TimestampsToReturn)
    out = []
    for rv, dv in zip(params.NodesToRead, results, strict=True):
        value = rv.AttributeId == VALUE
        out.append(returned(fresh.stamp(rv.NodeId, rv.AttributeId, dv), ttr, value))
    return out
