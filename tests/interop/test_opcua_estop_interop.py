"""The software e-stop over OPC UA from an integrator's node-opcua client (not asyncua; issue
32, finding 7): ``EmergencyStop`` and ``ResetEmergencyStop`` are methods of the Bench object.
A viewer's call is Bad_UserAccessDenied and trips nothing; an operator's trips every channel
(the ``estop`` alarm, with the session's user as the actor); the reset before the alarm is
acknowledged is Bad_InvalidState with the reason in its ``Result``, after it Good.

One server (opcuarig: commandrig's bench, virtual clock); each call runs
tests/interop/conditions.js in one session of the given user.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio
from opcuarig import Rig, opcua_rig
from test_opcua_conditions_interop import client

from supervisor.commands import Command, Verb
from supervisor.safety import AlarmState

pytestmark = [pytest.mark.integration, pytest.mark.asyncio(loop_scope="module")]
BENCH = "s:/Bench"


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def rig(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Rig]:
    tmp: Path = tmp_path_factory.mktemp("interop-estop")
    async with opcua_rig(tmp) as r:
        yield r


def call(method: str, obj: str = BENCH) -> dict[str, object]:
    return {"do": "call", "object": obj, "method": f"{BENCH}/{method}", "args": []}


async def test_a_viewer_is_denied_an_operator_trips_every_channel_and_resets_once_acked(
    rig: Rig,
) -> None:
    bench, db = rig.bench, rig.bench.db
    channels = [c.name for c in bench.cfg.channels]
    (browse,) = await client(rig, {"do": "browse", "node": BENCH})
    assert {"EmergencyStop", "ResetEmergencyStop"} <= set(browse["names"])

    (denied,) = await client(rig, call("EmergencyStop"), user="bob")
    assert denied["status"] == "BadUserAccessDenied"
    await rig.scans(2)
    assert bench.alarms["estop"].state is AlarmState.NORMAL
    assert all(db[f"{ch}.state"].value != "faulted" for ch in channels)

    # On a channel's object it is no method of that object: nothing pressed.
    (wrong,) = await client(rig, call("EmergencyStop", obj="s:/Bench/Channels/ch0"))
    assert wrong["status"] == "BadMethodInvalid"

    (pressed,) = await client(rig, call("EmergencyStop"))
    assert pressed["status"] == "Good", pressed
    assert str(pressed["outputs"][0]).startswith("software e-stop pressed by opcua:alice")
    await rig.scans(3)
    assert bench.alarms["estop"].message == "Software e-stop pressed by opcua:alice"
    for ch in channels:
        assert db[f"{ch}.state"].value == "faulted", ch
        assert db[f"{ch}.current_cmd"].value == 0.0

    early, again = await client(rig, call("ResetEmergencyStop"), call("EmergencyStop"))
    assert early["status"] == "BadInvalidState"
    assert "acknowledge the e-stop first" in str(early["outputs"][0])
    assert again["status"] == "Good"  # a second press is never refused
    assert "already pressed by opcua:alice" in str(again["outputs"][0])

    assert bench.commands.execute(Command.alarm("estop", Verb.ACKNOWLEDGE, "test")).accepted
    (reset,) = await client(rig, call("ResetEmergencyStop"))
    assert reset["status"] == "Good", reset
    await rig.scans(2)
    assert bench.alarms["estop"].state is AlarmState.NORMAL
    assert [
        (e.actor, e.command, e.accepted)
        for e in bench.commands.log
        if e.command.startswith("estop")
    ] == [
        ("opcua:bob", "estop", False),
        ("opcua:alice", "estop", True),
        ("opcua:alice", "estop_reset", False),
        ("opcua:alice", "estop", True),
        ("opcua:alice", "estop_reset", True),
    ]
