"""The embedded historian (supervisor/publish/historian, docs/adr/0013-historian.md).

Tags change on the virtual clock, one scan at a time; the historian queues each scan's
changes and its writer thread commits them; a test waits for the disk with
``writer.flush()`` (no timing assertion anywhere). Faults are real SQLite conditions on a
real file: a full database (``max_page_count``), a read-only connection, files that are
not a database, truncated, scribbled over or another program's.
"""

from __future__ import annotations

import logging
import math
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from supervisor.app.history import history_enabled, history_path
from supervisor.core.clock import VirtualClock
from supervisor.core.driver import Value
from supervisor.core.errors import ConfigErrors
from supervisor.core.gate import ScanGate
from supervisor.core.quality import Quality
from supervisor.core.records import BenchEvent
from supervisor.devices.registry import bench_from_data, load_bench
from supervisor.publish.changes import Sample
from supervisor.publish.historian import (
    CORRUPT_ALARM,
    CRASH_ALARM,
    OVERFLOW_ALARM,
    WRITE_ALARM,
    BadRange,
    Historian,
    HistoryQuery,
    UnknownTag,
    WriterSettings,
)
from supervisor.publish.historian.store import (
    CACHE_KIB,
    CACHE_KIB_PER_TAG,
    CACHE_MIN_KIB,
    TagInfo,
    cache_kib,
    connect,
    used_bytes,
)
from supervisor.tags import HistorySettings, TagDB, TagSpec

EPOCH = 1_767_225_600.0  # VirtualClock's default: 2026-01-01T00:00:00Z
FAST = WriterSettings(commit_interval_s=0.02, retry_s=0.02)


@dataclass
class Rig:
    db: TagDB
    clock: VirtualClock
    historian: Historian
    alarms: list[tuple[str, bool, str]] = field(default_factory=list)

    @property
    def query(self) -> HistoryQuery:
        return self.historian.query

    def scan(self, values: dict[str, Any] | None = None, dt_s: float = 1.0) -> None:
        """One scan ``dt_s`` after the last: the values acquired now, then publish."""
        self.clock.advance(dt_s)
        now = self.clock.now()
        self.db.set_scan_time(now)
        for name, v in (values or {}).items():
            quality = Quality.GOOD
            if isinstance(v, Quality):
                v, quality = None, v
            self.db.update(self.db[name], v, quality, source_t=now)
        self.historian.on_scan(self.db, now)

    def flush(self, **kw: Any) -> None:
        assert self.historian.writer.flush(**kw)

    def stored(self, tag: str) -> list[tuple[float, Value | None, Quality]]:
        """(seconds since the epoch of the clock, value, quality) of every stored sample."""
        series = self.query.samples(tag, 0.0, 4e9, limit=100_000)
        return [(s.t - EPOCH, s.value, s.quality) for s in series.samples]

    def active(self, alarm_id: str) -> bool | None:
        """The alarm's last state as the hook was told (None: never told)."""
        states = [a for i, a, _ in self.alarms if i == alarm_id]
        return states[-1] if states else None


Make = Callable[..., Rig]


@pytest.fixture
def make(tmp_path: Path) -> Iterator[Make]:
    rigs: list[Rig] = []

    def build(
        *specs: TagSpec,
        settings: WriterSettings = FAST,
        path: Path | None = None,
        clock: VirtualClock | None = None,
        open_now: bool = True,
        connect_hook: Callable[[sqlite3.Connection], None] | None = None,
    ) -> Rig:
        db = TagDB()
        for spec in specs or (TagSpec("ch0.voltage", unit="V"),):
            db.add(spec)
        clock = clock or VirtualClock()
        alarms: list[tuple[str, bool, str]] = []
        historian = Historian(
            db,
            clock,
            path or tmp_path / "state" / "history.sqlite",
            settings,
            alarm=lambda a, on, text: alarms.append((a, on, text)),
            connect_hook=connect_hook,
        )
        rig = Rig(db, clock, historian, alarms)
        rigs.append(rig)
        if open_now:
            historian.open()
        return rig

    yield build
    for rig in rigs:
        rig.historian.close()


# --- what is stored -----------------------------------------------------------------


def cache_kib_of(conn: sqlite3.Connection) -> int:
    return -int(conn.execute("PRAGMA cache_size").fetchone()[0])


