"""Forcing tags over OPC UA: the Bench object's ForceTag(Tag, Value) and UnforceTag(Tag),
through the one command path (engineers only, recorded with the OPC UA user). A forced
value reads Good_LocalOverride; a refusal is a Bad code with the reason as text: a viewer or
an operator Bad_UserAccessDenied, an unknown tag Bad_NodeIdUnknown, a value not of the tag's
type Bad_TypeMismatch, outside its range Bad_OutOfRange, a tag the e-stop or a channel's
guard reads Bad_NotSupported (docs/adr/0015-forcing-shelving-over-opcua.md).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from asyncua import Client, ua
from opcuarig import Rig, call, opcua_rig, text

pytestmark = pytest.mark.integration
VT = ua.VariantType
S = ua.StatusCodes


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path) as r:
        yield r


async def force(rig: Rig, c: Client, *args: str) -> ua.CallMethodResult:
    ns = await rig.ns(c)
    return await call(
        c,
        ua.NodeId("/Bench", ns),
        ua.NodeId("/Bench/ForceTag", ns),
        *(ua.Variant(a, VT.String) for a in args),
    )


async def unforce(rig: Rig, c: Client, tag: str) -> ua.CallMethodResult:
    ns = await rig.ns(c)
    return await call(
        c, ua.NodeId("/Bench", ns), ua.NodeId("/Bench/UnforceTag", ns), ua.Variant(tag, VT.String)
    )


async def test_an_engineer_forces_a_tag_and_reads_it_as_a_local_override(rig: Rig) -> None:
    async with rig.client("carol") as c:
        res = await force(rig, c, "room.temp", "31.5")
        assert res.StatusCode.is_good(), text(res)
        assert text(res) == "room.temp forced := 31.5 (until unforced)"
        await rig.scans(3)
        node = c.get_node(ua.NodeId("room.temp", await rig.ns(c)))
        dv = await node.read_data_value()
        assert dv.Value.Value == 31.5
        assert dv.StatusCode.value == S.GoodLocalOverride == 0x00960000
        assert rig.bench.commands.log[-1].actor == "opcua:carol"
        res = await unforce(rig, c, "room.temp")
        assert res.StatusCode.is_good(), text(res)
        await rig.scans(3)
        dv = await node.read_data_value()
        assert dv.StatusCode.value != S.GoodLocalOverride
        assert not rig.bench.db["room.temp"].forced


async def test_a_viewer_or_an_operator_may_not_force(rig: Rig) -> None:
    for user in ("bob", "alice"):
        async with rig.client(user) as c:
            res = await force(rig, c, "room.temp", "31.5")
            assert res.StatusCode.value == S.BadUserAccessDenied, (user, text(res))
            res = await unforce(rig, c, "room.temp")
            assert res.StatusCode.value == S.BadUserAccessDenied, (user, text(res))
    assert "needs engineer access" in text(res)
    assert not rig.bench.db["room.temp"].forced


async def test_the_estop_sense_is_never_forced_over_opcua(rig: Rig) -> None:
    async with rig.client("carol") as c:
        res = await force(rig, c, "estop.ok", "true")
        assert res.StatusCode.value == S.BadNotSupported
        assert text(res).startswith("estop.ok cannot be forced: the e-stop reads it")
        res = await force(rig, c, "ch0.voltage", "1.2")
        assert res.StatusCode.value == S.BadNotSupported
        assert "hard voltage limits" in text(res)
    assert not rig.bench.db["estop.ok"].forced


async def test_force_refusals_name_the_tag_the_type_and_the_range(rig: Rig) -> None:
    async with rig.client("carol") as c:
        res = await force(rig, c, "no.such.tag", "1")
        assert res.StatusCode.value == S.BadNodeIdUnknown
        assert text(res) == "ForceTag: unknown tag 'no.such.tag'"
        res = await force(rig, c, "room.temp", "warm")
        assert res.StatusCode.value == S.BadTypeMismatch
        assert list(res.InputArgumentResults)[1].value == S.BadTypeMismatch
        assert text(res) == "ForceTag: room.temp takes a number, not 'warm'"
        res = await force(rig, c, "room.temp", "nan")
        assert res.StatusCode.value == S.BadOutOfRange
        ns = await rig.ns(c)
        wrong = await call(
            c,
            ua.NodeId("/Bench", ns),
            ua.NodeId("/Bench/ForceTag", ns),
            ua.Variant("room.temp", VT.String),
            ua.Variant(31.5, VT.Double),
        )
        assert wrong.StatusCode.value == S.BadInvalidArgument
