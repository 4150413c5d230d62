"""A live test's summary is rewritten off the scan's thread (issue 13): the scan hands a
summary over and returns; the file always ends up holding the newest summary."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

from supervisor.core.records import ChainEvent
from supervisor.publish.results import ResultCollector, SummaryWriter


def _read(path: Path) -> dict[str, object]:
    return dict(json.loads(path.read_text(encoding="utf-8")))


def test_a_checkpoint_returns_before_the_file_is_written_and_the_file_follows(
    tmp_path: Path,
) -> None:
    writer = SummaryWriter("test")
    path = tmp_path / "summary.json"
    try:
        with writer._io:  # the disk is busy: the caller must not wait for it
            writer.put(path, "ch0", {"n": 1})
            assert not path.exists()
        assert writer.flush(10.0)
        assert _read(path) == {"n": 1}
    finally:
        writer.stop()


def test_a_burst_of_checkpoints_costs_fewer_writes_and_the_newest_wins(tmp_path: Path) -> None:
    writer = SummaryWriter("test")
    path = tmp_path / "summary.json"
    try:
        with writer._io:
            for n in range(50):  # 50 step changes while a write is under way
                writer.put(path, "ch0", {"n": n})
        assert writer.flush(10.0)
        assert _read(path) == {"n": 49}
        assert writer.written < 50
    finally:
        writer.stop()


def test_the_last_summary_written_at_once_is_not_overwritten_by_an_older_checkpoint(
    tmp_path: Path,
) -> None:
    writer = SummaryWriter("test")
    path = tmp_path / "summary.json"
    try:
        with writer._io:
            writer.put(path, "ch0", {"final": False})
        writer.write_now(path, "ch0", {"final": True})
        assert writer.flush(10.0)
        assert _read(path) == {"final": True}
    finally:
        writer.stop()


class WriterLast:
    """The writer's file lock, fake in one respect: its own thread gets it only after the
    caller's thread has had it once — the order a loaded machine may choose (found flaky
    under load: the thread held an older summary when the last one was written)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._caller_done = threading.Event()
        self.writer_waiting = threading.Event()
        self.caller = threading.current_thread()

    def __enter__(self) -> None:
        if threading.current_thread() is not self.caller:
            self.writer_waiting.set()
            self._caller_done.wait(10.0)
        self._lock.acquire()

    def __exit__(self, *exc: Any) -> None:
        self._lock.release()
        if threading.current_thread() is self.caller:
            self._caller_done.set()


def test_an_older_checkpoint_already_taken_by_the_thread_does_not_overwrite_the_last_summary(
    tmp_path: Path,
) -> None:
    writer = SummaryWriter("test")
    lock = WriterLast()
    writer._io = lock  # type: ignore[assignment]
    path = tmp_path / "summary.json"
    try:
        writer.put(path, "ch0", {"final": False})
        assert lock.writer_waiting.wait(10.0)  # the thread holds the older one
        writer.write_now(path, "ch0", {"final": True})
        assert writer.flush(10.0)
        assert _read(path) == {"final": True}
    finally:
        writer.stop()


def test_after_stop_a_checkpoint_is_written_on_the_callers_thread(tmp_path: Path) -> None:
    writer = SummaryWriter("test")
    writer.stop()
    path = tmp_path / "summary.json"
    writer.put(path, "ch0", {"n": 7})
    assert _read(path) == {"n": 7}


def test_a_collector_with_a_writer_gives_the_same_summary_as_one_without(tmp_path: Path) -> None:
    writer = SummaryWriter("test")
    try:
        files = {}
        for name, w in (("direct", None), ("threaded", writer)):
            c = ResultCollector("ch0", "r", "t1", tmp_path / name, writer=w)
            for k, step in enumerate(("charge", "rest", "discharge")):
                c.on_event(ChainEvent(float(k), float(k), "ch0", "step", f"to {step}", k, step, 1))
                c.checkpoint("Running", now=float(k))
            files[name] = c.summary_path
        assert writer.flush(10.0)
        direct, threaded = (_read(p) for p in files.values() if p is not None)
        assert threaded == direct
        assert [e["step"] for e in threaded["timeline"]] == ["charge", "rest", "discharge"]  # type: ignore[union-attr,index]
    finally:
        writer.stop()