def test_the_writers_page_cache_is_sized_for_the_tags_it_records_up_to_a_ceiling(
    make: Make,
) -> None:
    # A page cache fills up to its size as the file grows: sized for the worst case it grew
    # for an hour on the simulated bench (issue 13's memory figure).
    conns: list[sqlite3.Connection] = []
    names = [f"t{i:04d}" for i in range(600)]
    rig = make(*(TagSpec(n) for n in names), connect_hook=conns.append)
    assert cache_kib_of(conns[-1]) == CACHE_MIN_KIB  # no tag recorded yet
    rig.scan({n: float(i) for i, n in enumerate(names)})
    rig.flush()
    recorded = conns[-1].execute("SELECT count(*) FROM tags").fetchone()[0]
    assert recorded >= 600  # and the historian's own status tags
    assert cache_kib_of(conns[-1]) == recorded * CACHE_KIB_PER_TAG
    assert cache_kib(1) == CACHE_MIN_KIB
    assert cache_kib(100_000) == CACHE_KIB  # the ceiling it had before, for every size


def test_a_change_within_the_deadband_is_not_stored_and_one_beyond_it_is(make: Make) -> None:
    r = make(TagSpec("ch0.voltage", unit="V", history=HistorySettings(deadband=0.01)))
    for v in (1.000, 1.005, 1.009, 1.011, 1.015, 1.030):
        r.scan({"ch0.voltage": v})
    r.flush()
    assert [v for _, v, _ in r.stored("ch0.voltage")] == [1.000, 1.011, 1.030]


def test_changes_faster_than_the_minimum_interval_are_thinned_and_the_last_one_kept(
    make: Make,
) -> None:
    r = make(TagSpec("ch0.current", unit="A", history=HistorySettings(min_interval_s=10.0)))
    for k in range(25):  # a ramp, one change a second (t = 1 … 25 s)
        r.scan({"ch0.current": 0.1 * k})
    for _ in range(15):  # then constant: the held-back last value is stored when due
        r.scan()
    r.flush()
    stored = r.stored("ch0.current")
    # One per 10 s, then the final value at its own acquisition time.
    assert [t for t, _, _ in stored] == [1.0, 11.0, 21.0, 25.0]
    assert [v for _, v, _ in stored] == pytest.approx([0.0, 1.0, 2.0, 2.4])


def test_a_bad_value_is_stored_as_no_value_with_its_quality(make: Make) -> None:
    r = make()
    r.scan({"ch0.voltage": 1.2})
    r.scan({"ch0.voltage": Quality.BAD})
    r.scan({"ch0.voltage": 1.3})
    # A non-finite value handed to the writer (the tag database already makes it BAD):
    # read back as the HTTP API sends it, no value and BAD.
    t = r.clock.wall() + 1
    r.historian.writer.put_samples([Sample("ch0.voltage", math.inf, Quality.GOOD, 0.0, t)], t)
    r.flush()
    assert [(v, q) for _, v, q in r.stored("ch0.voltage")] == [
        (1.2, Quality.GOOD),
        (None, Quality.BAD),
        (1.3, Quality.GOOD),
        (None, Quality.BAD),
    ]


def test_text_boolean_and_integer_tags_come_back_with_their_types_and_units(
    make: Make,
) -> None:
    r = make(
        TagSpec("ch0.chain.state", dtype="str"),
        TagSpec("contactor.closed", dtype="bool"),
        TagSpec("ch0.chain.cycle", dtype="int"),
        TagSpec("ch0.temperature", unit="degC", description="cell"),
    )
    r.scan({"ch0.chain.state": "running", "contactor.closed": True, "ch0.chain.cycle": 3})
    r.scan({"ch0.temperature": 25.5})
    r.flush()
    assert r.stored("ch0.chain.state")[-1][1] == "running"
    assert r.stored("contactor.closed")[-1][1] is True
    assert r.stored("ch0.chain.cycle")[-1][1] == 3
    info = r.query.tag("ch0.temperature")
    assert info is not None and (info.unit, info.dtype, info.description) == (
        "degC",
        "float",
        "cell",
    )


