"""Retained state: a supervisor that dies brings its tests back Held after a restart.

docs/design.md "Safety": per channel the recipe, step, step time, cycle, Ah/Wh counters and
test id are persisted; after a restart a channel comes back Held with its test resumable,
never re-energised on its own (seed 001: the context is saved before every alarm so an
interrupted test resumes later). Here on the virtual clock: the first bench "dies" right
after its last save (no shutdown, nothing more written), a second one starts on the same
state directory.
"""

from __future__ import annotations

import csv
import itertools
import json
import logging
import re
import sqlite3
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from snapshot_cases import BAD_VALUES

from supervisor.app import Bench, build_bench
from supervisor.app.retained import RESTORE_ALARM, WRITE_ALARM
from supervisor.chains.states import State
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import bench_from_data
from supervisor.publish.retain import STATE_NAME, RetainStore
from supervisor.tags.spec import shown

pytestmark = pytest.mark.integration

EPOCH = 1_767_254_400.0  # 2026-01-01 08:00 UTC: reproducible Unix times
AWAY_S = 120.0  # how long the supervisor stays dead between the two benches

_OPEN: list[Bench] = []


@pytest.fixture(autouse=True)
async def _shutdown_benches() -> AsyncIterator[None]:
    yield
    while _OPEN:
        await _OPEN.pop().shutdown()


def bench_data(state_dir: Path, current_limit_a: float = 0.4) -> dict[str, Any]:
    """One Chadèche channel with a simulated NiMH cell (the board's simulator runs in
    process: the cell itself starts again from its configuration after a restart)."""
    return {
        "bench": "retain",
        "scan": {"period_s": 1.0},
        "state_dir": str(state_dir),
        "devices": {
            "chadeche": {
                "driver": "chadeche",
                "poll_period_s": 1.0,
                "stale_after_s": 3.0,
                "boards": [{"address": 0, "sim": {"model": "nimh-aa", "capacity_ah": 2.0}}],
            }
        },
        "channels": [
            {
                "name": "ch0",
                "source": {"device": "chadeche", "board": 0},
                "capacity_ah": 2.0,
                "limits": {
                    "current_a": [-current_limit_a, current_limit_a],
                    "voltage_v": [0.2, 2.0],
                },
            }
        ],
    }


def new_bench(state_dir: Path, wall_epoch_s: float = EPOCH, **kw: Any) -> Bench:
    b = build_bench(
        bench_from_data(bench_data(state_dir, **kw)), VirtualClock(wall_epoch_s=wall_epoch_s)
    )
    _OPEN.append(b)
    return b


RECIPE = (
    "recipe: cycle\n"
    "logging: {period: 10 s}\n"
    "steps:\n"
    "  - {id: charge, charge: 300 mA, duration: 600 s}\n"
    "  - {id: rest, rest: 120 s}\n"
    "  - {id: discharge, discharge: 200 mA, duration: 300 s}\n"
)


async def started(b: Bench, tmp_path: Path, text: str = RECIPE) -> Path:
    """A recipe loaded on ch0 and started; the test's result folder."""
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(text, encoding="utf-8")
    b.retain()
    runner = b.load_recipe("ch0", recipe, test_id="t1")
    await b.engine.run_for(3.0)
    runner.command("start")
    return Path(b.recipes["ch0"].folder)


def die(b: Bench) -> dict[str, Any]:
    """The process dies right after its last save: the saved document of ch0."""
    assert b.retention is not None
    store = b.retention.store
    assert store.flush()
    store.close()  # nothing is pending: this writes nothing more
    b.retention = None
    for c in b.results.values():
        c.abandon()  # the files stay as they are on disk
    _OPEN.remove(b)
    return store.read()["channel:ch0"]


def wall_of(b: Bench) -> float:
    return b.clock.wall()


def bdf_rows(folder: Path) -> list[dict[str, str]]:
    text = (folder / "t1.bdf.csv").read_text(encoding="utf-8")
    assert text.count("Test Time / s") == 1  # one header, even after a restart
    return list(csv.DictReader(text.splitlines()))


