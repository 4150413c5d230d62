"""What an integrator's node-opcua client (not asyncua) finds in Alarms & Conditions, method
calls and history (issue 31, findings 3, 5, 7 and 8):

- Acknowledge checks its EventId: one the condition never sent is Bad_EventIdUnknown, a
  String in its place Bad_InvalidArgument (Bad_TypeMismatch for that argument), none at all
  Bad_ArgumentsMissing, called on another object Bad_MethodInvalid (on the condition type
  itself Bad_NodeIdInvalid), and only the condition's unacknowledged occurrence is acknowledged:
  an EventId of an occurrence acknowledged before is Bad_ConditionBranchAlreadyAcked, even
  while a new occurrence waits. Confirm checks its EventId the same way. None of these
  refusals reaches the bench.
- A method called on an object it is not a component of (ch2's object, ch1's
  SetManualCurrent) is Bad_MethodInvalid, and nothing changes.
- The Server's AggregateFunctions folders list the aggregates HistoryRead serves, and
  Count is one of them.
- ConditionRefresh replays only retained conditions: never one back to normal.
- HistoryRead of a node that does not exist is Bad_NodeIdUnknown; of a node that exists
  but is not historised, Bad_HistoryOperationUnsupported.

One server for the module: a bench recording its history (opcuarig ``history=True``,
virtual clock; ``room.temp`` not historised, its H alarm active from the start), a
discharge on ch0 for 6 s of simulated time. Each check runs tests/interop/conditions.js
(one session, the actions it is given); the test drives the bench between two runs.
"""

from __future__ import annotations

import asyncio
import json
import os
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from commandrig import DISCHARGE, recipe
from opcuarig import CLIENT_URI, PASSWORDS, Rig, client_certificate, node, opcua_rig, pem_of, trust

from supervisor.commands import Command, Verb

pytestmark = [pytest.mark.integration, pytest.mark.asyncio(loop_scope="module")]
INTEROP = Path(__file__).resolve().parent
SCRIPT = INTEROP / "conditions.js"
TAG = "ch0.discharged_ah"  # historised, moves every scan of a discharge
NOT_KEPT = "room.temp"  # a tag, not historised
ESTOP = "s:/Bench/Alarms/estop"
ACKNOWLEDGE = "ns=0;i=9111"  # AcknowledgeableConditionType.Acknowledge
CONFIRM = "ns=0;i=9113"  # AcknowledgeableConditionType.Confirm
AGGREGATES = {
    "Average": "ns=0;i=2342",
    "TimeAverage": "ns=0;i=2343",
    "Minimum": "ns=0;i=2346",
    "Maximum": "ns=0;i=2347",
    "Count": "ns=0;i=2352",
}
SERVER_AGGREGATES = "ns=0;i=2997"  # Server/ServerCapabilities/AggregateFunctions
HISTORY_AGGREGATES = "ns=0;i=11201"  # Server/HistoryServerCapabilities/AggregateFunctions
NEVER_SENT = "00" * 16


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def rig(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Rig]:
    tmp = tmp_path_factory.mktemp("interop-conditions")
    async with opcua_rig(tmp, history=True, unhistorised=(NOT_KEPT,)) as r:
        started = r.bench.commands.execute(
            Command.channel("ch0", Verb.START, "test", recipe=recipe(tmp, DISCHARGE))
        )
        assert started.accepted, started.reason
        await r.scans(60)  # 6 s of discharge at 0.1 s per scan
        historian = r.bench.historian
        assert historian is not None and historian.writer.flush()
        yield r


async def client(rig: Rig, *actions: dict[str, Any], user: str = "alice") -> list[Any]:
    """Run ``actions`` in one node-opcua session as ``user``: their outcomes, in order."""
    tmp = rig.tmp / "node"
    tmp.mkdir(exist_ok=True)
    cert_der, key = await client_certificate(tmp, "node")
    # Trusted: the None endpoint's handling of a client certificate is finding 1's.
    trust(rig, cert_der)
    cert_pem = pem_of(cert_der, tmp / "node-cert.pem")
    cfg = {
        "endpoint": rig.server.endpoint,
        "namespace": rig.server.namespace,
        "user": user,
        "password": PASSWORDS[user],
        "applicationUri": CLIENT_URI,
        "cert": str(cert_pem),
        "key": str(key),
        "pki": str(tmp / "node-pki"),
        "actions": list(actions),
    }
    proc = await asyncio.create_subprocess_exec(
        node(),
        str(SCRIPT),
        json.dumps(cfg),
        cwd=INTEROP,
        stdout=asyncio.subprocess.PIPE,
        env={**os.environ, "NODEOPCUADEBUG": ""},
    )
    out, _ = await asyncio.wait_for(proc.communicate(), 120)
    result: dict[str, Any] = json.loads(out.decode().splitlines()[-1])
    assert proc.returncode == 0, result.get("error")
    results: list[Any] = result["results"]
    return results


def refresh() -> dict[str, Any]:
    return {"do": "refresh"}


