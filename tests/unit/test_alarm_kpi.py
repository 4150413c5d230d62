"""ISA-18.2 alarm performance (issue 34, supervisor/safety/kpi.py, ADR 0048): a scripted
hour of alarms on the virtual clock, each figure compared with a count made by hand."""

from __future__ import annotations

import json

import pytest

from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality
from supervisor.publish.changes import Sample
from supervisor.publish.influx.lineproto import LineEncoder
from supervisor.safety import Alarm, AlarmManager, Severity
from supervisor.safety.kpi import AlarmKpi
from supervisor.tags import TagDB

FLOOD_IDS = ["bench.estop", *(f"ch{i:02d}.hold" for i in range(1, 15))]


class Hour:
    """The scripted hour. The virtual clock's wall epoch is 2026-01-01T00:00Z, so t = 0 is
    the start of a fixed 10-minute interval.

    - t = 60: ``tank.level`` (low) activates and stays active (the future stale alarm);
    - t = 300, 310, 320, 330: ``di.door`` (medium) raised, cleared 5 s later each time:
      a chattering input, 4 activations in 40 s;
    - t = 1800 + 8 i, i = 0..14: an e-stop-like burst, 15 alarms in 2 minutes (the
      e-stop critical, 14 channel holds high), all cleared at t = 2000.
    """

    def __init__(self, max_kept: int = 100_000) -> None:
        self.clock = VirtualClock()
        self.alarms = AlarmManager(self.clock)
        self.db = TagDB()
        self.kpi = AlarmKpi(self.alarms, self.db, max_kept=max_kept)
        a = self.alarms
        self.tank = a.declare("tank.level", severity=Severity.LOW)
        self.door = a.declare("di.door", severity=Severity.MEDIUM)
        self.flood = [
            a.declare(i, severity=Severity.CRITICAL if i == "bench.estop" else Severity.HIGH)
            for i in FLOOD_IDS
        ]

    def at(self, t: float) -> None:
        self.clock.advance(t - self.clock.now())

    def set(self, t: float, alarm: Alarm, active: bool) -> None:
        self.at(t)
        self.alarms.set(alarm, active, f"{alarm.id} test")

    def run(self, until: float = 3600.0) -> None:
        script: list[tuple[float, Alarm, bool]] = [(60.0, self.tank, True)]
        for k in range(4):
            script += [(300.0 + 10 * k, self.door, True), (305.0 + 10 * k, self.door, False)]
        script += [(1800.0 + 8 * i, al, True) for i, al in enumerate(self.flood)]
        script += [(2000.0, al, False) for al in self.flood]
        for t, alarm, active in sorted(script, key=lambda s: s[0]):
            if t > until:
                break
            if t < self.clock.now():
                continue  # played by an earlier call
            self.set(t, alarm, active)
        self.at(until)


def test_the_scripted_hour_matches_the_hand_count() -> None:
    hour = Hour()
    hour.run()
    f = hour.kpi.figures()
    # 1 (tank) + 4 (door) + 15 (burst) activations in the last 24 h.
    assert f.per_day == 20
    # Now is 01:00:00: the current interval [01:00, 01:10) and the last [00:50, 01:00)
    # hold none.
    assert (f.per_10min, f.per_10min_last) == (0, 0)
    # The 11th burst alarm (t = 1880) starts the flood; it ends when the 11th newest
    # activation (the 5th of the burst, t = 1832) leaves the window: 1832 + 600 = 2432.
    assert f.flood_s == pytest.approx(2432 - 1880)
    assert f.flood_pct == pytest.approx(round(100 * 552 / 86400, 1))  # 0.6 %
    assert f.in_flood is False
    assert f.stale == 0  # tank.level active for 3540 s only
    assert f.chattering == ("di.door",)  # 3+ activations in 60 s; the burst's once each
    assert f.priority == {"low": 1, "medium": 4, "high": 14, "critical": 1}
    assert f.priority_pct == {"low": 5.0, "medium": 20.0, "high": 70.0, "critical": 5.0}
    # di.door 4 times, then nine of the alarms seen once, by id.
    assert f.top == (("di.door", 4), *((i, 1) for i in sorted(FLOOD_IDS)[:9]))
    assert f.dropped == 0


def test_alarms_per_10_minutes_count_fixed_intervals() -> None:
    hour = Hour()
    hour.run(until=599.0)
    f = hour.kpi.figures()
    assert (f.per_10min, f.per_10min_last) == (5, 0)  # tank + 4 door in [00:00, 00:10)
    hour.at(600.0)
    f = hour.kpi.figures()
    assert (f.per_10min, f.per_10min_last) == (0, 5)  # the interval completed
    hour.at(1200.0)
    assert hour.kpi.figures().per_10min_last == 0  # [00:10, 00:20) held none
    hour.run(until=2100.0)
    f = hour.kpi.figures()
    assert (f.per_10min, f.per_10min_last) == (15, 0)  # the burst in [00:30, 00:40)
    assert f.in_flood is True  # 15 activations in the last 10 minutes (more than 10)
    assert f.flood_s == pytest.approx(2100 - 1880)


