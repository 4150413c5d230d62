"""HistoryRead served from the embedded historian (docs/adr/0014-opcua-server.md, "History").

asyncua's own history (``HistorySQLite``) subscribes to the server's nodes and stores what
they publish, in tables named after the NodeIds (it fails on string NodeIds) and a second
copy of what the historian already keeps. Instead the server's ``history_manager`` is
replaced by ``HistoryService``, which answers HistoryRead (OPC UA Part 11) from
``HistoryQuery`` (supervisor.publish.historian, ADR 0013), the same read API the HTTP
trends use. Its queries run in a worker thread (``asyncio.to_thread``): the query holds its
own read connection under a lock, and a long range takes milliseconds to seconds the
server's loop must not wait.

- ``ReadRawModifiedDetails`` (raw only; IsReadModified answers the same raw values, nothing
  is ever modified): the stored samples of [start, end], oldest first, each with its source
  time and its quality as a status code (statuses.py; the historian keeps the quality, not
  its reason). At most ``NumValuesPerNode`` (0: ``PAGE``) per answer; more come with a
  continuation point that holds the time of the last sample sent (stateless: a tag has one
  sample per time). Reversed ranges (start after end) and bounding values are not served.
- ``ReadProcessedDetails``: Average, Minimum, Maximum per ProcessingInterval (Part 13; 0:
  one interval over the whole range) from ``HistoryQuery.aggregate``: an interval without
  values is Bad_NoData, one with some BAD samples Uncertain_DataSubNormal; other
  aggregates Bad_AggregateNotSupported. Average is the mean of the stored samples, not
  time-weighted (query.py says why). At most ``MAX_BUCKETS`` intervals, no continuation.
- ``ReadEventDetails`` on the Bench object (every event) or a channel (its own): the
  stored events, the filter's select clauses answered by field name; where clauses are not
  applied. At most ``NumValuesPerNode`` (0: ``PAGE``), no continuation.

A node that is not a historised tag answers Bad_HistoryOperationUnsupported; a historised
tag not yet written to the file, Good_NoData.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import math
import struct
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Final

from asyncua import ua
from asyncua.server.history import HistoryManager

from supervisor.core.quality import Quality, Reason
from supervisor.publish.historian import (
    MAX_BUCKETS,
    BadRange,
    HistoryQuery,
    StoredEvent,
    StoredSample,
    UnknownTag,
)
from supervisor.publish.opcua.statuses import quality_status

log = logging.getLogger(__name__)

S = ua.StatusCodes
VT = ua.VariantType
O = ua.ObjectIds  # noqa: E741 - asyncua's own abbreviation

PAGE: Final = 10_000
"""Values or events per answer at most (asyncua's own default response size)."""

AGGREGATES: Final[Mapping[int, str]] = {
    O.AggregateFunction_Average: "mean",
    O.AggregateFunction_Minimum: "min",
    O.AggregateFunction_Maximum: "max",
}
"""The aggregates the historian computes, by their standard NodeId (Part 13)."""

NO_END: Final = sys.float_info.max
"""An unspecified end time: every sample from the start on."""

Variant = Callable[[object, str], ua.Variant]


@dataclass
class HistorySpace:
    """What the history service must know of the address space."""

    tags: dict[ua.NodeId, tuple[str, str]] = field(default_factory=dict)  # node: (tag, kind)
    event_sources: dict[ua.NodeId, str | None] = field(default_factory=dict)  # node → channel
    event_types: dict[str, ua.NodeId] = field(default_factory=dict)  # event kind → type


def _seconds(t: datetime | None) -> float | None:
    """A request's time as Unix seconds; None when unspecified (null or MinDateTime)."""
    if t is None:
        return None
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    if t <= ua.get_win_epoch():
        return None
    return t.timestamp()


def _utc(wall: float) -> datetime:
    return datetime.fromtimestamp(wall, UTC)


def _result(status: int, data: Any = None, cont: bytes | None = None) -> ua.HistoryReadResult:
    res = ua.HistoryReadResult()
    res.StatusCode = ua.StatusCode(status)
    if data is not None:
        res.HistoryData = data
    res.ContinuationPoint = cont
    return res


class HistoryService(HistoryManager):  # type: ignore[misc]
    """The server's history manager: HistoryRead answered by the historian's query."""

    def __init__(
        self, iserver: Any, query: HistoryQuery | None, space: HistorySpace, variant: Variant
    ) -> None:
        super().__init__(iserver)
        self.query = query
        self.space = space
        self.variant = variant

    async def read_history(self, params: ua.HistoryReadParameters) -> list[ua.HistoryReadResult]:
        details = params.HistoryReadDetails
        out: list[ua.HistoryReadResult] = []
        for i, rv in enumerate(params.NodesToRead):
            try:
                out.append(await self._one(details, rv, i, params.ReleaseContinuationPoints))
            except Exception:
                log.exception("OPC UA HistoryRead of %s failed", rv.NodeId.to_string())
                out.append(_result(S.BadInternalError))
        return out

    async def _one(
        self, details: Any, rv: ua.HistoryReadValueId, i: int, release: bool
    ) -> ua.HistoryReadResult:
        if release:
            return _result(S.Good)  # stateless continuation points: nothing to release
        if self.query is None:
            return _result(S.BadHistoryOperationUnsupported)  # the bench records no history
        if isinstance(details, ua.ReadEventDetails):
            return await self._events(details, rv)
        target = self.space.tags.get(rv.NodeId)
        if target is None:
            return _result(S.BadHistoryOperationUnsupported)
        if isinstance(details, ua.ReadRawModifiedDetails):
            return await self._raw(details, rv, *target)
        if isinstance(details, ua.ReadProcessedDetails):
            return await self._processed(details, i, *target)
        return _result(S.BadHistoryOperationUnsupported)

    # --- raw ------------------------------------------------------------------------------
    def _value(self, s: StoredSample, kind: str) -> ua.DataValue:
        when = _utc(s.t)
        if s.value is None:
            return ua.DataValue(
                ua.Variant(None),
                StatusCode=ua.StatusCode(quality_status(Quality.BAD, Reason.NONE)),
                SourceTimestamp=when,
                ServerTimestamp=when,
            )
        try:
            variant = self.variant(s.value, kind)
        except (TypeError, ValueError):
            return ua.DataValue(StatusCode=ua.StatusCode(S.BadConfigurationError))
        return ua.DataValue(
            variant,
            StatusCode=ua.StatusCode(quality_status(s.quality, Reason.NONE)),
            # The historian keeps one time per sample, the source's (when it was acquired).
            SourceTimestamp=when,
            ServerTimestamp=when,
        )

    async def _raw(
        self, d: ua.ReadRawModifiedDetails, rv: ua.HistoryReadValueId, tag: str, kind: str
    ) -> ua.HistoryReadResult:
        start, end = _seconds(d.StartTime), _seconds(d.EndTime)
        after: float | None = None
        if rv.ContinuationPoint:
            if len(rv.ContinuationPoint) != 8:
                return _result(S.BadContinuationPointInvalid)
            (after,) = struct.unpack("<d", rv.ContinuationPoint)
            if not math.isfinite(after):
                return _result(S.BadContinuationPointInvalid)
        lo = 0.0 if start is None else start
        hi = NO_END if end is None else end
        if lo > hi:
            return _result(S.BadHistoryOperationUnsupported)  # reversed order: not served
        if after is not None:
            lo = max(lo, after)
        page = min(int(d.NumValuesPerNode) or PAGE, PAGE)
        query = self.query
        assert query is not None  # (checked by _one)
        try:
            series = await asyncio.to_thread(query.samples, tag, lo, hi, page + 1)
        except UnknownTag:
            return _result(S.GoodNoData, ua.HistoryData())
        except BadRange as exc:
            log.warning("OPC UA HistoryRead of %s refused: %s", tag, exc)
            return _result(S.BadHistoryOperationInvalid)
        samples = series.samples
        if after is not None:
            samples = [s for s in samples if s.t > after]
        more = len(samples) > page or series.truncated
        samples = samples[:page]
        data = ua.HistoryData()
        data.DataValues = [self._value(s, kind) for s in samples]
        cont = struct.pack("<d", samples[-1].t) if more and samples else None
        return _result(S.Good if samples else S.GoodNoData, data, cont)

    # --- processed ------------------------------------------------------------------------
    async def _processed(
        self, d: ua.ReadProcessedDetails, i: int, tag: str, kind: str
    ) -> ua.HistoryReadResult:
        types = list(d.AggregateType)
        if len(types) == 1:
            aggregate = types[0]
        elif i < len(types):
            aggregate = types[i]
        else:
            return _result(S.BadAggregateListMismatch)
        what = AGGREGATES.get(aggregate.Identifier) if aggregate.NamespaceIndex == 0 else None
        if what is None:
            return _result(S.BadAggregateNotSupported)
        start, end = _seconds(d.StartTime), _seconds(d.EndTime)
        if start is None or end is None or start > end:
            return _result(S.BadInvalidTimestampArgument)
        interval_s = float(d.ProcessingInterval) / 1000.0
        if interval_s <= 0.0:  # Part 11: one interval over the whole range
            interval_s = max(end - start, 1e-3)
        query = self.query
        assert query is not None  # (checked by _one)
        try:
            agg = await asyncio.to_thread(query.aggregate, tag, start, end, interval_s)
        except UnknownTag:
            return _result(S.GoodNoData, ua.HistoryData())
        except BadRange as exc:
            log.warning("OPC UA HistoryRead (processed) of %s refused: %s", tag, exc)
            return _result(S.BadHistoryOperationInvalid)
        if kind == "str":
            return _result(S.BadAggregateInvalidInputs)
        by_t = {round((b.t - start) / interval_s): b for b in agg.buckets}
        n = min(MAX_BUCKETS, max(1, math.ceil((end - start) / interval_s)))
        values = []
        for k in range(n):
            t = start + k * interval_s
            b = by_t.get(k)
            value = None if b is None else getattr(b, what)
            if b is None or value is None:
                values.append(
                    ua.DataValue(
                        ua.Variant(None),
                        StatusCode=ua.StatusCode(S.BadNoData),
                        SourceTimestamp=_utc(t),
                    )
                )
                continue
            if b.quality is Quality.BAD:
                status = S.UncertainDataSubNormal  # values, and BAD samples among them
            else:
                status = quality_status(b.quality, Reason.NONE)
            values.append(
                ua.DataValue(
                    ua.Variant(float(value), VT.Double),
                    StatusCode=ua.StatusCode(status),
                    SourceTimestamp=_utc(t),
                    ServerTimestamp=_utc(t),
                )
            )
        data = ua.HistoryData()
        data.DataValues = values
        return _result(S.Good, data)

    # --- events ---------------------------------------------------------------------------
    async def _events(
        self, d: ua.ReadEventDetails, rv: ua.HistoryReadValueId
    ) -> ua.HistoryReadResult:
        if rv.NodeId not in self.space.event_sources:
            return _result(S.BadHistoryOperationUnsupported)
        channel = self.space.event_sources[rv.NodeId]
        start, end = _seconds(d.StartTime), _seconds(d.EndTime)
        lo = 0.0 if start is None else start
        hi = NO_END if end is None else end
        if lo > hi:
            return _result(S.BadHistoryOperationUnsupported)
        limit = min(int(d.NumValuesPerNode) or PAGE, PAGE)
        query = self.query
        assert query is not None  # (checked by _one)
        try:
            events = await asyncio.to_thread(query.events, lo, hi, channel, None, limit)
        except BadRange as exc:
            log.warning("OPC UA HistoryRead (events) refused: %s", exc)
            return _result(S.BadHistoryOperationInvalid)
        clauses = list(d.Filter.SelectClauses) if d.Filter is not None else []
        data = ua.HistoryEvent()
        data.Events = [self._fields(ev, clauses, rv.NodeId) for ev in events]
        return _result(S.Good if events else S.GoodNoData, data)

    def _fields(
        self, ev: StoredEvent, clauses: list[Any], source: ua.NodeId
    ) -> ua.HistoryEventFieldList:
        when = _utc(ev.wall)
        key = f"{ev.wall!r}|{ev.kind}|{ev.channel}|{ev.source}|{ev.text}".encode()
        known: dict[str, ua.Variant] = {
            "EventId": ua.Variant(hashlib.sha1(key).digest(), VT.ByteString),
            "EventType": ua.Variant(
                self.space.event_types.get(ev.kind, ua.NodeId(O.BaseEventType)), VT.NodeId
            ),
            "SourceNode": ua.Variant(source, VT.NodeId),
            "SourceName": ua.Variant(ev.source or ev.channel or "bench", VT.String),
            "Time": ua.Variant(when, VT.DateTime),
            "ReceiveTime": ua.Variant(when, VT.DateTime),
            "Message": ua.Variant(ua.LocalizedText(ev.text), VT.LocalizedText),
            "Severity": ua.Variant(max(1, min(1000, int(ev.severity) or 1)), VT.UInt16),
            "Channel": ua.Variant(ev.channel, VT.String),
            "Kind": ua.Variant(ev.kind, VT.String),
            "Source": ua.Variant(ev.source, VT.String),
            "Actor": ua.Variant(ev.actor, VT.String),
            "TestId": ua.Variant(ev.test_id, VT.String),
            "Recipe": ua.Variant(ev.recipe, VT.String),
        }
        fields = ua.HistoryEventFieldList()
        for c in clauses:
            path = list(getattr(c, "BrowsePath", []) or [])
            name = path[-1].Name if path else ""
            fields.EventFields.append(known.get(name, ua.Variant(None)))
        return fields