def ack(event_id: dict[str, Any] | None, obj: str = ESTOP, method: str = ACKNOWLEDGE) -> dict:
    args = [] if event_id is None else [event_id, {"type": "LocalizedText", "value": "seen"}]
    return {"do": "call", "object": obj, "method": method, "args": args}


def event_id(hex_id: str) -> dict[str, Any]:
    return {"type": "ByteString", "hex": hex_id}


def replayed(result: dict[str, Any], name: str) -> list[dict[str, Any]]:
    assert result["status"] == "Good"
    return [e for e in result["conditions"] if e["ConditionName"] == name]


def called(result: dict[str, Any]) -> tuple[str, list[str]]:
    return result["status"], result["inputs"]


def estop_state(rig: Rig) -> str:
    alarms = rig.bench.alarms
    assert alarms is not None
    return str(alarms["estop"].state.value)


def ms(t: float) -> int:
    return int(t * 1000)


# --- finding 7: aggregates -----------------------------------------------------------------
async def test_the_aggregate_functions_folders_list_what_history_read_serves(rig: Rig) -> None:
    server, history = await client(
        rig,
        {"do": "browse", "node": SERVER_AGGREGATES},
        {"do": "browse", "node": HISTORY_AGGREGATES},
    )
    for folder in (server, history):
        assert folder["status"] == "Good"
        assert sorted(folder["names"]) == sorted(AGGREGATES)


