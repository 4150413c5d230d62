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

from supervisor.core.records import ChainEvent, Record
from supervisor.publish.display import ChadecheDisplay, display_line
from supervisor.publish.results import BDF_COLUMNS, ResultCollector, chadeche_line

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