def test_events_are_stored_with_their_actor_and_found_by_channel_and_kind(make: Make) -> None:
    r = make()
    w = r.clock.wall

    def event(kind: str, channel: str, actor: str, text: str) -> BenchEvent:
        r.clock.advance(1.0)
        return BenchEvent(r.clock.now(), w(), kind, channel, "src", text, actor, 0, "T1", "nimh")

    r.historian.on_event(event("command", "ch0", "alice", "start by alice"))
    r.historian.on_event(event("step", "ch0", "recipe", "step c started"))
    r.historian.on_event(event("alarm", "", "safety", "estop activated"))
    r.historian.on_event(event("command", "ch1", "bob", "stop by bob"))
    r.scan()
    r.flush()
    everything = r.query.events(0, 4e9)
    assert [(e.kind, e.channel, e.actor) for e in everything] == [
        ("command", "ch0", "alice"),
        ("step", "ch0", "recipe"),
        ("alarm", "", "safety"),
        ("command", "ch1", "bob"),
    ]
    assert everything[0].test_id == "T1" and everything[0].recipe == "nimh"
    assert [e.text for e in r.query.events(0, 4e9, channel="ch0", kind="command")] == [
        "start by alice"
    ]
    assert [e.text for e in r.query.events(0, 4e9, channel="")] == ["estop activated"]
    with pytest.raises(BadRange, match="unknown event kind 'alarms'"):
        r.query.events(0, 4e9, kind="alarms")


# --- queries --------------------------------------------------------------------------


def _reference(
    rows: list[tuple[float, float | None, int]], start: float, end: float, interval: float
) -> list[dict[str, Any]]:
    """min/max/mean/count/first/last per bucket, computed here from the rows."""
    n = max(1, math.ceil((end - start) / interval))
    buckets: dict[int, list[tuple[float, float | None, int]]] = {}
    for t, v, q in sorted(rows):
        if start <= t <= end:
            buckets.setdefault(min(int((t - start) / interval), n - 1), []).append((t, v, q))
    out = []
    for k in sorted(buckets):
        b = buckets[k]
        values = [v for _, v, _ in b if v is not None]
        out.append(
            {
                "t": start + k * interval,
                "count": len(values),
                "samples": len(b),
                "min": min(values) if values else None,
                "max": max(values) if values else None,
                "mean": sum(values) / len(values) if values else None,
                "first": values[0] if values else None,
                "last": values[-1] if values else None,
                "quality": Quality(max(q for _, _, q in b)),
            }
        )
    return out


def _write_rows(path: Path, rows: list[tuple[float, float | None, int]]) -> None:
    conn = connect(path)
    conn.execute("DELETE FROM samples")
    conn.execute(
        "INSERT OR IGNORE INTO tags (id, name, unit, dtype, description)"
        " VALUES (1, 'x', 'V', 'float', '')"
    )
    conn.executemany("INSERT INTO samples VALUES (1, ?, ?, ?)", rows)
    conn.close()


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    times_ms=st.sets(st.integers(0, 200_000), min_size=1, max_size=300),
    data=st.data(),
    interval_s=st.sampled_from([0.5, 1.0, 7.3, 10.0, 60.0, 250.0]),
    start_ms=st.integers(-10_000, 50_000),
    span_ms=st.integers(0, 250_000),
)
def test_the_aggregate_matches_min_max_mean_first_last_computed_from_the_rows(
    tmp_path: Path,
    times_ms: set[int],
    data: st.DataObject,
    interval_s: float,
    start_ms: int,
    span_ms: int,
) -> None:
    rows = []
    for ms in sorted(times_ms):
        bad = ms % 7 == 0 and data.draw(st.booleans())
        value = None if bad else data.draw(st.floats(-1e6, 1e6, allow_nan=False))
        quality = int(Quality.BAD) if bad else data.draw(st.sampled_from([0, 0, 0, 1]))
        rows.append((EPOCH + ms / 1000, value, quality))
    path = tmp_path / "agg.sqlite"
    _write_rows(path, rows)
    start = EPOCH + start_ms / 1000
    end = start + span_ms / 1000
    query = HistoryQuery(path)
    try:
        got = query.aggregate("x", start, end, interval_s)
    finally:
        query.close()
    want = _reference(rows, start, end, interval_s)
    assert [b.t for b in got.buckets] == pytest.approx([w["t"] for w in want])
    for b, w in zip(got.buckets, want, strict=True):
        assert (b.count, b.samples, b.quality) == (w["count"], w["samples"], w["quality"])
        assert (b.min, b.max, b.first, b.last) == (w["min"], w["max"], w["first"], w["last"])
        if w["mean"] is None:
            assert b.mean is None
        else:
            assert b.mean == pytest.approx(w["mean"], rel=1e-9, abs=1e-6)
    assert got.tag.unit == "V"


