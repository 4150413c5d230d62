"""The alarm KPIs (issue 34, ADR 0048) on the simulated bench: a scripted stretch of
alarms — a chattering input, an e-stop-like flood, the room's temperature alarm left
active past 24 h — gives ``alarms.*`` tags that match a count made by hand, in the tag
database and over OPC UA (a real asyncua client's read); the alarm journal
(``GET /api/alarms/journal``) answers them with its filters, as JSON and as CSV.

Virtual clock: the bench scans when the test says so (0.1 s a scan); the 24 h of the
stale alarm are a jump of the clock."""

from __future__ import annotations

import asyncio
import csv
import io
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from asyncua import ua
from opcuarig import Rig, opcua_rig

from supervisor.app import Bench
from supervisor.app.hmi import build_screens
from supervisor.config.models import HmiConfig
from supervisor.hmi import HttpApi
from supervisor.safety import Alarm, Severity, Transition

pytestmark = pytest.mark.integration

FLOOD = ["bench.estop_test", *(f"hold.{i:02d}" for i in range(1, 15))]


def declare(bench: Bench) -> None:
    """The scripted inputs' alarms, declared before the OPC UA server starts."""
    alarms = bench.alarms
    alarms.declare("di.door", severity=Severity.MEDIUM)
    for i in FLOOD:
        alarms.declare(i, severity=Severity.CRITICAL if i == "bench.estop_test" else Severity.HIGH)


def activations(bench: Bench) -> int:
    return sum(1 for e in bench.alarms.history if e.transition is Transition.ACTIVATED)


async def seconds(rig: Rig, s: float) -> None:
    await rig.scans(round(s / rig.bench.engine.period_s), settle=False)


async def script(rig: Rig) -> None:
    """The chattering door (4 activations in 40 s), then 15 alarms in 2 minutes."""
    bench = rig.bench
    door: Alarm = bench.alarms["di.door"]
    for _ in range(4):
        bench.alarms.set(door, True, "=door open")  # a formula-like text for the CSV
        await seconds(rig, 5)
        bench.alarms.set(door, False)
        await seconds(rig, 5)
    for i in FLOOD:
        bench.alarms.set(bench.alarms[i], True, f"{i} tripped")
        await seconds(rig, 8)
    await seconds(rig, 2)
    await rig.settled()


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path, prepare=declare, history=True) as r:
        yield r


async def opcua_value(rig: Rig, tag: str) -> Any:
    async with rig.client() as c:
        ns = await rig.ns(c)
        return await c.get_node(ua.NodeId(tag, ns)).read_value()


async def until(rig: Rig, t: float) -> None:
    """Scan until the bench's clock reads ``t``."""
    await seconds(rig, t - rig.bench.clock.now())


async def test_a_scripted_hour_gives_the_hand_count_in_the_tags_and_over_opcua(
    rig: Rig,
) -> None:
    """The hour (t on the bench's clock; t = 0 is 00:00 of the wall clock, a fixed
    interval's start): room.temp.H active from the start (the simulated room, 25 degC, is
    above its 20 degC limit); the door chatters at t = 300 (4 activations in 40 s); 15
    alarms from t = 1800, 8 s apart; all cleared at t = 2000; then quiet until t = 3600,
    and a day more for the stale alarm."""
    bench, db = rig.bench, rig.bench.db
    assert activations(bench) == 1 and bench.alarms["room.temp.H"].active
    door: Alarm = bench.alarms["di.door"]
    await until(rig, 300.0)
    for _ in range(4):
        bench.alarms.set(door, True, "door open")
        await seconds(rig, 5)
        bench.alarms.set(door, False)
        await seconds(rig, 5)
    await until(rig, 1800.0)
    for i in FLOOD:
        bench.alarms.set(bench.alarms[i], True, f"{i} tripped")
        await seconds(rig, 8)
    await until(rig, 2000.0)
    for i in FLOOD:
        bench.alarms.set(bench.alarms[i], False)
    await until(rig, 2100.0)
    await rig.settled()
    # [00:30, 00:40): the 15; [00:20, 00:30): none. In flood since the 11th (t = 1880).
    assert (db["alarms.per_10min"].value, db["alarms.per_10min_last"].value) == (15, 0)
    assert db["alarms.in_flood"].value is True
    assert await opcua_value(rig, "alarms.per_10min") == 15
    await until(rig, 3600.0)
    await seconds(rig, 1.1)  # one refresh past the hour
    await rig.settled()
    # 1 (room) + 4 (door) + 15 (burst) = 20 activations. The flood: from the 11th
    # (t = 1880) until the 5th (t = 1832) leaves the window, 2432: 552 s, 0.6 % of a day.
    assert db["alarms.per_day"].value == 20
    assert db["alarms.in_flood"].value is False
    assert db["alarms.flood_s"].value == pytest.approx(552.0)
    assert db["alarms.flood_pct"].value == pytest.approx(0.6)
    assert db["alarms.chattering"].value == 1
    assert db["alarms.chattering_ids"].value == "di.door"
    assert db["alarms.stale"].value == 0
    room = bench.alarms["room.temp.H"].severity.name.lower()
    by_hand = {"low": 0, "medium": 4, "high": 14, "critical": 1}
    by_hand[room] += 1
    assert {p: db[f"alarms.priority.{p}"].value for p in by_hand} == by_hand
    top = json.loads(str(db["alarms.top"].value))
    assert top[0] == {"id": "di.door", "count": 4} and len(top) == 10
    assert await opcua_value(rig, "alarms.per_day") == 20
    assert await opcua_value(rig, "alarms.flood_s") == pytest.approx(552.0)
    assert await opcua_value(rig, "alarms.chattering") == 1


