"""Publishers of a chain's events and records: result files and the Chadèche display line.

They take ``ChainEvent`` / ``Record`` values only, so they are tested with made-up ones.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import pytest

from supervisor.chains.compiler import compile_recipe
from supervisor.config.recipe import load_recipe_text
from supervisor.core.records import ChainEvent, Record
from supervisor.publish.display import ChadecheDisplay, display_line
from supervisor.publish.results import BDF_COLUMNS, CycleSummary, ResultCollector, chadeche_line

WALL = time.mktime((2017, 5, 22, 3, 21, 43, 0, 0, -1))  # seed 000's example date

REC = Record(
    t=17523.0,
    wall=WALL,
    test_time_s=17520.0,
    step_time_s=159.0,
    cycle_time_s=17520.0,
    cycle=1,
    step_count=7,
    step_index=6,
    step_id="maintain",
    step_type="CC_CHG",
    voltage_v=1.373,
    current_a=0.05,
    power_w=0.06865,
    temperature_c=None,
    charge_ah=1.3024,
    charged_ah=1.5,
    discharged_ah=0.2,
    charged_wh=2.0,
    discharged_wh=0.25,
    cycle_charged_ah=1.5,
    cycle_discharged_ah=0.2,
    cycle_charged_wh=2.0,
    cycle_discharged_wh=0.25,
    setpoint_a=0.05,
    step_remaining_s=21.0,
    reason="period",
    current_cmd_a=0.05,
    last_voltage_v=1.373,
)


def test_the_display_line_follows_the_chadeche_format() -> None:
    # Seed 000 §III.E.1: C/cycle/step dba mA CET SET TET STA V mAh, date.
    assert display_line(REC, dba=0) == (
        "C/01/07 dba=0 mA= 50 CET= 17520 SET= 159 TET= 17520 STA= 21 V=1.373 mAh=1302.4,"
        " Mon May 22 03:21:43 2017"
    )


def test_the_display_shows_what_the_channel_commands_and_the_last_voltage() -> None:
    rec = replace(REC, current_cmd_a=-0.2, setpoint_a=0.05, voltage_v=None, last_voltage_v=1.2)
    line = display_line(rec, dba=3)
    assert line.startswith("D/01/07 dba=3 mA=200 ")
    assert " V=1.200 " in line


def test_a_step_without_a_duration_shows_no_time_left() -> None:
    assert " STA= 0 " in display_line(replace(REC, step_remaining_s=None), dba=0)
    assert " STA= 0 " in display_line(replace(REC, step_remaining_s=-5.0), dba=0)


def test_the_display_asks_for_a_sample_every_period_and_logs_its_line(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d = ChadecheDisplay("ch0", dba=0, period_s=60.0)
    assert d.due(0.0)  # the first one at once
    with caplog.at_level(logging.INFO, logger="supervisor.publish.display"):
        d.on_sample(replace(REC, t=0.0))
    assert not d.due(59.0)
    assert d.due(60.0)
    assert d.last_line == display_line(REC, 0)
    assert caplog.messages == [f"ch0: {d.last_line}"]


def test_an_infinite_period_asks_for_the_first_sample_only() -> None:
    d = ChadecheDisplay("ch0", period_s=float("inf"))
    assert d.due(0.0)
    d.on_sample(replace(REC, t=0.0))
    assert not d.due(1e9)


def test_the_chadeche_result_line_uses_the_chains_setpoint() -> None:
    assert chadeche_line(REC, dba=0) == (
        "C;01;07;0; 50; 17520; 159; 17520; 21;1.373;1302.4;Mon May 22 03:21:43 2017"
    )


@pytest.mark.parametrize(
    ("step_type", "setpoint_a", "letter"),
    [
        ("CC_DCH", 0.0, "D"),  # issue 26, 6b: a discharge row at 0 mA is a D row
        ("CC_DCH", -0.0, "D"),
        ("CC_DCH", -0.2, "D"),
        ("CC_CHG", 0.0, "C"),
        ("CCCV_CHG", 0.05, "C"),
        ("REST", 0.0, "C"),
        ("PROFILE", -0.1, "D"),  # no direction of its own: the setpoint's sign
        ("PROFILE", 0.1, "C"),
    ],
)
def test_the_chadeche_line_letter_is_the_steps_direction_even_at_0_ma(
    step_type: str, setpoint_a: float, letter: str
) -> None:
    line = chadeche_line(replace(REC, step_type=step_type, setpoint_a=setpoint_a), dba=0)
    assert line.startswith(f"{letter};01;07;0;")


def test_a_charge_or_discharge_step_at_0_ma_keeps_its_bdf_step_type() -> None:
    text = (
        "recipe: r\nsteps:\n  - {id: c, charge: 0 mA, duration: 1 min}\n"
        "  - {id: d, discharge: 0 mA, duration: 1 min}\n"
    )
    recipe, pos = load_recipe_text(text, "r.yaml")
    program = compile_recipe(recipe, pos, "r.yaml")
    assert [s.step_type for s in program.steps] == ["CC_CHG", "CC_DCH"]


def test_result_files_are_written_from_events_and_records(tmp_path: Path) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path / "t1", dba=0)
    c.on_event(ChainEvent(3.0, WALL, "ch0", "state", "Idle → Running (start by operator)"))
    c.on_event(ChainEvent(3.0, WALL, "ch0", "message", "not in the timeline"))
    c.on_record(REC)
    c.on_event(ChainEvent(63.0, WALL, "ch0", "step", "starting step 2 b", 1, "b", 1))
    summary = c.close("duration elapsed", "Complete")
    bdf = (tmp_path / "t1" / "t1.bdf.csv").read_text(encoding="utf-8")
    rows = list(csv.reader(bdf.splitlines()))
    assert tuple(rows[0]) == BDF_COLUMNS
    row = dict(zip(BDF_COLUMNS, rows[1], strict=True))
    assert row["Step ID"] == "maintain" and row["Record Index / 1"] == "1"
    assert row["Net Capacity / Ah"] == "1.3"  # charged − discharged (BDF)
    assert row["Temperature T1 / degC"] == ""  # no reading: empty, never a stale value
    lines = (tmp_path / "t1" / "t1.chadeche.csv").read_text(encoding="utf-8").splitlines()
    assert lines == [chadeche_line(REC, 0)]
    on_disk = json.loads((tmp_path / "t1" / "summary.json").read_text(encoding="utf-8"))
    assert on_disk == summary
    assert [e["test_time_s"] for e in summary["timeline"]] == [0.0, 60.0]
    assert summary["cycles"][0]["coulombic_efficiency"] == pytest.approx(0.2 / 1.5, rel=1e-5)
    assert (summary["end_reason"], summary["state"]) == ("duration elapsed", "Complete")


# --- truthful summaries (users' finding 8) --------------------------------------------------
def cycle_rec(t: float, cycle: int, charged: float, discharged: float) -> Record:
    return replace(
        REC,
        t=t,
        test_time_s=t - 3.0,
        cycle=cycle,
        cycle_charged_ah=charged,
        cycle_discharged_ah=discharged,
        cycle_charged_wh=charged * 1.3,
        cycle_discharged_wh=discharged * 1.2,
    )


def test_nothing_is_written_before_the_test_starts(tmp_path: Path) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path / "t1")
    c.close("supervisor stopped", "Idle")
    assert not (tmp_path / "t1").exists()


def test_the_duration_is_the_test_time_at_the_end_not_the_last_records(tmp_path: Path) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path / "t1")
    c.on_event(ChainEvent(3.0, WALL, "ch0", "state", "Idle → Running (start by operator)"))
    c.on_record(cycle_rec(3.0, 1, 0.0, 0.0))  # the first step's record, at test time 0
    c.on_event(ChainEvent(38.0, WALL, "ch0", "state", "Running → Aborting (abort by operator)"))
    c.on_event(ChainEvent(38.0, WALL, "ch0", "state", "Aborting → Aborted (done)"))
    s = c.close("aborted: abort by operator", "Aborted")
    assert s["duration_s"] == 35.0
    assert s["complete"] is True


@pytest.mark.parametrize(
    ("charged", "discharged", "complete", "note"),
    [
        (1.0, 0.95, True, None),
        (1.0, 0.0, True, "cycle 1 has no discharge"),
        (0.0, 0.5, True, "cycle 1 has no charge"),
        (0.01, 3.96, True, "cycle 1 has no charge"),  # an offset, not a half-cycle
        (0.01, 3.96, False, "cycle 1 did not finish (aborted: abort by operator)"),
        (1.0, 0.95, False, "cycle 1 did not finish (aborted: abort by operator)"),
        # a test that starts at 50 % charge: its first charge is a top-up (issue 32's pack)
        (
            1.0,
            2.047,
            True,
            "cycle 1 discharged 2.05 times what it charged: it began partly charged,"
            " so the ratio is no efficiency",
        ),
    ],
)
def test_a_cycle_has_an_efficiency_only_with_both_a_charge_and_a_discharge(
    charged: float, discharged: float, complete: bool, note: str | None
) -> None:
    c = CycleSummary(1, charged, discharged, charged * 1.3, discharged * 1.2, complete)
    d = c.as_dict("aborted: abort by operator")
    assert d["efficiency_note"] == note
    if note is None:
        assert d["coulombic_efficiency"] == pytest.approx(0.95)
        assert d["energy_efficiency"] == pytest.approx(0.95 * 1.2 / 1.3)
    else:
        assert d["coulombic_efficiency"] is None and d["energy_efficiency"] is None


def test_a_cycle_is_complete_once_the_next_one_starts(tmp_path: Path) -> None:
    c = ResultCollector("ch0", "r", "t1", None)
    c.on_record(cycle_rec(3.0, 1, 0.3, 0.0))
    c.on_record(cycle_rec(100.0, 1, 0.3, 0.25))
    c.on_record(cycle_rec(200.0, 2, 0.1, 0.0))
    first, second = c.summary("aborted: abort by operator", "Aborted")["cycles"]
    assert first["complete"] and first["coulombic_efficiency"] == pytest.approx(0.25 / 0.3)
    assert not second["complete"] and second["coulombic_efficiency"] is None


def test_a_checkpoint_rewrites_the_summary_atomically_marked_incomplete(tmp_path: Path) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path / "t1")
    c.on_event(ChainEvent(3.0, WALL, "ch0", "state", "Idle → Running (start by operator)"))
    c.checkpoint("Running", now=13.0)
    s = json.loads((tmp_path / "t1" / "summary.json").read_text(encoding="utf-8"))
    assert (s["complete"], s["state"], s["duration_s"]) == (False, "Running", 10.0)
    assert [p.name for p in (tmp_path / "t1").iterdir()] == ["summary.json"]
    c.close("aborted: abort by operator", "Aborted", now=20.0)


def test_a_resumed_test_continues_its_files(tmp_path: Path) -> None:
    first = ResultCollector("ch0", "r", "t1", tmp_path / "t1")
    first.on_event(ChainEvent(3.0, WALL, "ch0", "state", "Idle → Running (start by operator)"))
    first.on_record(cycle_rec(3.0, 1, 0.0, 0.0))
    first.on_record(cycle_rec(13.0, 1, 0.1, 0.0))
    first.checkpoint("Running", now=13.0)
    first.abandon()  # the process dies

    # The next process: its clock starts again at 0; the test had run 10 s, away 5 s.
    again = ResultCollector("ch0", "r", "t1", tmp_path / "t1")
    again.resume(first_t=-15.0)
    again.on_event(ChainEvent(0.0, WALL, "ch0", "state", "supervisor restarted after 5.0 s"))
    again.on_record(replace(cycle_rec(10.0, 1, 0.2, 0.0), test_time_s=25.0))
    s = again.close("complete after step maintain of cycle 1: end", "Complete", now=10.0)
    rows = list(csv.reader((tmp_path / "t1" / "t1.bdf.csv").read_text().splitlines()))
    assert tuple(rows[0]) == BDF_COLUMNS and len(rows) == 4  # one header, three rows
    assert [r[BDF_COLUMNS.index("Record Index / 1")] for r in rows[1:]] == ["1", "2", "3"]
    assert [e["test_time_s"] for e in s["timeline"]] == [0.0, 15.0]
    assert s["duration_s"] == 25.0 and s["records"] == 3
    assert s["cycles"][0]["charge_capacity_ah"] == 0.2
    assert len((tmp_path / "t1" / "t1.chadeche.csv").read_text().splitlines()) == 3
