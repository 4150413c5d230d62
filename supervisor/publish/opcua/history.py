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
  sample per time). ReturnBounds: the sample at or before StartTime first (the value at
  that time: the historian stores a value when it changes) and the one at or after EndTime
  last, Bad_BoundNotFound where the file holds none. Reversed ranges are not served.
- ``ReadProcessedDetails``: Average, Minimum, Maximum, Count per ProcessingInterval (Part
  13; 0: one interval over the whole range) from ``HistoryQuery.aggregate``: an interval
  without values is Bad_NoData (Count: 0), one with some BAD samples
  Uncertain_DataSubNormal; other aggregates Bad_AggregateNotSupported. The Server's two
  AggregateFunctions folders list the aggregates served (``SERVED``, ``list_aggregates``).
  Average is the mean of the stored samples (query.py says why); TimeAverage is
  time-weighted, computed here from the raw samples (stepped: each value holds until the
  next; a range of more than ``MAX_RAW_ROWS`` samples answers Bad_AggregateInvalidInputs).
  At most ``MAX_BUCKETS`` intervals, no continuation.
- ``ReadEventDetails`` on the Bench object (every event) or a channel (its own): the
  stored events, each with the type it has live (alarm transitions AlarmConditionType with
  ConditionName and ConditionId), the filter's select clauses answered by field (browse)
  path; a where clause of event types (``EventType InList``, ``OfType``) is applied, any
  other is not. At most ``NumValuesPerNode`` (0: ``PAGE``), no continuation.

A node that is not a historised tag answers Bad_HistoryOperationUnsupported, a node the
address space does not hold Bad_NodeIdUnknown; a historised tag not yet written to the
file, Good_NoData.
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
    MAX_RAW_ROWS,
    BadRange,
    Bucket,
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

SERVED: Final[Mapping[int, str]] = {
    O.AggregateFunction_Average: "mean",
    O.AggregateFunction_Minimum: "min",
    O.AggregateFunction_Maximum: "max",
    O.AggregateFunction_Count: "count",
    O.AggregateFunction_TimeAverage: "time average",
}
"""The aggregates served, by their standard NodeId (Part 13): the historian computes the
first four per interval (``HistoryQuery.aggregate``, the field of its ``Bucket`` named
here); TimeAverage is computed here from the raw samples (stepped: the historian stores a
value when it moves past its deadband, so each value holds until the next sample). The
Server's AggregateFunctions folders list exactly these (``list_aggregates``)."""

NO_END: Final = sys.float_info.max
"""An unspecified end time: every sample from the start on."""

Variant = Callable[[object, str], ua.Variant]


@dataclass
class HistorySpace:
    """What the history service must know of the address space."""

    tags: dict[ua.NodeId, tuple[str, str]] = field(default_factory=dict)  # node: (tag, kind)
    event_sources: dict[ua.NodeId, str | None] = field(default_factory=dict)  # node → channel
    event_types: dict[str, ua.NodeId] = field(default_factory=dict)  # event kind → type
    # An event type → its supertypes below BaseEventType (for a where clause's OfType).
    supertypes: dict[ua.NodeId, tuple[ua.NodeId, ...]] = field(default_factory=dict)
    conditions: dict[str, ua.NodeId] = field(default_factory=dict)  # alarm id → its object

    def event_type(self, kind: str) -> ua.NodeId:
        return self.event_types.get(kind, ua.NodeId(O.BaseEventType))

    def is_of_type(self, kind: str, wanted: tuple[frozenset[ua.NodeId], bool]) -> bool:
        types, exact = wanted
        t = self.event_type(kind)
        if exact:
            return t in types
        lineage = {t, *self.supertypes.get(t, ()), ua.NodeId(O.BaseEventType)}
        return not types.isdisjoint(lineage)


