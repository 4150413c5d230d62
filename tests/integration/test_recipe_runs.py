"""Recipes executed by the step-chain engine on a simulated Chadèche channel."""

from __future__ import annotations

import asyncio
import csv
import json
import logging
import re
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from supervisor.app import Bench, build_bench
from supervisor.app.dryrun import DryRunResult, dry_run, dry_run_config
from supervisor.chains.states import OPCUA_CODE, TABLE, State
from supervisor.core.clock import RealClock, VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.importers import import_chadeche
from supervisor.publish.display import display_line

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration


_OPEN: list[Bench] = []


@pytest.fixture(autouse=True)
async def _shutdown_benches() -> AsyncIterator[None]:
    yield
    while _OPEN:
        await _OPEN.pop().shutdown()  # closes result files of tests that did not finish


def bench_with(tmp_path: Path, text: str, soc: float = 0.5, period_s: float = 1.0) -> Bench:
    path = tmp_path / "r.yaml"
    path.write_text(text, encoding="utf-8")
    bench = build_bench(dry_run_config("nimh-aa", 2.0, soc, period_s), VirtualClock())
    bench.load_recipe("ch0", path, results_dir=tmp_path / "results", test_id="t1")
    _OPEN.append(bench)
    return bench


async def start(bench: Bench) -> None:
    await bench.engine.run_for(3.0)
    bench.runners["ch0"].command("start")


def steps_started(bench: Bench) -> list[str]:
    return [e.step_id for e in bench.runners["ch0"].events if e.text.startswith("starting step")]


def assert_case_study_path(res: DryRunResult, ids_of: dict[str, str]) -> None:
    """Seed 000 §IV: rest, discharge until v_min or q_min, the rest → pulse → jump loop
    until v_max or q_max, top-off, maintenance, sleep until 20:00, end of cycle."""
    seq = [(ids_of.get(s, s), cause) for s, cause in res.step_sequence]
    ids = [s for s, _ in seq]
    assert ids[:4] == ["rest1", "discharge", "rest2", "pulse"]
    assert seq[0][1] == "start"
    assert seq[1][1] == "duration elapsed"  # the 60 s rest
    assert seq[2][1] in ("until #1: voltage <= v_min", "until #2: charge <= q_min")
    loop = [i for i, s in enumerate(ids) if s == "loop"]
    assert len(loop) >= 2
    for i in loop:
        assert ids[i + 1] == "rest2" and seq[i + 1][1].startswith("goto ")
    top = ids.index("topoff")
    assert ids[top - 1] == "pulse"
    assert seq[top][1] in ("until #1: voltage >= v_max", "until #2: charge >= q_max")
    assert ids[top:] == ["topoff", "maintain", "wake", "end"]
    assert seq[top + 1][1] == "duration elapsed" and seq[top + 2][1] == "duration elapsed"
    assert seq[-1][1] == "woke up"
    assert res.state is State.COMPLETE
    wake = next(e for e in res.summary["timeline"] if e["text"].startswith("starting step 9"))
    started = time.mktime((2026, 1, 1, 8, 0, 3, 0, 0, -1))
    assert time.localtime(started + wake["test_time_s"])[3:5] == (20, 0)  # sleep until 20:00


async def test_the_case_study_recipe_dry_runs_through_the_documented_path() -> None:
    res = await dry_run(ROOT / "recipes" / "nimh-ds2710.yaml")
    assert_case_study_path(res, {})


async def test_the_imported_case_study_dry_runs_through_the_documented_path(
    tmp_path: Path,
) -> None:
    imported = import_chadeche(
        ROOT / "tests" / "data" / "chadeche" / "figure10-cp1252-crlf.txt", overrides={"i": 1300}
    )
    path = tmp_path / "figure10.yaml"
    path.write_text(imported.yaml_text, encoding="utf-8")
    res = await dry_run(path)
    names = ["rest1", "discharge", "rest2", "pulse", "loop", "topoff", "maintain", "wake", "end"]
    assert_case_study_path(res, {f"s{k + 1}": n for k, n in enumerate(names)})


async def test_a_25_hour_recipe_dry_runs_to_completion() -> None:
    res = await dry_run(ROOT / "recipes" / "nimh-25h-slow-cycle.yaml", soc=0.0)
    assert res.state is State.COMPLETE
    assert res.simulated_s > 20 * 3600
    assert [s for s, _ in res.step_sequence] == ["charge", "rest1", "discharge", "rest2"]


