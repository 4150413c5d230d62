"""The retained-state store on its own: documents by key in SQLite, written off the
caller's thread, latest per key wins, failures reported and retried, unreadable files
moved aside."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import pytest

from supervisor.publish.retain import FORMAT, STATE_NAME, RetainStore


def test_documents_put_are_on_disk_after_a_flush(tmp_path: Path) -> None:
    store = RetainStore(tmp_path / STATE_NAME)
    assert store.open().documents == {}
    store.put("channel:ch0", {"step": 3, "counters": {"charge_ah": 0.25}})
    assert store.flush()
    assert RetainStore(tmp_path / STATE_NAME).read() == {
        "channel:ch0": {"step": 3, "counters": {"charge_ah": 0.25}}
    }
    store.close()


def test_the_latest_document_of_a_key_wins_and_the_queue_holds_one_per_key(
    tmp_path: Path,
) -> None:
    store = RetainStore(tmp_path / STATE_NAME)  # not open yet: nothing writes
    for step in range(100):
        store.put("channel:ch0", {"step": step})
    store.put("channel:ch1", {"step": 7})
    assert store.pending == 2  # bounded by the keys, however often the scan saves
    store.open()
    assert store.flush()
    assert store.read() == {"channel:ch0": {"step": 99}, "channel:ch1": {"step": 7}}
    store.close()


def test_the_file_is_sqlite_in_wal_mode_with_its_format(tmp_path: Path) -> None:
    store = RetainStore(tmp_path / STATE_NAME)
    store.open()
    store.put("k", {})
    assert store.flush()
    with sqlite3.connect(tmp_path / STATE_NAME) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone() == ("wal",)
        assert conn.execute("SELECT value FROM meta WHERE key = 'format'").fetchone() == (
            str(FORMAT),
        )
    conn.close()
    store.close()


def test_what_was_saved_is_read_back_by_the_next_process(tmp_path: Path) -> None:
    first = RetainStore(tmp_path / STATE_NAME)
    first.open()
    first.put("alarms", {"alarms": [{"id": "ch0.internal"}]})
    first.close()  # close writes what is pending
    loaded = RetainStore(tmp_path / STATE_NAME).open()
    assert loaded.problem == ""
    assert loaded.documents == {"alarms": {"alarms": [{"id": "ch0.internal"}]}}


def test_an_unreadable_file_is_moved_aside_with_the_time_in_its_name(tmp_path: Path) -> None:
    path = tmp_path / STATE_NAME
    path.write_bytes(b"\x00garbage" * 1000)
    store = RetainStore(path, wall=lambda: 1_767_254_400.0)
    loaded = store.open()
    assert loaded.documents == {}
    assert "not a database" in loaded.problem
    assert loaded.moved_to is not None and loaded.moved_to.name.startswith(
        f"{STATE_NAME}.corrupt-2026"
    )
    assert loaded.moved_to.read_bytes() == b"\x00garbage" * 1000
    store.put("k", {"fresh": True})  # and a new file is written in its place
    assert store.flush()
    assert store.read() == {"k": {"fresh": True}}
    store.close()


def test_a_failed_write_is_reported_kept_and_retried(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = RetainStore(tmp_path / STATE_NAME, retry_s=0.01)
    store.open()
    attempts: list[int] = []
    real = RetainStore._write

    def flaky(self: RetainStore, conn: sqlite3.Connection, batch: Any) -> None:
        attempts.append(len(batch))
        if len(attempts) <= 3:
            raise sqlite3.OperationalError("attempt to write a readonly database")
        real(self, conn, batch)

    monkeypatch.setattr(RetainStore, "_write", flaky)
    store.put("channel:ch0", {"step": 1})
    assert not store.flush(timeout_s=5.0)  # the first attempt failed
    assert store.error == "OperationalError: attempt to write a readonly database"
    store.put("channel:ch0", {"step": 2})  # a newer document replaces the one kept
    for _ in range(10):
        if store.flush(timeout_s=5.0):
            break
    assert store.error is None
    assert store.read() == {"channel:ch0": {"step": 2}}
    assert store.failures == 3 and len(attempts) >= 4
    store.close()


def test_put_never_raises_even_when_the_directory_is_gone(tmp_path: Path) -> None:
    store = RetainStore(tmp_path / "var" / STATE_NAME, retry_s=0.01)
    store.open()
    (tmp_path / "var").rmdir()  # nothing written yet: the directory is empty
    (tmp_path / "var").write_text("a file where the directory was")
    store.put("k", {"v": 1})
    assert not store.flush(timeout_s=5.0)
    assert store.error is not None
    store.close()