def test_an_aggregate_skips_bad_values_and_reports_the_worst_quality(make: Make) -> None:
    r = make()
    for v in (1.0, 3.0, Quality.BAD, 2.0, Quality.UNCERTAIN, 5.0):
        r.scan({"ch0.voltage": v})
    r.flush()
    (bucket,) = r.query.aggregate("ch0.voltage", EPOCH, EPOCH + 10, 10.0).buckets
    assert (bucket.min, bucket.max, bucket.mean) == (1.0, 5.0, pytest.approx(11 / 4))
    assert (bucket.first, bucket.last, bucket.count, bucket.samples) == (1.0, 5.0, 4, 6)
    assert bucket.quality is Quality.BAD


def test_raw_samples_come_with_the_sample_before_the_range_and_a_truncation_flag(
    make: Make,
) -> None:
    r = make()
    for k in range(20):
        r.scan({"ch0.voltage": float(k)})
    r.flush()
    series = r.query.samples("ch0.voltage", EPOCH + 5, EPOCH + 15, limit=4)
    assert [s.value for s in series.samples] == [4.0, 5.0, 6.0, 7.0]
    assert series.truncated
    assert series.before is not None and series.before.value == 3.0
    assert series.tag.unit == "V"
    whole = r.query.samples("ch0.voltage", EPOCH + 5, EPOCH + 15)
    assert len(whole.samples) == 11 and not whole.truncated
    assert r.query.count("ch0.voltage", EPOCH + 5, EPOCH + 15) == 11


def test_a_query_refuses_what_it_cannot_answer_with_the_reason(make: Make) -> None:
    r = make()
    r.scan({"ch0.voltage": 1.0})
    r.flush()
    with pytest.raises(UnknownTag, match=r"no history of tag 'ch9\.voltage'"):
        r.query.samples("ch9.voltage", 0, 1)
    with pytest.raises(BadRange, match=r"start .* is after end"):
        r.query.samples("ch0.voltage", 10, 5)
    with pytest.raises(BadRange, match="gives 604800 buckets, at most 10000"):
        r.query.aggregate("ch0.voltage", 0, 7 * 86400, 1.0)
    with pytest.raises(BadRange, match="interval_s must be a finite number > 0"):
        r.query.aggregate("ch0.voltage", 0, 10, 0.0)
    with pytest.raises(BadRange, match="finite"):
        r.query.samples("ch0.voltage", 0, math.inf)


def test_a_query_of_a_file_not_created_yet_knows_nothing(tmp_path: Path) -> None:
    query = HistoryQuery(tmp_path / "none.sqlite")
    assert query.tags() == [] and query.events(0, 1) == []
    with pytest.raises(UnknownTag):
        query.samples("ch0.voltage", 0, 1)
    assert not (tmp_path / "none.sqlite").exists()  # a query never creates the file


# --- retention ------------------------------------------------------------------------


def test_retention_by_age_deletes_samples_and_events_older_than_max_age(make: Make) -> None:
    r = make(settings=WriterSettings(commit_interval_s=0.02, max_age_s=100.0, chunk_rows=7))
    for k in range(300):
        r.scan({"ch0.voltage": float(k)})
        if k % 10 == 0:
            r.historian.on_event(
                BenchEvent(r.clock.now(), r.clock.wall(), "step", "ch0", "s", f"step {k}")
            )
    r.flush(retention=True)
    times = [t for t, _, _ in r.stored("ch0.voltage")]
    assert times[0] >= 300 - 100 and times[-1] == 300  # the newest 100 s, nothing older
    assert len(times) == 101
    assert r.query.events(0, 4e9)[0].text == "step 200"
    assert r.historian.writer.rows_deleted > 0


def test_a_flush_asking_for_retention_waits_for_a_pass_that_starts_after_it_asks(
    make: Make,
) -> None:
    # A pass already running when the flush asks began with an older cut-off: its end
    # does not answer the request (CI saw the flush return with nothing deleted).
    held, entered = threading.Event(), threading.Event()

    def hold_the_first_delete(conn: sqlite3.Connection) -> None:
        def trace(sql: str) -> None:
            if sql.startswith("DELETE") and not entered.is_set():
                entered.set()
                held.wait(10.0)

        conn.set_trace_callback(trace)

    settings = WriterSettings(commit_interval_s=0.02, max_age_s=100.0, chunk_rows=7)
    r = make(settings=settings, connect_hook=hold_the_first_delete)
    r.scan({"ch0.voltage": 0.0})  # the first wall time: the start-up pass begins
    assert entered.wait(10.0)  # ... and is held in its first delete, cut-off t=-99
    for k in range(1, 300):
        r.scan({"ch0.voltage": float(k)})
    answered: list[bool] = []
    flusher = threading.Thread(
        target=lambda: answered.append(r.historian.writer.flush(retention=True))
    )
    flusher.start()
    while r.historian.writer._flush_req == 0:  # the request is in: let the pass go on
        time.sleep(0.001)
    held.set()
    flusher.join(15.0)
    assert answered == [True]
    times = [t for t, _, _ in r.stored("ch0.voltage")]
    assert times[0] >= 300 - 100 and times[-1] == 300
    assert r.historian.writer.retention_runs >= 2