def of_types(where: Any) -> tuple[frozenset[ua.NodeId], bool] | None:
    """The event types a where clause asks for: (types, exact). ``EventType InList [...]``
    (asyncua's ``read_event_history(evtypes=…)``, the subtypes listed) is exact; ``OfType``
    elements joined by Or include subtypes. None for no clause or any other clause (not
    applied: ADR 0014)."""
    elements = list(getattr(where, "Elements", None) or [])
    if not elements:
        return None
    wanted: set[ua.NodeId] = set()
    exact = False
    for e in elements:
        operands = list(e.FilterOperands)
        if e.FilterOperator == ua.FilterOperator.Or:
            continue
        if e.FilterOperator == ua.FilterOperator.InList and operands:
            path = list(getattr(operands[0], "BrowsePath", None) or [])
            if [p.Name for p in path] != ["EventType"]:
                return None
            operands, exact = operands[1:], True
        elif e.FilterOperator != ua.FilterOperator.OfType or len(operands) != 1:
            return None
        for operand in operands:
            value = getattr(getattr(operand, "Value", None), "Value", None)
            if not isinstance(value, ua.NodeId):
                return None
            wanted.add(value)
    return (frozenset(wanted), exact) if wanted else None


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


def time_average(
    samples: list[StoredSample],
    before: StoredSample | None,
    start: float,
    end: float,
    interval_s: float,
    n: int,
) -> list[tuple[float | None, bool]]:
    """Per interval [start + k·interval_s, + interval_s) ∩ [start, end]: the time-weighted
    mean of the stepped value (each sample holds until the next; ``before`` holds from
    ``start``), and whether part of the interval had no usable value (BAD, or before the
    first sample): (None, True) when none of it had one."""
    # Steps: (from time, value or None), from start on.
    steps: list[tuple[float, float | None]] = []
    if before is not None:
        steps.append((start, _number(before.value)))
    for smp in samples:
        steps.append((max(smp.t, start), _number(smp.value)))
    out: list[tuple[float | None, bool]] = []
    i = 0
    for k in range(n):
        lo = start + k * interval_s
        hi = min(end, lo + interval_s)
        while i + 1 < len(steps) and steps[i + 1][0] <= lo:
            i += 1
        area = covered = 0.0
        j = i
        while j < len(steps) and steps[j][0] < hi:
            t0 = max(steps[j][0], lo)
            t1 = min(steps[j + 1][0], hi) if j + 1 < len(steps) else hi
            v = steps[j][1]
            if v is not None and t1 > t0:
                area += v * (t1 - t0)
                covered += t1 - t0
            j += 1
        span = hi - lo
        if covered <= 0.0:
            out.append((None, True))
        else:
            out.append((area / covered, covered < span * (1 - 1e-9)))
    return out


def _number(v: object) -> float | None:
    if v is None or isinstance(v, str):
        return None
    return float(v)  # type: ignore[arg-type]


def _no_bound(t: float) -> ua.DataValue:
    when = _utc(t)
    return ua.DataValue(
        ua.Variant(None),
        StatusCode=ua.StatusCode(S.BadBoundNotFound),
        SourceTimestamp=when,
        ServerTimestamp=when,
    )


def _result(status: int, data: Any = None, cont: bytes | None = None) -> ua.HistoryReadResult:
    res = ua.HistoryReadResult()
    res.StatusCode = ua.StatusCode(status)
    if data is not None:
        res.HistoryData = data
    res.ContinuationPoint = cont
    return res


AGGREGATE_FOLDERS: Final = (
    O.Server_ServerCapabilities_AggregateFunctions,
    O.HistoryServerCapabilities_AggregateFunctions,
)
"""Where a client looks for the aggregates a server computes (Part 5 ServerCapabilities,
Part 11 HistoryServerCapabilities): empty in asyncua's standard address space."""


async def list_aggregates(server: Any) -> None:
    """List the standard AggregateFunction objects served (``SERVED``) in both
    AggregateFunctions folders of the Server object (issue 31, finding 7), with HasComponent
    as Part 13 §4.2.2.1 relates them."""
    refs = []
    for folder in AGGREGATE_FOLDERS:
        for aggregate in SERVED:
            ref = ua.AddReferencesItem()
            ref.IsForward = True
            ref.ReferenceTypeId = ua.NodeId(O.HasComponent)
            ref.SourceNodeId = ua.NodeId(folder)
            ref.TargetNodeClass = ua.NodeClass.Object
            ref.TargetNodeId = ua.NodeId(aggregate)
            refs.append(ref)
    results = await server.iserver.isession.add_references(refs)
    for ref, status in zip(refs, results, strict=True):
        if not status.is_good():
            log.warning(
                "OPC UA: aggregate %s not listed in %s: %s",
                ref.TargetNodeId.to_string(),
                ref.SourceNodeId.to_string(),
                status,
            )


