"""The historian on a whole bench: the simulated bench writes its history, the HTTP API
answers the screens' trend and event requests (real aiohttp server on loopback), a
restart keeps the history, a clean stop loses nothing, a corrupt file is set aside with an
alarm in the alarm model.

Virtual clock (sim.yaml's four Chadèche channels and its ADAM, every device in process);
requests are made between scans, as a screen makes them between two scans of a real
bench. The last test runs ``supervisor run`` as a process on the real clock (bounded
waits, no timing claim).
"""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import yaml
from commandrig import DISCHARGE, chadeche_map, io_map, recipe

from supervisor.app import Bench, build_bench
from supervisor.commands import Command, Verb
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.hmi import HttpApi
from supervisor.hmi.history_api import DEFAULT_BUCKETS
from supervisor.publish.changes import ChangeBatch, Sample
from supervisor.publish.historian import CORRUPT_ALARM, HistoryQuery
from supervisor.publish.historian.store import problem_of
from supervisor.safety.alarms import AlarmState
from supervisor.testing import run_scans

pytestmark = pytest.mark.integration

EPOCH = 1_767_225_600.0  # the virtual clock's 2026-01-01T00:00:00Z


def history_file(tmp: Path) -> Path:
    return tmp / "state" / "history.sqlite"


async def recording_bench(
    tmp: Path, spy: Callable[[Bench], None] | None = None, **history: Any
) -> Bench:
    """The command-path bench, recording its history, started, its first images in."""
    path = io_map(tmp)
    if history:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        data["history"] = history
        path.write_text(yaml.safe_dump(data), encoding="utf-8")
    bench = build_bench(load_bench(path), VirtualClock(), in_process=True)
    bench.record_history()
    if spy is not None:
        spy(bench)
    await bench.start()
    await run_scans(bench.engine, 10)
    return bench


@dataclass
class Client:
    bench: Bench
    api: HttpApi
    session: aiohttp.ClientSession

    async def get(self, path: str, **params: Any) -> tuple[int, Any]:
        query = {k: str(v) for k, v in params.items()}
        async with self.session.get(self.api.url + path, params=query) as resp:
            return resp.status, await resp.json()

    async def scans(self, n: int) -> None:
        await run_scans(self.bench.engine, n)

    def flush(self) -> None:
        assert self.bench.historian is not None
        assert self.bench.historian.writer.flush()


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[Client]:
    bench = await recording_bench(tmp_path)
    assert bench.historian is not None
    api = HttpApi(
        bench.db,
        bench.clock,
        "127.0.0.1",
        0,
        commands=bench.commands,
        history=bench.historian.query,
    )
    await api.start()
    try:
        async with aiohttp.ClientSession() as session:
            yield Client(bench, api, session)
    finally:
        await api.stop()
        await bench.shutdown()


async def discharge(c: Client, tmp_path: Path, actor: str = "alice") -> None:
    result = c.bench.commands.execute(
        Command.channel("ch0", Verb.START, actor, recipe=recipe(tmp_path, DISCHARGE))
    )
    assert result.accepted, result.reason
    await c.scans(600)  # ten minutes of discharge at 0.2 A, one scan a second
    c.flush()


# --- trends ---------------------------------------------------------------------------


async def test_the_history_of_a_tag_comes_with_its_unit_and_each_sample_quality(
    client: Client, tmp_path: Path
) -> None:
    await discharge(client, tmp_path)
    end = client.bench.clock.wall()
    status, body = await client.get("/history", tag="ch0.current", start=EPOCH, end=end)
    assert status == 200, body
    assert (body["tag"], body["unit"], body["dtype"], body["mode"]) == (
        "ch0.current",
        "A",
        "float",
        "raw",
    )
    assert body["count"] == len(body["samples"]) > 0 and not body["truncated"]
    assert all(s["quality"] in ("GOOD", "UNCERTAIN", "BAD") for s in body["samples"])
    assert any(
        s["value"] == pytest.approx(-0.2, abs=0.01) and s["quality"] == "GOOD"
        for s in body["samples"]
    )
    times = [s["t"] for s in body["samples"]]
    assert times == sorted(times) and times[0] >= EPOCH and times[-1] <= end