async def test_hold_freezes_the_step_timer_and_resume_continues_where_it_was(
    tmp_path: Path,
) -> None:
    b = bench_with(
        tmp_path,
        "recipe: r\nsteps:\n  - {id: a, charge: 100 mA, duration: 100 s}\n"
        "  - {id: b, rest: 10 s}\n",
    )
    await start(b)
    await b.engine.run_for(40.0)
    r = b.runners["ch0"]
    r.command("hold")
    await b.engine.run_for(500.0)
    assert r.state is State.HELD
    assert b.channels["ch0"].current_cmd.value == 0.0
    r.command("resume")
    await b.engine.run_for(50.0)
    assert b.db["ch0.chain.step"].value == "a"  # 40 s + 50 s < 100 s despite 500 s held
    await b.engine.run_for(20.0)
    assert b.db["ch0.chain.step"].value == "b"


async def test_commands_follow_the_state_table_and_others_are_refused(tmp_path: Path) -> None:
    b = bench_with(tmp_path, "recipe: r\nsteps:\n  - {id: a, rest: 100 s}\n")
    r = b.runners["ch0"]
    with pytest.raises(OperatorError, match="resume is not allowed while Idle"):
        r.command("resume")
    await start(b)
    assert b.db["ch0.chain.state_code"].value == OPCUA_CODE[State.RUNNING]
    r.command("stop")
    await b.engine.run_for(2.0)
    assert r.state is State.STOPPED
    r.command("reset")
    await b.engine.run_for(1.0)
    assert r.state is State.IDLE
    assert set(TABLE[State.HELD]) == {"resume", "stop", "abort"}


async def test_an_operator_command_written_to_the_command_tag_is_executed(tmp_path: Path) -> None:
    b = bench_with(tmp_path, "recipe: r\nsteps:\n  - {id: a, rest: 100 s}\n")
    await start(b)
    b.db.write("ch0.command", "abort")
    await b.engine.run_for(2.0)
    assert b.runners["ch0"].state is State.ABORTED
    assert b.db["ch0.command"].value == ""


async def test_operator_advance_moves_on_only_where_the_step_allows_it(tmp_path: Path) -> None:
    b = bench_with(
        tmp_path,
        "recipe: r\nsteps:\n  - {id: a, rest: 1 h, advance: false}\n"
        "  - {id: b, rest: 1 h}\n  - {id: c, rest: 1 h}\n",
    )
    await start(b)
    r = b.runners["ch0"]
    r.command("advance")
    await b.engine.run_for(2.0)
    assert b.db["ch0.chain.step"].value == "a"
    assert any("advance refused" in e.text for e in r.events)
    await b.engine.run_for(3600.0)
    r.command("advance")
    await b.engine.run_for(2.0)
    assert b.db["ch0.chain.step"].value == "c"
    assert any(e.text.endswith("(operator advance)") for e in r.events)


async def test_supervision_max_time_halts_the_chain_until_acknowledged(tmp_path: Path) -> None:
    b = bench_with(
        tmp_path,
        "recipe: r\nsteps:\n  - id: a\n    charge: 100 mA\n    until: [{voltage >= 5 V: next}]\n"
        "    supervision: {max_time: 60 s}\n",
    )
    await start(b)
    await b.engine.run_for(70.0)
    r = b.runners["ch0"]
    assert r.state is State.HELD
    assert "exceeded 60 s" in str(b.db["ch0.chain.alarm"].value)
    assert b.channels["ch0"].current_cmd.value == 0.0
    with pytest.raises(OperatorError, match="acknowledge the alarm first"):
        r.command("resume")
    r.command("ack")
    r.command("resume")
    await b.engine.run_for(2.0)
    assert r.state is State.RUNNING


async def test_a_false_interlock_makes_outputs_safe_while_the_step_stays_active(
    tmp_path: Path,
) -> None:
    b = bench_with(
        tmp_path,
        "recipe: r\nparameters: {t_max: 30 degC}\nsteps:\n"
        "  - {id: a, charge: 100 mA, duration: 1 h, interlock: step_time < 100 s or "
        "step_time > 200 s}\n",
    )
    await start(b)
    await b.engine.run_for(50.0)
    assert b.channels["ch0"].current_cmd.value == pytest.approx(0.1)
    await b.engine.run_for(100.0)
    assert b.channels["ch0"].current_cmd.value == 0.0
    assert b.db["ch0.chain.interlock"].value
    assert b.db["ch0.chain.step"].value == "a"
    await b.engine.run_for(100.0)
    assert b.channels["ch0"].current_cmd.value == pytest.approx(0.1)


async def test_a_recipe_limit_crossed_holds_the_chain_with_a_latched_alarm(tmp_path: Path) -> None:
    b = bench_with(
        tmp_path,
        "recipe: r\nlimits: {voltage: [0.9 V, 1.3 V]}\nsteps:\n"
        "  - {id: a, charge: 400 mA, duration: 5 h}\n",
        soc=0.6,
    )
    await start(b)
    await b.engine.run_for(3600.0)
    assert b.runners["ch0"].state is State.HELD
    assert "above 1.3 V" in str(b.db["ch0.chain.alarm"].value)