def aggregate_of(types: list[ua.NodeId], i: int) -> str | int:
    """The aggregate asked for the ``i``-th node (one for all, or one per node): its name
    in ``SERVED``, or the status code refusing it."""
    if len(types) == 1:
        aggregate = types[0]
    elif i < len(types):
        aggregate = types[i]
    else:
        return int(S.BadAggregateListMismatch)
    what = SERVED.get(aggregate.Identifier) if aggregate.NamespaceIndex == 0 else None
    return int(S.BadAggregateNotSupported) if what is None else what


def bucket_value(b: Bucket | None, what: str, t: float) -> ua.DataValue:
    """One interval's value of ``what`` (a ``SERVED`` name but TimeAverage), at its start
    time. Count (Part 13 §5.4.3.21: Int32, the values that are not BAD; zero, Good, for an
    interval without any) is never Bad_NoData; the others are, for an interval without
    values. The status is the worst quality's, but some BAD samples among values are
    Uncertain_DataSubNormal (they were left out)."""
    when = _utc(t)
    if what == "count":
        variant = ua.Variant(0 if b is None else b.count, VT.Int32)
    else:
        value: float | None = None if b is None else getattr(b, what)
        if value is None:
            return ua.DataValue(
                ua.Variant(None), StatusCode=ua.StatusCode(S.BadNoData), SourceTimestamp=when
            )
        variant = ua.Variant(float(value), VT.Double)
    if b is None:
        status = S.Good  # (a count of zero)
    elif b.quality is Quality.BAD:
        status = S.UncertainDataSubNormal  # values, and BAD samples among them
    else:
        status = quality_status(b.quality, Reason.NONE)
    return ua.DataValue(
        variant, StatusCode=ua.StatusCode(status), SourceTimestamp=when, ServerTimestamp=when
    )


