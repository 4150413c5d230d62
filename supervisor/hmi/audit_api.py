"""The audit trail over HTTP, read-only, for engineers (issue 34; docs/audit.md).

- ``GET /api/audit?since=&until=&actor=&kind=&channel=&limit=&before=``: entries newest
  first, ``limit`` at a time (default 100, at most ``MAX_LIMIT``); the answer's
  ``next_before`` is the ``before`` of the next (older) page, null after the last. Times
  are ISO 8601 (without a zone: UTC); ``kind`` is a kind or a family (``command``);
  ``channel`` selects the entries whose target or details name it.
  ``format=csv``: every entry the filters select (``limit`` and ``before`` ignored), oldest
  first, as ``supervisor audit export`` writes them (columns ``CSV_COLUMNS``, details as
  canonical JSON, a formula-like text with a leading ``'``): the Audit screen's export.
- ``GET /api/audit/verify``: the whole chain checked, ``{ok, entries, head,
  first_broken}`` (``first_broken``: ``{seq, time, problem}`` or null).

An engineer's (without logins, loopback only: everyone's); a viewer or an operator gets
403 with the reason, no session 401. The file is read in a worker thread, never on the
scan's loop. A missing or unreadable log: 503 with the reason.
"""

from __future__ import annotations

import asyncio
import csv
import dataclasses
import io
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Final

from aiohttp import web

from supervisor.audit import AuditFileError, Entry, Query, read_entries, utc_of_iso, verify_file
from supervisor.hmi.auth import refuse_unless
from supervisor.hmi.journal_api import csv_cell
from supervisor.hmi.server import json_dumps

__all__ = ["DEFAULT_LIMIT", "MAX_LIMIT", "add_audit_routes"]

DEFAULT_LIMIT: Final = 100
MAX_LIMIT: Final = 1000
WHAT: Final = "read the audit log"
MAX_FILTER_CHARS: Final = 256
CSV_COLUMNS: Final = ("seq", "time", "actor", "kind", "target", "details", "prev_hash", "hash")
"""As ``supervisor audit export`` (cli/audit.py, a layer above: not importable here)."""


class _BadQuery(Exception):
    pass


def _answer(body: dict[str, Any], status: int = 200) -> web.Response:
    return web.json_response(body, status=status, dumps=json_dumps)


def _refused(status: int, error: str, reason: str) -> web.Response:
    return _answer({"ok": False, "error": error, "reason": reason}, status)


def _int(request: web.Request, name: str, default: int | None, low: int, high: int) -> int | None:
    text = request.query.get(name)
    if text is None or text == "":
        return default
    try:
        value = int(text)
    except ValueError:
        raise _BadQuery(f"{name} must be an integer, not {text[:40]!r}") from None
    if not low <= value <= high:
        raise _BadQuery(f"{name} must be between {low} and {high}, not {value}")
    return value


def _text(request: web.Request, name: str) -> str:
    text = request.query.get(name, "")
    if len(text) > MAX_FILTER_CHARS:
        raise _BadQuery(f"{name} is longer than {MAX_FILTER_CHARS} characters")
    return text


def _time(request: web.Request, name: str) -> str:
    text = _text(request, name)
    if not text:
        return ""
    try:
        return utc_of_iso(text)
    except (ValueError, OverflowError, OSError) as exc:
        raise _BadQuery(f"{name}: {exc}") from None


def query_of(request: web.Request) -> Query:
    """The request's filters and page (``_BadQuery`` naming the wrong parameter)."""
    limit = _int(request, "limit", DEFAULT_LIMIT, 1, MAX_LIMIT)
    return Query(
        since=_time(request, "since"),
        until=_time(request, "until"),
        actor=_text(request, "actor"),
        kind=_text(request, "kind"),
        channel=_text(request, "channel"),
        before_seq=_int(request, "before", None, 1, 2**62),
        limit=limit,
        newest_first=True,
    )


def audit_csv(entries: Iterable[Entry]) -> str:
    """The entries as CSV, a header row first, formula-like texts escaped."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\r\n")
    w.writerow(CSV_COLUMNS)
    for e in entries:
        w.writerow([csv_cell(getattr(e, c)) for c in CSV_COLUMNS])
    return out.getvalue()


def _csv_answer(entries: list[Entry]) -> web.Response:
    return web.Response(
        text=audit_csv(entries),
        content_type="text/csv",
        headers={"Content-Disposition": 'attachment; filename="audit-trail.csv"'},
    )


def add_audit_routes(app: web.Application, path: Callable[[], Path] | Path) -> None:
    """``GET /api/audit`` and ``/api/audit/verify`` on the log at ``path`` (the bench's
    ``<state_dir>/audit.sqlite``; a callable: looked up at each request)."""
    where = path if callable(path) else (lambda: path)

    async def entries(request: web.Request) -> web.Response:
        refused = refuse_unless(request, "engineer", WHAT)
        if refused is not None:
            return refused
        fmt = request.query.get("format", "json")
        try:
            if fmt not in ("json", "csv"):
                raise _BadQuery("format: json or csv")
            query = query_of(request)
        except _BadQuery as exc:
            return _refused(400, "bad request", str(exc))
        if fmt == "csv":  # the whole selection, oldest first (an export, not a page)
            query = dataclasses.replace(query, before_seq=None, limit=None, newest_first=False)
        try:
            found = await asyncio.to_thread(read_entries, where(), query)
        except AuditFileError as exc:
            return _refused(503, "no audit log", str(exc))
        if fmt == "csv":
            return _csv_answer(found)
        more = query.limit is not None and len(found) == query.limit and found[-1].seq > 1
        return _answer(
            {
                "entries": [e.as_json() for e in found],
                "next_before": found[-1].seq if more else None,
            }
        )

    async def verify(request: web.Request) -> web.Response:
        refused = refuse_unless(request, "engineer", WHAT)
        if refused is not None:
            return refused
        try:
            v = await asyncio.to_thread(verify_file, where())
        except AuditFileError as exc:
            return _refused(503, "no audit log", str(exc))
        return _answer(v.as_json())

    app.add_routes([web.get("/api/audit", entries), web.get("/api/audit/verify", verify)])
