"""The test endpoints of the HTTP API, for the Tests screen (issue 12).

A test is a folder of the results directory (``<state_dir>/results/<test id>/``, written by
``publish/results.py``: ``<id>.bdf.csv``, ``<id>.chadeche.csv``, ``<id>.timeline.jsonl``,
``<id>.cycles.jsonl``, ``summary.json``) or a test under way on a channel (its collector,
live).

- ``GET /api/tests``: every test, newest first: ``{"tests": [{"id", "channel", "recipe",
  "started", "ended", "state", "end_reason", "running", "complete", "duration_s",
  "files": [{"name", "kind", "bytes"}]}]}``. Times are Unix seconds: ``started`` is the
  first BDF row's time less its test time, ``ended`` ``started + duration_s`` once the
  summary is final (else null). A test under way takes its state from its chain.
- ``GET /api/tests/{id}``: the same entry with the summary's ``records``, ``timeline`` and
  ``cycles: [{"cycle", "charge_ah", "discharge_ah", "efficiency", ...}]`` (as the dry-run
  preview gives them; of a long test the first and the latest, ``timeline_omitted`` and
  ``cycles_omitted`` count the others, which its ``.jsonl`` files hold); a test under
  way's summary as it stands.
- ``GET /api/tests/{id}/files/{name}``: one of its listed files as an attachment
  (``Content-Disposition``), 404 for anything else.

Ids and file names match :data:`ID_PATTERN` (no folder, no ``..``, no hidden or temporary
file) and a file must be one the listing shows: nothing else under the state directory can
be fetched. Folders are read in a worker thread; summaries are cached by size and mtime.
"""

from __future__ import annotations

import asyncio
import csv
import json
import logging
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from aiohttp import web

from supervisor.chains.engine import ChainRunner
from supervisor.chains.states import ACTIVE
from supervisor.core.clock import Clock
from supervisor.hmi.recipes_api import _dumps, cycle_json, timeline_json
from supervisor.publish.provenance import (
    BDF_METADATA_SUFFIX,
    PROVENANCE_NAME,
    MetadataError,
    check_cell_id,
)
from supervisor.publish.results import (
    CYCLES_SUFFIX,
    SUMMARY_NAME,
    TIMELINE_SUFFIX,
    ResultCollector,
)

log = logging.getLogger(__name__)

__all__ = ["ID_PATTERN", "TestsApi", "TestsConfig", "add_test_routes", "file_kind"]

ID_PATTERN: Final = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
"""A test id or one of its file names: no folder, no leading dot, no ``..`` (checked too)."""

CONTENT_TYPES: Final = {
    "bdf": "text/csv",
    "chadeche": "text/csv",
    "summary": "application/json",
    "timeline": "application/x-ndjson",
    "cycles": "application/x-ndjson",
    "bdf-metadata": "application/json",
    "provenance": "application/json",
}
LIST_QUERY: Final = ("cell",)
"""What ``GET /api/tests`` may be asked (anything else is refused: 400)."""


def valid_id(name: str) -> bool:
    return bool(ID_PATTERN.match(name)) and ".." not in name and not name.endswith(".tmp")


def file_kind(name: str) -> str:
    if name.endswith(".bdf.csv"):
        return "bdf"
    if name.endswith(".chadeche.csv"):
        return "chadeche"
    if name.endswith(TIMELINE_SUFFIX):
        return "timeline"
    if name.endswith(CYCLES_SUFFIX):
        return "cycles"
    if name == SUMMARY_NAME:
        return "summary"
    if name.endswith(BDF_METADATA_SUFFIX):
        return "bdf-metadata"
    if name == PROVENANCE_NAME:
        return "provenance"
    return "other"


@dataclass
class TestsConfig:
    """Where the results are, and the tests under way (``supervisor run`` builds it)."""

    __test__ = False  # not a pytest class, whatever its name

    results_dir: Path
    live: Mapping[str, ResultCollector] = field(default_factory=dict)
    """Each channel's collector (``Bench.results``, live: a new test replaces one)."""
    runners: Mapping[str, ChainRunner] = field(default_factory=dict)


