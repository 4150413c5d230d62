"""Shelving and confirming through OPC UA Alarms & Conditions, bound to the alarm model
(supervisor.safety): TimedShelve / Unshelve on a condition's ShelvingState shelve it there
(ISA-18.2 timed shelving), a trip is never shelved (Bad_NotSupported with the reason),
OneShotShelve is not offered; Confirm is the reset of a latched trip whose cause is gone.
Every event carries the shelving state, and ConditionRefresh replays a shelved condition
(docs/adr/0015-forcing-shelving-over-opcua.md).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from opcuarig import Collector, Rig, call, eventually, opcua_rig, text

pytestmark = pytest.mark.integration
VT = ua.VariantType
S = ua.StatusCodes
O = ua.ObjectIds  # noqa: E741
ALARM = O.AlarmConditionType
ROOM = "room.temp.H"  # a plain alarm, active from the start (the room is at 25 degC)


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path) as r:
        yield r


def conditions(got: Collector, name: str) -> list[Any]:
    return [e for e in got.events if getattr(e, "ConditionName", None) == name]


async def shelving(rig: Rig, c: Client, alarm: str, method: int, *args: ua.Variant) -> Any:
    ns = await rig.ns(c)
    return await call(
        c, ua.NodeId(f"/Bench/Alarms/{alarm}/ShelvingState", ns), ua.NodeId(method), *args
    )


def ms(x: float) -> ua.Variant:
    return ua.Variant(x, VT.Double)


async def test_timed_shelve_and_unshelve_through_a_and_c(rig: Rig) -> None:
    got = Collector()
    alarms = rig.bench.alarms
    assert alarms is not None
    async with rig.client("alice") as c:
        sub = await c.create_subscription(20, got)
        await sub.subscribe_events(c.nodes.server, ALARM)
        res = await shelving(rig, c, ROOM, O.ShelvedStateMachineType_TimedShelve, ms(60_000))
        assert res.StatusCode.is_good(), text(res)
        assert alarms[ROOM].shelved(rig.bench.clock.now())
        await rig.scans(1)
        await eventually(lambda: bool(conditions(got, ROOM)), "the shelved condition")
        shelved = conditions(got, ROOM)[-1]
        assert shelved.SuppressedOrShelved is True
        assert getattr(shelved, "ShelvingState/CurrentState").Text == "TimedShelved"
        assert shelved.Retain is True
        ns = await rig.ns(c)
        flag = c.get_node(ua.NodeId(f"/Bench/Alarms/{ROOM}/Shelved", ns))
        assert await flag.read_value() is True
        # AlarmConditionType's own instance declaration of Unshelve works as well.
        res = await shelving(rig, c, ROOM, O.AlarmConditionType_ShelvingState_Unshelve)
        assert res.StatusCode.is_good(), text(res)
        await rig.scans(1)
        await eventually(
            lambda: conditions(got, ROOM)[-1].SuppressedOrShelved is False,
            "the unshelved condition",
        )
        assert not alarms[ROOM].shelved(rig.bench.clock.now())
        again = await shelving(rig, c, ROOM, O.ShelvedStateMachineType_Unshelve)
        assert again.StatusCode.value == S.BadConditionNotShelved
        assert text(again) == f"alarm {ROOM} is not shelved"
        await sub.delete()
    shelves = [e for e in rig.bench.commands.log if e.target == f"alarm {ROOM}"]
    assert [(e.command, e.actor, e.accepted) for e in shelves] == [
        ("shelve for 60.0 s", "opcua:alice", True),
        ("unshelve", "opcua:alice", True),
        ("unshelve", "opcua:alice", False),
    ]


async def test_a_trip_is_never_shelved_and_bad_shelving_gets_its_code(rig: Rig) -> None:
    async with rig.client("alice") as c:
        res = await shelving(rig, c, "estop", O.ShelvedStateMachineType_TimedShelve, ms(60_000))
        assert res.StatusCode.value == S.BadNotSupported
        assert text(res) == "alarm estop is a trip: it protects its channel and cannot be shelved"
        res = await shelving(rig, c, ROOM, O.ShelvedStateMachineType_TimedShelve, ms(8 * 86400e3))
        assert res.StatusCode.value == S.BadShelvingTimeOutOfRange
        res = await shelving(rig, c, ROOM, O.ShelvedStateMachineType_OneShotShelve)
        assert res.StatusCode.value == S.BadNotSupported
        assert "shelve for a time" in text(res)
        res = await shelving(rig, c, ROOM, O.ShelvedStateMachineType_TimedShelve)
        assert res.StatusCode.value == S.BadArgumentsMissing
    async with rig.client("bob") as c:  # a viewer reads
        res = await shelving(rig, c, ROOM, O.ShelvedStateMachineType_TimedShelve, ms(60_000))
        assert res.StatusCode.value == S.BadUserAccessDenied
    alarms = rig.bench.alarms
    assert alarms is not None and not alarms[ROOM].shelved(rig.bench.clock.now())


async def test_condition_refresh_reports_a_shelved_condition(rig: Rig) -> None:
    async with rig.client("alice") as c:
        res = await shelving(rig, c, ROOM, O.ShelvedStateMachineType_TimedShelve, ms(60_000))
        assert res.StatusCode.is_good(), text(res)
    await rig.scans(1)
    got = Collector()
    async with rig.client("bob") as c:
        sub = await c.create_subscription(20, got)
        await sub.subscribe_events(c.nodes.server, ALARM)
        res = await call(
            c,
            ua.NodeId(O.ConditionType),
            ua.NodeId(O.ConditionType_ConditionRefresh),
            ua.Variant(sub.subscription_id, VT.UInt32),
        )
        assert res.StatusCode.is_good()
        await eventually(lambda: bool(conditions(got, ROOM)), "the refreshed condition")
        (room,) = conditions(got, ROOM)
        assert room.SuppressedOrShelved is True
        assert getattr(room, "ShelvingState/CurrentState").Text == "TimedShelved"
        assert 0 < getattr(room, "ShelvingState/UnshelveTime") <= 60_000
        await sub.delete()


async def test_confirm_is_the_reset_of_a_latched_trip(rig: Rig) -> None:
    got = Collector()
    sim = rig.bench.sim
    assert sim is not None
    async with rig.client("alice") as c:
        ns = await rig.ns(c)
        estop = ua.NodeId("/Bench/Alarms/estop", ns)
        sub = await c.create_subscription(20, got)
        await sub.subscribe_events(c.nodes.server, ALARM)
        sim.press_estop(True)
        await rig.scans(5)
        await eventually(lambda: bool(conditions(got, "estop")), "the e-stop condition")
        pressed = conditions(got, "estop")[-1]
        assert getattr(pressed, "ConfirmedState/Id") is False  # a trip waits for its reset
        confirm = ua.NodeId(O.AcknowledgeableConditionType_Confirm)
        args = (
            ua.Variant(pressed.EventId, VT.ByteString),
            ua.Variant(ua.LocalizedText("reset"), VT.LocalizedText),
        )
        res = await call(c, estop, confirm, *args)
        assert res.StatusCode.value == S.BadInvalidState
        assert text(res).startswith("cannot reset estop: the cause is still present")
        sim.press_estop(False)
        await rig.scans(5)
        res = await call(c, estop, confirm, *args)
        assert res.StatusCode.is_good(), text(res)
        await rig.scans(1)
        await eventually(
            lambda: getattr(conditions(got, "estop")[-1], "ConfirmedState/Id") is True,
            "the confirmed condition",
        )
        assert rig.bench.alarms is not None
        assert rig.bench.alarms["estop"].state.value == "normal"
        again = await call(c, estop, confirm, *args)
        assert again.StatusCode.value == S.BadConditionBranchAlreadyConfirmed
        await sub.delete()