async def test_pulses_alternate_current_and_rest_then_move_on(tmp_path: Path) -> None:
    b = bench_with(
        tmp_path,
        "recipe: r\nsteps:\n"
        "  - {id: p, pulse: {current: 200 mA, on_time: 10 s, off_time: 20 s, count: 3}}\n"
        "  - {id: after, rest: 1 h}\n",
    )
    await start(b)
    seen = []
    for _ in range(95):
        await b.engine.run_for(1.0)
        seen.append(b.channels["ch0"].current_cmd.as_float())
    assert max(seen) == pytest.approx(0.2) and min(seen) == 0.0
    assert b.db["ch0.chain.step"].value == "after"
    # DC internal resistance from each pulse: the NiMH model's R is tens of milliohms.
    r = b.db["ch0.chain.internal_resistance"].as_float()
    assert 0.01 < r < 0.5
    assert sum("DC internal resistance" in e.text for e in b.runners["ch0"].events) == 3


async def test_a_group_time_limit_ends_a_loop_of_several_steps(tmp_path: Path) -> None:
    b = bench_with(
        tmp_path,
        "recipe: r\ngroups: [{id: g, steps: [a, b, back], duration: 300 s}]\nsteps:\n"
        "  - {id: a, charge: 100 mA, duration: 60 s}\n  - {id: b, rest: 30 s}\n"
        "  - {id: back, goto: a}\n  - {id: out, rest: 1 h}\n",
    )
    await start(b)
    await b.engine.run_for(400.0)
    assert b.db["ch0.chain.step"].value == "out"
    assert any("group g duration elapsed" in e.text for e in b.runners["ch0"].events)


async def test_result_files_hold_bdf_columns_chadeche_lines_and_a_summary(tmp_path: Path) -> None:
    b = bench_with(
        tmp_path,
        "recipe: r\ncycles: 2\nlogging: {period: 10 s}\nsteps:\n"
        "  - {id: c, charge: 300 mA, duration: 60 s}\n"
        "  - {id: d, discharge: 200 mA, duration: 60 s}\n",
    )
    await start(b)
    await b.engine.run_for(300.0)
    assert b.runners["ch0"].state is State.COMPLETE
    folder = tmp_path / "results" / "t1"
    rows = list(csv.DictReader((folder / "t1.bdf.csv").read_text(encoding="utf-8").splitlines()))
    assert {"Test Time / s", "Voltage / V", "Current / A", "Cycle Count / 1"} <= set(rows[0])
    assert [r["Step ID"] for r in rows if r["Step Time / s"] == "0.000"] == ["c", "d", "c", "d"]
    step_counts = [int(r["Step Count / 1"]) for r in rows]
    assert step_counts == sorted(step_counts) and step_counts[-1] == 4
    charging = [float(r["Current / A"]) for r in rows if r["Step ID"] == "c" and r["Current / A"]]
    assert max(charging) == pytest.approx(0.3, abs=1e-3)  # + charges the cell (BDF)
    summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    assert summary["state"] == "Complete"
    cyc = summary["cycles"]
    assert [c["cycle"] for c in cyc] == [1, 2]
    assert cyc[0]["charge_capacity_ah"] == pytest.approx(0.3 * 60 / 3600, rel=0.05)
    assert cyc[0]["coulombic_efficiency"] == pytest.approx(0.2 / 0.3, rel=0.05)
    lines = (folder / "t1.chadeche.csv").read_text(encoding="utf-8").splitlines()
    first = lines[0].split(";")
    assert first[:5] == ["C", "01", "01", "0", "300"]
    assert len(first) == 12


