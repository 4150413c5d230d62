"""Interoperability: node-opcua-client (not asyncua) against the bench's server, without
and with SignAndEncrypt. tests/interop/interop.js browses, reads a value with its EU and
EURange, subscribes, calls Start, receives the step event and, after a ConditionRefresh, an
alarm condition; it prints what it saw as JSON, checked here.

node-opcua comes from npm: ``make node_modules`` (``make unit`` runs it) installs the
version locked in tests/interop/package-lock.json into tests/interop/node_modules.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from commandrig import DISCHARGE, recipe
from opcuarig import CLIENT_URI, PASSWORDS, Rig, client_certificate, node, opcua_rig, pem_of, trust

pytestmark = pytest.mark.integration
INTEROP = Path(__file__).resolve().parents[1] / "interop"
SCRIPT = INTEROP / "interop.js"


@pytest.fixture(params=[False, True], ids=["thread", "process"])
async def running(tmp_path: Path, request: pytest.FixtureRequest) -> AsyncIterator[Rig]:
    """The server on a thread of the bench's process, and in a process of its own (what
    ``supervisor run`` runs, ADR 0029): an independent client sees the same server."""
    async with opcua_rig(tmp_path, real_clock=True, process=request.param) as r:
        yield r


async def run_client(rig: Rig, secure: bool, tmp: Path) -> dict[str, object]:
    cert_der, key = await client_certificate(tmp, "node")
    if secure:
        # On None the certificate is ignored (Part 4 §5.7.2.2): the None case runs with a
        # certificate nobody trusted, as node-opcua's default client comes (issue 31).
        trust(rig, cert_der)
    cert_pem = pem_of(cert_der, tmp / "node-cert.pem")
    cfg = {
        "endpoint": rig.server.endpoint,
        "namespace": rig.server.namespace,
        "recipe": recipe(tmp, DISCHARGE, f"d-{secure}.yaml"),
        "user": "alice",
        "password": PASSWORDS["alice"],
        "secure": secure,
        "applicationUri": CLIENT_URI,
        "cert": str(cert_pem),
        "key": str(key),
        "pki": str(tmp / "node-pki"),
    }
    proc = await asyncio.create_subprocess_exec(
        node(), str(SCRIPT), json.dumps(cfg), cwd=INTEROP, stdout=asyncio.subprocess.PIPE
    )
    out, _ = await asyncio.wait_for(proc.communicate(), 120)
    result: dict[str, object] = json.loads(out.decode().splitlines()[-1])
    assert proc.returncode == 0, result.get("error")
    return result


@pytest.mark.parametrize("secure", [False, True], ids=["None", "SignAndEncrypt"])
async def test_node_opcua_browses_reads_subscribes_calls_and_receives_events(
    running: Rig, tmp_path: Path, secure: bool
) -> None:
    seen = await run_client(running, secure, tmp_path)
    assert seen["channels"] == ["ch0", "ch1", "ch2", "ch3"]
    assert seen["voltage"] == {
        "value": pytest.approx(running.bench.db["ch0.voltage"].value, abs=0.05),
        "status": "Good",
    }
    low, high = running.bench.db["ch0.voltage"].spec.range or (0, 0)
    assert seen["euRange"] == {"low": pytest.approx(low), "high": pytest.approx(high)}
    assert seen["engineeringUnits"] == {
        "unitId": 5655636,
        "displayName": "V",
        "namespaceUri": "http://www.opcfoundation.org/UA/units/un/cefact",
    }
    assert seen["typeDefinition"] == ["ns=0;i=2368"]  # AnalogItemType
    start = seen["start"]
    assert isinstance(start, dict) and start["status"] == "Good"
    assert "started" in start["result"]
    assert seen["refused"] == {
        "status": "BadInvalidArgument",
        "result": "SetManualCurrent: Current must be a Double or Float, got String '0.3'",
    }
    counts = seen["counts"]
    assert isinstance(counts, list) and len(counts) >= 3 and counts == sorted(counts)
    events = seen["events"]
    assert isinstance(events, list)
    steps = [e for e in events if str(e["Message"]).startswith("starting step")]
    assert steps and steps[0]["SourceName"] == "ch0"
    alarms = [e for e in events if e["ConditionName"]]
    room = next(e for e in alarms if e["ConditionName"] == "room.temp.H")
    assert (room["EventType"], room["Severity"], room["Retain"]) == ("ns=0;i=2915", 500, True)
    assert seen["refresh"] == "Good"
    commands = [e for e in running.bench.commands.log if e.actor == "opcua:alice"]
    assert [(e.command.split()[0], e.accepted) for e in commands] == [("start", True)]