async def test_an_interval_gives_min_max_mean_per_bucket(client: Client, tmp_path: Path) -> None:
    await discharge(client, tmp_path)
    end = client.bench.clock.wall()
    status, raw = await client.get("/history", tag="ch0.voltage", start=EPOCH, end=end)
    status, body = await client.get(
        "/history", tag="ch0.voltage", start=EPOCH, end=end, interval_s=60
    )
    assert status == 200, body
    assert body["mode"] == "aggregate" and body["interval_s"] == 60 and body["unit"] == "V"
    values = [s["value"] for s in raw["samples"] if s["value"] is not None]
    buckets = body["buckets"]
    assert sum(b["count"] for b in buckets) == len(values)
    assert min(b["min"] for b in buckets) == min(values)
    assert max(b["max"] for b in buckets) == max(values)
    assert buckets[0]["first"] == values[0] and buckets[-1]["last"] == values[-1]
    assert all(b["min"] <= b["mean"] <= b["max"] for b in buckets)
    assert [b["t"] for b in buckets] == sorted(b["t"] for b in buckets)


async def test_iso_8601_and_unix_seconds_ask_for_the_same_range(
    client: Client, tmp_path: Path
) -> None:
    await discharge(client, tmp_path)
    start, end = EPOCH + 60, EPOCH + 300
    iso = {
        "start": datetime.fromtimestamp(start, UTC).isoformat().replace("+00:00", "Z"),
        "end": datetime.fromtimestamp(end, UTC).astimezone().isoformat(),  # local offset
    }
    _, by_unix = await client.get("/history", tag="ch0.voltage", start=start, end=end)
    _, by_iso = await client.get("/history", tag="ch0.voltage", **iso)
    assert by_iso == by_unix and by_unix["start"] == start and by_unix["end"] == end


async def test_a_range_with_more_samples_than_the_limit_is_aggregated(
    client: Client, tmp_path: Path
) -> None:
    await discharge(client, tmp_path)
    end = client.bench.clock.wall()
    status, body = await client.get("/history", tag="scan.count", start=EPOCH, end=end, limit=50)
    assert status == 200, body
    assert body["mode"] == "aggregate"
    assert body["aggregated_because"] == "more than 50 samples in the range"
    assert body["interval_s"] == pytest.approx((end - EPOCH) / DEFAULT_BUCKETS)
    assert sum(b["count"] for b in body["buckets"]) > 50


@pytest.mark.parametrize(
    ("params", "status", "words"),
    [
        ({}, 400, "tag is required"),
        ({"tag": "ch0.voltage", "start": "yesterday"}, 400, "start='yesterday': not a time"),
        ({"tag": "ch0.voltage", "end": "2026-01-01T08:00:00"}, 400, "no time zone"),
        ({"tag": "ch0.voltage", "start": "nan"}, 400, "not a finite time"),
        ({"tag": "ch0.voltage", "start": 2e9, "end": 1e9}, 400, "is after end"),
        ({"tag": "ch0.voltage", "start": 0, "end": 604800, "interval_s": 1}, 400, "604800 buckets"),
        ({"tag": "ch0.voltage", "interval_s": 0}, 400, "interval_s must be a finite number > 0"),
        ({"tag": "ch0.voltage", "interval_s": "often"}, 400, "interval_s='often': not a number"),
        ({"tag": "ch0.voltage", "limit": 0}, 400, "limit=0: between 1 and 100000"),
        ({"tag": "ch9.voltage"}, 404, "unknown tag 'ch9.voltage'"),
    ],
)
async def test_a_bad_history_request_is_refused_with_its_reason(
    client: Client, params: dict[str, Any], status: int, words: str
) -> None:
    got, body = await client.get("/history", **params)
    assert got == status, body
    assert words in body["error"]


async def test_a_tag_not_recorded_is_404_and_one_not_written_yet_is_empty(
    tmp_path: Path,
) -> None:
    path = io_map(tmp_path)
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    for t in data["tags"]:
        if t["name"] == "room.temp":
            t["history"] = {"enabled": False}
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    bench = build_bench(load_bench(path), VirtualClock(), in_process=True)
    historian = bench.record_history()
    assert historian is not None
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, history=historian.query)
    await bench.start()
    await api.start()
    try:
        async with aiohttp.ClientSession() as session:
            c = Client(bench, api, session)
            status, body = await c.get("/history", tag="room.temp")
            assert status == 404 and "not recorded" in body["error"]
            status, body = await c.get("/history", tag="ch0.voltage")  # before any scan
            assert status == 200 and body["samples"] == [] and body["unit"] == "V"
    finally:
        await api.stop()
        await bench.shutdown()


# --- events ---------------------------------------------------------------------------