def summary(folder: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    return data


async def test_a_killed_supervisor_brings_its_test_back_held_at_the_same_step(
    tmp_path: Path,
) -> None:
    b1 = new_bench(tmp_path / "var")
    folder = await started(b1, tmp_path)
    await b1.engine.run_for(650.0)  # 50 s into the rest
    assert b1.db["ch0.chain.step"].value == "rest"
    saved = die(b1)
    chain = saved["chain"]
    assert (chain["state"], chain["step_id"], chain["cycle"]) == ("Running", "rest", 1)

    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S)
    report = b2.retain()
    runner, db = b2.runners["ch0"], b2.db
    assert runner.state is State.HELD
    assert "ch0: test t1 (cycle) restored Held in step rest" in report[0]
    assert db["ch0.chain.step"].value == "rest"
    assert db["ch0.chain.cycle"].value == 1
    assert db["ch0.chain.step_time"].value == pytest.approx(chain["step_time_s"])
    for name in ("charge_ah", "charged_ah", "discharged_ah", "energy_wh", "charged_wh"):
        assert db[f"ch0.{name}"].value == pytest.approx(saved["tags"][f"ch0.{name}"])
    assert db["ch0.mode"].value == "auto"

    # Never re-energised on its own: Held, no current, nothing enabled.
    await b2.engine.run_for(60.0)
    assert runner.state is State.HELD
    assert db["ch0.current_cmd"].value == 0.0
    assert db["ch0.enable"].value is False
    assert db["ch0.charge_ah"].value == pytest.approx(saved["tags"]["ch0.charge_ah"], abs=1e-9)
    assert db["ch0.chain.step_time"].value == pytest.approx(chain["step_time_s"])

    runner.command("resume")
    await b2.engine.run_for(400.0)
    assert runner.state is State.COMPLETE
    s = summary(folder)
    assert s["complete"] is True and s["state"] == "Complete"
    restart = [e for e in s["timeline"] if "supervisor restarted" in e["text"]]
    assert len(restart) == 1
    assert re.match(r"supervisor restarted after 12[01]\.\d s; test held", restart[0]["text"])
    rows = bdf_rows(folder)
    assert [int(r["Record Index / 1"]) for r in rows] == list(range(1, len(rows) + 1))
    rest = [r for r in rows if r["Step ID"] == "rest"]
    step_times = [float(r["Step Time / s"]) for r in rest]
    # The step goes on where it was saved: the time away and the hold are not step time.
    assert step_times == sorted(step_times) and step_times[-1] == pytest.approx(120.0, abs=1.0)
    test_times = [float(r["Test Time / s"]) for r in rows]
    assert test_times == sorted(test_times)
    # The time away is test time (a hold is too): the test ends later than 1020 s.
    assert s["duration_s"] > 600 + 120 + 300 + AWAY_S
    assert s["duration_s"] == pytest.approx(test_times[-1], abs=1.0)
    (cycle,) = s["cycles"]
    # Both the efficiency and the capacities it comes from are rounded to 6 decimals.
    assert cycle["coulombic_efficiency"] == pytest.approx(
        cycle["discharge_capacity_ah"] / cycle["charge_capacity_ah"], abs=1e-4
    )


async def test_a_held_step_and_the_time_away_do_not_count_as_step_time(tmp_path: Path) -> None:
    b1 = new_bench(tmp_path / "var")
    await started(b1, tmp_path)
    await b1.engine.run_for(100.0)
    b1.runners["ch0"].command("hold")
    await b1.engine.run_for(50.0)  # held for 50 s: step time stands at about 100 s
    chain = die(b1)["chain"]
    assert chain["state"] == "Held"
    assert chain["step_time_s"] == pytest.approx(100.0, abs=1.5)

    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S)
    b2.retain()
    runner = b2.runners["ch0"]
    assert runner.state is State.HELD
    assert b2.db["ch0.chain.test_time"].value == pytest.approx(
        chain["test_time_s"] + AWAY_S, abs=1.5
    )
    runner.command("resume")
    await b2.engine.run_for(10.0)
    assert b2.db["ch0.chain.step"].value == "charge"
    assert b2.db["ch0.chain.step_time"].value == pytest.approx(chain["step_time_s"] + 9, abs=1.5)