def test_flood_ends_when_the_window_holds_ten_or_fewer() -> None:
    hour = Hour()
    hour.run(until=2431.0)
    assert hour.kpi.figures().in_flood is True
    hour.at(2432.0)
    f = hour.kpi.figures()
    assert f.in_flood is False
    assert f.flood_s == pytest.approx(552.0)


def test_an_alarm_active_past_24_hours_is_stale_and_the_day_forgets_older_ones() -> None:
    hour = Hour()
    hour.run()
    hour.at(60.0 + 86_400.0 + 1.0)  # tank.level, activated at t = 60, still active
    f = hour.kpi.figures()
    assert f.stale == 1
    # Its activation (t = 60) has left the 24 h window; the door's and the burst's not.
    assert f.per_day == 19
    assert f.priority["low"] == 0
    assert f.flood_s == pytest.approx(552.0)  # the flood is within the last 24 h
    hour.at(2432.0 + 86_400.0)
    f = hour.kpi.figures()
    assert (f.per_day, f.flood_s, f.chattering) == (0, 0.0, ())
    assert f.stale == 1  # still active


def test_a_shelved_alarm_is_not_annunciated_and_not_counted() -> None:
    hour = Hour()
    hour.alarms.shelve("di.door", 3600.0, "op")
    hour.run(until=600.0)
    f = hour.kpi.figures()
    assert f.per_day == 1  # tank.level only
    assert f.chattering == ()


def test_two_activations_in_a_minute_do_not_chatter_three_do() -> None:
    hour = Hour()
    for t in (100.0, 130.0):
        hour.set(t, hour.door, True)
        hour.set(t + 1, hour.door, False)
    hour.set(200.0, hour.door, True)  # 3 within 100 s, not within 60 s
    assert hour.kpi.figures().chattering == ()
    hour.set(201.0, hour.door, False)
    hour.set(229.0, hour.door, True)  # 130, 200, 229: still 99 s apart
    hour.set(230.0, hour.door, False)
    hour.set(250.0, hour.door, True)  # 200, 229, 250: 50 s
    assert hour.kpi.figures().chattering == ("di.door",)


def test_a_week_of_activations_keeps_only_the_day_and_at_most_the_cap() -> None:
    hour = Hour()
    for k in range(7 * 8640):  # one activation every 10 s for a week
        hour.set(10.0 * k + 1, hour.door, True)
        hour.set(10.0 * k + 2, hour.door, False)
    assert hour.kpi.kept == 8640  # the last 24 h only
    assert hour.kpi.figures().per_day == 8640
    capped = Hour(max_kept=1000)
    for k in range(3000):
        capped.set(10.0 * k + 1, capped.door, True)
        capped.set(10.0 * k + 2, capped.door, False)
    assert capped.kpi.kept == 1000
    f = capped.kpi.figures()
    assert (f.per_day, f.dropped) == (1000, 2000)
    assert f.top == (("di.door", 1000),)


def test_the_tags_carry_the_figures_refreshed_at_most_once_a_second() -> None:
    hour = Hour()
    hour.run()
    db, kpi = hour.db, hour.kpi
    kpi.on_scan(db, hour.clock.now())
    assert db["alarms.per_day"].value == 20
    assert db["alarms.flood_s"].value == pytest.approx(552.0)
    assert db["alarms.flood_s"].spec.unit == "s"
    assert db["alarms.chattering"].value == 1
    assert db["alarms.chattering_ids"].value == "di.door"
    assert db["alarms.priority.high"].value == 14
    assert db["alarms.priority.high_pct"].value == pytest.approx(70.0)
    assert json.loads(str(db["alarms.top"].value))[0] == {"id": "di.door", "count": 4}
    hour.set(3600.5, hour.door, True)
    kpi.on_scan(db, hour.clock.now())  # half a second later: not refreshed
    assert db["alarms.per_day"].value == 20
    hour.at(3601.0)
    kpi.on_scan(db, hour.clock.now())
    assert db["alarms.per_day"].value == 21
    assert db["alarms.per_10min"].value == 1


def test_influxdb_gets_the_figures_as_diagnostics_of_source_alarms() -> None:
    lines = LineEncoder("sim", ["ch0"], {"alarms.per_day": "int"}.get).encode(
        [Sample("alarms.per_day", 20, Quality.GOOD, 3600.0, 1_767_229_200.0)]
    )
    text = "\n".join(line for group in lines.values() for line in group)
    assert text.startswith("diagnostics,bench=sim,source=alarms per_day=20.0 ")
