"""The history endpoints of the HTTP API, for the screens' trends and event lists.

- ``GET /api/history?tag=ch0.voltage&start=…&end=…[&interval_s=…][&limit=…]``: the tag's
  samples in [start, end] with its unit and each sample's quality. With ``interval_s``,
  min/max/mean/count/first/last per interval ("aggregate"); without it, the raw samples,
  unless there are more than ``limit`` (default 5000): then aggregated into about
  ``DEFAULT_BUCKETS`` intervals, so that a week of 1 s data draws in one request.
  ``before`` is the last sample before ``start`` (where the trend's line comes from).
- ``GET /api/events?start=…&end=…[&channel=ch0][&kind=alarm][&limit=…]``: the bench's
  events (step and state changes, alarms, operator commands with their actor), oldest
  first; ``channel=`` (empty) asks for the bench's own events.

Times are ISO 8601 with a time zone (``2026-01-01T08:00:00Z``, ``…+01:00``) or Unix
seconds; answers give Unix seconds. ``end`` defaults to now, ``start`` to
``DEFAULT_SPAN_S`` before ``end``. A bad request is answered 400 with the reason (a
missing or unknown parameter value, a time that is not one, start after end, an interval
giving more than ``MAX_BUCKETS`` buckets, see historian/query.py), an unknown tag or
channel 404. The query runs on a worker thread (``asyncio.to_thread``): the event loop,
and so the scan, never waits for the disk.
"""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import Collection, Mapping
from datetime import datetime
from typing import Any, Final

from aiohttp import web

from supervisor.core.clock import Clock
from supervisor.publish.historian import (
    MAX_RAW_ROWS,
    Aggregate,
    BadRange,
    HistoryQuery,
    Series,
    StoredSample,
    TagInfo,
    UnknownTag,
    check_interval,
    check_range,
)
from supervisor.publish.historian.query import MAX_EVENTS
from supervisor.tags import TagDB

__all__ = ["DEFAULT_BUCKETS", "DEFAULT_LIMIT", "HistoryQuery", "add_history_routes", "parse_time"]

DEFAULT_LIMIT: Final = 5000
"""Raw samples answered at most before the answer is aggregated instead."""
DEFAULT_BUCKETS: Final = 1000
"""Intervals of an automatic aggregate (a trend is about a thousand pixels wide)."""
DEFAULT_SPAN_S: Final = 3600.0
"""The range asked when ``start`` is not given: the last hour before ``end``."""


class BadRequest(ValueError):
    """A request parameter that cannot be used (the message names it)."""


def parse_time(text: str, name: str) -> float:
    """Unix seconds from ISO 8601 with a time zone or from Unix seconds."""
    s = text.strip()
    try:
        value = float(s)
    except ValueError:
        pass
    else:
        if not math.isfinite(value):
            raise BadRequest(f"{name}={text!r}: not a finite time")
        return value
    try:
        dt = datetime.fromisoformat(s)
    except ValueError:
        raise BadRequest(
            f"{name}={text!r}: not a time (ISO 8601 such as 2026-01-01T08:00:00Z, or Unix seconds)"
        ) from None
    if dt.tzinfo is None:
        raise BadRequest(f"{name}={text!r}: no time zone (add Z or an offset such as +01:00)")
    return dt.timestamp()


def _number(query: Mapping[str, str], name: str) -> float | None:
    text = query.get(name)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise BadRequest(f"{name}={text!r}: not a number") from None
    if not math.isfinite(value):
        raise BadRequest(f"{name}={text!r}: not a finite number")
    return value


def _limit(query: Mapping[str, str], default: int, most: int) -> int:
    text = query.get("limit")
    if text is None:
        return default
    try:
        value = int(text)
    except ValueError:
        raise BadRequest(f"limit={text!r}: not an integer") from None
    if not 1 <= value <= most:
        raise BadRequest(f"limit={value}: between 1 and {most}")
    return value


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    return obj


def _dumps(obj: Any) -> str:
    """JSON any parser reads (RFC 8259 has no NaN nor Infinity; see hmi/server.py)."""
    try:
        return json.dumps(obj, allow_nan=False)
    except ValueError:
        return json.dumps(_finite(obj), allow_nan=False)


def _json(data: Any, status: int = 200) -> web.Response:
    return web.json_response(data, status=status, dumps=_dumps)


def _error(status: int, reason: str) -> web.Response:
    return _json({"error": reason}, status)


def _sample(s: StoredSample) -> dict[str, Any]:
    return {"t": s.t, "value": s.value, "quality": s.quality.name}


def _head(info: TagInfo, start: float, end: float, mode: str) -> dict[str, Any]:
    return {
        "tag": info.name,
        "unit": info.unit,
        "dtype": info.dtype,
        "description": info.description,
        "start": start,
        "end": end,
        "mode": mode,
    }


