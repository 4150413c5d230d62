"""Channel methods over OPC UA: each call goes through the one command path with the
session's user as its actor, and answers a status code with the reason as its ``Result``
output; step changes and commands come back as events. Each refusal case of issue 11 has
its test: wrong types, out-of-range values, unknown recipes, a role without the right.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from asyncua import Client, ua
from commandrig import DISCHARGE, recipe
from opcuarig import Collector, Rig, call, eventually, opcua_rig, text

pytestmark = pytest.mark.integration
VT = ua.VariantType
S = ua.StatusCodes

WITH_PARAMETER = (
    "recipe: p\nparameters: {v_min: 1.0 V}\nsteps:\n"
    "  - id: d\n    discharge: 200 mA\n    duration: 1 h\n    until: [{voltage <= v_min: next}]\n"
    "  - {id: r, rest: 1 h}\n"
)


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path) as r:
        yield r


def s(value: str) -> ua.Variant:
    return ua.Variant(value, VT.String)


class Channel:
    """A channel object as a client calls it."""

    def __init__(self, c: Client, ns: int, name: str = "ch0") -> None:
        self.c = c
        self.ns = ns
        self.node = ua.NodeId(f"/Bench/Channels/{name}", ns)

    async def __call__(self, method: str, *args: ua.Variant) -> ua.CallMethodResult:
        return await call(
            self.c, self.node, ua.NodeId(f"{self.node.Identifier}/{method}", self.ns), *args
        )

    async def value(self, tag: str) -> object:
        return await self.c.get_node(ua.NodeId(tag, self.ns)).read_value()


async def test_start_with_a_recipe_runs_it_and_the_step_change_event_arrives(
    rig: Rig, tmp_path: Path
) -> None:
    at_server, at_channel = Collector(), Collector()
    async with rig.client("alice") as c:
        ns = await rig.ns(c)
        ch0 = Channel(c, ns)
        types = [
            c.get_node(ua.NodeId(f"/Types/{t}", ns)) for t in ("ChainEventType", "CommandEventType")
        ]
        sub = await c.create_subscription(20, at_server)
        await sub.subscribe_events(c.nodes.server, types)
        sub2 = await c.create_subscription(20, at_channel)
        await sub2.subscribe_events(c.get_node(ch0.node), types)
        res = await ch0("Start", s(recipe(tmp_path, DISCHARGE)), s(""))
        assert res.StatusCode.is_good(), text(res)
        assert "recipe d loaded" in text(res) and "started" in text(res)
        await rig.scans(3)
        assert await ch0.value("ch0.chain.state_code") == 4  # Execute
        assert await ch0.value("ch0.chain.step") == "d"
        await eventually(lambda: "starting step 1 d (start)" in at_server.messages(), "step event")
        step = next(e for e in at_server.events if e.Message.Text == "starting step 1 d (start)")
        assert (step.Channel, step.Kind, step.Source, step.Recipe) == ("ch0", "step", "d", "d")
        assert step.EventType == ua.NodeId("/Types/ChainEventType", ns)
        assert step.SourceNode == ch0.node and step.SourceName == "ch0"
        # The command's event and the step's leave on different paths (the command path's
        # log, the scan's chain): either may be published first.
        await eventually(lambda: any(e.Kind == "command" for e in at_server.events), "command")
        command = next(e for e in at_server.events if e.Kind == "command")
        assert command.Actor == "opcua:alice"  # the session's user
        assert (
            command.Message.Text.startswith("start ")
            and "by opcua:alice: accepted" in command.Message.Text
        )
        await eventually(
            lambda: "starting step 1 d (start)" in at_channel.messages(), "the same on the channel"
        )
        await sub.delete()
        await sub2.delete()


async def test_start_finds_a_recipe_by_name_and_takes_its_parameters(rig: Rig) -> None:
    folder = rig.tmp  # the rig's recipe folder (commandrig.io_map)
    (folder / "low.yaml").write_text(WITH_PARAMETER, encoding="utf-8")
    async with rig.client("alice") as c:
        ch0 = Channel(c, await rig.ns(c))
        res = await ch0("Start", s("low"), s("v_min=5 V"))  # above the cell: ends at once
        assert res.StatusCode.is_good(), text(res)
        await rig.scans(3)
        assert await ch0.value("ch0.chain.step") == "r"
        await ch0("Stop")
        await ch0("Reset")
        await rig.scans(2)
        res = await ch0("Start", s("low"), ua.Variant(["v_min = 0.5 V"], VT.String))  # an array
        assert res.StatusCode.is_good(), text(res)
        await rig.scans(3)
        assert await ch0.value("ch0.chain.step") == "d"


async def test_the_isa88_commands_answer_the_state_table(rig: Rig, tmp_path: Path) -> None:
    async with rig.client("alice") as c:
        ch0 = Channel(c, await rig.ns(c))
        hold = await ch0("Hold")
        assert hold.StatusCode.value == S.BadInvalidState
        assert text(hold) == "ch0: hold is not allowed while Idle (allowed: start)"
        assert (await ch0("Start", s(recipe(tmp_path, DISCHARGE)), s(""))).StatusCode.is_good()
        await rig.scans(2)
        for method, state in (("Hold", 15), ("Resume", 4), ("Stop", 0), ("Reset", 2)):
            res = await ch0(method)
            assert res.StatusCode.is_good(), text(res)
            await rig.scans(2)
            assert await ch0.value("ch0.chain.state_code") == state, method
        res = await ch0("Advance")
        assert res.StatusCode.value == S.BadInvalidState
        assert "advance is not allowed while Idle" in text(res)


async def test_wrong_argument_types_and_counts_are_refused_before_any_command(rig: Rig) -> None:
    before = len(rig.bench.commands.log)
    async with rig.client("alice") as c:
        ch0 = Channel(c, await rig.ns(c))
        res = await ch0("Start", ua.Variant(1.0, VT.Double), s(""))
        assert res.StatusCode.value == S.BadInvalidArgument
        assert [r.value for r in res.InputArgumentResults] == [S.BadTypeMismatch, S.Good]
        assert text(res) == "Start: Recipe must be a String, got Double 1.0"
        res = await ch0("SetManualCurrent", s("0.3"))
        assert res.StatusCode.value == S.BadInvalidArgument
        assert text(res) == "SetManualCurrent: Current must be a Double or Float, got String '0.3'"
        res = await ch0("SetMode", ua.Variant(["auto"], VT.String))
        assert res.StatusCode.value == S.BadInvalidArgument
        assert (await ch0("Start", s(""))).StatusCode.value == S.BadArgumentsMissing
        assert (
            await ch0("Hold", ua.Variant(1, VT.Int32))
        ).StatusCode.value == S.BadTooManyArguments
        res = await ch0("Start", s("x"), s("v_min"))
        assert res.StatusCode.value == S.BadInvalidArgument
        assert "'v_min' is not name=value" in text(res)
    assert len(rig.bench.commands.log) == before  # nothing reached the bench


async def test_refusals_are_bad_status_codes_with_the_command_path_s_reason(
    rig: Rig, tmp_path: Path
) -> None:
    async with rig.client("alice") as c:
        ch0 = Channel(c, await rig.ns(c))
        res = await ch0("Start", s("no-such-recipe"), s(""))
        assert res.StatusCode.value == S.BadNotFound
        # Looked for in the recipe folders (ADR 0026), named in the answer.
        assert text(res) == f"no-such-recipe: no such recipe in {rig.tmp}/"
        broken = recipe(tmp_path, "recipe: x\nsteps:\n  - {id: a, charge: 9 V}\n", "broken.yaml")
        res = await ch0("Start", s(broken), s(""))
        assert res.StatusCode.value == S.BadConfigurationError
        assert text(res).startswith(f"ch0: recipe refused: {broken}:3:")
        res = await ch0("SetMode", s("Sideways"))
        assert res.StatusCode.value == S.BadInvalidArgument
        assert text(res) == "ch0: mode is auto or manual, not 'sideways'"
        res = await ch0("SetManualCurrent", ua.Variant(float("nan"), VT.Double))
        assert res.StatusCode.value == S.BadInvalidArgument
        assert "finite" in text(res)
        assert (await ch0("Start", s(recipe(tmp_path, DISCHARGE)), s(""))).StatusCode.is_good()
        res = await ch0("SetManualCurrent", ua.Variant(0.1, VT.Double))
        assert res.StatusCode.value == S.BadInvalidState
        assert "in auto" in text(res)


async def test_a_viewer_and_an_anonymous_session_may_only_read(rig: Rig) -> None:
    for user in ("bob", None):
        async with rig.client(user) as c:
            ch0 = Channel(c, await rig.ns(c))
            assert await ch0.value("ch0.voltage") == rig.bench.db["ch0.voltage"].value
            res = await ch0("Hold")
            assert res.StatusCode.value == S.BadUserAccessDenied
            who = "opcua:bob" if user else "an anonymous session"
            assert text(res) == f"{who} may only read (role viewer): log in as an operator"
    refused = [e for e in rig.bench.commands.log if e.actor in ("opcua:bob", "opcua:anonymous")]
    assert [(e.actor, e.accepted, e.kind.value) for e in refused] == [
        ("opcua:bob", False, "forbidden"),
        ("opcua:anonymous", False, "forbidden"),
    ]


async def test_manual_mode_through_the_methods(rig: Rig) -> None:
    async with rig.client("alice") as c:
        ch1 = Channel(c, await rig.ns(c), "ch1")
        res = await ch1("SetMode", s("Auto"))
        assert res.StatusCode.is_good(), text(res)
        assert (await ch1("SetMode", s("Manual"))).StatusCode.is_good()
        res = await ch1("SetManualCurrent", ua.Variant(0.15, VT.Double))
        assert res.StatusCode.is_good()
        assert text(res) == "ch1: manual setpoint 0.15 A (enable is off: nothing flows yet)"
        await rig.scans(1)
        assert await ch1.value("ch1.manual_current") == 0.15
        assert rig.bench.db["ch1.mode"].value == "manual"


async def test_writes_go_through_the_command_path_checked_for_type_range_and_role(
    rig: Rig,
) -> None:
    db = rig.bench.db
    async with rig.client("alice") as c:
        ns = await rig.ns(c)

        async def write(tag: str, variant: ua.Variant) -> int:
            node = c.get_node(ua.NodeId(tag, ns))
            params = ua.WriteParameters()
            wv = ua.WriteValue()
            wv.NodeId = node.nodeid
            wv.AttributeId = ua.AttributeIds.Value
            wv.Value = ua.DataValue(variant)
            params.NodesToWrite = [wv]
            (status,) = await c.uaclient.write(params)
            return int(status.value)

        assert await write("ch1.manual_current", ua.Variant(0.2, VT.Double)) == S.Good
        assert db["ch1.manual_current"].value == 0.2
        assert await write("ch1.enable", ua.Variant(False, VT.Boolean)) == S.Good
        assert await write("ch1.manual_current", s("0.2")) == S.BadTypeMismatch
        assert await write("ch1.mode", s("sideways")) == S.BadOutOfRange
        assert await write("ch1.voltage", ua.Variant(1.0, VT.Double)) == S.BadNotWritable
        assert await write("ch1.mode", s("auto")) == S.Good  # a mode change is that command
        assert db["ch1.mode"].value == "auto"
        # In auto the chain drives the channel: the command path refuses, in this state.
        assert await write("ch1.manual_current", ua.Variant(0.1, VT.Double)) == S.BadInvalidState
    async with rig.client("bob") as c:
        node = c.get_node(ua.NodeId("ch2.manual_current", await rig.ns(c)))
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            await node.write_value(ua.DataValue(ua.Variant(0.1, VT.Double)))
    writes = [
        e for e in rig.bench.commands.log if e.command.startswith(("write", "manual", "mode"))
    ]
    assert {e.actor for e in writes} == {"opcua:alice", "opcua:bob"}


async def test_an_engineer_writes_engineer_tags_an_operator_may_not(tmp_path: Path) -> None:
    from supervisor.tags import Access, TagSpec

    def add_limit(bench: object) -> None:
        db = bench.db  # type: ignore[attr-defined]
        spec = TagSpec(
            "ch0.limit_set.voltage_max", unit="V", range=(0.8, 1.9), access=Access.ENGINEER
        )
        tag = db.add(spec)
        db.update(tag, 1.8)

    async with opcua_rig(tmp_path, prepare=add_limit) as rig:
        for user, expected in (("alice", S.BadUserAccessDenied), ("carol", S.Good)):
            async with rig.client(user) as c:
                node = c.get_node(ua.NodeId("ch0.limit_set.voltage_max", await rig.ns(c)))
                wv = ua.WriteValue()
                wv.NodeId = node.nodeid
                wv.AttributeId = ua.AttributeIds.Value
                wv.Value = ua.DataValue(ua.Variant(1.7, VT.Double))
                params = ua.WriteParameters()
                params.NodesToWrite = [wv]
                (status,) = await c.uaclient.write(params)
                assert status.value == expected, user
                wv.Value = ua.DataValue(ua.Variant(5.0, VT.Double))
                (status,) = await c.uaclient.write(params)
                assert status.value == (
                    S.BadUserAccessDenied if user == "alice" else S.BadOutOfRange
                )
        assert rig.bench.db["ch0.limit_set.voltage_max"].value == 1.7


async def test_issue26_finding_4_a_setpoint_beyond_the_hard_limits_is_bad_out_of_range(
    rig: Rig,
) -> None:
    async with rig.client("alice") as c:
        ns = await rig.ns(c)
        ch1 = Channel(c, ns, "ch1")
        res = await ch1("SetManualCurrent", ua.Variant(5.0, VT.Double))
        assert res.StatusCode.value == S.BadOutOfRange
        assert text(res) == (
            "ch1: manual setpoint 5 A is beyond the channel's hard limit of 0.4 A"
            " (range -0.4 … 0.4 A); refused"
        )
        node = c.get_node(ua.NodeId("ch1.manual_current", ns))
        with pytest.raises(ua.uaerrors.BadOutOfRange):
            await node.write_value(ua.DataValue(ua.Variant(-5.0, VT.Double)))
        # The hard limits are the variable's EURange: a client can know them beforehand.
        eu = await c.get_node(ua.NodeId("ch1.manual_current.EURange", ns)).read_value()
        assert (eu.Low, eu.High) == (-0.4, 0.4)
        assert (await ch1("SetManualCurrent", ua.Variant(0.4, VT.Double))).StatusCode.is_good()
    assert rig.bench.db["ch1.manual_current"].value == 0.4
