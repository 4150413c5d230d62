"""The shelf of OPC UA's standard address space (ADR 0020): one per asyncua and Python
version, shared by every process of the machine, built once and renamed into place, so
that concurrent first starts, a crash while building and an asyncua upgrade never leave a
reader with a half-written or stale shelf. The builder is a stand-in here (the real one
runs asyncua in a child process: tests/integration/test_opcua_standard_space_shelf.py)."""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from importlib import metadata
from pathlib import Path

import pytest

from supervisor.publish.opcua import shelf

pytestmark = pytest.mark.filterwarnings("error")


def fake_maker(calls: list[Path], gate: threading.Barrier | None = None) -> shelf.Maker:
    def make(path: Path) -> None:
        calls.append(path)
        if gate is not None:
            gate.wait(timeout=10)  # every builder has made its own folder
        path.with_suffix(".dat").write_bytes(b"nodes")
        path.with_suffix(".dir").write_bytes(b"'i=84', (0, 5)\n")
        path.touch()

    return make


def listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_the_shelf_is_keyed_by_the_asyncua_and_python_versions(tmp_path: Path) -> None:
    key = shelf.shelf_key()
    assert f"asyncua-{metadata.version('asyncua')}" in key
    assert f"py{sys.version_info.major}.{sys.version_info.minor}" in key
    assert shelf.shelf_path(tmp_path) == tmp_path / key / "aspace"


def test_the_cache_folder_follows_the_override_then_systemd_then_xdg(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(shelf.CACHE_ENV, raising=False)
    monkeypatch.delenv("CACHE_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert shelf.cache_dir() == tmp_path / "xdg" / "bench-supervisor"
    monkeypatch.setenv("CACHE_DIRECTORY", f"{tmp_path / 'systemd'}:/elsewhere")
    assert shelf.cache_dir() == tmp_path / "systemd"
    monkeypatch.setenv(shelf.CACHE_ENV, str(tmp_path / "mine"))
    assert shelf.cache_dir() == tmp_path / "mine"


async def test_the_first_start_builds_the_shelf_and_the_next_ones_reuse_it(
    tmp_path: Path,
) -> None:
    calls: list[Path] = []
    path = await shelf.ensure_shelf(tmp_path, fake_maker(calls))
    assert path == shelf.shelf_path(tmp_path)
    assert shelf.ready(path)
    assert (path.with_suffix(".dat")).read_bytes() == b"nodes"
    assert await shelf.ensure_shelf(tmp_path, fake_maker(calls)) == path
    assert len(calls) == 1
    # built in a private folder, renamed into place: nothing else is left in the cache
    assert listing(tmp_path) == [shelf.shelf_key()]


def test_concurrent_first_starts_leave_one_complete_shelf(tmp_path: Path) -> None:
    calls: list[Path] = []
    gate = threading.Barrier(3)
    path = shelf.shelf_path(tmp_path)
    errors: list[BaseException] = []

    def start() -> None:
        try:
            shelf.build_shelf(path, fake_maker(calls, gate))
        except BaseException as exc:  # pragma: no cover - reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=start) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert errors == []
    assert len({p.parent for p in calls}) == 3  # each built its own
    assert shelf.ready(path)
    assert listing(tmp_path) == [shelf.shelf_key()]


async def test_a_failed_build_means_no_shelf_and_the_space_in_memory(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    def broken(path: Path) -> None:
        path.with_suffix(".dat").write_bytes(b"half")
        raise RuntimeError("building it failed (1): MemoryError")

    with caplog.at_level(logging.WARNING):
        assert await shelf.ensure_shelf(tmp_path, broken) is None
    assert "MemoryError" in caplog.text
    assert listing(tmp_path) == []  # nothing half-written left for the next start


async def test_a_cache_that_cannot_be_written_means_no_shelf(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder", encoding="utf-8")
    assert await shelf.ensure_shelf(blocker / "cache", fake_maker([])) is None


async def test_the_shelf_can_be_turned_off(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(shelf.SHELF_ENV, "0")
    calls: list[Path] = []
    assert await shelf.ensure_shelf(tmp_path, fake_maker(calls)) is None
    assert calls == []


def test_builds_left_by_a_dead_process_are_dropped_after_an_hour(tmp_path: Path) -> None:
    old = tmp_path / f".build-{shelf.shelf_key()}-dead"
    old.mkdir()
    recent = tmp_path / f".build-{shelf.shelf_key()}-running"
    recent.mkdir()
    hour_ago = time.time() - shelf.STALE_BUILD_S - 60
    os.utime(old, (hour_ago, hour_ago))
    shelf.build_shelf(shelf.shelf_path(tmp_path), fake_maker([]))
    assert not old.exists()
    assert recent.exists()  # another process may be building there right now