async def test_a_restored_test_shows_the_test_charge_it_had_and_goes_on_from_it(
    tmp_path: Path,
) -> None:
    """Issue 26: ``chN.chain.charge_ah`` after a restart is the held test's charge (from
    the recipe's initial_charge), not empty nor the channel's counter."""
    b1 = new_bench(tmp_path / "var")
    await started(b1, tmp_path, RECIPE.replace("steps:", "initial_charge: 1000 mAh\nsteps:"))
    await b1.engine.run_for(100.0)
    b1.runners["ch0"].command("hold")
    await b1.engine.run_for(5.0)
    held = b1.db["ch0.chain.charge_ah"].as_float()
    assert held == pytest.approx(1.0 + 0.3 * 100 / 3600, abs=2e-4)
    die(b1)

    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S)
    b2.retain()
    assert b2.runners["ch0"].state is State.HELD
    assert b2.db["ch0.chain.charge_ah"].as_float() == pytest.approx(held, abs=1e-6)
    b2.runners["ch0"].command("resume")
    await b2.engine.run_for(10.0)
    assert b2.db["ch0.chain.charge_ah"].as_float() == pytest.approx(held + 0.3 * 9 / 3600, abs=2e-4)


async def test_a_test_that_had_ended_comes_back_idle_with_its_files_closed(
    tmp_path: Path,
) -> None:
    b1 = new_bench(tmp_path / "var")
    folder = await started(
        b1, tmp_path, "recipe: short\nsteps:\n  - {id: c, charge: 100 mA, duration: 30 s}\n"
    )
    await b1.engine.run_for(60.0)
    assert b1.runners["ch0"].state is State.COMPLETE
    assert die(b1)["chain"]["state"] == "Complete"

    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S)
    assert b2.retain() == []
    assert b2.runners["ch0"].state is State.IDLE
    assert b2.runners["ch0"].program is None
    s = summary(folder)
    assert s["complete"] is True
    assert not any("restarted" in e["text"] for e in s["timeline"])


async def test_latched_alarms_come_back_and_must_be_acknowledged_before_resume(
    tmp_path: Path,
) -> None:
    b1 = new_bench(tmp_path / "var")
    await started(b1, tmp_path)
    await b1.engine.run_for(20.0)
    # A fault in the channel's own logic trips it (latched) and holds the test.
    b1.db.update(b1.db["ch0.logic_error"], "ZeroDivisionError: boom")
    await b1.engine.run_for(2.0)
    b1.db.update(b1.db["ch0.logic_error"], "")
    await b1.engine.run_for(2.0)
    assert b1.runners["ch0"].state is State.HELD
    assert b1.db["ch0.fault"].value == "internal error: ZeroDivisionError: boom"
    die(b1)

    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S)
    b2.retain()
    await b2.engine.run_for(2.0)
    assert b2.alarms is not None
    alarm = b2.alarms["ch0.internal"]
    assert alarm.tripped and alarm.first_out and not alarm.acked
    assert b2.db["ch0.fault"].value == "internal error: ZeroDivisionError: boom"
    runner = b2.runners["ch0"]
    assert runner.state is State.HELD
    with pytest.raises(Exception, match="channel fault must be acknowledged first"):
        runner.command("resume")
    b2.db.write("ch0.ack", True)
    await b2.engine.run_for(2.0)
    assert b2.db["ch0.fault"].value == ""
    runner.command("resume")
    await b2.engine.run_for(2.0)
    assert runner.state is State.RUNNING