def series_json(series: Series) -> dict[str, Any]:
    out = _head(series.tag, series.start, series.end, "raw")
    out["count"] = len(series.samples)
    out["truncated"] = series.truncated
    out["before"] = None if series.before is None else _sample(series.before)
    out["samples"] = [_sample(s) for s in series.samples]
    return out


def aggregate_json(agg: Aggregate) -> dict[str, Any]:
    out = _head(agg.tag, agg.start, agg.end, "aggregate")
    out["interval_s"] = agg.interval_s
    out["buckets"] = [
        {
            "t": b.t,
            "min": b.min,
            "max": b.max,
            "mean": b.mean,
            "count": b.count,
            "samples": b.samples,
            "first": b.first,
            "last": b.last,
            "quality": b.quality.name,
        }
        for b in agg.buckets
    ]
    return out


class HistoryApi:
    """The handlers (``add_history_routes`` registers them)."""

    def __init__(
        self, query: HistoryQuery, db: TagDB, clock: Clock, channels: Collection[str]
    ) -> None:
        self.query = query
        self.db = db
        self.clock = clock
        self.channels = channels  # live: a mapping of the bench's channels

    def _range(self, q: Mapping[str, str]) -> tuple[float, float]:
        end = parse_time(q["end"], "end") if "end" in q else self.clock.wall()
        start = parse_time(q["start"], "start") if "start" in q else end - DEFAULT_SPAN_S
        try:
            check_range(start, end)
        except BadRange as exc:
            raise BadRequest(str(exc)) from None
        return start, end

    async def history(self, request: web.Request) -> web.Response:
        q = request.query
        name = q.get("tag", "")
        if not name:
            return _error(400, "tag is required (e.g. /api/history?tag=ch0.voltage)")
        try:
            start, end = self._range(q)
            interval_s = _number(q, "interval_s")
            limit = _limit(q, DEFAULT_LIMIT, MAX_RAW_ROWS)
            if interval_s is not None:
                check_interval(start, end, interval_s)
        except (BadRequest, BadRange) as exc:
            return _error(400, str(exc))
        live = self.db.get(name)
        if live is not None and not live.spec.history.enabled:
            return _error(404, f"tag {name!r} is not recorded (history disabled in the I/O map)")
        try:
            answer = await asyncio.to_thread(self._history, name, start, end, interval_s, limit)
        except UnknownTag:
            if live is None:
                return _error(404, f"unknown tag {name!r}")
            # Declared and recorded, nothing written yet (e.g. it never had a value).
            s = live.spec
            info = TagInfo(name, s.unit, s.dtype, s.description)
            answer = series_json(Series(info, start, end, [], False, None))
        except BadRange as exc:
            return _error(400, str(exc))
        return _json(answer)

    def _history(
        self, name: str, start: float, end: float, interval_s: float | None, limit: int
    ) -> dict[str, Any]:
        if interval_s is not None:
            return aggregate_json(self.query.aggregate(name, start, end, interval_s))
        series = self.query.samples(name, start, end, limit)
        if not series.truncated:
            return series_json(series)
        # Too many to draw one by one: about DEFAULT_BUCKETS intervals instead.
        auto = (end - start) / DEFAULT_BUCKETS
        out = aggregate_json(self.query.aggregate(name, start, end, auto))
        out["aggregated_because"] = f"more than {limit} samples in the range"
        return out

    async def events(self, request: web.Request) -> web.Response:
        q = request.query
        channel = q.get("channel")
        kind = q.get("kind")
        try:
            start, end = self._range(q)
            limit = _limit(q, 10_000, MAX_EVENTS)
        except BadRequest as exc:
            return _error(400, str(exc))
        if channel and self.channels and channel not in self.channels:
            known = ", ".join(sorted(self.channels))
            return _error(404, f"unknown channel {channel!r} ({known})")
        try:
            found = await asyncio.to_thread(self.query.events, start, end, channel, kind, limit)
        except BadRange as exc:
            return _error(400, str(exc))
        return _json(
            {
                "start": start,
                "end": end,
                "count": len(found),
                "limit_reached": len(found) >= limit,  # there may be more: ask from the last
                "events": [
                    {
                        "time": e.wall,
                        "kind": e.kind,
                        "channel": e.channel,
                        "source": e.source,
                        "text": e.text,
                        "actor": e.actor,
                        "severity": e.severity,
                        "test_id": e.test_id,
                        "recipe": e.recipe,
                    }
                    for e in found
                ],
            }
        )


def add_history_routes(
    app: web.Application,
    query: HistoryQuery,
    db: TagDB,
    clock: Clock,
    channels: Collection[str] = (),
) -> HistoryApi:
    """Register ``GET /api/history`` and ``GET /api/events`` on ``app``."""
    api = HistoryApi(query, db, clock, channels)
    app.add_routes([web.get("/api/history", api.history), web.get("/api/events", api.events)])
    return api