def test_retention_by_size_deletes_the_oldest_first_and_the_file_shrinks(make: Make) -> None:
    specs = [TagSpec(f"gen.ai{k}", unit="V") for k in range(20)]
    big = WriterSettings(commit_interval_s=0.02, max_bytes=10**9, chunk_rows=500)
    r = make(*specs, settings=big)
    for k in range(2000):
        r.scan({s.name: k + i / 100 for i, s in enumerate(specs)})
    r.flush()
    path = r.historian.path
    r.historian.close()  # the last connection: the WAL is copied into the file
    before = path.stat().st_size
    assert before > 1_000_000  # 40 000 samples

    bound = before // 3
    small = WriterSettings(commit_interval_s=0.02, max_bytes=bound, chunk_rows=500)
    r2 = make(*specs, settings=small, path=path, clock=r.clock)
    r2.scan()
    r2.flush(retention=True)
    after = path.stat().st_size
    conn = sqlite3.connect(path)
    try:
        assert used_bytes(conn) <= bound
    finally:
        conn.close()
    # Oldest first: what is left of every tag is each sample from about one instant on.
    firsts = []
    for s in specs:
        kept = [t for t, _, _ in r2.stored(s.name)]
        assert kept[-1] == 2000.0 and len(kept) == round(kept[-1] - kept[0]) + 1  # no hole
        firsts.append(kept[0])
    assert min(firsts) > 0 and max(firsts) - min(firsts) <= 1.0
    assert after <= bound < before  # the file itself shrank (incremental vacuum)
    assert not path.with_name(path.name + "-wal").exists() or (
        path.with_name(path.name + "-wal").stat().st_size == 0
    )


# --- files that cannot be used --------------------------------------------------------


def _valid_history(path: Path) -> None:
    conn = connect(path)
    conn.execute("INSERT INTO tags VALUES (1, 'ch0.voltage', 'V', 'float', '')")
    conn.executemany(
        "INSERT INTO samples VALUES (1, ?, ?, 0)", [(EPOCH + k, k * 0.1) for k in range(30000)]
    )
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    conn.close()


def _not_a_database(path: Path) -> None:
    path.write_bytes(b"this is not a database\n" * 200)


def _truncated(path: Path) -> None:
    _valid_history(path)
    with path.open("r+b") as f:
        f.truncate(path.stat().st_size // 2)


def _scribbled(path: Path) -> None:
    _valid_history(path)
    with path.open("r+b") as f:
        f.seek(path.stat().st_size // 2)
        f.write(bytes(range(256)) * 32)


def _foreign(path: Path) -> None:
    conn = sqlite3.connect(path)
    conn.execute("CREATE TABLE accounts (name TEXT)")
    conn.commit()
    conn.close()


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        (_not_a_database, "file is not a database"),
        (_truncated, "malformed"),
        (_scribbled, "integrity check failed"),
        (_foreign, "not a history file of this supervisor"),
    ],
    ids=["not-a-database", "truncated", "scribbled", "another-program's"],
)
def test_an_unusable_file_is_set_aside_with_an_alarm_and_a_new_one_started(
    make: Make,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    damage: Callable[[Path], None],
    words: str,
) -> None:
    path = tmp_path / "state" / "history.sqlite"
    path.parent.mkdir(parents=True)
    damage(path)
    original = path.read_bytes()
    with caplog.at_level(logging.ERROR):
        r = make(path=path)
    report = r.historian.opened
    assert report is not None and report.set_aside is not None
    moved = path.with_name("history.sqlite.corrupt-20260101T000000Z")
    assert report.set_aside.moved_to == moved
    assert moved.read_bytes() == original  # kept for whoever wants to look, untouched
    assert words in report.set_aside.problem
    assert str(moved) in caplog.text and words in caplog.text
    r.scan({"ch0.voltage": 1.5})
    r.flush()
    # Raised and cleared at once: the operator acknowledges that history moved.
    ((alarm, on, text), (alarm2, off, _)) = [a for a in r.alarms if a[0] == CORRUPT_ALARM]
    assert (alarm, on, alarm2, off) == (CORRUPT_ALARM, True, CORRUPT_ALARM, False)
    assert str(moved) in text and words in text
    assert r.stored("ch0.voltage") == [(1.0, 1.5, Quality.GOOD)]  # the new file works


