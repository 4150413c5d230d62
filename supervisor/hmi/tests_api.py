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
- ``GET /api/tests/{id}/curves?cycles=1,5``: voltage against charge of each half of those
  cycles (default: up to ``CURVE_CYCLES_MAX`` cycles spread over the test, the first and
  the latest among them), read from its BDF file, decimated (``publish/curves.py``):
  ``{"id", "cycles", "cycles_total", "points_max", "curves": [{"cycle", "half", "index",
  "rows", "ah", "v"}]}``.
- ``GET /api/fade?cell=ID``: the capacity fade of one cell: every test of it, oldest
  first, with the discharge capacity of each finished cycle against the cell's cumulative
  cycle number (the cycles of its earlier tests before): ``{"cell", "tests": [{"id",
  "started", "offset", "cycle", "cumulative_cycle", "discharge_ah"}]}``.

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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from aiohttp import web

from supervisor.chains.engine import ChainRunner
from supervisor.chains.states import ACTIVE
from supervisor.core.clock import Clock
from supervisor.hmi.recipes_api import _dumps, cycle_json, timeline_json
from supervisor.publish.curves import (
    MAX_POINTS_PER_CURVE,
    cycle_capacities,
    cycle_numbers,
    half_curves,
)
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
CURVES_QUERY: Final = ("cycles",)
CURVE_CYCLES_MAX: Final = 24
"""Cycles of one answer of ``/curves``: each of their halves is a curve on one chart."""
FADE_POINTS_MAX: Final = 5000
"""Cycles of one test in the fade chart (more are thinned evenly, the last one kept)."""


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

    # --- tests compared (issue 33 finding 10) -------------------------------------------
    def _curves(self, test_id: str, asked: Sequence[int] | None) -> tuple[int, dict[str, Any]]:
        folder = self.root / test_id
        if not folder.is_dir():
            return 404, {"error": "not found", "reason": f"no test {test_id!r}"}
        bdf = _bdf_of(folder)
        if bdf is None:
            return 404, {"error": "not found", "reason": f"test {test_id!r} has no BDF file"}
        numbers = cycle_numbers(folder, self._summary(folder))
        cycles = asked if asked is not None else spread(numbers, CURVE_CYCLES_MAX)
        curves = half_curves(bdf, cycles)
        return 200, {
            "id": test_id,
            "cycles": cycles,
            "cycles_total": len(numbers),
            "points_max": MAX_POINTS_PER_CURVE,
            "curves": [c.as_dict() for c in curves],
        }

    async def curves(self, request: web.Request) -> web.Response:
        """V against Ah of each half of some cycles of one test (read-only, a viewer's)."""
        test_id = self._id(request)
        if test_id is None:
            return _error(404, f"no test {request.match_info['id'][:80]!r} (a test id)")
        unknown = sorted(set(request.query) - set(CURVES_QUERY))
        if unknown:
            return _error(400, f"unknown query {', '.join(unknown)} (expected: cycles)")
        asked = None
        if "cycles" in request.query:
            try:
                asked = parse_cycles(request.query["cycles"])
            except ValueError as exc:
                return _error(400, str(exc))
        status, body = await asyncio.to_thread(self._curves, test_id, asked)
        return _json(body, status)

    def _fade(self, cell: str) -> Sequence[dict[str, Any]]:
        tests = [t for t in self._listing({}) if t["metadata"].get("cell_id") == cell]
        tests.sort(key=lambda t: (t["started"] or 0.0, t["id"]))  # oldest first
        out, offset = [], 0
        for t in tests:
            folder = self.root / t["id"]
            caps, seen = cycle_capacities(folder, self._summary(folder))
            caps = [caps[k] for k in spread(list(range(len(caps))), FADE_POINTS_MAX)]
            out.append(
                {
                    "id": t["id"],
                    "started": t["started"],
                    "offset": offset,
                    "cycle": [c.cycle for c in caps],
                    "cumulative_cycle": [offset + c.cycle for c in caps],
                    "discharge_ah": [c.discharge_ah for c in caps],
                }
            )
            offset += seen
        return out

    async def fade(self, request: web.Request) -> web.Response:
        """The discharge capacity per cycle of every test of one cell (read-only)."""
        unknown = sorted(set(request.query) - set(LIST_QUERY))
        if unknown or "cell" not in request.query:
            return _error(400, "expected the query cell=ID (a cell id)")
        try:
            cell = check_cell_id(request.query["cell"])
        except MetadataError as exc:
            return _error(400, str(exc))
        if not cell:
            return _error(400, "cell: empty (a cell id)")
        tests = await asyncio.to_thread(self._fade, cell)
        if not tests:
            return _error(404, f"no finished or running test of cell {cell!r} in the results")
        return _json({"cell": cell, "tests": tests})


def spread(numbers: list[int], limit: int) -> list[int]:
    """At most ``limit`` of ``numbers``, evenly spread, the first and the last kept."""
    if len(numbers) <= limit:
        return numbers
    step = (len(numbers) - 1) / (limit - 1)
    return sorted({numbers[round(k * step)] for k in range(limit)})


def parse_cycles(text: str) -> list[int]:
    """``1,5,9`` as cycle numbers; ValueError naming what is wrong."""
    out = []
    for part in text.split(","):
        part = part.strip()
        if not part.isdigit() or not 0 < int(part) < 10**9:
            raise ValueError(f"cycles: {part[:20]!r} is not a cycle number (1, 2, …)")
        out.append(int(part))
    if len(set(out)) > CURVE_CYCLES_MAX:
        raise ValueError(f"cycles: at most {CURVE_CYCLES_MAX} cycles at once")
    return sorted(set(out))


# --- tests compared (issue 33 finding 10) -------------------------------------------------
def _bdf_of(folder: Path) -> Path | None:
    """The test's BDF file, never one out of the results directory (a link)."""
    name = next((str(f["name"]) for f in _files(folder) if f["kind"] == "bdf"), None)
    if name is None:
        return None
    path = folder / name
    if not path.resolve().is_relative_to(folder.parent.resolve()):
        log.warning("tests: %s points out of %s; refused", path, folder.parent)
        return None
    return path


def add_test_routes(app: web.Application, config: TestsConfig, clock: Clock) -> TestsApi:
    """Register ``GET /api/tests``, ``/api/tests/{id}``, ``/api/tests/{id}/files/{name}``,
    ``/api/tests/{id}/curves`` and ``/api/fade``."""
    api = TestsApi(config, clock)
    app.add_routes(
        [
            web.get("/api/tests", api.list),
            web.get("/api/tests/{id}", api.get),
            web.get("/api/tests/{id}/files/{name}", api.file),
            web.get("/api/tests/{id}/curves", api.curves),
            web.get("/api/fade", api.fade),
        ]
    )
    return api