async def test_a_chain_alarm_is_retained_with_the_test(tmp_path: Path) -> None:
    b1 = new_bench(tmp_path / "var")
    await started(
        b1,
        tmp_path,
        "recipe: slow\nsteps:\n"
        "  - {id: c, charge: 100 mA, duration: 600 s, supervision: {max_time: 30 s}}\n",
    )
    await b1.engine.run_for(40.0)
    assert b1.runners["ch0"].state is State.HELD
    die(b1)

    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S)
    b2.retain()
    runner = b2.runners["ch0"]
    assert "exceeded 30 s" in str(b2.db["ch0.chain.alarm"].value)
    with pytest.raises(Exception, match="acknowledge the alarm first"):
        runner.command("resume")
    runner.command("ack")
    runner.command("resume")
    await b2.engine.run_for(5.0)
    assert runner.state is State.RUNNING  # an acknowledged step-time error does not refire


async def test_a_recipe_that_no_longer_compiles_leaves_the_channel_idle_and_says_why(
    tmp_path: Path,
) -> None:
    b1 = new_bench(tmp_path / "var")
    folder = await started(b1, tmp_path)
    await b1.engine.run_for(100.0)
    die(b1)

    # The I/O map changed meanwhile: the channel now allows 0.2 A, the recipe asks 0.3 A.
    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S, current_limit_a=0.2)
    report = b2.retain()
    assert b2.runners["ch0"].state is State.IDLE
    assert len(report) == 1 and "ch0: test t1 not resumed after a restart" in report[0]
    assert "recipe cycle no longer compiles against ch0" in report[0]
    assert "allows [-0.2, 0.2] A" in report[0]
    assert b2.alarms is not None
    alarm = b2.alarms[RESTORE_ALARM]
    assert alarm.in_alarm and not alarm.acked and alarm.message == report[0]
    assert b2.db["retain.restore"].value == report[0]
    s = summary(folder)
    assert s["complete"] is True and s["state"] == "Aborted"
    assert s["end_reason"].startswith("aborted: not resumed after a restart: recipe cycle")
    assert "test not resumed" in s["timeline"][-1]["text"]
    assert bdf_rows(folder)  # what was recorded before is still there


async def test_the_recipe_is_recompiled_from_its_saved_text_even_if_the_file_changed(
    tmp_path: Path,
) -> None:
    b1 = new_bench(tmp_path / "var")
    await started(b1, tmp_path)
    await b1.engine.run_for(100.0)
    die(b1)
    (tmp_path / "recipe.yaml").write_text("this is: [not a recipe\n", encoding="utf-8")

    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S)
    b2.retain()
    runner = b2.runners["ch0"]
    assert runner.state is State.HELD
    assert runner.program is not None and [s.id for s in runner.program.steps] == [
        "charge",
        "rest",
        "discharge",
    ]


@pytest.mark.parametrize(
    "content",
    [b"this is not a database, just bytes\n" * 100, b""],
    ids=["garbage", "empty"],
)
async def test_an_unreadable_state_file_is_moved_aside_and_every_channel_starts_idle(
    tmp_path: Path, content: bytes
) -> None:
    state = tmp_path / "var" / STATE_NAME
    state.parent.mkdir(parents=True)
    state.write_bytes(content)
    b = new_bench(tmp_path / "var")
    report = b.retain()
    assert b.runners["ch0"].state is State.IDLE
    assert len(report) == 1 and "unreadable" in report[0]
    assert "every channel starts Idle" in report[0]
    moved = sorted(p.name for p in state.parent.glob(f"{STATE_NAME}.corrupt-*"))
    assert len(moved) == 1 and moved[0] in report[0]
    assert (state.parent / moved[0]).read_bytes() == content
    assert b.alarms is not None and b.alarms[RESTORE_ALARM].in_alarm
    await b.engine.run_for(3.0)  # and the bench saves a fresh state file
    assert b.retention is not None and b.retention.store.flush()
    assert "channel:ch0" in RetainStore(state).read()


async def test_a_state_file_of_an_older_format_is_moved_aside(tmp_path: Path) -> None:
    state = tmp_path / "var" / STATE_NAME
    state.parent.mkdir(parents=True)
    with sqlite3.connect(state) as conn:
        conn.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        conn.execute("INSERT INTO meta VALUES ('format', '0')")
    conn.close()
    b = new_bench(tmp_path / "var")
    report = b.retain()
    assert "format 0, this supervisor reads format 1" in report[0]
    assert list(state.parent.glob(f"{STATE_NAME}.corrupt-*"))