def test_a_restart_keeps_the_history_and_adds_to_it(make: Make, tmp_path: Path) -> None:
    r = make()
    for k in range(10):
        r.scan({"ch0.voltage": float(k)})
    r.historian.on_event(BenchEvent(r.clock.now(), r.clock.wall(), "state", "ch0", "", "run"))
    r.historian.close()
    r2 = make(path=r.historian.path, clock=r.clock)
    assert r2.historian.opened is not None and r2.historian.opened.set_aside is None
    r2.scan({"ch0.voltage": 100.0}, dt_s=60.0)
    r2.flush()
    assert [v for _, v, _ in r2.stored("ch0.voltage")] == [float(k) for k in range(10)] + [100.0]
    assert [e.text for e in r2.query.events(0, 4e9)] == ["run"]
    assert [t.name for t in r2.query.tags()].count("ch0.voltage") == 1
    assert not r2.alarms or all(on is False for _, on, _ in r2.alarms)


def test_a_clean_stop_writes_everything_queued(make: Make) -> None:
    # A commit interval far longer than the test: nothing is written before the stop.
    r = make(settings=WriterSettings(commit_interval_s=10.0))
    for k in range(500):
        r.scan({"ch0.voltage": float(k)})
    r.historian.on_event(BenchEvent(r.clock.now(), r.clock.wall(), "state", "ch0", "", "end"))
    assert r.historian.writer.rows_written == 0
    r.historian.close()
    assert len(r.stored("ch0.voltage")) == 500
    assert [e.text for e in r.query.events(0, 4e9)] == ["end"]
    assert r.historian.writer.rows_dropped == 0


# --- the scan never waits -------------------------------------------------------------


def test_a_full_queue_drops_the_newest_counts_them_raises_an_alarm_and_resends_values(
    make: Make, caplog: pytest.LogCaptureFixture
) -> None:
    specs = [TagSpec(f"gen.ai{k}", unit="V") for k in range(10)]
    # Not opened: nothing drains the queue (a disk that does not answer).
    r = make(*specs, settings=WriterSettings(queue_max_rows=1000), open_now=False)
    with caplog.at_level(logging.ERROR):
        for k in range(150):  # 1500 changes for 1000 places
            r.scan({s.name: float(k) for s in specs})
    w = r.historian.writer
    assert w.queued_rows == 1000
    assert w.rows_dropped >= 500
    assert r.db["historian.rows_dropped"].value == w.rows_dropped
    assert r.db["historian.queue_rows"].value == 1000
    assert r.active(OVERFLOW_ALARM) is True
    assert "samples" in r.alarms[-1][2] and "dropped" in r.alarms[-1][2]
    assert caplog.text.count("history queue full") == 1  # said once, counted always
    r.historian.open()
    r.flush()
    r.scan()  # room again: every tag's current value is sent once
    r.scan()
    r.flush()
    assert r.active(OVERFLOW_ALARM) is False
    for s in specs:
        assert r.stored(s.name)[-1][1] == 149.0  # the gap ends with the true value


def test_a_full_event_queue_drops_counts_and_alarms(make: Make) -> None:
    r = make(settings=WriterSettings(events_max=10), open_now=False)
    for k in range(15):
        r.historian.on_event(BenchEvent(0.0, EPOCH + k, "message", "ch0", "", f"m{k}"))
    r.scan()
    assert r.historian.writer.events_dropped == 5
    assert r.db["historian.events_dropped"].value == 5
    assert r.active(OVERFLOW_ALARM) is True and "5 events dropped" in r.alarms[-1][2]
    r.historian.open()
    r.flush()
    assert [e.text for e in r.query.events(0, 4e9)] == [f"m{k}" for k in range(10)]


class Disk:
    """A full disk or a read-only file system, as SQLite refuses them, on the writer's own
    connection (sqlite3 connections are serialized: a statement from this thread waits for
    the writer's) and on every connection it opens next, until ``fix``."""

    def __init__(self) -> None:
        self.fault = ""
        self.conn: sqlite3.Connection | None = None

    def hook(self, conn: sqlite3.Connection) -> None:
        self.conn = conn
        self._apply(conn)

    def fail(self, fault: str) -> None:
        self.fault = fault
        assert self.conn is not None
        self._apply(self.conn)

    def fix(self) -> None:
        self.fault = ""

    def _apply(self, conn: sqlite3.Connection) -> None:
        if self.fault == "full":  # no page beyond the current size
            conn.execute("PRAGMA max_page_count = 1")
        elif self.fault == "read-only":
            conn.execute("PRAGMA query_only = 1")


