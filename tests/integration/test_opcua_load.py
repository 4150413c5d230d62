"""Clients that misbehave or crowd the server: a client killed mid-subscription, twenty
connecting at once. The scan keeps its period — shown by its own counters (overruns, missed
deadlines), never by a timing claim — and the other clients keep their updates.

The clients run in a process of their own (supervisor/bench/opcuaclients.py): on the bench's loop
they would be part of what is measured.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from asyncua import ua
from opcuarig import Collector, Rig, eventually, opcua_rig

from supervisor.testing import wait_until

# It asserts the scan kept its timing (no stall, no overrun) under load it makes itself:
# it runs alone, after the tests that run in parallel (Makefile: the "quiet" marker).
pytestmark = [pytest.mark.integration, pytest.mark.quiet]
TAGS = (
    ",".join(
        f"ch{k}.{t}" for k in range(4) for t in ("voltage", "current", "chain.step_time", "power")
    )
    + ",scan.count,scan.duration_s,scan.jitter_s,opcua.clients"
)


async def clients(rig: Rig, n: int, seconds: float) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "supervisor.bench.opcuaclients",
        rig.server.endpoint,
        rig.server.namespace,
        "--clients",
        str(n),
        "--tags",
        TAGS,
        "--seconds",
        str(seconds),
        stdout=asyncio.subprocess.PIPE,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )


@pytest.fixture
async def running(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path, real_clock=True) as r:
        yield r


async def test_a_client_killed_mid_subscription_leaves_the_others_served(running: Rig) -> None:
    rig, db = running, running.bench.db
    victim = await clients(rig, 1, 0)
    try:
        assert victim.stdout is not None
        assert await asyncio.wait_for(victim.stdout.readline(), 60) == b"subscribed\n"
        got = Collector()
        async with rig.client("bob") as c:
            ns = await rig.ns(c)
            sub = await c.create_subscription(20, got)
            await sub.subscribe_data_change([c.get_node(ua.NodeId("scan.count", ns))])
            await wait_until(lambda: db["opcua.clients"].value == 2, "two clients")
            victim.send_signal(signal.SIGKILL)  # no CloseSession, no goodbye: a lost link
            await victim.wait()
            await wait_until(lambda: db["opcua.clients"].value == 1, "the lost client gone")
            seen = len(got.values("scan.count"))
            await eventually(lambda: len(got.values("scan.count")) > seen + 5, "more updates")
            await sub.delete()
    finally:
        if victim.returncode is None:
            victim.kill()
            await victim.wait()
    st = rig.bench.engine.stats
    assert (st.overruns, st.skipped) == (0, 0)


async def test_twenty_clients_at_once_are_served_and_the_scan_keeps_its_period(
    running: Rig,
) -> None:
    rig, db = running, running.bench.db
    proc = await clients(rig, 20, 3.0)
    peak = 0

    async def watch() -> None:
        nonlocal peak
        while True:
            peak = max(peak, int(db["opcua.clients"].value or 0))
            await asyncio.sleep(0.05)

    watcher = asyncio.create_task(watch())
    try:
        out, _ = await asyncio.wait_for(proc.communicate(), 120)
    finally:
        watcher.cancel()
        await asyncio.gather(watcher, return_exceptions=True)
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    lines = out.decode().splitlines()
    assert lines[0] == "subscribed", lines
    result = json.loads(lines[-1])
    assert result["errors"] == []
    assert len(result["updates"]) == 20
    assert all(n > 0 for n in result["updates"]), result["updates"]
    assert peak == 20
    st = rig.bench.engine.stats
    assert st.count > 0
    assert (st.overruns, st.skipped) == (0, 0)  # the scan kept its period
    assert db["scan.logic_errors"].value == 0
