"""Result files per test: BDF CSV, the Chadèche ``;`` line, and a summary.

Layout: ``<results>/<test id>/`` with
- ``<test id>.bdf.csv`` — Battery Data Format columns (positive current charges);
- ``<test id>.chadeche.csv`` — seed 000 §III.E.2 result lines, for continuity;
- ``summary.json`` — capacity and energy per cycle, efficiencies, duration, end reason,
  and the step timeline with the cause of every step change.

Nothing is created before the test starts (a recipe loaded and never started leaves no
file). Rows are flushed as they are written (a live test's by a thread of its own,
:mod:`supervisor.publish.rows`): a crash loses nothing already written. A
live test's summary is rewritten atomically (temporary file, then rename) at every event
of its timeline and periodically (``checkpoint``), marked ``"complete": false``, so a supervisor
killed outright leaves the last one; the final one (``"complete": true``) is written when
the test ends. After a restart the files of a resumed test continue in the same folder
(``resume``): rows append, the record index and the timeline go on.
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
from functools import partial
from pathlib import Path
from typing import IO, Any, Generic, TypeVar

from supervisor.core.records import ChainEvent, Record
from supervisor.publish.rows import RowWriter

log = logging.getLogger(__name__)

SUMMARY_NAME = "summary.json"
SUMMARY_FORMAT = 2
"""2: ``complete``, ``duration_s`` as the test time at the end, efficiencies only for a
cycle with both a charge and a discharge (``efficiency_note`` says why not)."""

MIN_HALF_CYCLE_FRACTION = 0.01
"""A charge (or discharge) smaller than this fraction of the other side of its cycle is
an offset integrated during a rest or a top-off, not a half-cycle: the cycle then has no
efficiency (a ratio against it would read 0 or several hundred)."""

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


def chadeche_line(rec: Record, dba: int) -> str:
    """``C;01;07;0; 50; 17520; 159; 17520; 21;1.373;1302.4;Mon May 22 03:21:43 2017``."""
    amps = rec.setpoint_a
    cd = "C" if amps >= 0 else "D"
    sta = max(0.0, rec.step_remaining_s) if rec.step_remaining_s is not None else 0.0
    date = time.strftime("%a %b %d %H:%M:%S %Y", time.localtime(rec.wall))
    v = rec.voltage_v if rec.voltage_v is not None else 0.0
    return (
        f"{cd};{rec.cycle:02d};{rec.step_index + 1:02d};{dba};{abs(amps) * 1000:3.0f};"
        f" {rec.cycle_time_s:.0f}; {rec.step_time_s:.0f}; {rec.test_time_s:.0f}; {sta:.0f};"
        f"{v:.3f};{rec.charge_ah * 1000:.1f};{date}"
    )


@dataclass
class CycleSummary:
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

    def __len__(self) -> int:
        return len(self.first) + len(self.last)


class SummaryWriter:
    """Rewrites test summaries on a thread of its own, off the scan's (issue 13).

    A live test's summary is rewritten at every timeline event (a step change) and
    periodically; on the scan's thread that was a JSON dump and a file replaced per channel
    per event — 16 channels changing step in one scan cost that scan 10–25 ms. Here the
    scan hands over the summary (a dict it will not touch again) and returns; the thread
    writes the latest summary of each file, so a burst of checkpoints costs one write and a
    reader (or a restart after a kill) still finds the old file or the new one, never half.
    ``write_now`` (a test's last summary) writes at once, after anything older of that file.
    """

    def __init__(self, name: str = "results") -> None:
        self.name = name
        self._cond = threading.Condition()
        self._pending: dict[Path, tuple[str, dict[str, Any]]] = {}
        self._io = threading.Lock()  # one file write at a time: the newest is written last
        self._writing = 0
        self._stopping = False
        self._thread: threading.Thread | None = None
        self.written = 0

    def put(self, path: Path, channel: str, summary: dict[str, Any]) -> None:
        """Write ``summary`` to ``path`` soon (replacing one not written yet); returns at once."""
        with self._cond:
            if not self._stopping:
                self._pending[path] = (channel, summary)
                if self._thread is None:
                    self._thread = threading.Thread(
                        target=self._run, name=f"{self.name}-summaries", daemon=True
                    )
                    self._thread.start()
                self._cond.notify_all()
                return
        self.write_now(path, channel, summary)  # stopped: on the caller's thread

    def write_now(self, path: Path, channel: str, summary: dict[str, Any]) -> None:
        """Write ``summary`` now (the older one waiting for ``path`` is dropped)."""
        with self._cond:
            self._pending.pop(path, None)
        with self._io:
            write_summary(path, channel, summary)
            self.written += 1

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until every summary handed over is on disk; False after ``timeout_s``."""
        end = time.monotonic() + timeout_s
        with self._cond:
            while self._pending or self._writing:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def stop(self, timeout_s: float = 10.0) -> None:
        """Write what is waiting, then end the thread; later summaries are written at once."""
        if not self.flush(timeout_s):
            log.error("%s: summaries not written within %g s", self.name, timeout_s)
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
            thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._stopping:
                    self._cond.wait()
                if not self._pending:
                    return
                path = next(iter(self._pending))
                channel, summary = self._pending.pop(path)
                self._writing += 1
            try:
                with self._io:
                    write_summary(path, channel, summary)
                    self.written += 1
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
        tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
        tmp.replace(path)
    except OSError:
        log.exception("%s: cannot write %s", channel, path)


@dataclass
class ResultCollector:
    """Keeps the timeline and per-cycle figures in memory; writes files if given a folder.

    The owner of a live test calls ``checkpoint`` at every timeline event and periodically
    (the summary of the test under way); a dry run only calls ``close``. ``events_kept``
    and ``cycles_kept`` (a dry run's ``DRY_RUN_EVENTS_KEPT``, ``DRY_RUN_CYCLES_KEPT``) bound
    what is kept in memory to the first and the last halves; the summary then counts the
    rest (``timeline_omitted`` after the first ``timeline_omitted_at`` events,
    ``cycles_omitted``). None: everything is kept (a live test's record).
    """

    channel: str
    recipe: str
    test_id: str
    folder: Path | None = None
    dba: int = 0
    records: int = 0
    timeline: list[dict[str, Any]] = field(default_factory=list)
    cycles: dict[int, CycleSummary] = field(default_factory=dict)
    first_t: float | None = None  # Clock.now() of the test start (test time 0)
    last_t: float | None = None  # the latest event or record
    last_rec: Record | None = None
    state: str = "Running"  # the chain's state at the last checkpoint
    closed: bool = False
    _bdf: IO[str] | None = None
    _bdf_writer: Any = None
    _cha: IO[str] | None = None
    _resumed: bool = False
    events_kept: int | None = None
    cycles_kept: int | None = None
    _events: FirstAndLast[dict[str, Any]] | None = None
    _kept_cycles: FirstAndLast[int] | None = None
    _open_cycles: set[int] = field(default_factory=set)  # not known complete yet
    writer: SummaryWriter | None = None
    """Checkpoints go through it, off the caller's thread (None: written at once)."""
    rows: RowWriter | None = None
    """Rows go through it, off the caller's thread (None: written at once)."""

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
    def summary_path(self) -> Path | None:
        return None if self.folder is None else self.folder / SUMMARY_NAME

    def _open_files(self) -> None:
        """Opened at the first record (so never for a test that did not start), in append
        mode: a resumed test continues its files; the BDF header only once."""
        if self._bdf is not None or self.folder is None or self.closed:
            return
        bdf, cha = self.bdf_path, self.chadeche_path
        assert bdf is not None and cha is not None
        self.folder.mkdir(parents=True, exist_ok=True)
        fresh = not bdf.exists() or bdf.stat().st_size == 0
        self._bdf = bdf.open("a", newline="", encoding="utf-8")
        self._bdf_writer = csv.writer(self._bdf)
        if fresh:
            self._bdf_writer.writerow(BDF_COLUMNS)
            self._bdf.flush()
        self._cha = cha.open("a", encoding="utf-8")

    # --- what the chain emits ----------------------------------------------------------
    def on_event(self, ev: ChainEvent) -> None:
        if ev.kind not in TIMELINE_KINDS or self.closed:
            return
        if self.first_t is None:
            self.first_t = ev.t  # the start event (the first record sets it exactly)
        self.last_t = ev.t if self.last_t is None else max(self.last_t, ev.t)
        entry = {
            "test_time_s": round(ev.t - self.first_t, 3),
            "kind": ev.kind,
            "cycle": ev.cycle,
            "step": ev.step_id,
            "text": ev.text,
        }
        (self._events if self._events is not None else self.timeline).append(entry)

    def on_record(self, rec: Record) -> None:
        if self.closed:
            return
        if self.last_rec is None and not self._resumed:
            # Test time 0 is the chain's, whatever the first event's time was.
            self.first_t = rec.t - rec.test_time_s
        self._open_files()
        self.records += 1
        self.last_rec = rec
        self.last_t = rec.t if self.last_t is None else max(self.last_t, rec.t)
        # A later cycle started: the earlier ones reached their end (only those not yet
        # known complete are looked at: a million cycles stay linear).
        for n in [n for n in self._open_cycles if n < rec.cycle]:
            self._open_cycles.discard(n)
            if n in self.cycles:
                self.cycles[n].complete = True
        c = self.cycles.get(rec.cycle)
        if c is None:
            c = self.cycles[rec.cycle] = CycleSummary(rec.cycle)
            self._open_cycles.add(rec.cycle)
            if self._kept_cycles is not None:
                dropped = self._kept_cycles.append(rec.cycle)
                if dropped is not None:
                    self.cycles.pop(dropped, None)
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
            )
        )
        self._bdf.flush()
        self._cha.write(chadeche_line(rec, self.dba) + "\n")
        self._cha.flush()

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
        """The summary as it stands; ``complete``: the test is over (final summary)."""
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
            "cycles": [c.as_dict(why_open) for _, c in sorted(self.cycles.items())],
            "timeline": self.timeline if self._events is None else list(self._events),
        }
        if self._events is not None:
            out["timeline_omitted"] = self._events.omitted
            out["timeline_omitted_at"] = len(self._events.first)
        if self._kept_cycles is not None:
            out["cycles_omitted"] = self._kept_cycles.omitted
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
            # The writer's thread dumps it later: nothing in it may change meanwhile.
            summary["timeline"] = list(summary["timeline"])
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
        restart), so the summary is not final."""
        s = self.summary(end_reason, state, complete=complete, now=now)
        self._rows_written()
        if self.folder is not None and self.first_t is not None and not self.closed:
            self._write(s)
        for f in (self._bdf, self._cha):
            if f is not None:
                f.close()
        self._bdf = self._cha = None
        self._bdf_writer = None
        self.closed = True
        return s

    def abandon(self) -> None:
        """Close the files and write nothing more (this process goes away without the
        test ending, e.g. a start-up that failed); the last summary stays as it is."""
        self._rows_written()
        for f in (self._bdf, self._cha):
            if f is not None:
                f.close()
        self._bdf = self._cha = None
        self._bdf_writer = None
        self.closed = True

    def _rows_written(self) -> None:
        """Every row handed over is in the files (before they close, and before the last
        summary counts them)."""
        if self.rows is not None and self._bdf is not None and not self.rows.flush():
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
        """Continue the files of this test after a restart: the timeline and the cycles
        from the last summary, the record index from the BDF rows; test time 0 at
        ``first_t`` (the restored chain's)."""
        self.first_t = first_t
        self.last_t = None
        self._resumed = True
        path = self.summary_path
        if path is not None and path.exists():
            try:
                old = json.loads(path.read_text(encoding="utf-8"))
                self.timeline = list(old.get("timeline", []))
                self.cycles = {
                    int(c["cycle"]): CycleSummary.from_dict(c) for c in old.get("cycles", [])
                }
                self._open_cycles = {n for n, c in self.cycles.items() if not c.complete}
            except (OSError, ValueError, KeyError, TypeError) as exc:
                log.warning(
                    "%s: summary %s unreadable (%s); starting a new one", self.channel, path, exc
                )
        bdf = self.bdf_path
        if bdf is not None and bdf.exists():
            with contextlib.suppress(OSError), bdf.open(encoding="utf-8") as f:
                self.records = max(0, sum(1 for _ in f) - 1)  # minus the header

    @staticmethod
    def final_summary(folder: Path) -> bool:
        """Whether ``folder`` holds a final summary (the test there is over)."""
        try:
            data = json.loads((folder / SUMMARY_NAME).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        return isinstance(data, dict) and data.get("complete") is True