@pytest.mark.parametrize(
    ("fault", "words"),
    [("full", "database or disk is full"), ("read-only", "readonly database")],
)
def test_a_failing_disk_is_reported_once_counted_alarmed_and_retried_losing_nothing(
    make: Make, caplog: pytest.LogCaptureFixture, fault: str, words: str
) -> None:
    disk = Disk()
    r = make(connect_hook=disk.hook)
    r.scan({"ch0.voltage": 0.0})
    r.flush()
    # The fault goes onto the writer's own connection from this thread: only once the
    # writer is idle (its start-up retention pass done too), or a failure of that pass
    # would close the connection under this statement (a segfault in sqlite3).
    deadline = time.monotonic() + 30.0
    while r.historian.writer.retention_runs < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert r.historian.writer.retention_runs >= 1
    disk.fail(fault)
    with caplog.at_level(logging.ERROR):
        for k in range(1, 400):
            r.scan({"ch0.voltage": float(k)})  # the scan goes on; writes fail meanwhile
            if k % 100 == 0:
                assert not r.historian.writer.flush(timeout_s=5.0)
    w = r.historian.writer
    assert w.write_errors >= 3  # at least one per flush that waited for it
    assert words in (w.error or "")
    assert r.db["historian.last_error"].value == w.error
    assert r.db["historian.write_errors"].value == w.write_errors
    assert r.active(WRITE_ALARM) is True
    assert caplog.text.count("write failed") == 1  # reported once, with its cause
    assert words in caplog.text
    disk.fix()
    r.flush()
    r.scan()
    assert r.active(WRITE_ALARM) is False
    assert r.db["historian.last_error"].value == ""
    assert [v for _, v, _ in r.stored("ch0.voltage")] == [float(k) for k in range(400)]
    assert w.rows_dropped == 0


def test_a_folder_that_cannot_be_created_is_alarmed_and_retried_until_it_can(
    make: Make, tmp_path: Path
) -> None:
    blocker = tmp_path / "state"
    blocker.write_text("a file where the state folder should be")
    r = make(path=blocker / "history.sqlite")
    report = r.historian.opened
    assert report is not None and report.error is not None and "Errno" in report.error
    for k in range(5):
        r.scan({"ch0.voltage": float(k)})  # the bench runs meanwhile
    assert r.active(WRITE_ALARM) is True
    blocker.unlink()  # someone fixes it
    r.flush()
    r.scan()
    assert r.active(WRITE_ALARM) is False
    assert [v for _, v, _ in r.stored("ch0.voltage")] == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_the_diagnostic_tags_are_named_with_their_units(make: Make) -> None:
    r = make()
    r.scan({"ch0.voltage": 1.0})
    r.flush()
    r.scan()
    units = {t.name: t.spec.unit for t in r.db if t.name.startswith("historian.")}
    assert units == {
        "historian.queue_rows": "",
        "historian.rows_written": "",
        "historian.rows_dropped": "",
        "historian.events_written": "",
        "historian.events_dropped": "",
        "historian.rows_deleted": "",
        "historian.write_errors": "",
        "historian.last_error": "",
        "historian.crashes": "",
        "historian.last_crash": "",
        "historian.file_bytes": "B",
        "historian.oldest_sample_age_s": "s",
        "historian.commit_duration_s": "s",
    }
    assert r.db["historian.rows_written"].value >= 1
    assert r.db["historian.file_bytes"].value > 0
    # The oldest sample: the tags' first values, at t = 0 of the clock, now at t = 2 s.
    assert r.db["historian.oldest_sample_age_s"].value == pytest.approx(2.0)
    # The historian records its own diagnostics too (a trend of its health).
    assert r.query.tag("historian.rows_written") is not None


# --- configuration --------------------------------------------------------------------

IO_MAP = """bench: h
history:
  max_age: 86400
devices:
  chadeche:
    driver: chadeche
    boards:
      - address: 0
"""


def test_a_misspelt_history_key_is_refused_with_file_line_and_column(tmp_path: Path) -> None:
    path = tmp_path / "bench.yaml"
    path.write_text(IO_MAP, encoding="utf-8")
    with pytest.raises(ConfigErrors) as info:
        load_bench(path)
    first = info.value.errors[0]
    assert (first.file, first.line, first.col) == (str(path), 3, 3)
    assert "unknown key 'max_age' in history" in first.message
    assert "max_age_s" in first.message  # did you mean


