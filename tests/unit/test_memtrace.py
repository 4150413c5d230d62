"""The memory tracing switch (bench/memtrace.py): off unless the environment names a
folder; on, it writes snapshots there and tells what grew between two of them, by line."""

from __future__ import annotations

import time
import tracemalloc
from pathlib import Path

from supervisor.bench import memtrace


def test_tracing_is_off_unless_the_environment_names_a_folder() -> None:
    assert memtrace.start_from_env({}) is None
    assert memtrace.start_from_env({memtrace.ENV: ""}) is None
    assert not tracemalloc.is_tracing()


def test_the_snapshots_tell_what_grew_by_source_line(tmp_path: Path) -> None:
    trace = memtrace.start_from_env({memtrace.ENV: str(tmp_path), memtrace.EVERY_ENV: "3600"})
    assert trace is not None
    kept: list[bytes] = []
    try:
        before = trace.dump()
        kept.extend(bytes(1000) + bytes([i % 256]) for i in range(2000))  # about 2 MB
        after = trace.dump()
        assert before is not None and after is not None
    finally:
        trace.stop()
    assert not tracemalloc.is_tracing()
    assert [p for _, p in memtrace.snapshots(tmp_path)] == sorted([before, after])
    lines = memtrace.compare(before, after, top=3)
    assert lines[0].startswith("traced: +")
    assert any(f"{Path(__file__).name}:" in line for line in lines[1:])
    assert len(kept) == 2000
    rows = (tmp_path / memtrace.SUMMARY).read_text(encoding="utf-8").splitlines()
    assert rows[0].split("\t") == list(memtrace.COLUMNS)
    assert len(rows) == 3  # one line per snapshot
    assert all(int(v) > 0 for v in rows[2].split("\t")[1:3])


def test_sqlite_memory_counts_the_page_caches() -> None:
    import sqlite3

    before = memtrace.sqlite_memory_b()
    conn = sqlite3.connect(":memory:")
    conn.execute("CREATE TABLE t (x)")
    conn.executemany("INSERT INTO t VALUES (?)", [(bytes(100),) for _ in range(20_000)])
    try:
        assert memtrace.sqlite_memory_b() > before + 1_000_000
    finally:
        conn.close()


def test_a_folder_without_snapshots_has_none(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("x", encoding="utf-8")
    assert memtrace.snapshots(tmp_path) == []


def test_snapshots_come_on_their_own_every_period(tmp_path: Path) -> None:
    trace = memtrace.start_from_env({memtrace.ENV: str(tmp_path), memtrace.EVERY_ENV: "0.2"})
    assert trace is not None
    try:
        deadline = time.monotonic() + 60.0  # a generous wait, not a timing assertion
        while len(memtrace.snapshots(tmp_path)) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        trace.stop()
    assert len(memtrace.snapshots(tmp_path)) >= 2


def test_without_frames_only_the_summary_is_written(tmp_path: Path) -> None:
    env = {memtrace.ENV: str(tmp_path), memtrace.EVERY_ENV: "3600", memtrace.FRAMES_ENV: "0"}
    trace = memtrace.start_from_env(env)
    assert trace is not None
    try:
        assert not tracemalloc.is_tracing()
        assert trace.dump() is None
    finally:
        trace.stop()
    assert memtrace.snapshots(tmp_path) == []
    rows = (tmp_path / memtrace.SUMMARY).read_text(encoding="utf-8").splitlines()
    assert len(rows) == 2