@dataclass(frozen=True)
class _Live:
    """A test under way, as seen on the event loop."""

    channel: str
    state: str
    started: float | None
    summary: dict[str, Any]


def _json(data: Any, status: int = 200) -> web.Response:
    return web.json_response(data, status=status, dumps=_dumps)


def _error(status: int, reason: str) -> web.Response:
    word = {400: "bad request", 404: "not found"}.get(status, "error")
    return _json({"error": word, "reason": reason}, status)


def _files(folder: Path) -> list[dict[str, Any]]:
    out = []
    try:
        entries = sorted(folder.iterdir())
    except OSError:
        return []
    for p in entries:
        if not valid_id(p.name) or not p.is_file():
            continue
        try:
            size = p.stat().st_size
        except OSError:
            continue
        out.append({"name": p.name, "kind": file_kind(p.name), "bytes": size})
    return out


def _started(folder: Path, files: list[dict[str, Any]]) -> float | None:
    """The wall time of test time 0: the first BDF row's Unix time less its test time."""
    bdf = next((f["name"] for f in files if f["kind"] == "bdf"), None)
    if bdf is None:
        return None
    try:
        with (folder / bdf).open(encoding="utf-8", newline="") as f:
            rows = csv.reader(f)
            next(rows, None)  # the header
            first = next(rows, None)
        if first is None or len(first) < 2:
            return None
        return float(first[1]) - float(first[0])
    except (OSError, ValueError):
        return None


