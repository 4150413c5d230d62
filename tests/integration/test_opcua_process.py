"""The OPC UA server in a process of its own (ADR 0029, issue 30): whatever the server's
process does — killed, hung, sending what it should not — the bench scans on, and the
server comes back with the bench's values as they are then.

The bench scans on the real clock (as ``supervisor run``); its server is ``OpcUaProcess``;
the client is asyncua's (node-opcua's interoperability test runs against this arrangement
too: tests/integration/test_opcua_interop.py, ``process``).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from asyncua import ua
from opcuarig import Rig, call, opcua_rig, text

from supervisor.publish.opcua import OpcUaProcess
from supervisor.testing import wait_until

pytestmark = pytest.mark.integration

RESTART_WAIT_S = 60.0  # a restart imports asyncua and builds the address space again


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path, real_clock=True, process=True) as r:
        yield r


def server_of(rig: Rig) -> OpcUaProcess:
    server = rig.server
    assert isinstance(server, OpcUaProcess)
    return server


async def voltage_over_opcua(rig: Rig) -> ua.DataValue:
    async with rig.client() as c:
        node = c.get_node(ua.NodeId("ch0.voltage", await rig.ns(c)))
        return await node.read_data_value(raise_on_bad_status=False)


async def scans_go_on(rig: Rig, n: int = 20) -> None:
    """The bench scans ``n`` more times (it scans at its period on the real clock)."""
    stats = rig.bench.engine.stats
    target = stats.count + n
    await wait_until(lambda: stats.count >= target, f"{n} more scans")


async def test_the_server_runs_in_another_process_and_serves_the_benchs_values(rig: Rig) -> None:
    server = server_of(rig)
    assert server.pid is not None and server.pid != os.getpid()
    await scans_go_on(rig)
    seen = await voltage_over_opcua(rig)
    assert seen.StatusCode.is_good()
    assert seen.Value.Value == pytest.approx(rig.bench.db["ch0.voltage"].value, abs=0.05)


async def test_a_killed_server_is_started_again_while_the_bench_scans_on(rig: Rig) -> None:
    server = server_of(rig)
    first = server.pid
    assert first is not None
    server.kill()
    await scans_go_on(rig)  # the scan does not wait for its server
    await wait_until(
        lambda: server.starts == 2 and server.serving, "the server started again", RESTART_WAIT_S
    )
    assert server.pid != first
    await wait_until(lambda: rig.bench.db["opcua.restarts"].value == 1, "the restart shown")
    seen = await voltage_over_opcua(rig)
    assert seen.StatusCode.is_good()
    assert seen.Value.Value == pytest.approx(rig.bench.db["ch0.voltage"].value, abs=0.05)


async def test_a_hung_server_is_killed_and_started_again(rig: Rig) -> None:
    server = server_of(rig)
    server.hang_s = 2.0
    first = server.pid
    assert first is not None
    os.kill(first, signal.SIGSTOP)  # alive, silent: what a deadlocked server looks like
    try:
        await scans_go_on(rig)
        await wait_until(
            lambda: server.starts == 2 and server.serving,
            "the hung server replaced",
            RESTART_WAIT_S,
        )
    finally:
        with contextlib.suppress(ProcessLookupError):  # killed, as it should be
            os.kill(first, signal.SIGCONT)
    with pytest.raises(ProcessLookupError):
        os.kill(first, 0)
    seen = await voltage_over_opcua(rig)
    assert seen.StatusCode.is_good()


async def channel_call(rig: Rig, method: str, *args: ua.Variant) -> ua.CallMethodResult:
    async with rig.client("alice") as c:
        ns = await rig.ns(c)
        node = ua.NodeId("/Bench/Channels/ch0", ns)
        return await call(c, node, ua.NodeId(f"/Bench/Channels/ch0/{method}", ns), *args)


async def test_a_method_call_is_run_by_the_benchs_command_path(rig: Rig) -> None:
    res = await channel_call(rig, "Stop")  # nothing runs: the chain's own refusal
    assert not res.StatusCode.is_good()
    assert text(res) == "ch0: stop is not allowed while Idle (allowed: start)"
    logged = [e for e in rig.bench.commands.log if e.actor == "opcua:alice"]
    assert [(e.command.split()[0], e.accepted) for e in logged] == [("stop", False)]


async def test_a_request_after_closing_is_refused_as_the_outputs_go_safe(rig: Rig) -> None:
    server_of(rig).closing()
    res = await channel_call(rig, "Stop")
    assert not res.StatusCode.is_good()
    assert "outputs going safe" in text(res)
    assert not [e for e in rig.bench.commands.log if e.actor == "opcua:alice"]


async def test_the_server_process_ends_with_the_bench(tmp_path: Path) -> None:
    async with opcua_rig(tmp_path, real_clock=True, process=True) as r:
        pid = server_of(r).pid
        assert pid is not None
    await asyncio.sleep(0)
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