async def test_a_short_recipe_in_real_time_follows_the_dry_runs_step_sequence(
    tmp_path: Path,
) -> None:
    text = (
        "recipe: short\ncycles: 2\nlogging: {period: 1 s}\nsteps:\n"
        "  - {id: rest, rest: 1 s}\n  - {id: charge, charge: 300 mA, duration: 2 s}\n"
        "  - {id: discharge, discharge: 200 mA, duration: 1 s}\n"
    )
    path = tmp_path / "short.yaml"
    path.write_text(text, encoding="utf-8")
    dry = await dry_run(path, period_s=0.1, results_dir=tmp_path / "dry")
    live = build_bench(dry_run_config("nimh-aa", 2.0, 0.5, 0.1), RealClock())
    live.load_recipe("ch0", path, results_dir=tmp_path / "live", test_id="live")
    stop = asyncio.Event()
    task = asyncio.create_task(live.run(stop))
    try:
        await asyncio.sleep(0.3)
        live.runners["ch0"].command("start")
        deadline = time.monotonic() + 60  # generous bound, not a timing claim
        while live.runners["ch0"].state is not State.COMPLETE:
            assert time.monotonic() < deadline, "the live run did not complete"
            await asyncio.sleep(0.1)
    finally:
        stop.set()
        await task
        await live.shutdown()

    def sequence(csv_path: Path) -> list[tuple[str, str]]:
        rows = csv.DictReader(csv_path.read_text(encoding="utf-8").splitlines())
        out: list[tuple[str, str]] = []
        for r in rows:
            key = (r["Cycle Count / 1"], r["Step ID"])
            if not out or out[-1] != key:
                out.append(key)
        return out

    dry_csv = next((tmp_path / "dry").rglob("*.bdf.csv"))
    live_csv = tmp_path / "live" / "live" / "live.bdf.csv"
    assert sequence(live_csv) == sequence(dry_csv)
    assert [s for _, s in sequence(live_csv)] == ["rest", "charge", "discharge"] * 2
    assert dry.state is State.COMPLETE


async def test_a_capacity_test_publishes_progress_and_eta_against_the_rated_capacity(
    tmp_path: Path,
) -> None:
    text = (ROOT / "recipes" / "capacity-test.yaml").read_text(encoding="utf-8")
    b = bench_with(tmp_path, text, soc=0.95)
    await start(b)
    await b.engine.run_for(600.0 + 3600.0)  # settle, then one hour at 400 mA
    assert b.db["ch0.chain.step"].value == "discharge"
    assert b.db["ch0.chain.progress"].as_float() == pytest.approx(0.4 / 2.0, abs=0.01)
    assert b.db["ch0.chain.eta_s"].as_float() == pytest.approx(4 * 3600, rel=0.02)


async def test_a_profile_from_csv_follows_its_rows_and_holds_on_a_row_limit(
    tmp_path: Path,
) -> None:
    (tmp_path / "profile.csv").write_text(
        "Temps (s);Courant (A);Tension Min/Max;Courant Min/Max;Température Min/Max\n"
        "0;0,1;0.5/2.0;-1/1;0/60\n"
        "60;-0,1;0.5/2.0;-1/1;0/60\n"
        "120;0,2;0.5/1.0;-1/1;0/60\n"
        "180;0;0.5/2.0;-1/1;0/60\n",
        encoding="cp1252",
    )
    b = bench_with(
        tmp_path,
        "recipe: r\nsteps:\n  - {id: p, profile: {file: profile.csv}}\n  - {id: z, rest: 1 h}\n",
    )
    await start(b)
    await b.engine.run_for(30.0)
    assert b.channels["ch0"].current_cmd.value == pytest.approx(0.1)
    await b.engine.run_for(60.0)
    assert b.channels["ch0"].current_cmd.value == pytest.approx(-0.1)
    await b.engine.run_for(60.0)  # row 3 allows at most 1.0 V: a NiMH cell is above that
    assert b.runners["ch0"].state is State.HELD
    assert "above 1 V" in str(b.db["ch0.chain.alarm"].value)


async def test_the_status_line_follows_the_chadeche_display_format(tmp_path: Path) -> None:
    b = bench_with(tmp_path, "recipe: r\nsteps:\n  - {id: a, charge: 50 mA, duration: 180 s}\n")
    await start(b)
    await b.engine.run_for(129.0)
    snapshot = b.runners["ch0"].sample(b.clock.now())
    assert snapshot is not None
    line = display_line(snapshot, b.displays["ch0"].dba)
    assert re.match(
        r"^C/01/01 dba=0 mA= 50 CET= 129 SET= 129 TET= 129 STA= 51 V=\d\.\d{3}"
        r" mAh=\d+\.\d, \w{3} \w{3} \d{2} \d{2}:\d{2}:\d{2} \d{4}$",
        line,
    ), line


async def test_the_status_line_is_logged_every_display_period_while_a_test_runs(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    b = bench_with(tmp_path, "recipe: r\nsteps:\n  - {id: a, charge: 50 mA, duration: 180 s}\n")
    b.displays["ch0"].period_s = 60.0
    with caplog.at_level(logging.INFO, logger="supervisor.publish.display"):
        await start(b)
        await b.engine.run_for(200.0)
    lines = [m for m in caplog.messages if m.startswith("ch0: C/01/01 dba=0")]
    assert [re.findall(r" SET= (\d+) ", m) for m in lines] == [["0"], ["60"], ["120"]]
    assert b.runners["ch0"].state is State.COMPLETE