def test_history_defaults_and_bounds() -> None:
    cfg = bench_from_data(
        {"bench": "h", "devices": {"chadeche": {"driver": "chadeche", "boards": [{"address": 0}]}}}
    )
    h = cfg.history
    assert (h.enabled, h.path, h.max_age_s, h.max_bytes) == (
        None,
        "history.sqlite",
        90 * 86400.0,
        1024**3,
    )
    assert history_enabled(cfg)  # no influxdb: section, so on
    assert history_path(cfg) == Path("var") / "history.sqlite"
    for bad in ({"enabled": 1}, {"max_bytes": 1000}, {"commit_interval_s": 0.0}):
        with pytest.raises(ConfigErrors):
            bench_from_data(
                {
                    "bench": "h",
                    "history": bad,
                    "devices": {"chadeche": {"driver": "chadeche", "boards": [{"address": 0}]}},
                }
            )


def test_the_writer_looks_at_the_scan_gate_between_every_scans_samples_of_a_batch(
    make: Make,
) -> None:
    """A batch is made and inserted a piece at a time, the scan's turn in between: a
    second of the load case's changes in one go held the interpreter lock for ms."""
    r = make(settings=WriterSettings(commit_interval_s=60.0, retry_s=0.02))
    gate = ScanGate(max_wait_s=0.001)  # closed for good: every look at it counts a wait
    for k in range(5):
        r.scan({"ch0.voltage": 1.0 + k / 10})
    r.historian.writer.gate = gate
    gate.close()
    r.flush()
    assert gate.waits >= 5 + 1  # before each scan's rows, and before the first insert
    assert [v for _, v, _ in r.stored("ch0.voltage")][-5:] == [1.0, 1.1, 1.2, 1.3, 1.4]


# --- issue 28, finding 1: no value stops the writer; a crash is said and restarts it ------


def test_a_text_utf8_cannot_encode_is_stored_escaped_and_the_writer_goes_on(make: Make) -> None:
    r = make(TagSpec("ch0.chain.state", dtype="str"), TagSpec("ch0.voltage", unit="V"))
    w = r.clock.wall
    r.historian.on_event(
        BenchEvent(r.clock.now(), w(), "command", "ch1", "ch1.command", "x := '\ud800' \udcff")
    )
    r.scan({"ch0.chain.state": "a\ud800b"})
    r.flush()
    r.scan({"ch0.voltage": 3.5})
    r.flush()
    assert [e.text for e in r.query.events(0, 4e9)] == ["x := '\\ud800' \\udcff"]
    assert r.stored("ch0.chain.state")[-1][1] == "a\\ud800b"
    assert r.stored("ch0.voltage")[-1][1] == 3.5
    writer = r.historian.writer
    assert (writer.crashes, writer.write_errors, writer.error) == (0, 0, None)


def test_a_writer_thread_that_crashes_raises_an_alarm_and_is_started_again(
    make: Make, caplog: pytest.LogCaptureFixture
) -> None:
    r = make(TagSpec("ch0.voltage", unit="V"), TagSpec("ch0.current", unit="A"))
    real = r.historian._describe
    calls = {"n": 0}

    def describe_once_broken(name: str) -> TagInfo:
        # A fake collaborator: an exception no write expects, escaping the thread's loop.
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("injected fault")
        return real(name)

    r.historian.writer._describe = describe_once_broken
    with caplog.at_level(logging.ERROR):
        r.scan({"ch0.voltage": 3.5})
        r.historian.writer.flush()  # its batch is lost in the crash (counted)
    r.scan({"ch0.current": 1.25})
    r.flush()  # the thread runs again
    r.scan()  # the diagnostics and alarms of what happened
    writer = r.historian.writer
    assert writer.crashes == 1 and writer.write_errors == 1
    assert "RuntimeError: injected fault" in writer.last_crash
    assert writer.rows_dropped >= 1  # the batch it was writing
    assert r.stored("ch0.current")[-1][1] == 1.25
    raised = [(on, text) for i, on, text in r.alarms if i == CRASH_ALARM]
    assert raised[0][0] is True and "injected fault" in raised[0][1]
    assert r.db["historian.crashes"].value == 1
    assert "injected fault" in r.db["historian.last_crash"].value
    assert "writer thread crashed" in caplog.text
