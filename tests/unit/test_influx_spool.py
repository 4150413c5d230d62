"""The InfluxDB spool on disk: oldest first, deleted only once acknowledged, bounded (the
oldest dropped and counted), and what a restart finds is what was committed."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from supervisor.publish.influx.spool import DeadLetter, Spool, SpoolCounts


def lines(measurement: str, first: int, n: int) -> list[str]:
    """Lines of one length (the bound is in bytes)."""
    return [f"{measurement},bench=b v={k:04d}.0 {k:04d}" for k in range(first, first + n)]


def opened(path: Path, max_bytes: int = 1 << 30) -> Spool:
    spool = Spool(path, max_bytes)
    spool.open()
    return spool


def balanced(c: SpoolCounts) -> bool:
    return c.produced == c.sent + c.dropped + c.dead + c.waiting


def drain(spool: Spool, batch: int = 1000) -> list[bytes]:
    out: list[bytes] = []
    while (b := spool.next_batch(batch)) is not None:
        out.extend(b.lines())
        spool.ack(b)
    return out


def test_chunks_come_out_oldest_first_and_leave_only_when_acknowledged(tmp_path: Path) -> None:
    spool = opened(tmp_path / "s.sqlite")
    spool.append([("channel", lines("channel", 0, 3)), ("device", lines("device", 0, 2))], 100)
    spool.append([("channel", lines("channel", 3, 2))], 100)
    first = spool.next_batch(5)
    assert first is not None
    assert first.points == 5 and len(first.chunks) == 2
    assert first.lines() == [x.encode() for x in lines("channel", 0, 3) + lines("device", 0, 2)]
    spool.release()  # a failed send: the same batch again
    again = spool.next_batch(5)
    assert again is not None and again.ids == first.ids
    spool.ack(again)
    rest = spool.next_batch(5)
    assert rest is not None and min(rest.ids) > max(first.ids)
    spool.ack(rest)
    assert spool.next_batch(5) is None
    c = spool.counts()
    assert (c.waiting, c.produced, c.sent) == (0, 7, 7)
    assert c.by_measurement["channel"] == {"produced": 5, "sent": 5}
    spool.close()


def test_a_chunk_holds_at_most_batch_size_lines_and_a_batch_at_least_one_chunk(
    tmp_path: Path,
) -> None:
    spool = opened(tmp_path / "s.sqlite")
    spool.append([("channel", lines("channel", 0, 25))], 10)
    batch = spool.next_batch(3)  # smaller than a chunk: the whole (oldest) chunk
    assert batch is not None and batch.points == 10
    assert spool.counts().chunks == 3
    spool.close()


def test_a_restart_resumes_from_what_was_committed_in_the_same_order(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    spool = opened(path)
    spool.append([("channel", lines("channel", 0, 10))], 4)
    b = spool.next_batch(4)
    assert b is not None
    spool.ack(b)  # acknowledged: never sent again
    spool.close()
    spool = opened(path)
    assert spool.counts().waiting == 6
    assert drain(spool) == [x.encode() for x in lines("channel", 4, 6)]
    c = spool.counts()
    assert (c.produced, c.sent, c.waiting) == (10, 10, 0) and balanced(c)
    spool.close()


def test_ids_keep_growing_after_the_spool_was_emptied_and_reopened(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    spool = opened(path)
    spool.append([("channel", lines("channel", 0, 2))], 10)
    last = max(spool.waiting_ids())
    drain(spool)
    spool.close()
    spool = opened(path)
    spool.append([("channel", lines("channel", 2, 2))], 10)
    assert min(spool.waiting_ids()) > last  # "oldest first" is "smallest id first"
    spool.close()


def test_past_its_bound_the_oldest_points_are_dropped_and_counted(tmp_path: Path) -> None:
    size = len("\n".join(lines("channel", 0, 10)).encode())
    spool = opened(tmp_path / "s.sqlite", max_bytes=3 * size)
    for k in range(5):
        spool.append([("channel", lines("channel", 10 * k, 10))], 10)
    c = spool.counts()
    assert c.waiting_bytes <= 3 * size
    assert c.dropped == 20 and c.waiting == 30 and balanced(c)
    assert spool.overflowing
    kept = drain(spool)
    assert kept == [x.encode() for x in lines("channel", 20, 30)]  # the newest survive
    assert not spool.overflowing  # below 90 % of the bound again
    spool.close()


def test_the_chunk_being_sent_is_not_dropped_by_the_bound(tmp_path: Path) -> None:
    size = len("\n".join(lines("channel", 0, 10)).encode())
    spool = opened(tmp_path / "s.sqlite", max_bytes=2 * size)
    spool.append([("channel", lines("channel", 0, 10))], 10)
    sending = spool.next_batch(10)
    assert sending is not None
    spool.append([("channel", lines("channel", 10, 10))], 10)
    spool.append([("channel", lines("channel", 20, 10))], 10)  # over the bound
    spool.ack(sending)
    c = spool.counts()
    assert c.sent == 10 and c.dropped == 10 and balanced(c)
    assert drain(spool) == [x.encode() for x in lines("channel", 20, 10)]
    spool.close()


def test_a_lowered_bound_applies_at_open(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    spool = opened(path)
    spool.append([("channel", lines("channel", 0, 100))], 10)
    spool.close()
    size = len("\n".join(lines("channel", 90, 10)).encode())
    spool = opened(path, max_bytes=size + 1)
    c = spool.counts()
    assert c.waiting == 10 and c.dropped == 90 and balanced(c)
    spool.close()


def test_dead_letters_keep_the_line_status_and_reason_and_are_counted(tmp_path: Path) -> None:
    spool = opened(tmp_path / "s.sqlite")
    spool.append([("channel", lines("channel", 0, 4))], 10)
    batch = spool.next_batch(10)
    assert batch is not None
    bad = batch.lines()[2]
    spool.ack(batch, [DeadLetter(bad, 400, "400 partial write: field type conflict")])
    c = spool.counts()
    assert (c.sent, c.dead, c.dead_letters) == (3, 1, 1) and balanced(c)
    ((_, status, reason, line),) = spool.dead_letters()
    assert (status, reason, line) == (400, "400 partial write: field type conflict", bad.decode())
    spool.close()


def test_counters_survive_a_restart(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    spool = opened(path)
    spool.append([("channel", lines("channel", 0, 3))], 10, extra=2)  # 2 lost in memory
    drain(spool)
    spool.close()
    c = opened(path).counts()
    assert (c.produced, c.sent, c.dropped) == (5, 3, 2) and balanced(c)


def test_a_corrupt_spool_is_moved_aside_and_a_new_one_started(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    path.write_bytes(b"this is not SQLite" * 100)
    spool = opened(path)
    assert spool.problem and spool.moved_to is not None and spool.moved_to.exists()
    spool.append([("channel", lines("channel", 0, 1))], 10)
    assert spool.counts().waiting == 1
    spool.close()


def test_another_programs_sqlite_file_is_not_taken_for_a_spool(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE notes (text TEXT)")
    conn.close()
    spool = opened(path)
    assert "not an InfluxDB spool" in spool.problem
    spool.close()


def test_a_spool_that_cannot_be_created_raises_and_keeps_nothing_half_open(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    spool = Spool(tmp_path / "file" / "s.sqlite", 1 << 20)
    with pytest.raises(OSError):
        spool.open()
    assert not spool.is_open
