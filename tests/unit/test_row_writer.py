"""A live test's result rows are written off the scan's thread (issue 13): a record hands
its row over and returns; every row reaches its files, in order, before they close."""

from __future__ import annotations

import csv
import json
import logging
import threading
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from supervisor.core.records import ChainEvent, Record
from supervisor.publish.results import ResultCollector
from supervisor.publish.rows import RowWriter
from supervisor.testing.records import make_record

REC = make_record(
    t=1000.0,
    wall=1.8e9,
    step_id="charge",
    step_type="charge",
    voltage_v=1.31,
    power_w=0.0655,
    temperature_c=25.0,
    step_remaining_s=4.0,
)


def record(i: int) -> Record:
    return replace(REC, t=REC.t + i, test_time_s=float(i), step_time_s=float(i))


def bdf_rows(c: ResultCollector) -> list[list[str]]:
    assert c.bdf_path is not None
    with c.bdf_path.open(encoding="utf-8", newline="") as f:
        return list(csv.reader(f))[1:]  # without the header


def cha_lines(c: ResultCollector) -> list[str]:
    assert c.chadeche_path is not None
    return c.chadeche_path.read_text(encoding="utf-8").splitlines()


@pytest.fixture
def rows() -> Iterator[RowWriter]:
    writer = RowWriter("test")
    yield writer
    writer.stop()


def test_a_record_returns_before_its_row_is_written_and_the_row_follows(
    tmp_path: Path, rows: RowWriter
) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path, rows=rows)
    disk_busy = threading.Event()

    def earlier_write() -> None:
        disk_busy.wait(10.0)  # the writer is held up by an earlier write

    rows.put(earlier_write)
    for i in range(3):
        c.on_record(record(i))
    assert bdf_rows(c) == [] and cha_lines(c) == []  # the caller did not wait for the disk
    disk_busy.set()
    assert rows.flush(10.0)
    assert [r[0] for r in bdf_rows(c)] == ["0.000", "1.000", "2.000"]
    assert [r[10] for r in bdf_rows(c)] == ["1", "2", "3"]  # the record index, as handed over
    assert len(cha_lines(c)) == 3
    c.abandon()


def test_the_files_hold_the_same_rows_as_when_written_at_once(
    tmp_path: Path, rows: RowWriter
) -> None:
    direct = ResultCollector("ch0", "r", "t1", tmp_path / "direct")
    threaded = ResultCollector("ch0", "r", "t1", tmp_path / "threaded", rows=rows)
    for i in range(200):
        direct.on_record(record(i))
        threaded.on_record(record(i))
    direct.close("done", "Complete", now=REC.t + 200)
    threaded.close("done", "Complete", now=REC.t + 200)
    for name in ("t1.bdf.csv", "t1.chadeche.csv"):
        assert (tmp_path / "threaded" / name).read_bytes() == (
            tmp_path / "direct" / name
        ).read_bytes()


def test_the_end_of_a_test_writes_every_row_handed_over_before_its_files_close(
    tmp_path: Path, rows: RowWriter
) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path, rows=rows)
    for i in range(500):
        c.on_record(record(i))
    summary = c.close("done", "Complete", now=REC.t + 500)
    assert len(bdf_rows(c)) == 500 == summary["records"]
    assert len(cha_lines(c)) == 500


def test_a_test_abandoned_keeps_the_rows_handed_over(tmp_path: Path, rows: RowWriter) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path, rows=rows)
    for i in range(20):
        c.on_record(record(i))
    c.abandon()
    assert len(bdf_rows(c)) == 20


def test_after_the_writer_stopped_a_row_is_written_at_once(tmp_path: Path) -> None:
    writer = RowWriter("test")
    c = ResultCollector("ch0", "r", "t1", tmp_path, rows=writer)
    c.on_record(record(0))
    writer.stop()
    c.on_record(record(1))  # a test ending during the supervisor's stop
    assert len(bdf_rows(c)) == 2
    c.abandon()


def test_a_row_that_fails_is_logged_and_the_next_ones_are_still_written(
    tmp_path: Path, rows: RowWriter, caplog: pytest.LogCaptureFixture
) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path, rows=rows)

    def broken() -> None:
        raise OSError("disk full")

    with caplog.at_level(logging.ERROR, logger="supervisor.publish.rows"):
        rows.put(broken)
        c.on_record(record(0))
        assert rows.flush(10.0)
    assert rows.failed == 1
    assert any("could not be written" in r.getMessage() for r in caplog.records)
    assert len(bdf_rows(c)) == 1
    c.abandon()


def test_a_step_change_returns_before_its_timeline_line_is_written_and_it_follows(
    tmp_path: Path, rows: RowWriter
) -> None:
    """The timeline's JSON lines go through the row writer too: 16 channels changing step
    in one scan were 16 writes on the scan's thread."""
    c = ResultCollector("ch0", "r", "t1", tmp_path, rows=rows)
    c.on_record(record(0))  # the files open at the first record
    assert rows.flush(10.0)
    disk_busy = threading.Event()
    rows.put(lambda: disk_busy.wait(10.0))
    c.on_event(ChainEvent(REC.t + 1, REC.wall + 1, "ch0", "step", "starting step 2 d", 1, "d", 1))
    assert c.timeline_path is not None
    assert c.timeline_path.read_text(encoding="utf-8") == ""  # not waited for
    disk_busy.set()
    c.close("aborted: abort by bob", "Aborted")  # the line before the file closes
    lines = [json.loads(x) for x in c.timeline_path.read_text(encoding="utf-8").splitlines()]
    assert [e["text"] for e in lines] == ["starting step 2 d"]