async def test_count_is_served_per_interval_and_counts_the_stored_values(rig: Rig) -> None:
    assert rig.bench.historian is not None
    samples = rig.bench.historian.query.samples(TAG, 0.0, 1e12).samples
    start, end = ms(samples[0].t) - 1, ms(samples[-1].t) + 1
    interval_ms = 1000
    counted, averaged = await client(
        rig,
        *(
            {
                "do": "processed",
                "node": f"s:{TAG}",
                "aggregate": AGGREGATES[name],
                "start": start,
                "end": end,
                "intervalMs": interval_ms,
            }
            for name in ("Count", "Average")
        ),
    )
    assert counted["status"] == "Good"
    assert averaged["status"] == "Good"
    assert len(counted["values"]) == len(averaged["values"])
    assert {v["type"] for v in counted["values"]} == {"Int32"}
    assert {v["status"] for v in counted["values"]} == {"Good"}
    # Each interval counts its stored values: together, every sample of the range.
    in_range = [s for s in samples if start / 1000 <= s.t <= end / 1000 and s.value is not None]
    assert sum(v["value"] for v in counted["values"]) == len(in_range)
    expected = [0] * len(counted["values"])
    for s in in_range:
        expected[min(int((s.t - start / 1000) // (interval_ms / 1000)), len(expected) - 1)] += 1
    assert [v["value"] for v in counted["values"]] == expected


# --- finding 8: history of an unknown node -------------------------------------------------
async def test_history_read_of_an_unknown_node_is_bad_node_id_unknown(rig: Rig) -> None:
    span = {"start": 0, "end": 4_000_000_000_000}
    unknown, not_kept, an_object, unknown_processed = await client(
        rig,
        {"do": "raw", "node": "s:no.such.tag", **span},
        {"do": "raw", "node": f"s:{NOT_KEPT}", **span},
        {"do": "raw", "node": "s:/Bench/Channels/ch0", **span},
        {
            "do": "processed",
            "node": "s:no.such.tag",
            "aggregate": AGGREGATES["Average"],
            "intervalMs": 1000,
            **span,
        },
    )
    assert unknown["status"] == "BadNodeIdUnknown"
    assert unknown_processed["status"] == "BadNodeIdUnknown"
    # Known nodes without history keep Part 11's answer.
    assert not_kept["status"] == "BadHistoryOperationUnsupported"
    assert an_object["status"] == "BadHistoryOperationUnsupported"


# --- finding 5: a method on an object it does not belong to --------------------------------
async def test_a_method_called_on_another_channels_object_is_bad_method_invalid(
    rig: Rig,
) -> None:
    db, log = rig.bench.db, rig.bench.commands.log
    before = (db["ch1.manual_current"].value, db["ch2.manual_current"].value, len(log))
    (wrong, bench_method) = await client(
        rig,
        {
            "do": "call",
            "object": "s:/Bench/Channels/ch2",
            "method": "s:/Bench/Channels/ch1/SetManualCurrent",
            "args": [{"type": "Double", "value": 0.15}],
        },
        {
            "do": "call",
            "object": "s:/Bench/Channels/ch2",
            "method": "s:/Bench/UnforceTag",
            "args": [{"type": "String", "value": "room.temp"}],
        },
    )
    assert wrong["status"] == "BadMethodInvalid"
    assert bench_method["status"] == "BadMethodInvalid"
    await rig.scans(1)
    assert (db["ch1.manual_current"].value, db["ch2.manual_current"].value, len(log)) == before


# --- findings 3 and 8: Acknowledge's EventId, ConditionRefresh of a closed condition -------
async def estop_back_to_normal(rig: Rig) -> None:
    """Released, acknowledged and reset: each test below starts from there (in any order)."""
    sim = rig.bench.sim
    assert sim is not None
    sim.press_estop(False)
    await rig.scans(5)
    rig.bench.commands.execute(Command.channel("ch0", Verb.ACKNOWLEDGE, "test"))
    await rig.scans(2)
    assert estop_state(rig) == "normal"


async def estop_pressed(rig: Rig) -> dict[str, Any]:
    """The e-stop pressed: its condition as a refresh shows it (active, unacknowledged)."""
    await estop_back_to_normal(rig)
    sim = rig.bench.sim
    assert sim is not None
    sim.press_estop(True)
    await rig.scans(5)
    assert estop_state(rig) == "active, unacknowledged"
    (seen,) = await client(rig, refresh())
    (pressed,) = replayed(seen, "estop")
    assert (pressed["Retain"], pressed["ActiveState.Id"], pressed["AckedState.Id"]) == (
        True,
        True,
        False,
    )
    return pressed


async def test_acknowledge_refuses_an_eventid_never_sent_and_a_wrong_argument(rig: Rig) -> None:
    pressed = await estop_pressed(rig)
    (seen,) = await client(rig, refresh())
    (room,) = replayed(seen, "room.temp.H")
    log = rig.bench.commands.log
    before = len(log)
    never, text, missing, other, wrong_object, the_type = await client(
        rig,
        ack(event_id(NEVER_SENT)),
        ack({"type": "String", "value": pressed["EventId"]}),
        ack(None),
        ack(event_id(room["EventId"])),  # another condition's occurrence
        ack(event_id(pressed["EventId"]), obj="s:/Bench/Channels/ch0"),
        ack(event_id(pressed["EventId"]), obj="ns=0;i=2881"),  # AcknowledgeableConditionType
    )
    assert called(never) == ("BadEventIdUnknown", ["Good", "Good"])
    assert called(text) == ("BadInvalidArgument", ["BadTypeMismatch", "Good"])
    assert missing["status"] == "BadArgumentsMissing"
    assert called(other)[0] == "BadEventIdUnknown"
    assert wrong_object["status"] == "BadMethodInvalid"
    assert the_type["status"] == "BadNodeIdInvalid"  # Part 9 §5.7.3
    assert len(log) == before  # none of them reached the bench
    await rig.scans(1)
    assert estop_state(rig) == "active, unacknowledged"
    (acked,) = await client(rig, ack(event_id(pressed["EventId"])))
    assert acked["status"] == "Good"
    await rig.scans(1)
    assert estop_state(rig) == "active, acknowledged"
    assert [(e.actor, e.accepted) for e in list(log)[before:]] == [("opcua:alice", True)]


async def test_an_occurrence_acknowledged_before_does_not_acknowledge_a_new_one(
    rig: Rig,
) -> None:
    """The operator saw the first press, not the second: its EventId answers the first."""
    first = await estop_pressed(rig)
    (acked,) = await client(rig, ack(event_id(first["EventId"])))
    assert acked["status"] == "Good"
    second = await estop_pressed(rig)
    assert second["EventId"] != first["EventId"]
    log = rig.bench.commands.log
    before = len(log)
    stale, stale_confirm, confirm_never = await client(
        rig,
        ack(event_id(first["EventId"])),
        ack(event_id(first["EventId"]), method=CONFIRM),
        ack(event_id(NEVER_SENT), method=CONFIRM),
    )
    assert stale["status"] == "BadConditionBranchAlreadyAcked"
    assert stale_confirm["status"] == "BadConditionBranchAlreadyConfirmed"
    assert confirm_never["status"] == "BadEventIdUnknown"
    assert len(log) == before
    await rig.scans(1)
    assert estop_state(rig) == "active, unacknowledged"
    (acked,) = await client(rig, ack(event_id(second["EventId"])))
    assert acked["status"] == "Good"


async def test_condition_refresh_does_not_replay_a_condition_back_to_normal(rig: Rig) -> None:
    await estop_pressed(rig)
    await estop_back_to_normal(rig)
    (closed,) = await client(rig, refresh())
    assert replayed(closed, "estop") == []
    assert [e["Retain"] for e in closed["conditions"]] == [True] * len(closed["conditions"])
    assert replayed(closed, "room.temp.H")  # still active: still replayed


async def test_condition_refresh_never_replays_a_condition_the_alarm_model_closed(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Even when the closing event never reached the server: the feed's bounded queue drops
    what does not fit, and a closing event may still be on its way when a client that just
    reset the alarm refreshes."""
    await estop_pressed(rig)
    feed = rig.server.feed
    on_alarm = feed.on_alarm

    def closing_events_lost(view: Any) -> None:
        if view.id != "estop" or view.retained:
            on_alarm(view)

    monkeypatch.setattr(feed, "on_alarm", closing_events_lost)
    await estop_back_to_normal(rig)
    (closed,) = await client(rig, refresh())
    assert replayed(closed, "estop") == []
    assert [e["Retain"] for e in closed["conditions"]] == [True] * len(closed["conditions"])
    assert replayed(closed, "room.temp.H")