async def test_a_failing_disk_raises_an_alarm_retries_and_never_stops_the_scan(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    b = new_bench(tmp_path / "var")
    await started(b, tmp_path)
    assert b.retention is not None and b.alarms is not None
    store = b.retention.store
    store.retry_s = 0.01
    assert store.flush()
    real_write = RetainStore._write

    def disk_full(self: RetainStore, conn: sqlite3.Connection, batch: Any) -> None:
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(RetainStore, "_write", disk_full)
    await b.engine.run_for(5.0)
    assert not store.flush(timeout_s=1.0)
    await b.engine.run_for(1.0)  # the scan raises the alarm from the writer's report
    alarm = b.alarms[WRITE_ALARM]
    assert alarm.active and alarm.severity.name == "HIGH"
    assert "database or disk is full" in alarm.message
    assert "database or disk is full" in str(b.db["retain.error"].value)
    assert b.runners["ch0"].state is State.RUNNING  # the test goes on
    step_time = b.db["ch0.chain.step_time"].as_float()

    monkeypatch.setattr(RetainStore, "_write", real_write)
    await b.engine.run_for(2.0)
    assert store.flush()
    await b.engine.run_for(1.0)
    assert not alarm.active and b.db["retain.error"].value == ""
    saved = store.read()["channel:ch0"]["chain"]
    assert saved["step_time_s"] >= step_time  # what was written is the latest


async def test_every_step_change_is_saved_at_once(tmp_path: Path) -> None:
    b = new_bench(tmp_path / "var")
    b_cfg_period = b.cfg.retain.period_s
    assert b_cfg_period == 1.0
    await started(b, tmp_path)
    assert b.retention is not None
    b.retention.period_s = 1e9  # only the changes are saved now
    await b.engine.run_for(601.0)
    assert b.db["ch0.chain.step"].value == "rest"
    assert b.retention.store.flush()
    chain = b.retention.store.read()["channel:ch0"]["chain"]
    assert chain["step_id"] == "rest"


async def test_the_periodic_saves_of_the_channels_are_spread_over_the_period(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 13's load case: 16 channel documents built in the same scan every second cost
    that scan over a millisecond. Each channel is still saved every period, each in a scan
    of its own."""
    data = bench_data(tmp_path / "var")
    data["scan"]["period_s"] = 0.1
    data["devices"]["chadeche"]["poll_period_s"] = 0.1
    data["devices"]["chadeche"]["boards"] = [
        {"address": a, "sim": {"model": "nimh-aa", "capacity_ah": 2.0}} for a in range(4)
    ]
    ch0 = data["channels"][0]
    data["channels"] = [
        {**ch0, "name": f"ch{a}", "source": {"device": "chadeche", "board": a}} for a in range(4)
    ]
    b = build_bench(bench_from_data(data), VirtualClock(wall_epoch_s=EPOCH))
    _OPEN.append(b)
    b.retain()
    assert b.retention is not None
    store = b.retention.store
    saves: list[tuple[float, str]] = []
    real_put = store.put

    def put(key: str, document: Any) -> None:
        if key.startswith("channel:"):
            saves.append((round(b.clock.now(), 6), key))
        real_put(key, document)

    monkeypatch.setattr(store, "put", put)
    await b.engine.run_for(0.1)  # the first scan saves everything (nothing saved yet)
    assert {key for _, key in saves} == {f"channel:ch{a}" for a in range(4)}
    saves.clear()
    await b.engine.run_for(5.0)  # idle channels: only the periodic saves
    per_scan: dict[float, int] = {}
    for t, _ in saves:
        per_scan[t] = per_scan.get(t, 0) + 1
    assert max(per_scan.values()) == 1
    for a in range(4):
        times = [t for t, key in saves if key == f"channel:ch{a}"]
        gaps = [t1 - t0 for t0, t1 in itertools.pairwise(times)]
        assert len(times) >= 4 and max(gaps) <= 1.0 + 1e-6, (a, times)


@pytest.mark.parametrize("command", ["stop", "abort"])
async def test_a_restored_test_then_ended_closes_its_files_and_the_next_start_is_a_new_test(
    tmp_path: Path, command: str
) -> None:
    b1 = new_bench(tmp_path / "var")
    folder = await started(b1, tmp_path)
    await b1.engine.run_for(100.0)
    die(b1)

    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S)
    b2.retain()
    runner = b2.runners["ch0"]
    assert runner.state is State.HELD
    runner.command(command, actor="dora")
    await b2.engine.run_for(5.0)
    s = summary(folder)
    verb = "stopped" if command == "stop" else "aborted"
    assert (s["complete"], s["end_reason"]) == (True, f"{verb}: {command} by dora")
    assert [e for e in s["timeline"] if "supervisor restarted" in e["text"]]

    # Reset and start again: a new test in a folder of its own, the restored one untouched.
    before = (folder / "t1.bdf.csv").read_bytes()
    runner.command("reset", actor="dora")
    runner.command("start", actor="dora")
    await b2.engine.run_for(30.0)
    assert runner.test_id != "t1"
    new_folder = folder.parent / runner.test_id
    assert (new_folder / f"{runner.test_id}.bdf.csv").exists()
    assert (folder / "t1.bdf.csv").read_bytes() == before
    assert b2.recipes["ch0"].folder == str(new_folder.resolve())  # what a restart resumes


async def test_a_running_channel_is_saved_one_scan_before_its_period_is_over(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A SIGKILL loses at most one ``retain.period_s`` of the counters (docs/operator.md "Retained
    state"): the store's worker commits a save after the scan that put it, so the periodic
    saves are put at most one period less one scan apart; a save put a whole period after
    the last one would be on disk a period plus its write after it."""
    data = bench_data(tmp_path / "var")
    data["scan"]["period_s"] = 0.1
    data["devices"]["chadeche"]["poll_period_s"] = 0.1
    b = build_bench(bench_from_data(data), VirtualClock(wall_epoch_s=EPOCH))
    _OPEN.append(b)
    await started(b, tmp_path)  # logging every 10 s: nearly every save is a periodic one
    assert b.retention is not None
    store = b.retention.store
    saves: list[float] = []
    real_put = store.put

    def put(key: str, document: Any) -> None:
        if key == "channel:ch0":
            saves.append(b.clock.now())
        real_put(key, document)

    monkeypatch.setattr(store, "put", put)
    await b.engine.run_for(30.0)
    assert b.db["ch0.chain.state"].value == "Running"
    gaps = [t1 - t0 for t0, t1 in itertools.pairwise(saves)]
    assert len(saves) >= 30
    assert max(gaps) <= b.cfg.retain.period_s - b.cfg.scan.period_s + 1e-6, gaps


# --- issue 26, finding 5: a corrupt saved test is refused, never taken for an ended one -----
def corrupt(state_dir: Path, edit: Any) -> None:
    """Edit ch0's saved document in place, as a person (or a bad disk) would."""
    with sqlite3.connect(state_dir / STATE_NAME) as conn:
        (text,) = conn.execute("SELECT document FROM retained WHERE key = 'channel:ch0'").fetchone()
        doc = json.loads(text)
        edit(doc)
        conn.execute(
            "UPDATE retained SET document = ? WHERE key = 'channel:ch0'", (json.dumps(doc),)
        )
    conn.close()


async def a_saved_test_corrupted(tmp_path: Path, edit: Any) -> tuple[Bench, Path, list[str]]:
    """A test under way on ch0, the supervisor killed, its saved document edited, a new
    supervisor started on it: that bench, the test's folder and the restore's report."""
    b1 = new_bench(tmp_path / "var")
    folder = await started(b1, tmp_path)
    await b1.engine.run_for(30.0)
    die(b1)
    corrupt(tmp_path / "var", edit)
    b2 = new_bench(tmp_path / "var", wall_of(b1) + AWAY_S)
    return b2, folder, b2.retain()


def assert_refused_and_said(
    b: Bench, folder: Path, report: list[str], says: list[str], caplog: pytest.LogCaptureFixture
) -> None:
    """Not resumed and not ended: Idle, the test's record left as it was (not completed),
    the alarm raised, a log line and the report saying what was wrong, a copy of the file
    as it was kept beside it."""
    runner = b.runners["ch0"]
    assert runner.state is State.IDLE and runner.program is None
    s = summary(folder)
    assert s["complete"] is False and s["state"] not in ("Complete", "Stopped", "Aborted"), s
    assert len(report) == 1, report
    for text in ["ch0: retained state unreadable", "starts Idle", *says]:
        assert text in report[0], report[0]
    assert b.alarms is not None
    alarm = b.alarms[RESTORE_ALARM]
    assert alarm.in_alarm and not alarm.acked and alarm.message == report[0]
    assert b.db["retain.restore"].value == report[0]
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert report[0] in errors
    assert b.retention is not None
    state_dir = b.retention.store.path.parent
    copies = sorted(state_dir.glob(f"{STATE_NAME}.corrupt-*"))
    assert len(copies) == 1 and f"the state file as it was is kept as {copies[0]}" in report[0]
    assert "channel:ch0" in RetainStore(copies[0]).read()


@pytest.mark.parametrize("name", sorted(BAD_VALUES))
async def test_a_wrong_value_in_any_field_of_the_saved_test_is_refused_with_the_alarm(
    tmp_path: Path, name: str, caplog: pytest.LogCaptureFixture
) -> None:
    bad = BAD_VALUES[name][0]  # "Xunning" for the state: the finding itself

    def edit(doc: dict[str, Any]) -> None:
        doc["chain"][name] = bad

    caplog.set_level(logging.ERROR)
    b, folder, report = await a_saved_test_corrupted(tmp_path, edit)
    assert_refused_and_said(b, folder, report, [f"field {name}", shown(bad)], caplog)
    # Nothing of it was restored, and the channel saves its true state from now on.
    await b.engine.run_for(3.0)
    assert b.retention is not None and b.retention.store.flush()
    assert RetainStore(tmp_path / "var" / STATE_NAME).read()["channel:ch0"]["chain"] is None


@pytest.mark.parametrize(
    ("edit", "says"),
    [
        (lambda d: d.update(mode="sideways"), "field mode: 'sideways' is not one of manual, auto"),
        (lambda d: d["tags"].update({"ch0.charged_ah": "lots"}), "tags.ch0.charged_ah: 'lots'"),
        (lambda d: d["recipe"].update(text=None), "recipe field text: null is not a text"),
        (lambda d: d["recipe"].update(parameters=[]), "recipe field parameters: an empty list"),
        (lambda d: d.update(speed=3), "unknown field 'speed'"),
        (lambda d: d.update(chain=[]), "chain snapshot is a mapping"),
    ],
    ids=["mode", "counter", "recipe-text", "recipe-parameters", "unknown", "chain-shape"],
)
async def test_a_wrong_value_anywhere_in_the_channels_document_is_refused_with_the_alarm(
    tmp_path: Path, edit: Any, says: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.ERROR)
    b, folder, report = await a_saved_test_corrupted(tmp_path, edit)
    assert_refused_and_said(b, folder, report, [says], caplog)
    assert b.db["ch0.mode"].value == "manual"  # nothing of the document was applied
    assert b.db["ch0.charged_ah"].value == 0.0


async def test_a_saved_sleep_or_group_beyond_the_recipe_is_not_resumed_and_says_why(
    tmp_path: Path,
) -> None:
    b, folder, report = await a_saved_test_corrupted(
        tmp_path, lambda d: d["chain"].update(group_time_s={"3": 10.0})
    )
    assert b.runners["ch0"].state is State.IDLE
    assert "the saved group times name group 4, beyond the 0 groups of recipe cycle" in report[0]
    s = summary(folder)
    assert s["state"] == "Aborted" and "not resumed after a restart" in s["end_reason"]
