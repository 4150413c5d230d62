"""The alarm journal over HTTP, read-only, for viewers and up (issue 34; docs/alarms.md).

``GET /api/alarms/journal?since=&until=&channel=&alarm=&actor=&transition=&limit=&format=``:
every transition of the alarm model (activated, cleared, acknowledged, reset, shelved,
unshelved, silenced) with its time, alarm, channel, priority, message and actor, oldest
first. ``since``/``until``: ISO 8601 with a zone or Unix seconds (default: the last 24 h);
``channel``: a channel's name, or empty for the bench's own alarms; ``alarm``, ``actor``
and ``transition``: exact matches; ``limit`` (default ``DEFAULT_LIMIT``, at most
``MAX_LIMIT``): the newest ``limit`` of the matches (``truncated`` says some older ones
were left out: ask again with an earlier ``until``). ``format=csv``: the same rows as a
CSV file with a header row, a text a spreadsheet would run as a formula written with a
leading ``'`` (as ``supervisor audit export`` does).

Where it reads (ADR 0048): the historian's events when the bench records history (on disk:
the journal survives a restart and goes as far back as the history file); otherwise the
alarm model's in-memory log (``AlarmManager.history``, the last ``LOG_LENGTH``
transitions since the start; the answer's ``source`` says which). The file is read in a
worker thread, never on the scan's loop.
"""

from __future__ import annotations

import asyncio
import csv
import io
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import Any, Final

from aiohttp import web

from supervisor.hmi.auth import refuse_unless
from supervisor.hmi.history_api import BadRequest, parse_time
from supervisor.hmi.server import json_dumps
from supervisor.publish.historian import BadRange, HistoryQuery
from supervisor.publish.historian.query import MAX_EVENTS
from supervisor.safety import AlarmEvent, AlarmManager, Severity, Transition

__all__ = ["DEFAULT_LIMIT", "MAX_LIMIT", "JournalRow", "add_journal_routes"]

DEFAULT_LIMIT: Final = 1000
MAX_LIMIT: Final = 10_000
DEFAULT_SPAN_S: Final = 86_400.0
MAX_FILTER_CHARS: Final = 256
WHAT: Final = "read the alarm journal"
FORMULA_STARTS: Final = ("=", "+", "-", "@", "\t", "\r")
"""As ``supervisor audit export`` (cli/audit.py, a layer above: not importable here)."""
TRANSITIONS: Final = frozenset(t.value for t in Transition)
COLUMNS: Final = (
    "time",
    "time_iso",
    "alarm",
    "channel",
    "transition",
    "priority",
    "message",
    "actor",
)


@dataclass(frozen=True, slots=True)
class JournalRow:
    time: float  # Unix seconds
    time_iso: str
    alarm: str
    channel: str
    transition: str
    priority: str
    message: str
    actor: str


@dataclass(frozen=True, slots=True)
class _Filter:
    since: float
    until: float
    channel: str | None
    alarm: str
    actor: str
    transition: str
    limit: int

    def keeps(self, row: JournalRow) -> bool:
        return (
            self.since <= row.time <= self.until
            and (self.channel is None or row.channel == self.channel)
            and (not self.alarm or row.alarm == self.alarm)
            and (not self.actor or row.actor == self.actor)
            and (not self.transition or row.transition == self.transition)
        )


def _iso(wall: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(wall)) + f".{int(wall % 1 * 1000):03d}Z"


def _priority(severity: int) -> str:
    try:
        return Severity(severity).name.lower()
    except ValueError:
        return str(severity)


def _of_event(ev: AlarmEvent, channels: Callable[[str], str]) -> JournalRow:
    return JournalRow(
        ev.wall,
        _iso(ev.wall),
        ev.alarm_id,
        channels(ev.group),
        ev.transition.value,
        _priority(int(ev.severity)),
        ev.message,
        ev.actor or "safety",
    )


def _from_history(query: HistoryQuery, f: _Filter) -> list[JournalRow]:
    """The historian's alarm events (text ``"<alarm> <transition>: <message>"``,
    app/events.py)."""
    rows = []
    for e in query.events(f.since, f.until, f.channel, "alarm", MAX_EVENTS):
        head, _, message = e.text.partition(": ")
        transition = head[len(e.source) + 1 :] if head.startswith(e.source + " ") else head
        row = JournalRow(
            e.wall,
            _iso(e.wall),
            e.source,
            e.channel,
            transition,
            _priority(e.severity),
            message,
            e.actor,
        )
        if f.keeps(row):
            rows.append(row)
    return rows