async def test_events_list_commands_with_their_actor_and_step_changes(
    client: Client, tmp_path: Path
) -> None:
    await discharge(client, tmp_path, actor="alice")
    end = client.bench.clock.wall()
    status, body = await client.get("/events", start=EPOCH, end=end, channel="ch0")
    assert status == 200, body
    events = body["events"]
    start = next(e for e in events if e["kind"] == "command")
    assert start["actor"] == "alice" and start["channel"] == "ch0" and "start" in start["text"]
    steps = [e for e in events if e["kind"] == "step"]
    assert steps and steps[0]["source"] == "d" and steps[0]["actor"] == "recipe"
    assert steps[0]["test_id"] and steps[0]["recipe"] == "d"
    _, only = await client.get("/events", start=EPOCH, end=end, kind="command")
    assert {e["kind"] for e in only["events"]} == {"command"}
    _, other = await client.get("/events", start=EPOCH, end=end, channel="ch1")
    assert other["events"] == []


@pytest.mark.parametrize(
    ("params", "status", "words"),
    [
        ({"kind": "alarms"}, 400, "unknown event kind 'alarms'"),
        ({"channel": "ch9"}, 404, "unknown channel 'ch9' (ch0, ch1, ch2, ch3)"),
        ({"start": "soon"}, 400, "start='soon': not a time"),
        ({"start": 10, "end": 5}, 400, "is after end"),
    ],
)
async def test_a_bad_events_request_is_refused_with_its_reason(
    client: Client, params: dict[str, Any], status: int, words: str
) -> None:
    got, body = await client.get("/events", **params)
    assert got == status, body
    assert words in body["error"]


# --- the bench's life -----------------------------------------------------------------


async def test_a_clean_stop_loses_nothing_and_a_restart_keeps_the_history(
    tmp_path: Path,
) -> None:
    # Commits far apart: what the stop writes is everything since the start.
    handed: dict[tuple[str, float], Any] = {}  # every sample the writer's filter kept

    def spy(bench: Bench) -> None:
        assert bench.historian is not None
        changes = bench.historian.writer._filter
        apply = changes.apply

        def record(batch: ChangeBatch) -> list[Sample]:
            samples = apply(batch)
            for s in samples:
                handed[(s.name, s.wall)] = s.value  # a later one at the same instant wins
            return samples

        changes.apply = record  # type: ignore[method-assign]

    bench = await recording_bench(tmp_path, spy, commit_interval_s=10.0)
    assert bench.historian is not None
    writer = bench.historian.writer
    bench.db.write("ch0.manual_current", 0.1)
    await run_scans(bench.engine, 30)
    bench.db.write("ch0.manual_current", 0.3)  # the very last change before the stop
    await run_scans(bench.engine, 1)
    await bench.shutdown()
    assert writer.rows_dropped == 0 and writer.queued_rows == 0
    conn = sqlite3.connect(history_file(tmp_path))
    try:
        stored = {
            (name, t): v
            for name, t, v in conn.execute(
                "SELECT name, t, value FROM samples JOIN tags ON tags.id = tag_id"
            )
        }
    finally:
        conn.close()
    assert len(handed) > 100
    assert stored == {k: (int(v) if isinstance(v, bool) else v) for k, v in handed.items()}
    last = max(t for name, t in stored if name == "ch0.manual_current")
    assert stored[("ch0.manual_current", last)] == 0.3

    again = await recording_bench(tmp_path)  # the same state directory: a restart
    try:
        assert again.historian is not None
        assert again.historian.opened is not None and again.historian.opened.set_aside is None
        series = again.historian.query.samples("ch0.manual_current", 0, 4e9)
        assert [s.value for s in series.samples][-2:] == [0.1, 0.3]
        await run_scans(again.engine, 5)
        assert again.historian.writer.flush()
        assert again.historian.query.count("scan.count", 0, 4e9) > 31
    finally:
        await again.shutdown()


async def test_a_corrupt_history_file_is_set_aside_and_raises_an_alarm(tmp_path: Path) -> None:
    path = history_file(tmp_path)
    path.parent.mkdir(parents=True)
    path.write_bytes(b"\x00garbage" * 1000)
    bench = await recording_bench(tmp_path)
    try:
        alarm = bench.alarms[CORRUPT_ALARM] if bench.alarms is not None else None
        assert alarm is not None
        # The condition is over (a new file is in use): it waits for an acknowledge.
        assert alarm.state is AlarmState.RETURNED_UNACKED
        moved = path.with_name("history.sqlite.corrupt-20260101T000000Z")
        assert str(moved) in alarm.message and "file is not a database" in alarm.message
        assert moved.read_bytes() == b"\x00garbage" * 1000
        assert bench.historian is not None and bench.historian.writer.flush()
        assert bench.historian.query.count("scan.count", 0, 4e9) > 0  # the new file
        events = bench.historian.query.events(0, 4e9, kind="alarm")
        assert any(CORRUPT_ALARM in e.text for e in events)  # itself on the record
    finally:
        await bench.shutdown()


