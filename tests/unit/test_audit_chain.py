"""The audit log on its own (issue 34, "Audit trail"): entries appended off the caller's
thread, each chained to the one before by its hash; ``verify_file`` checks the chain and
names the first entry where it breaks — a changed value, a byte flipped in the file, a
deleted entry, a rewritten hash — and an export's head hash shows a log cut short."""

from __future__ import annotations

import json
import sqlite3
import threading
from pathlib import Path

import pytest

from supervisor.audit import (
    AUDIT_NAME,
    GENESIS,
    AuditFileError,
    AuditLog,
    Query,
    append_now,
    read_entries,
    text_change,
    verify_file,
)
from supervisor.audit.chain import entry_hash
from supervisor.core.clock import VirtualClock


def _log(path: Path, n: int, clock: VirtualClock | None = None) -> None:
    """``n`` entries, each with a marker of its own in its details."""
    clock = clock or VirtualClock()
    with AuditLog(path, wall=clock.wall) as audit:
        for i in range(1, n + 1):
            audit.append(f"hmi:user{i}", "command.start", f"ch{i}", {"marker": f"MARK{i:04d}"})
            clock.advance(1.5)
        assert audit.flush()


def _writable(path: Path) -> sqlite3.Connection:
    """The file opened as someone who can write it and means to: the append-only
    triggers dropped (they stop mistakes, not intent)."""
    conn = sqlite3.connect(path, isolation_level=None)
    conn.execute("DROP TRIGGER entries_no_update")
    conn.execute("DROP TRIGGER entries_no_delete")
    return conn