class TestsApi:
    """The handlers (``add_test_routes`` registers them)."""

    __test__ = False

    def __init__(self, config: TestsConfig, clock: Clock) -> None:
        self.config = config
        self.root = config.results_dir
        self.clock = clock
        self._summaries: dict[Path, tuple[tuple[int, int], dict[str, Any] | None]] = {}

    # --- reading (worker thread) --------------------------------------------------------
    def _summary(self, folder: Path) -> dict[str, Any] | None:
        path = folder / SUMMARY_NAME
        try:
            st = path.stat()
        except OSError:
            return None
        key = (st.st_mtime_ns, st.st_size)
        cached = self._summaries.get(path)
        if cached is not None and cached[0] == key:
            return cached[1]
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            log.warning("tests: %s unreadable: %s", path, exc)
            data = None
        summary = data if isinstance(data, dict) else None
        self._summaries[path] = (key, summary)
        return summary

    def _entry(self, test_id: str, live: _Live | None, detail: bool) -> dict[str, Any] | None:
        folder = self.root / test_id
        on_disk = folder.is_dir()
        if not on_disk and live is None:
            return None
        files = _files(folder) if on_disk else []
        summary = live.summary if live is not None else (self._summary(folder) or {})
        started = live.started if live is not None else _started(folder, files)
        complete = bool(summary.get("complete")) and live is None
        duration = summary.get("duration_s")
        ended = (
            started + float(duration)
            if complete and started is not None and isinstance(duration, int | float)
            else None
        )
        entry: dict[str, Any] = {
            "id": test_id,
            "channel": live.channel if live is not None else summary.get("channel"),
            "recipe": summary.get("recipe"),
            "started": started,
            "ended": ended,
            "state": live.state if live is not None else summary.get("state"),
            "end_reason": "" if live is not None else summary.get("end_reason"),
            "running": live is not None,
            "complete": complete,
            "duration_s": duration,
            "metadata": summary.get("metadata") or {},
            "files": files,
        }
        if detail:
            entry["records"] = summary.get("records")
            entry["cycles"] = [cycle_json(c) for c in summary.get("cycles", [])]
            entry["cycles_omitted"] = summary.get("cycles_omitted", 0)
            entry["timeline"] = [timeline_json(e) for e in summary.get("timeline", [])]
            # A long test's summary has its first and latest events (ADR 0022): every
            # one is in its timeline file, listed in ``files``.
            entry["timeline_omitted"] = summary.get("timeline_omitted", 0)
        return entry

    def _listing(self, live: Mapping[str, _Live]) -> list[dict[str, Any]]:
        ids = set(live)
        try:
            ids |= {p.name for p in self.root.iterdir() if valid_id(p.name) and p.is_dir()}
        except FileNotFoundError:
            pass  # no test ran yet
        except OSError as exc:
            log.warning("tests: cannot list %s: %s", self.root, exc)
        out = [e for i in ids if (e := self._entry(i, live.get(i), False)) is not None]
        out.sort(key=lambda e: (e["started"] or 0.0, e["id"]), reverse=True)
        return out

    # --- the tests under way (event loop) ----------------------------------------------
    def _live(self, detail: bool = False) -> dict[str, _Live]:
        out = {}
        for channel, collector in list(self.config.live.items()):
            runner = self.config.runners.get(channel)
            if runner is None or runner.state not in ACTIVE or collector.first_t is None:
                continue
            if runner.test_id != collector.test_id:
                continue
            state, now = runner.state.value, self.clock.now()
            # Test time now, not at the last record (records may be minutes apart).
            summary = (
                collector.summary("", state, complete=False, now=now)
                if detail
                else {
                    "recipe": collector.recipe,
                    "duration_s": round(collector.test_time_s(now), 3),
                    "channel": channel,
                    "metadata": collector.metadata.as_dict(),
                }
            )
            started = self.clock.to_wall(collector.first_t)
            out[collector.test_id] = _Live(channel, state, started, summary)
        return out

    # --- handlers -----------------------------------------------------------------------
    async def list(self, request: web.Request) -> web.Response:
        """Every test, newest first; ``?cell=ID``: every test of that cell."""
        unknown = sorted(set(request.query) - set(LIST_QUERY))
        if unknown:
            return _error(
                400, f"unknown query {', '.join(unknown)} (expected: {', '.join(LIST_QUERY)})"
            )
        cell = None
        if "cell" in request.query:
            try:
                cell = check_cell_id(request.query["cell"])
            except MetadataError as exc:
                return _error(400, str(exc))
        live = self._live()
        tests = await asyncio.to_thread(self._listing, live)
        if cell is not None:
            tests = [t for t in tests if t["metadata"].get("cell_id") == cell]
        return _json({"tests": tests})

    def _id(self, request: web.Request) -> str | None:
        test_id = request.match_info["id"]
        return test_id if valid_id(test_id) else None

    async def get(self, request: web.Request) -> web.Response:
        test_id = self._id(request)
        if test_id is None:
            return _error(400, f"test id {request.match_info['id'][:80]!r} refused (no folder)")
        live = self._live(detail=True).get(test_id)
        entry = await asyncio.to_thread(self._entry, test_id, live, True)
        if entry is None:
            return _error(404, f"no test {test_id!r}")
        return _json(entry)

    async def file(self, request: web.Request) -> web.StreamResponse:
        test_id, name = self._id(request), request.match_info["name"]
        if test_id is None or not valid_id(name):
            return _error(404, "no such file (a test id and one of its files' names)")
        folder = self.root / test_id
        listed = await asyncio.to_thread(_files, folder)
        found = next((f for f in listed if f["name"] == name), None)
        if found is None:
            return _error(404, f"test {test_id!r} has no file {name!r}")
        path = folder / name
        resolved = await asyncio.to_thread(path.resolve)
        root = await asyncio.to_thread(self.root.resolve)
        if not resolved.is_relative_to(root):  # a link out of the results directory
            log.warning("tests: %s points out of %s; refused", path, root)
            return _error(404, f"test {test_id!r} has no file {name!r}")
        return web.FileResponse(
            path,
            headers={
                "Content-Disposition": f'attachment; filename="{name}"',
                "Content-Type": CONTENT_TYPES.get(found["kind"], "application/octet-stream"),
            },
        )


def add_test_routes(app: web.Application, config: TestsConfig, clock: Clock) -> TestsApi:
    """Register ``GET /api/tests``, ``/api/tests/{id}``, ``/api/tests/{id}/files/{name}``."""
    api = TestsApi(config, clock)
    app.add_routes(
        [
            web.get("/api/tests", api.list),
            web.get("/api/tests/{id}", api.get),
            web.get("/api/tests/{id}/files/{name}", api.file),
        ]
    )
    return api