async def test_history_is_on_by_default_and_off_when_disabled(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    on = build_bench(load_bench(io_map(tmp_path / "a")), VirtualClock(), in_process=True)
    assert on.record_history() is not None
    assert on.historian in on.engine.publishers
    (tmp_path / "b").mkdir()
    path = io_map(tmp_path / "b")
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data["history"] = {"enabled": False}
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    off = build_bench(load_bench(path), VirtualClock(), in_process=True)
    assert off.record_history() is None
    assert not history_file(tmp_path / "b").exists()


# --- a real run -----------------------------------------------------------------------


CLI = (sys.executable, "-m", "supervisor.cli.main")


def _get(url: str) -> tuple[int, Any]:
    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        with exc:
            return exc.code, json.loads(exc.read())


def test_supervisor_run_records_history_served_while_running_and_complete_after_stop(
    tmp_path: Path,
) -> None:
    io = chadeche_map(tmp_path)
    file = recipe(tmp_path, DISCHARGE)
    proc = subprocess.Popen(
        [*CLI, "run", io, "--http-port", "0", "--recipe", f"ch0={file}", "--start"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    try:
        assert proc.stdout is not None
        url = history_line = None
        for line in proc.stdout:
            m = re.search(r"HTTP API listening on (http://127\.0\.0\.1:\d+/api)", line)
            url = m.group(1) if m else url
            history_line = line if line.startswith("history: ") else history_line
            if line.startswith("Ctrl-C"):
                break
        assert url, "the bench never said where it listens"
        assert history_line is not None and str(history_file(tmp_path)) in history_line
        deadline = time.monotonic() + 30  # an upper bound for a slow machine
        body: Any = None
        while time.monotonic() < deadline:
            status, body = _get(f"{url}/history?tag=ch0.current&start=0")
            if status == 200 and any(
                s["value"] is not None and s["value"] < -0.1 for s in body["samples"]
            ):
                break
            time.sleep(0.2)
        assert body is not None and body["unit"] == "A", body
        assert any(s["value"] is not None and s["value"] < -0.1 for s in body["samples"])
        status, events = _get(f"{url}/events?start=0&channel=ch0&kind=command")
        assert status == 200
        assert any(e["actor"] == "command line" for e in events["events"])
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        assert "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
    conn = sqlite3.connect(history_file(tmp_path))
    try:
        names = {r[0] for r in conn.execute("SELECT name FROM tags")}
        kinds = {r[0] for r in conn.execute("SELECT DISTINCT kind FROM events")}
        (latest,) = conn.execute(
            "SELECT max(t) FROM samples JOIN tags ON tags.id = tag_id WHERE name = 'scan.count'"
        ).fetchone()
    finally:
        conn.close()
    assert {"ch0.voltage", "ch0.current", "ch0.chain.state", "historian.rows_written"} <= names
    assert {"command", "step", "state"} <= kinds
    # The stop's own last scan is on disk (a clean stop writes what was queued).
    assert latest is not None and time.time() - latest < 60


def test_a_killed_supervisor_leaves_a_usable_history_file(tmp_path: Path) -> None:
    """SIGKILL: what was committed is there and the file opens without being set aside
    (what is lost is at most the last commit interval, ADR 0013)."""
    io = chadeche_map(tmp_path)
    proc = subprocess.Popen(
        [*CLI, "run", io, "--http-port", "0"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    try:
        assert proc.stdout is not None
        url = None
        for line in proc.stdout:
            m = re.search(r"HTTP API listening on (http://127\.0\.0\.1:\d+/api)", line)
            url = m.group(1) if m else url
            if line.startswith("Ctrl-C"):
                break
        assert url
        deadline = time.monotonic() + 30
        count = 0
        while time.monotonic() < deadline and count < 20:
            _, body = _get(f"{url}/history?tag=scan.count&start=0")
            count = len(body.get("samples", []))
            time.sleep(0.2)
        assert count >= 20
        proc.kill()
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
    path = history_file(tmp_path)
    assert problem_of(path) == ""  # replays its WAL; passes the integrity check
    query = HistoryQuery(path)
    try:
        assert query.count("scan.count", 0, 4e9) >= count
    finally:
        query.close()
