"""Result files per test: BDF CSV, the Chadèche ``;`` line, the timeline, and a summary.

Layout: ``<results>/<test id>/`` with
- ``<test id>.bdf.csv`` — Battery Data Format columns (positive current charges);
- ``<test id>.chadeche.csv`` — seed 000 §III.E.2 result lines, for continuity;
- ``<test id>.timeline.jsonl`` — every timeline event (a step change with its cause, a
  state change, an alarm, an operator command), one JSON object a line, as it happens;
- ``<test id>.cycles.jsonl`` — every cycle's capacity, energy and efficiencies, one JSON
  object a line, written once the cycle is over (the next one started, or the test ended);
- ``summary.json`` — capacity and energy per cycle, efficiencies, duration, end reason,
  and the step timeline with the cause of every step change: of a long test the first
  and the latest ones only (``LIVE_EVENTS_KEPT``, ``LIVE_CYCLES_KEPT``), with the count of
  those between; the two ``.jsonl`` files hold them all (ADR 0022).

Nothing is created before the test starts (a recipe loaded and never started leaves no
file); the data files are opened at the first record. Rows are flushed as they are
written (a live test's by a thread of its own, :mod:`supervisor.publish.rows`): a crash
loses nothing already written. A live test's summary is rewritten atomically (temporary
file, then rename) at every event of its timeline and periodically (``checkpoint``),
marked ``"complete": false``, so a supervisor killed outright leaves the last one; the
final one (``"complete": true``) is written when the test ends. After a restart the files
of a resumed test continue in the same folder (``resume``): rows append, the record index,
the timeline and the cycles go on. What a test keeps in memory is bounded whatever its
length (issue 13: a week-long test is not a growing process).
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import IO, Any, Generic, TypeVar

from supervisor.core.encoding import WRITE_ERRORS
from supervisor.core.records import ChainEvent, Record
from supervisor.publish.provenance import (
    BDF_METADATA_SUFFIX,
    PROVENANCE_NAME,
    Provenance,
    TestMetadata,
    bdf_metadata,
    manifest,
    utc_iso,
    write_once,
)
from supervisor.publish.rows import RowWriter, ThreadWriter

log = logging.getLogger(__name__)

SUMMARY_NAME = "summary.json"
TIMELINE_SUFFIX = ".timeline.jsonl"
CYCLES_SUFFIX = ".cycles.jsonl"
SUMMARY_FORMAT = 3
"""2: ``complete``, ``duration_s`` as the test time at the end, efficiencies only for a
cycle with both a charge and a discharge (``efficiency_note`` says why not). 3 (ADR
0022): a live test's timeline and cycles are the first and the latest ones
(``timeline_omitted`` events after the first ``timeline_omitted_at``, ``cycles_omitted``),
every one of them in ``<id>.timeline.jsonl`` and ``<id>.cycles.jsonl``."""

LIVE_EVENTS_KEPT = 200
"""Timeline events a live test keeps in memory and in its summary: the first 100 (how the
test began) and the latest 100 (what it is doing), what the Tests screen shows; every
event is in the timeline file. Full after 200 step changes (8 minutes of
benchmarks/load-cycle.yaml, whose steps last 1 to 4 s)."""
LIVE_CYCLES_KEPT = 100
"""Cycles a live test keeps in memory and in its summary (the first 50 and the latest
50), besides the one under way; every cycle is in the cycles file."""

MIN_HALF_CYCLE_FRACTION = 0.01
"""A charge (or discharge) smaller than this fraction of the other side of its cycle is
an offset integrated during a rest or a top-off, not a half-cycle: the cycle then has no
efficiency (a ratio against it would read 0 or several hundred)."""

MAX_CLOSED_CYCLE_EFFICIENCY = 1.02
"""A cycle that gives back more charge than it took (beyond the 2 % a current sensor's
offset and gain may account for) did not begin where it ended: its first charge was a
top-up of a partly charged cell (a test starting at 50 % state of charge). Its ratio is
true arithmetic but no efficiency of the cell, so it is not given as one."""

BDF_COLUMNS = (
    "Test Time / s",
    "Unix Time / s",
    "Voltage / V",
    "Current / A",
    "Power / W",
    "Cycle Count / 1",
    "Step Count / 1",
    "Step ID",
    "Step Type",
    "Step Time / s",
    "Record Index / 1",
    "Charging Capacity / Ah",
    "Discharging Capacity / Ah",
    "Net Capacity / Ah",
    "Charging Energy / Wh",
    "Discharging Energy / Wh",
    "Cycle Charging Capacity / Ah",
    "Cycle Discharging Capacity / Ah",
    "Temperature T1 / degC",
)


def _f(x: float | None, digits: int = 6) -> str:
    return "" if x is None else f"{x:.{digits}g}"


def _aux_cell(x: object) -> object:
    """An auxiliary column's cell: a number as the BDF columns write theirs, a boolean as
    1 or 0 (a column a spreadsheet can sum), a text as it is, "" for a value not GOOD."""
    if x is None:
        return ""
    if isinstance(x, bool):
        return int(x)
    if isinstance(x, float):
        return _f(x)
    return x


def chadeche_line(rec: Record, dba: int) -> str:
    """``C;01;07;0; 50; 17520; 159; 17520; 21;1.373;1302.4;Mon May 22 03:21:43 2017``."""
    amps = rec.setpoint_a
    # The step's direction, not the sign of its setpoint: a discharge row at 0 mA is a
    # "D" row (the seed's letter sets the relay), which 0 ≥ 0 made "C" (issue 26, 6b).
    kind = rec.step_type
    cd = "D" if "DCH" in kind else "C" if "CHG" in kind else "C" if amps >= 0 else "D"
    sta = max(0.0, rec.step_remaining_s) if rec.step_remaining_s is not None else 0.0
    date = time.strftime("%a %b %d %H:%M:%S %Y", time.localtime(rec.wall))
    v = rec.voltage_v if rec.voltage_v is not None else 0.0
    return (
        f"{cd};{rec.cycle:02d};{rec.step_index + 1:02d};{dba};{abs(amps) * 1000:3.0f};"
        f" {rec.cycle_time_s:.0f}; {rec.step_time_s:.0f}; {rec.test_time_s:.0f}; {sta:.0f};"
        f"{v:.3f};{rec.charge_ah * 1000:.1f};{date}"
    )


@dataclass(slots=True)
class CycleSummary:
    """One cycle's figures (slots: a live test keeps up to ``LIVE_CYCLES_KEPT``)."""

    cycle: int
    charged_ah: float = 0.0
    discharged_ah: float = 0.0
    charged_wh: float = 0.0
    discharged_wh: float = 0.0
    complete: bool = False  # the next cycle started, or the test completed in this one

    def efficiency_note(self, why_open: str = "") -> str | None:
        """Why this cycle has no efficiency (None when it has one); ``why_open``: why an
        unfinished cycle stopped ("" while the test is under way)."""
        if not self.complete:
            if not why_open:
                return f"cycle {self.cycle} is under way"
            return f"cycle {self.cycle} did not finish ({why_open})"
        charged, discharged = self.charged_ah, self.discharged_ah
        if charged <= 0 or charged < MIN_HALF_CYCLE_FRACTION * discharged:
            return f"cycle {self.cycle} has no charge"
        if discharged <= 0 or discharged < MIN_HALF_CYCLE_FRACTION * charged:
            return f"cycle {self.cycle} has no discharge"
        if discharged > MAX_CLOSED_CYCLE_EFFICIENCY * charged:
            return (
                f"cycle {self.cycle} discharged {discharged / charged:.2f} times what it"
                " charged: it began partly charged, so the ratio is no efficiency"
            )
        return None

    def as_dict(self, why_open: str = "") -> dict[str, Any]:
        note = self.efficiency_note(why_open)
        ce = ee = None
        if note is None:
            ce = self.discharged_ah / self.charged_ah
            ee = self.discharged_wh / self.charged_wh if self.charged_wh > 0 else None
            if ee is None:
                note = f"cycle {self.cycle} has no charge energy (no voltage reading)"
        return {
            "cycle": self.cycle,
            "complete": self.complete,
            "charge_capacity_ah": round(self.charged_ah, 6),
            "discharge_capacity_ah": round(self.discharged_ah, 6),
            "charge_energy_wh": round(self.charged_wh, 6),
            "discharge_energy_wh": round(self.discharged_wh, 6),
            "coulombic_efficiency": None if ce is None else round(ce, 6),
            "energy_efficiency": None if ee is None else round(ee, 6),
            "efficiency_note": note,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CycleSummary:
        return cls(
            int(d["cycle"]),
            float(d.get("charge_capacity_ah", 0.0)),
            float(d.get("discharge_capacity_ah", 0.0)),
            float(d.get("charge_energy_wh", 0.0)),
            float(d.get("discharge_energy_wh", 0.0)),
            bool(d.get("complete", False)),
        )


# "command": an operator command of the running test, accepted or refused, by whom.
TIMELINE_KINDS = ("step", "state", "alarm", "command")

T = TypeVar("T")


class FirstAndLast(Generic[T]):
    """At most ``limit`` of the items appended: the first half and the latest half, and
    the count of those dropped between them (a dry run's timeline and cycles: the start
    and the end of a long run are what a reader looks at, memory stays bounded)."""

    def __init__(self, limit: int) -> None:
        if limit < 1:
            raise ValueError("keep at least one item")
        self.limit = limit
        self.first: list[T] = []
        self.last: deque[T] = deque(maxlen=limit - limit // 2)
        self.omitted = 0

    def append(self, item: T) -> T | None:
        """Keep ``item``; returns the item it pushed out, if any."""
        if len(self.first) < self.limit // 2:
            self.first.append(item)
            return None
        dropped = None
        if len(self.last) == self.last.maxlen:
            dropped = self.last[0]
            self.omitted += 1
        self.last.append(item)
        return dropped

    def __iter__(self) -> Iterator[T]:
        yield from self.first
        yield from self.last

    def items(self) -> list[T]:
        """The items kept, in order, as a new list (without a generator: a live test's
        summary takes them at every step change)."""
        return [*self.first, *self.last]

    def __len__(self) -> int:
        return len(self.first) + len(self.last)


class SummaryWriter(ThreadWriter):
    """Rewrites test summaries on a thread of its own, off the scan's (issue 13).

    A live test's summary is rewritten at every timeline event (a step change) and
    periodically; on the scan's thread that was a JSON dump and a file replaced per channel
    per event — 16 channels changing step in one scan cost that scan 10–25 ms. Here the
    scan hands over the summary (a dict it will not touch again) and returns; the thread
    writes the latest summary of each file, so a burst of checkpoints costs one write and a
    reader (or a restart after a kill) still finds the old file or the new one, never half.
    ``write_now`` (a test's last summary) writes at once, after anything older of that file.
    """

    what = "summaries"

    def __init__(self, name: str = "results") -> None:
        super().__init__(name)
        self._pending: dict[Path, tuple[str, dict[str, Any], int]] = {}
        self._io = threading.Lock()  # one file write at a time
        # Each summary handed over for a file gets the next number of that file: a write
        # whose number is no longer the file's latest is skipped. The thread may have taken
        # an older summary and be waiting for the disk when the test's last one is written
        # at once; the lock alone would let it overwrite the last one (found under load).
        self._generation: dict[Path, int] = {}
        self._writing = 0
        self.written = 0

    def put(self, path: Path, channel: str, summary: dict[str, Any]) -> None:
        """Write ``summary`` to ``path`` soon (replacing one not written yet); returns at once."""
        with self._cond:
            stopped = self._stopping
            if not stopped:
                self._pending[path] = (channel, summary, self._next_generation(path))
                self._start_thread()
        if stopped:
            self.write_now(path, channel, summary)  # stopped: on the caller's thread
        else:
            self._wake()

    def write_now(self, path: Path, channel: str, summary: dict[str, Any]) -> None:
        """Write ``summary`` now (an older one for ``path``, waiting or taken by the thread,
        is not written after it)."""
        with self._cond:
            self._pending.pop(path, None)
            generation = self._next_generation(path)
        self._write(path, channel, summary, generation)

    def _next_generation(self, path: Path) -> int:
        """(Under ``_cond``.)"""
        n = self._generation.get(path, 0) + 1
        self._generation[path] = n
        return n

    def _write(self, path: Path, channel: str, summary: dict[str, Any], generation: int) -> None:
        with self._io:
            with self._cond:
                latest = self._generation.get(path) == generation
            if latest:
                write_summary(path, channel, summary)
                self.written += 1

    def _busy(self) -> bool:
        return bool(self._pending or self._writing)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._stopping:
                    self._cond.wait()
            self._give_way()
            with self._cond:
                if not self._pending:
                    return
                path = next(iter(self._pending))
                channel, summary, generation = self._pending.pop(path)
                self._writing += 1
            try:
                self._write(path, channel, summary, generation)
            finally:
                with self._cond:
                    self._writing -= 1
                    self._cond.notify_all()


def write_summary(path: Path, channel: str, summary: dict[str, Any]) -> None:
    """Atomically: a reader (or a restart after a kill) sees the old or the new file,
    never half of one. No fsync: the failure this guards against is the process
    dying; the retained state (SQLite) is what survives a power cut."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8", errors=WRITE_ERRORS)
        tmp.replace(path)
    except OSError:
        log.exception("%s: cannot write %s", channel, path)


PAUSES_KEPT = 100
"""Pauses and restarts a summary lists (the first and the latest halves; every one of them
is in the timeline file)."""

PENDING_EVENTS_MAX = 32
"""Timeline events that may wait for the first record before the timeline file is opened
anyway (a test held before its first step, an operator's commands meanwhile)."""


def read_jsonl(path: Path) -> Iterator[dict[str, Any]]:
    """The objects of a JSON-lines result file, in order (none if there is no file). A
    line that is not a JSON object (the last one, cut short by a power cut) is skipped
    with a warning naming the file and the line."""
    try:
        f = path.open(encoding="utf-8")
    except FileNotFoundError:
        return
    with f:
        for n, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                obj = json.loads(line)
            except ValueError as exc:
                log.warning("%s:%d: not a JSON line (%s); skipped", path, n, exc)
                continue
            if isinstance(obj, dict):
                yield obj
            else:
                log.warning("%s:%d: not a JSON object; skipped", path, n)


def read_timeline(folder: Path) -> Iterator[dict[str, Any]]:
    """Every timeline event of the test in ``folder``: its timeline file, or the summary's
    timeline for a test recorded before there were timeline files (summary format 2)."""
    files = sorted(folder.glob(f"*{TIMELINE_SUFFIX}"))
    if files:
        yield from read_jsonl(files[0])
        return
    try:
        summary = json.loads((folder / SUMMARY_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return
    if isinstance(summary, dict):
        yield from summary.get("timeline", [])


def _open_jsonl(path: Path) -> IO[str]:
    """``path`` opened to append lines; a last line cut short (a power cut) is ended first
    so that the next line is whole (``read_jsonl`` skips the broken one)."""
    # A text UTF-8 cannot encode (a lone surrogate) is written as its escape, never an
    # exception that loses the line (``core/encoding.py``).
    f = path.open("a", encoding="utf-8", errors=WRITE_ERRORS)
    try:
        with path.open("rb") as r:
            size = r.seek(0, 2)
            if size > 0:
                r.seek(size - 1)
                if r.read(1) != b"\n":
                    f.write("\n")
                    f.flush()
    except OSError:
        f.close()
        raise
    return f


def _line(obj: dict[str, Any]) -> str:
    return json.dumps(obj, ensure_ascii=False) + "\n"


def _append_line(f: IO[str], obj: dict[str, Any]) -> None:
    f.write(_line(obj))
    f.flush()


@dataclass
class ResultCollector:
    """Writes a test's result files and keeps what its summary shows, bounded.

    The owner of a live test calls ``checkpoint`` at every timeline event and periodically
    (the summary of the test under way); a dry run only calls ``close``. ``events_kept``
    and ``cycles_kept`` bound what is kept in memory to the first and the latest halves
    (a live test's ``LIVE_EVENTS_KEPT``, ``LIVE_CYCLES_KEPT``; a dry run's
    ``DRY_RUN_EVENTS_KEPT``, ``DRY_RUN_CYCLES_KEPT``); the summary then counts the rest
    (``timeline_omitted`` after the first ``timeline_omitted_at`` events,
    ``cycles_omitted``). Every event and every cycle goes to the files (with a folder).
    None: everything is kept in memory too.
    """

    channel: str
    recipe: str
    test_id: str
    folder: Path | None = None
    dba: int = 0
    aux_columns: tuple[str, ...] = ()
    """Headers of the auxiliary columns after ``BDF_COLUMNS``, one per value of a
    record's ``aux`` (the channel's ``record:`` tags), fixed at the test's start."""
    records: int = 0
    timeline: list[dict[str, Any]] = field(default_factory=list)
    """The timeline when ``events_kept`` is None (else empty: see ``kept_timeline``)."""
    cycles: dict[int, CycleSummary] = field(default_factory=dict)
    """The cycles kept (``cycles_kept``) and the ones under way, by number."""
    first_t: float | None = None  # Clock.now() of the test start (test time 0)
    last_t: float | None = None  # the latest event or record
    last_rec: Record | None = None
    state: str = "Running"  # the chain's state at the last checkpoint
    closed: bool = False
    _bdf: IO[str] | None = None
    _bdf_writer: Any = None
    _cha: IO[str] | None = None
    _timeline_file: IO[str] | None = None
    _cycles_file: IO[str] | None = None
    _resumed: bool = False
    _aux_order: tuple[int | None, ...] | None = None
    """A resumed file's auxiliary columns as indexes into a record's ``aux`` (None: the
    same columns; an index None: a column no longer recorded, left empty)."""
    events_kept: int | None = LIVE_EVENTS_KEPT
    cycles_kept: int | None = LIVE_CYCLES_KEPT
    _events: FirstAndLast[dict[str, Any]] | None = None
    _kept_cycles: FirstAndLast[int] | None = None
    _open_cycles: set[int] = field(default_factory=set)  # not known complete yet
    _done_dicts: dict[int, dict[str, Any]] = field(default_factory=dict)
    """The summary's dicts of the finished cycles kept (``_cycle_dicts``)."""
    _unwritten_events: list[dict[str, Any]] = field(default_factory=list)
    """Events waiting for the timeline file (before the first record; after a restart)."""
    _unwritten_cycles: list[dict[str, Any]] = field(default_factory=list)
    """Finished cycles waiting for the cycles file (a summary of format 2 resumed)."""
    writer: SummaryWriter | None = None
    """Checkpoints go through it, off the caller's thread (None: written at once)."""
    rows: RowWriter | None = None
    """Rows go through it, off the caller's thread (None: written at once)."""
    metadata: TestMetadata = field(default_factory=TestMetadata)
    """The cell, its chemistry and capacity, the operator, the comment (summary, sidecar)."""
    provenance: Provenance | None = None
    """What produced the test: ``provenance.json``, written when the files are opened."""
    started_wall: float | None = None  # Unix time of test time 0
    last_wall: float | None = None  # Unix time of the latest event or record
    pauses: FirstAndLast[dict[str, Any]] = field(default_factory=lambda: FirstAndLast(PAUSES_KEPT))
    """Every hold and resume (state changes into or out of Held), first and latest ones."""
    restarts: FirstAndLast[str] = field(default_factory=lambda: FirstAndLast(PAUSES_KEPT))
    """When the test was resumed after a restart of the supervisor (UTC)."""

    def __post_init__(self) -> None:
        if self.events_kept is not None:
            self._events = FirstAndLast(self.events_kept)
        if self.cycles_kept is not None:
            self._kept_cycles = FirstAndLast(self.cycles_kept)

    # --- files -----------------------------------------------------------------------
    @property
    def bdf_path(self) -> Path | None:
        return None if self.folder is None else self.folder / f"{self.test_id}.bdf.csv"

    @property
    def chadeche_path(self) -> Path | None:
        return None if self.folder is None else self.folder / f"{self.test_id}.chadeche.csv"

    @property
    def timeline_path(self) -> Path | None:
        return None if self.folder is None else self.folder / f"{self.test_id}{TIMELINE_SUFFIX}"

    @property
    def cycles_path(self) -> Path | None:
        return None if self.folder is None else self.folder / f"{self.test_id}{CYCLES_SUFFIX}"

    @property
    def summary_path(self) -> Path | None:
        return None if self.folder is None else self.folder / SUMMARY_NAME

    @property
    def bdf_metadata_path(self) -> Path | None:
        return None if self.folder is None else self.folder / f"{self.test_id}{BDF_METADATA_SUFFIX}"

    def data_files(self) -> list[str]:
        """The files the final summary's manifest lists (those that exist)."""
        paths = (
            self.bdf_path,
            self.chadeche_path,
            self.timeline_path,
            self.cycles_path,
            self.bdf_metadata_path,
            None if self.folder is None else self.folder / PROVENANCE_NAME,
        )
        return [p.name for p in paths if p is not None]

    def _write_origin(self) -> None:
        """``provenance.json`` and the BDF metadata sidecar, once, at the test's start (a
        resumed test's stay as they were written: they describe how it began)."""
        if self.folder is None or self.started_wall is None:
            return
        try:
            if self.provenance is not None:
                doc = self.provenance.document(self.started_wall)
                write_once(self.folder / PROVENANCE_NAME, doc)
            path = self.bdf_metadata_path
            assert path is not None
            bench = self.provenance.bench if self.provenance is not None else ""
            write_once(
                path,
                bdf_metadata(self.test_id, self.channel, bench, self.metadata, self.started_wall),
            )
        except OSError:
            log.exception("%s: cannot write the provenance of %s", self.channel, self.folder)

    @property
    def kept_timeline(self) -> list[dict[str, Any]]:
        """The timeline events the summary shows (all of them when ``events_kept`` is None)."""
        return list(self.timeline) if self._events is None else self._events.items()

    def _open_files(self) -> None:
        """Opened at the first record (so never for a test that did not start), in append
        mode: a resumed test continues its files; the BDF header only once."""
        if self._bdf is not None or self.folder is None or self.closed:
            return
        bdf, cha = self.bdf_path, self.chadeche_path
        assert bdf is not None and cha is not None
        self.folder.mkdir(parents=True, exist_ok=True)
        fresh = not bdf.exists() or bdf.stat().st_size == 0
        if not fresh:
            self._resume_columns(bdf)
        self._bdf = bdf.open("a", newline="", encoding="utf-8", errors=WRITE_ERRORS)
        self._bdf_writer = csv.writer(self._bdf)
        if fresh:
            self._bdf_writer.writerow(BDF_COLUMNS + self.aux_columns)
            self._bdf.flush()
        self._cha = cha.open("a", encoding="utf-8", errors=WRITE_ERRORS)
        self._write_origin()
        self._open_timeline()
        self._open_cycles_file()

    def _resume_columns(self, bdf: Path) -> None:
        """The columns of a file this test started stay its columns (its header): if the
        I/O map's ``record:`` changed meanwhile, each row fills them from this one."""
        try:
            with bdf.open(encoding="utf-8", newline="") as f:
                header = tuple(next(csv.reader(f), ()))
        except OSError:
            return
        had = header[len(BDF_COLUMNS) :]
        if had != self.aux_columns:
            log.warning(
                "%s: %s has the columns %s; the channel records %s now (the file's kept)",
                self.channel,
                bdf,
                list(had),
                list(self.aux_columns),
            )
            index = {c: k for k, c in enumerate(self.aux_columns)}
            self._aux_order = tuple(index.get(c) for c in had)

    def _open_timeline(self) -> None:
        """The timeline file, and the events that waited for it written."""
        if self._timeline_file is not None or self.folder is None:
            return
        path = self.timeline_path
        assert path is not None
        self.folder.mkdir(parents=True, exist_ok=True)
        self._timeline_file = _open_jsonl(path)
        if self._unwritten_events:
            self._timeline_file.write("".join(_line(e) for e in self._unwritten_events))
            self._timeline_file.flush()
            self._unwritten_events.clear()

    def _open_cycles_file(self) -> None:
        """The cycles file, and the rows that waited for it written."""
        if self._cycles_file is not None or self.folder is None:
            return
        path = self.cycles_path
        assert path is not None
        self.folder.mkdir(parents=True, exist_ok=True)
        self._cycles_file = _open_jsonl(path)
        if self._unwritten_cycles:
            self._cycles_file.write("".join(_line(c) for c in self._unwritten_cycles))
            self._cycles_file.flush()
            self._unwritten_cycles.clear()

    def _close_files(self) -> None:
        self._rows_written()  # the lines handed over go to the files before they close
        for f in (self._bdf, self._cha, self._timeline_file, self._cycles_file):
            if f is not None:
                f.close()
        self._bdf = self._cha = self._timeline_file = self._cycles_file = None
        self._bdf_writer = None

    def _keep_event(self, entry: dict[str, Any]) -> None:
        (self._events if self._events is not None else self.timeline).append(entry)

    def _keep_cycle(self, c: CycleSummary) -> None:
        """A new cycle in memory; with a bound, the one it pushes out is forgotten (it is
        over, and in the cycles file: cycles end in order)."""
        self.cycles[c.cycle] = c
        self._done_dicts.pop(c.cycle, None)
        if self._kept_cycles is not None:
            dropped = self._kept_cycles.append(c.cycle)
            if dropped is not None:
                self.cycles.pop(dropped, None)
                self._done_dicts.pop(dropped, None)

    def _cycle_over(self, c: CycleSummary, why_open: str = "") -> None:
        """``c`` has its final figures: its row in the cycles file."""
        self._open_cycles.discard(c.cycle)
        if self._cycles_file is not None:
            self._append(self._cycles_file, c.as_dict(why_open))

    # --- what the chain emits ----------------------------------------------------------
    def on_event(self, ev: ChainEvent) -> None:
        if ev.kind not in TIMELINE_KINDS or self.closed:
            return
        if self.first_t is None:
            self.first_t = ev.t  # the start event (the first record sets it exactly)
        if self.started_wall is None:
            self.started_wall = ev.wall
        self.last_t = ev.t if self.last_t is None else max(self.last_t, ev.t)
        self.last_wall = ev.wall if self.last_wall is None else max(self.last_wall, ev.wall)
        if ev.kind == "state" and "Held" in ev.text:
            # "Running → Held (cause)", "Held → Running (resume by …)": a pause or its end.
            at_s = round(ev.t - self.first_t, 3)
            self.pauses.append({"test_time_s": at_s, "utc": utc_iso(ev.wall), "text": ev.text})
        entry = {
            "test_time_s": round(ev.t - self.first_t, 3),
            "kind": ev.kind,
            "cycle": ev.cycle,
            "step": ev.step_id,
            "text": ev.text,
        }
        self._keep_event(entry)
        if self._timeline_file is not None:
            self._append(self._timeline_file, entry)
        elif self.folder is not None:
            self._unwritten_events.append(entry)
            if len(self._unwritten_events) >= PENDING_EVENTS_MAX:
                self._open_timeline()

    def on_record(self, rec: Record) -> None:
        if self.closed:
            return
        if self.last_rec is None and not self._resumed:
            # Test time 0 is the chain's, whatever the first event's time was.
            self.first_t = rec.t - rec.test_time_s
            self.started_wall = rec.wall - rec.test_time_s
        self.last_wall = rec.wall if self.last_wall is None else max(self.last_wall, rec.wall)
        self._open_files()
        self.records += 1
        self.last_rec = rec
        self.last_t = rec.t if self.last_t is None else max(self.last_t, rec.t)
        # A later cycle started: the earlier ones reached their end (only those not yet
        # known complete are looked at: a million cycles stay linear).
        for n in sorted(n for n in self._open_cycles if n < rec.cycle):
            if n in self.cycles:
                self.cycles[n].complete = True
                self._cycle_over(self.cycles[n])
            self._open_cycles.discard(n)
        c = self.cycles.get(rec.cycle)
        if c is None:
            c = CycleSummary(rec.cycle)
            self._open_cycles.add(rec.cycle)
            self._keep_cycle(c)
        c.charged_ah = rec.cycle_charged_ah
        c.discharged_ah = rec.cycle_discharged_ah
        c.charged_wh = rec.cycle_charged_wh
        c.discharged_wh = rec.cycle_discharged_wh
        if self._bdf_writer is not None:
            if self.rows is not None:
                self.rows.put(partial(self._write_row, rec, self.records))
            else:
                self._write_row(rec, self.records)

    def _write_row(self, rec: Record, index: int) -> None:
        """The record's BDF row and Chadèche line, each flushed (on the row writer's
        thread when there is one)."""
        if self._bdf_writer is None or self._bdf is None or self._cha is None:
            return
        self._bdf_writer.writerow(
            (
                f"{rec.test_time_s:.3f}",
                f"{rec.wall:.3f}",
                _f(rec.voltage_v),
                _f(rec.current_a),
                _f(rec.power_w),
                rec.cycle,
                rec.step_count,
                rec.step_id,
                rec.step_type,
                f"{rec.step_time_s:.3f}",
                index,
                _f(rec.charged_ah),
                _f(rec.discharged_ah),
                _f(rec.charged_ah - rec.discharged_ah),
                _f(rec.charged_wh),
                _f(rec.discharged_wh),
                _f(rec.cycle_charged_ah),
                _f(rec.cycle_discharged_ah),
                _f(rec.temperature_c),
                *self._aux_cells(rec.aux),
            )
        )
        self._bdf.flush()
        self._cha.write(chadeche_line(rec, self.dba) + "\n")
        self._cha.flush()

    def _aux_cells(self, aux: tuple[object, ...]) -> list[object]:
        order = self._aux_order
        if order is None:
            return [_aux_cell(x) for x in aux]
        return [_aux_cell(aux[k]) if k is not None and k < len(aux) else "" for k in order]

    # --- the summary -------------------------------------------------------------------
    def test_time_s(self, now: float | None = None) -> float:
        """Test time at ``now`` (default: the latest event or record)."""
        t = now if now is not None else self.last_t
        if t is None or self.first_t is None:
            return 0.0
        return max(0.0, t - self.first_t)

    def summary(
        self,
        end_reason: str,
        state: str,
        *,
        complete: bool = True,
        now: float | None = None,
    ) -> dict[str, Any]:
        """The summary as it stands; ``complete``: the test is over (final summary). Its
        lists are its own (a writer's thread may dump it while the test goes on)."""
        if complete and state == "Complete" and self.cycles:
            self.cycles[max(self.cycles)].complete = True  # the recipe's own end
        why_open = (end_reason or "the test ended") if complete else ""
        out = {
            "format": SUMMARY_FORMAT,
            "test_id": self.test_id,
            "channel": self.channel,
            "recipe": self.recipe,
            "state": state,
            "complete": complete,
            "end_reason": end_reason,
            "duration_s": round(self.test_time_s(now), 3),
            "records": self.records,
            "cycles": self._cycle_dicts(why_open),
            "timeline": self.kept_timeline,
            "metadata": self.metadata.as_dict(),
            "started_utc": None if self.started_wall is None else utc_iso(self.started_wall),
            "ended_utc": (
                utc_iso(self.last_wall) if complete and self.last_wall is not None else None
            ),
            "pauses": self.pauses.items(),
            "pauses_omitted": self.pauses.omitted,
            "restarts": self.restarts.items(),
        }
        if self._events is not None:
            out["timeline_omitted"] = self._events.omitted
            out["timeline_omitted_at"] = len(self._events.first)
        if self._kept_cycles is not None:
            out["cycles_omitted"] = self._kept_cycles.omitted
        return out

    def _cycle_dicts(self, why_open: str) -> list[dict[str, Any]]:
        """Every kept cycle as the summary shows it. A finished cycle's figures no longer
        change: its dict is made once (a live test's summary is made at every step change,
        and keeps up to ``cycles_kept`` cycles: made anew each time, that was 100 cycles per
        step change and channel on the scan's thread after a few hours)."""
        done = self._done_dicts
        out = []
        for n, c in sorted(self.cycles.items()):
            d = done.get(n) if c.complete else None
            if d is None:
                d = c.as_dict(why_open)
                if c.complete and n not in self._open_cycles:
                    done[n] = d  # read only from here on (a writer's thread may dump it)
            out.append(d)
        return out

    def checkpoint(self, state: str = "", now: float | None = None) -> None:
        """Rewrite the summary of the test under way (``"complete": false``); ``state``:
        the chain's state now (default: the last one given)."""
        if state:
            self.state = state
        if self.closed or self.folder is None or self.first_t is None:
            return
        summary = self.summary("", self.state, complete=False, now=now)
        if self.writer is None:
            self._write(summary)
        else:
            # The writer's thread dumps it later: nothing in it changes meanwhile.
            path = self.summary_path
            assert path is not None
            self.writer.put(path, self.channel, summary)

    def close(
        self,
        end_reason: str,
        state: str,
        *,
        complete: bool = True,
        now: float | None = None,
    ) -> dict[str, Any]:
        """The test's last summary, and the files closed. ``complete=False``: the test
        did not end (the supervisor stops with it under way; it may resume after a
        restart), so the summary is not final and the cycle under way has no row yet."""
        s = self.summary(end_reason, state, complete=complete, now=now)
        self._rows_written()
        if self.folder is not None and self.first_t is not None and not self.closed:
            # A test that ended before its first record (after a restart: before the
            # next one) has its events and its cycles' rows too.
            self._open_timeline()
            self._open_cycles_file()
            if complete:
                why_open = end_reason or "the test ended"
                for n in sorted(self._open_cycles):
                    if n in self.cycles:
                        self._cycle_over(self.cycles[n], why_open)
                # The data files are final: their hashes go in the final summary, for
                # ``supervisor results verify`` (provenance.verify).
                self._close_files()
                s["manifest"] = manifest(self.folder, self.data_files())
            self._write(s)
        self._close_files()
        self.closed = True
        return s

    def abandon(self) -> None:
        """Close the files and write nothing more (this process goes away without the
        test ending, e.g. a start-up that failed); the last summary stays as it is."""
        self._rows_written()
        self._close_files()
        self.closed = True

    def _append(self, f: IO[str], entry: dict[str, Any]) -> None:
        """One line of a JSON-lines file (the timeline, the cycles), flushed: on the row
        writer's thread when there is one, as the rows (16 channels changing step in one
        scan were 16 writes on the scan's thread, each a system call; issue 13)."""
        if self.rows is not None:
            self.rows.put(partial(_append_line, f, entry))
        else:
            _append_line(f, entry)

    def _rows_written(self) -> None:
        """Every row and line handed over is in the files (before they close, and before
        the last summary counts them)."""
        files = (self._bdf, self._timeline_file, self._cycles_file)
        if self.rows is not None and any(f is not None for f in files) and not self.rows.flush():
            log.error(
                "%s: result rows still not written; the files close without them", self.channel
            )

    def _write(self, summary: dict[str, Any]) -> None:
        """At once (after a checkpoint of the same file still waiting in the writer)."""
        path = self.summary_path
        assert path is not None and self.folder is not None
        if self.writer is not None:
            self.writer.write_now(path, self.channel, summary)
        else:
            write_summary(path, self.channel, summary)

    # --- after a restart ------------------------------------------------------------------
    def resume(self, first_t: float) -> None:
        """Continue the files of this test after a restart, with test time 0 at
        ``first_t`` (the restored chain's): the record index from the BDF rows, the
        timeline and the finished cycles from their files (read line by line into the
        bounded memory, as if the test had run on), the cycle under way from the last
        summary. A summary of format 2 (the timeline and the cycles whole in it, no
        ``.jsonl`` files) gives its events and finished cycles to the new files."""
        self.first_t = first_t
        self.last_t = None
        self._resumed = True
        self.restarts.append(utc_iso(time.time()))
        old: dict[str, Any] = {}
        path = self.summary_path
        if path is not None and path.exists():
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
                old = data if isinstance(data, dict) else {}
            except (OSError, ValueError) as exc:
                log.warning(
                    "%s: summary %s unreadable (%s); starting a new one", self.channel, path, exc
                )
        self._resume_record(old)
        try:
            self._resume_timeline(old)
            self._resume_cycles(old)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning(
                "%s: results of %s unreadable (%s); the summary starts again",
                self.channel,
                self.folder,
                exc,
            )
        bdf = self.bdf_path
        if bdf is not None and bdf.exists():
            with contextlib.suppress(OSError), bdf.open(encoding="utf-8") as f:
                self.records = max(0, sum(1 for _ in f) - 1)  # minus the header

    def _resume_record(self, old: dict[str, Any]) -> None:
        """The metadata, the start time, the pauses and the restarts the last summary had
        (the metadata given at the start hold for the whole test)."""
        if old.get("metadata") and self.metadata == TestMetadata():
            self.metadata = TestMetadata.from_dict(old["metadata"])
        started = old.get("started_utc")
        if isinstance(started, str) and self.started_wall is None:
            with contextlib.suppress(ValueError):
                self.started_wall = datetime.fromisoformat(started).timestamp()
        earlier = self.restarts.items()
        self.restarts = FirstAndLast(PAUSES_KEPT)
        for key, kept in (("pauses", self.pauses), ("restarts", self.restarts)):
            items = old.get(key)
            if isinstance(items, list):
                for item in items:
                    kept.append(item)
        for item in earlier:
            self.restarts.append(item)

    def _resume_timeline(self, old: dict[str, Any]) -> None:
        path = self.timeline_path
        assert path is not None
        n = 0
        for entry in read_jsonl(path):
            self._keep_event(entry)
            n += 1
        if n == 0:
            # No timeline file (format 2, or killed before the first record): the
            # summary's events are the timeline so far, and go to the file.
            for entry in old.get("timeline", []):
                self._keep_event(dict(entry))
                self._unwritten_events.append(dict(entry))

    def _resume_cycles(self, old: dict[str, Any]) -> None:
        path = self.cycles_path
        assert path is not None
        last = 0
        for row in read_jsonl(path):
            c = CycleSummary.from_dict(row)
            if c.cycle > last:
                self._keep_cycle(c)
                last = c.cycle
        # The summary's later cycles: the one under way (and, from a summary of format 2,
        # every finished one, which the cycles file has not got yet).
        for row in old.get("cycles", []):
            c = CycleSummary.from_dict(row)
            if c.cycle <= last:
                continue
            self._keep_cycle(c)
            last = c.cycle
            if c.complete:
                self._unwritten_cycles.append(c.as_dict())
            else:
                self._open_cycles.add(c.cycle)

    @staticmethod
    def final_summary(folder: Path) -> bool:
        """Whether ``folder`` holds a final summary (the test there is over)."""
        try:
            data = json.loads((folder / SUMMARY_NAME).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        return isinstance(data, dict) and data.get("complete") is True
