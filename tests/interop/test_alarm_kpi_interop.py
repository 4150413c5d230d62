"""The alarm KPI tags (issue 34, ADR 0048) read by an integrator's node-opcua client, the
independent peer of asyncua: after a chattering input (4 activations in 40 s) on the
simulated bench, ``alarms.per_10min`` and ``alarms.chattering`` read over OPC UA are the
hand count, Good. One server (opcuarig: commandrig's bench, virtual clock);
tests/interop/alarm_kpi.js reads the nodes in one session.
"""

from __future__ import annotations

import asyncio
import json
import os
from pathlib import Path
from typing import Any

import pytest
from opcuarig import CLIENT_URI, PASSWORDS, Rig, client_certificate, node, opcua_rig, pem_of, trust

from supervisor.app import Bench
from supervisor.safety import Severity, Transition

pytestmark = pytest.mark.integration

INTEROP = Path(__file__).resolve().parent
SCRIPT = INTEROP / "alarm_kpi.js"
TAGS = ["alarms.per_10min", "alarms.per_day", "alarms.chattering", "alarms.chattering_ids"]


async def read(rig: Rig, tags: list[str]) -> dict[str, Any]:
    tmp = rig.tmp / "node"
    tmp.mkdir(exist_ok=True)
    cert_der, key = await client_certificate(tmp, "node")
    trust(rig, cert_der)
    cfg = {
        "endpoint": rig.server.endpoint,
        "namespace": rig.server.namespace,
        "user": "alice",
        "password": PASSWORDS["alice"],
        "applicationUri": CLIENT_URI,
        "cert": str(pem_of(cert_der, tmp / "node-cert.pem")),
        "key": str(key),
        "pki": str(tmp / "node-pki"),
        "tags": tags,
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
    last = [line for line in out.decode().splitlines() if line.startswith("{")][-1]
    result: dict[str, Any] = json.loads(last)
    assert proc.returncode == 0, result.get("error")
    return result


def declare(bench: Bench) -> None:
    bench.alarms.declare("di.door", severity=Severity.MEDIUM)


async def test_node_opcua_reads_the_hand_count(tmp_path: Path) -> None:
    async with opcua_rig(tmp_path, prepare=declare) as rig:
        bench = rig.bench
        own = sum(1 for e in bench.alarms.history if e.transition is Transition.ACTIVATED)
        door = bench.alarms["di.door"]
        for _ in range(4):  # raised 5 s, cleared 5 s: 4 activations in 40 s
            bench.alarms.set(door, True, "door open")
            await rig.scans(50, settle=False)
            bench.alarms.set(door, False)
            await rig.scans(50, settle=False)
        await rig.scans(1)
        got = await read(rig, TAGS)
    assert got["status"] == dict.fromkeys(TAGS, "Good")
    assert got["values"] == {
        "alarms.per_10min": own + 4,  # all within the first 10 minutes of the clock
        "alarms.per_day": own + 4,
        "alarms.chattering": 1,
        "alarms.chattering_ids": "di.door",
    }