class HistoryService(HistoryManager):  # type: ignore[misc]
    """The server's history manager: HistoryRead answered by the historian's query."""

    def __init__(
        self, iserver: Any, query: HistoryQuery | None, space: HistorySpace, variant: Variant
    ) -> None:
        super().__init__(iserver)
        self.query = query
        self.space = space
        self.variant = variant

    def known(self, nid: ua.NodeId) -> bool:
        """The address space holds ``nid`` (a shelf-backed space looks it up in its file)."""
        return nid in self.space.tags or nid in self.iserver.aspace

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
        if not self.known(rv.NodeId):
            # Part 11 §6.4 / Part 4 §7.34: a node the server does not have is not a node
            # without history (issue 31, finding 8).
            return _result(S.BadNodeIdUnknown)
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
        values = [self._value(s, kind) for s in samples]
        if d.ReturnBounds:
            values = await self._bounds(
                values, samples, series.before, tag, kind, start, end, after, more
            )
        data = ua.HistoryData()
        data.DataValues = values
        cont = struct.pack("<d", samples[-1].t) if more and samples else None
        return _result(S.Good if values else S.GoodNoData, data, cont)

    async def _bounds(
        self,
        values: list[ua.DataValue],
        samples: list[StoredSample],
        before: StoredSample | None,
        tag: str,
        kind: str,
        start: float | None,
        end: float | None,
        after: float | None,
        more: bool,
    ) -> list[ua.DataValue]:
        """Part 11 §6.4.3.2 bounding values: the sample at or before StartTime on the first
        page, the sample at or after EndTime on the last; Bad_BoundNotFound (at that time)
        when the file holds none. The historian keeps a value until it changes (its
        deadband), so the sample before a time is the value at that time."""
        out = list(values)
        if start is not None and after is None and not (samples and samples[0].t == start):
            if before is not None:
                out.insert(0, self._value(before, kind))
            else:
                out.insert(0, _no_bound(start))
        if (
            end is not None
            and end != NO_END
            and not more
            and not (samples and samples[-1].t == end)
        ):
            query = self.query
            assert query is not None
            nxt = await asyncio.to_thread(query.samples, tag, end, NO_END, 1)
            out.append(self._value(nxt.samples[0], kind) if nxt.samples else _no_bound(end))
        return out

    # --- processed ------------------------------------------------------------------------
    async def _processed(
        self, d: ua.ReadProcessedDetails, i: int, tag: str, kind: str
    ) -> ua.HistoryReadResult:
        what = aggregate_of(list(d.AggregateType), i)
        if isinstance(what, int):
            return _result(what)
        start, end = _seconds(d.StartTime), _seconds(d.EndTime)
        if start is None or end is None or start > end:
            return _result(S.BadInvalidTimestampArgument)
        interval_s = float(d.ProcessingInterval) / 1000.0
        if interval_s <= 0.0:  # Part 11: one interval over the whole range
            interval_s = max(end - start, 1e-3)
        query = self.query
        assert query is not None  # (checked by _one)
        if what == "time average":
            return await self._time_average(tag, kind, start, end, interval_s)
        if kind == "str" and what != "count":
            return _result(S.BadAggregateInvalidInputs)
        try:
            agg = await asyncio.to_thread(query.aggregate, tag, start, end, interval_s)
        except UnknownTag:
            return _result(S.GoodNoData, ua.HistoryData())
        except BadRange as exc:
            log.warning("OPC UA HistoryRead (processed) of %s refused: %s", tag, exc)
            return _result(S.BadHistoryOperationInvalid)
        by_t = {round((b.t - start) / interval_s): b for b in agg.buckets}
        n = min(MAX_BUCKETS, max(1, math.ceil((end - start) / interval_s)))
        data = ua.HistoryData()
        data.DataValues = [
            bucket_value(by_t.get(k), what, start + k * interval_s) for k in range(n)
        ]
        return _result(S.Good, data)

    async def _time_average(
        self, tag: str, kind: str, start: float, end: float, interval_s: float
    ) -> ua.HistoryReadResult:
        if kind == "str":
            return _result(S.BadAggregateInvalidInputs)
        n = math.ceil((end - start) / interval_s) if end > start else 1
        if n > MAX_BUCKETS:
            return _result(S.BadHistoryOperationInvalid)
        query = self.query
        assert query is not None
        try:
            series = await asyncio.to_thread(query.samples, tag, start, end, MAX_RAW_ROWS)
        except UnknownTag:
            return _result(S.GoodNoData, ua.HistoryData())
        except BadRange as exc:
            log.warning("OPC UA HistoryRead (TimeAverage) of %s refused: %s", tag, exc)
            return _result(S.BadHistoryOperationInvalid)
        if series.truncated:  # more raw samples than one read takes: Average serves it
            log.warning("OPC UA TimeAverage of %s: over %d samples", tag, MAX_RAW_ROWS)
            return _result(S.BadAggregateInvalidInputs)
        values = []
        for k, (avg, partial) in enumerate(
            time_average(series.samples, series.before, start, end, interval_s, max(1, n))
        ):
            t = _utc(start + k * interval_s)
            if avg is None:
                values.append(
                    ua.DataValue(
                        ua.Variant(None), StatusCode=ua.StatusCode(S.BadNoData), SourceTimestamp=t
                    )
                )
                continue
            status = S.UncertainDataSubNormal if partial else S.Good
            values.append(
                ua.DataValue(
                    ua.Variant(avg, VT.Double),
                    StatusCode=ua.StatusCode(status),
                    SourceTimestamp=t,
                    ServerTimestamp=t,
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
        wanted = of_types(d.Filter.WhereClause) if d.Filter is not None else None
        if wanted is not None:
            events = [ev for ev in events if self.space.is_of_type(ev.kind, wanted)]
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
            "EventType": ua.Variant(self.space.event_type(ev.kind), VT.NodeId),
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
        if ev.kind == "alarm":  # the transition of a condition: which one
            known["ConditionName"] = ua.Variant(ev.source, VT.String)
            condition = self.space.conditions.get(ev.source)
            if condition is not None:
                known["NodeId"] = ua.Variant(condition, VT.NodeId)  # ConditionId (Part 9)
        fields = ua.HistoryEventFieldList()
        for c in clauses:
            path = list(getattr(c, "BrowsePath", []) or [])
            if path:
                name = "/".join(p.Name for p in path)
            elif getattr(c, "AttributeId", None) == ua.AttributeIds.NodeId:
                name = "NodeId"  # Part 9: the ConditionId is the NodeId of the condition type
            else:
                name = ""
            fields.EventFields.append(known.get(name, ua.Variant(None)))
        return fields