async def test_an_alarm_active_past_24_hours_is_counted_stale(rig: Rig) -> None:
    bench, db = rig.bench, rig.bench.db
    door: Alarm = bench.alarms["di.door"]
    bench.alarms.set(door, True, "door open")
    await seconds(rig, 1)
    # The door stays open past a day: the clock jumps, the scans go on from there (the
    # scans missed are skipped, as after a long stall).
    bench.clock.advance(86_400.0)
    await bench.engine.run(asyncio.Event(), until_t=bench.clock.now() + 2.0)
    await rig.settled()
    stale = sum(1 for a in bench.alarms if a.active and not a.shelved(bench.clock.now()))
    assert db["alarms.stale"].value == stale >= 1
    assert await opcua_value(rig, "alarms.stale") == stale


async def test_the_journal_filters_and_exports_csv(rig: Rig, tmp_path: Path) -> None:
    bench = rig.bench
    await script(rig)
    bench.alarms.acknowledge("di.door", "hmi:alice")
    await seconds(rig, 1)
    assert bench.historian is not None and bench.historian.writer.flush()
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, commands=bench.commands)
    build_screens(bench, api, root=tmp_path / "no-hmi", cfg=HmiConfig(login=False))
    await api.start()
    try:
        async with aiohttp.ClientSession() as s:
            url = api.url + "/alarms/journal"
            async with s.get(url, params={"alarm": "di.door"}) as resp:
                assert resp.status == 200
                body = await resp.json()
            assert body["source"] == "historian"
            kinds = [e["transition"] for e in body["entries"]]
            assert kinds == ["activated", "cleared"] * 4 + ["acknowledged"]
            assert body["entries"][-1]["actor"] == "hmi:alice"
            params = {"transition": "activated", "channel": "", "limit": "5"}
            async with s.get(url, params=params) as resp:
                body = await resp.json()
            assert body["count"] == 5 and body["truncated"] is True
            assert [e["alarm"] for e in body["entries"]] == FLOOD[-5:]  # the newest five
            params = {"alarm": "di.door", "actor": "hmi:alice", "format": "csv"}
            async with s.get(url, params=params) as resp:
                assert resp.status == 200
                assert resp.content_type == "text/csv"
                rows = list(csv.reader(io.StringIO(await resp.text())))
            assert rows[0] == [
                "time", "time_iso", "alarm", "channel", "transition", "priority", "message",
                "actor",
            ]  # fmt: skip
            assert len(rows) == 2
            assert rows[1][2:6] == ["di.door", "", "acknowledged", "medium"]
            assert rows[1][6] == "'=door open"  # a formula is not run by a spreadsheet
            async with s.get(url, params={"transition": "exploded"}) as resp:
                assert resp.status == 400
    finally:
        await api.stop()