def csv_cell(value: object) -> object:
    """A text a spreadsheet would run as a formula, with a leading ``'`` (the audit
    trail's CSV over HTTP uses it too)."""
    if isinstance(value, str) and value[:1] in FORMULA_STARTS:
        return "'" + value
    return value


def journal_csv(rows: Iterable[JournalRow]) -> str:
    """The rows as CSV, a header row first, formula-like texts escaped."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\r\n")
    w.writerow(COLUMNS)
    for row in rows:
        w.writerow([csv_cell(v) for v in asdict(row).values()])
    return out.getvalue()


def _text(request: web.Request, name: str) -> str:
    text = request.query.get(name, "")
    if len(text) > MAX_FILTER_CHARS:
        raise BadRequest(f"{name} is longer than {MAX_FILTER_CHARS} characters")
    return text


def _limit(request: web.Request) -> int:
    text = request.query.get("limit", "")
    if not text:
        return DEFAULT_LIMIT
    try:
        value = int(text)
    except ValueError:
        raise BadRequest(f"limit={text[:40]!r}: not an integer") from None
    if not 1 <= value <= MAX_LIMIT:
        raise BadRequest(f"limit={value}: between 1 and {MAX_LIMIT}")
    return value


def _filter_of(request: web.Request, now_wall: float) -> _Filter:
    until_text, since_text = _text(request, "until"), _text(request, "since")
    until = parse_time(until_text, "until") if until_text else now_wall
    since = parse_time(since_text, "since") if since_text else until - DEFAULT_SPAN_S
    if since > until:
        raise BadRequest("since is after until")
    transition = _text(request, "transition")
    if transition and transition not in TRANSITIONS:
        raise BadRequest(f"transition: one of {', '.join(sorted(TRANSITIONS))}")
    return _Filter(
        since,
        until,
        request.query.get("channel"),  # absent: every channel; empty: the bench's own
        _text(request, "alarm"),
        _text(request, "actor"),
        transition,
        _limit(request),
    )


def add_journal_routes(
    app: web.Application,
    alarms: AlarmManager,
    history: Callable[[], HistoryQuery | None],
    channels: Callable[[str], str] = lambda group: group,
) -> None:
    """``GET /api/alarms/journal`` on ``alarms``' transitions, read from the historian that
    ``history`` returns (looked up at each request), or from the in-memory log without.
    ``channels``: an alarm's group as the historian records its channel."""

    async def journal(request: web.Request) -> web.StreamResponse:
        refused = refuse_unless(request, "viewer", WHAT)
        if refused is not None:
            return refused
        fmt = request.query.get("format", "json")
        try:
            if fmt not in ("json", "csv"):
                raise BadRequest("format: json or csv")
            f = _filter_of(request, alarms.clock.wall())
        except BadRequest as exc:
            return _answer({"ok": False, "error": "bad request", "reason": str(exc)}, 400)
        query = history()
        if query is not None:
            source = "historian"
            try:
                rows = await asyncio.to_thread(_from_history, query, f)
            except BadRange as exc:
                return _answer({"ok": False, "error": "bad request", "reason": str(exc)}, 400)
        else:
            source = "memory"
            rows = [r for r in (_of_event(e, channels) for e in list(alarms.history)) if f.keeps(r)]
        truncated = len(rows) > f.limit
        rows = rows[-f.limit :]
        if fmt == "csv":
            return web.Response(
                text=journal_csv(rows),
                content_type="text/csv",
                headers={"Content-Disposition": 'attachment; filename="alarm-journal.csv"'},
            )
        return _answer(
            {
                "source": source,
                "since": f.since,
                "until": f.until,
                "count": len(rows),
                "truncated": truncated,
                "entries": [asdict(r) for r in rows],
            }
        )

    app.add_routes([web.get("/api/alarms/journal", journal)])


def _answer(body: dict[str, Any], status: int = 200) -> web.Response:
    return web.json_response(body, status=status, dumps=json_dumps)