def test_entries_are_numbered_timed_and_chained_and_verify_says_ok(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    _log(path, 3, VirtualClock(wall_epoch_s=1_796_500_000.0))
    entries = read_entries(path)
    assert [e.seq for e in entries] == [1, 2, 3]
    assert [e.time for e in entries] == [
        "2026-12-05T19:46:40.000000Z",
        "2026-12-05T19:46:41.500000Z",
        "2026-12-05T19:46:43.000000Z",
    ]
    assert entries[0].prev_hash == GENESIS
    assert [e.prev_hash for e in entries[1:]] == [e.hash for e in entries[:-1]]
    assert entries[1].actor == "hmi:user2" and entries[1].target == "ch2"
    assert entries[1].details == '{"marker":"MARK0002"}'  # canonical JSON
    v = verify_file(path)
    assert v.ok and v.entries == 3 and v.head == entries[-1].hash and v.broken is None


def test_the_hash_covers_every_field_and_the_previous_hash() -> None:
    base = (7, "2026-12-05T20:00:00.000000Z", "cli", "user.add", "alice", "{}", GENESIS)
    h = entry_hash(*base)
    for i in range(len(base)):
        changed = list(base)
        changed[i] = changed[i] + 1 if isinstance(changed[i], int) else str(changed[i]) + "x"
        assert entry_hash(*changed) != h, f"field {i} not covered"
    # Delimited: moving a character from one field to the next changes the hash.
    assert entry_hash(7, "t", "ab", "c", "", "{}", GENESIS) != entry_hash(
        7, "t", "a", "bc", "", "{}", GENESIS
    )


def test_a_details_value_changed_with_sqlite_is_named_by_verify(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    _log(path, 5)
    with _writable(path) as conn:
        conn.execute('UPDATE entries SET details = \'{"marker":"MARK9999"}\' WHERE seq = 3')
    v = verify_file(path)
    assert not v.ok
    assert v.broken is not None and v.broken.seq == 3
    assert v.broken.time == "2026-01-01T00:00:03.000000Z"
    assert v.broken.problem.startswith("content changed")
    assert v.entries == 2 and v.head == read_entries(path)[1].hash  # the last good one


def test_a_byte_flipped_in_the_middle_of_the_file_is_named_by_verify(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    _log(path, 9)
    assert not (tmp_path / (AUDIT_NAME + "-wal")).exists()  # all in the main file now
    data = bytearray(path.read_bytes())
    at = data.find(b"MARK0005")
    assert at > 0 and data.count(b"MARK0005") == 1
    data[at + 7] ^= 0x01  # '5' -> '4': one bit of one byte
    path.write_bytes(bytes(data))
    v = verify_file(path)
    assert v.broken is not None
    assert (v.broken.seq, v.broken.problem.split(":")[0]) == (5, "content changed")
    assert v.broken.line().startswith("entry 5 (2026-01-01T00:00:06.000000Z): content changed")


def test_a_deleted_entry_leaves_a_gap_that_verify_names(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    _log(path, 6)
    with _writable(path) as conn:
        conn.execute("DELETE FROM entries WHERE seq = 4")
    v = verify_file(path)
    assert v.broken is not None and v.broken.seq == 5
    assert v.broken.problem == "gap in sequence: follows entry 3 (entry 4 missing)"


def test_the_first_entries_deleted_are_a_gap_at_the_start(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    _log(path, 4)
    with _writable(path) as conn:
        conn.execute("DELETE FROM entries WHERE seq <= 2")
    v = verify_file(path)
    assert v.broken is not None and v.broken.seq == 3
    assert "the log begins at 3 (entries 1..2 missing)" in v.broken.problem


def test_an_entry_rewritten_with_its_hash_breaks_the_next_ones_link(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    _log(path, 4)
    e = read_entries(path)[1]
    forged = entry_hash(e.seq, e.time, "hmi:mallory", e.kind, e.target, e.details, e.prev_hash)
    with _writable(path) as conn:
        conn.execute("UPDATE entries SET actor = 'hmi:mallory', hash = ? WHERE seq = 2", (forged,))
    v = verify_file(path)
    assert v.broken is not None and v.broken.seq == 3
    assert v.broken.problem.startswith("previous hash mismatch")


def test_an_anchor_kept_elsewhere_shows_a_log_cut_short_or_rewritten(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    _log(path, 5)
    exported_head = verify_file(path).head
    assert verify_file(path, anchor=exported_head).ok
    with _writable(path) as conn:
        conn.execute("DELETE FROM entries WHERE seq = 5")  # the last entry: no gap
    cut = verify_file(path, anchor=exported_head)
    assert cut.broken is None and cut.anchor_found is False and not cut.ok
    assert verify_file(path).ok  # without the anchor, nothing shows it (ADR 0047)


def test_the_triggers_refuse_an_update_or_a_delete(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    _log(path, 2)
    with sqlite3.connect(path) as conn:
        for stmt in ("UPDATE entries SET actor = 'x'", "DELETE FROM entries"):
            with pytest.raises(sqlite3.IntegrityError, match="append-only"):
                conn.execute(stmt)
    assert verify_file(path).entries == 2


def test_two_threads_appending_at_once_keep_one_chain(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    audit = AuditLog(path).open()
    start = threading.Barrier(2)

    def appender(who: str) -> None:
        start.wait()
        for i in range(300):
            audit.append(who, "command.write", "bench", {"i": i})

    threads = [threading.Thread(target=appender, args=(w,)) for w in ("hmi:a", "opcua:b")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert audit.flush()
    audit.close()
    v = verify_file(path)
    assert v.ok and v.entries == 600
    for who in ("hmi:a", "opcua:b"):
        mine = read_entries(path, Query(actor=who))
        assert [json.loads(e.details)["i"] for e in mine] == list(range(300))


def test_two_writers_on_one_file_continue_one_chain(tmp_path: Path) -> None:
    """The running supervisor and a command-line tool (another process) append to one
    bench's log: each numbers its entries from the file's last one, not from memory."""
    path = tmp_path / AUDIT_NAME
    running = AuditLog(path).open()
    running.append("hmi:alice", "login")
    assert running.flush()
    assert append_now(path, "cli", "user.add", "bob", {"role": "operator"}) is None
    running.append("hmi:alice", "logout")
    assert running.flush()
    running.close()
    v = verify_file(path)
    assert v.ok and v.entries == 3
    assert [e.kind for e in read_entries(path)] == ["login", "user.add", "logout"]


def test_a_failed_write_is_counted_and_retried_never_raised(tmp_path: Path) -> None:
    blocker = tmp_path / "state"
    blocker.write_text("a file where the state folder should be")
    path = blocker / AUDIT_NAME
    audit = AuditLog(path, retry_s=0.01).open()
    audit.append("hmi:alice", "command.start", "ch0")  # does not raise
    assert not audit.flush(timeout_s=5.0)
    assert audit.failures >= 1 and audit.error is not None and audit.pending == 1
    blocker.unlink()  # the disk is back
    assert audit.flush(timeout_s=5.0)
    audit.close()
    assert audit.error is None and verify_file(path).entries == 1


def test_past_its_bound_the_queue_drops_and_counts(tmp_path: Path) -> None:
    audit = AuditLog(tmp_path / AUDIT_NAME, max_pending=3)  # not open: nothing writes
    for i in range(5):
        audit.append("cli", "command.write", "bench", {"i": i})
    assert (audit.pending, audit.dropped) == (3, 2)


def test_details_are_canonical_whatever_a_caller_hands_over(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    with AuditLog(path) as audit:
        audit.append(
            "hmi:\ud800x", "command.write", "ch0", {"b": float("nan"), "a": Path("r.yaml")}
        )
    (e,) = read_entries(path)
    assert e.actor == "hmi:\\ud800x"  # stored escaped (core/encoding.py)
    assert e.details == '{"a":"r.yaml","b":"nan"}'
    assert verify_file(path).ok


def test_a_missing_file_or_one_that_is_no_audit_log_is_told_apart(tmp_path: Path) -> None:
    with pytest.raises(AuditFileError, match="no audit log there"):
        verify_file(tmp_path / AUDIT_NAME)
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"not a database" * 100)
    with pytest.raises(AuditFileError, match="not an audit log"):
        verify_file(junk)


def test_a_query_selects_by_time_actor_kind_family_and_channel(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_NAME
    clock = VirtualClock()
    with AuditLog(path, wall=clock.wall) as audit:
        audit.append("hmi:alice", "login")
        clock.advance(60)
        audit.append("hmi:alice", "command.start", "ch0", {"channel": "ch0"})
        clock.advance(60)
        audit.append("hmi:bob", "command.acknowledge", "alarm ch1.temp", {"channel": "ch1"})
        clock.advance(60)
        audit.append("hmi:alice", "recipe.save", "recipes/a.yaml")
    seqs = lambda q: [e.seq for e in read_entries(path, q)]  # noqa: E731
    assert seqs(Query(kind="command")) == [2, 3]
    assert seqs(Query(kind="command.start")) == [2]
    assert seqs(Query(kind="comm")) == []  # a family is a whole name
    assert seqs(Query(actor="hmi:alice", newest_first=True)) == [4, 2, 1]
    assert seqs(Query(channel="ch1")) == [3]
    assert seqs(Query(since="2026-01-01T00:01:00", until="2026-01-01T00:02:00.000000Z")) == [2, 3]
    assert seqs(Query(newest_first=True, limit=2)) == [4, 3]
    assert seqs(Query(newest_first=True, before_seq=3, limit=5)) == [2, 1]


def test_a_text_change_has_both_hashes_and_a_unified_diff() -> None:
    first = text_change(None, "recipe: a\nsteps: []\n", "recipes/a.yaml")
    assert first["previous_sha256"] is None and "+++ b/recipes/a.yaml" in first["diff"]
    again = text_change("recipe: a\nsteps: []\n", "recipe: a\nsteps: [x]\n", "recipes/a.yaml")
    assert again["previous_sha256"] == first["sha256"]
    assert "-steps: []\n+steps: [x]\n" in again["diff"]


def test_appends_return_while_the_file_is_locked_and_are_written_once_it_is_free(
    tmp_path: Path,
) -> None:
    """The caller (a command on the scan's loop) never waits for SQLite: another process
    holding the write lock delays the writer thread, not the appends."""
    path = tmp_path / AUDIT_NAME
    _log(path, 1)
    blocker = sqlite3.connect(path, isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")  # the write lock, held
    audit = AuditLog(path).open()
    for i in range(100):
        audit.append("hmi:otto", "command.write", "bench", {"i": i})
    assert audit.appended == 100 and audit.written == 0
    blocker.execute("COMMIT")
    blocker.close()
    assert audit.flush(timeout_s=30.0)
    audit.close()
    assert verify_file(path).entries == 101
