"""One bench, one supervisor (docs/design.md "Safety"; users' finding 2, the lock side).

A second ``supervisor run`` of a bench that is already running used to connect to the
running bench's devices and switch them safe before it failed on the HTTP port. The lock
on the state directory is taken before any device, simulator or port is touched: the
second instance exits 2 naming the first, and the devices never see it.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from supervisor.app.lock import BenchBusy, BenchLock
from supervisor.app.simulation import SimulatedBench, build_simulation
from supervisor.core.clock import RealClock
from supervisor.devices.registry import load_bench
from supervisor.testing import free_tcp_port

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration


# --- the lock itself -----------------------------------------------------------------------
def test_the_lock_is_exclusive_and_names_its_holder(tmp_path: Path) -> None:
    first = BenchLock(tmp_path / "var", "sim").acquire()
    try:
        assert (tmp_path / "var" / "supervisor.lock").read_text() == f"{os.getpid()}\n"
        with pytest.raises(BenchBusy) as info:
            BenchLock(tmp_path / "var", "sim").acquire()
        assert str(info.value) == (
            f"bench 'sim' is already run by pid {os.getpid()}"
            f" (lock {tmp_path / 'var' / 'supervisor.lock'})"
        )
    finally:
        first.release()
    with BenchLock(tmp_path / "var", "sim") as again:  # free once released
        assert again.held


def test_the_kernel_drops_the_lock_of_a_killed_holder(tmp_path: Path) -> None:
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "from supervisor.app.lock import BenchLock\n"
            f"BenchLock({str(tmp_path / 'var')!r}, 'sim').acquire()\n"
            "print('locked', flush=True)\n"
            "time.sleep(60)\n",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "locked\n"
        with pytest.raises(BenchBusy, match=f"pid {holder.pid} "):
            BenchLock(tmp_path / "var", "sim").acquire()
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait(timeout=10)
        with BenchLock(tmp_path / "var", "sim") as lock:  # no stale lock to clean up
            assert lock.held
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
        if holder.stdout is not None:
            holder.stdout.close()


# --- two supervisors on one bench ----------------------------------------------------------
def seed002_map(tmp_path: Path) -> Path:
    """sim.yaml without the Chadèche stack, on free loopback ports, state in tmp_path."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["hmi"]["login"] = False  # its HTTP clients do not log in
    del data["devices"]["chadeche"]
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    for name in ("adam", "ea", "bms"):
        data["devices"][name]["port"] = free_tcp_port()
    data["hmi"]["port"] = free_tcp_port()  # both instances ask for the same port
    data.pop("opcua", None)  # not part of this test (and 4840 may be taken)
    data.pop("modbus_server", None)  # nor Modbus (1502 may be taken)
    data["state_dir"] = str(tmp_path / "var")
    path = tmp_path / "seed002.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def _counting(handler: Callable[..., Awaitable[None]], n: list[int]) -> Callable[..., Any]:
    async def counted(*args: Any) -> None:
        n.append(1)
        await handler(*args)

    return counted


@pytest.fixture
async def devices(tmp_path: Path) -> AsyncIterator[tuple[Path, dict[str, list[int]]]]:
    """The bench's devices, simulated in this process, counting the clients they accept."""
    io_map = seed002_map(tmp_path)
    sim = build_simulation(load_bench(io_map), RealClock())
    assert isinstance(sim, SimulatedBench)
    accepted: dict[str, list[int]] = {"adam": [], "ea": [], "bms": []}
    ea = sim.devices["ea"]
    ea._serve = _counting(ea._serve, accepted["ea"])  # type: ignore[attr-defined]
    server = sim.devices["bms"].server  # type: ignore[attr-defined]
    server._handle = _counting(server._handle, accepted["bms"])
    await sim.start()
    adam = sim.devices["adam"]
    adam._server.trace_connect = (  # type: ignore[attr-defined]
        lambda connected: accepted["adam"].append(1) if connected else None
    )
    try:
        yield io_map, accepted
    finally:
        await sim.stop()


def _get(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=5) as resp:
        return json.loads(resp.read())


async def test_a_second_supervisor_exits_2_without_touching_the_devices(
    tmp_path: Path, devices: tuple[Path, dict[str, list[int]]]
) -> None:
    io_map, accepted = devices
    cmd = [sys.executable, "-m", "supervisor.cli.main", "run", "--no-sim", str(io_map)]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    first = await asyncio.create_subprocess_exec(
        *cmd,
        cwd=tmp_path,
        env=env,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.DEVNULL,
    )
    try:
        assert first.stdout is not None
        url = ""
        while True:
            line = (await asyncio.wait_for(first.stdout.readline(), 30)).decode()
            assert line, "the first supervisor ended before it said where it listens"
            if line.startswith("HTTP API listening on "):
                url = line.split()[-1].removesuffix("/tags")
            if line.startswith("Ctrl-C"):
                break
        state: dict[str, Any] = {}

        async def connected() -> bool:
            for tag in ("ea.connected", "adam.connected", "bms.connected"):
                state[tag] = (await asyncio.to_thread(_get, f"{url}/tags/{tag}"))["value"]
            return all(state.values())

        deadline = time.monotonic() + 30
        while not await connected():
            assert time.monotonic() < deadline, f"the first supervisor never connected: {state}"
            await asyncio.sleep(0.1)
        await asyncio.sleep(1.0)  # the first one's connections settle (python-can may retry)
        before = {k: len(v) for k, v in accepted.items()}
        assert all(before.values()), before

        second = await asyncio.create_subprocess_exec(
            *cmd,
            cwd=tmp_path,
            env=env,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )
        out, err = await asyncio.wait_for(second.communicate(), 60)
        assert second.returncode == 2
        # The devices never saw a second client; the first keeps its connections.
        assert {k: len(v) for k, v in accepted.items()} == before
        lock = tmp_path / "var" / "supervisor.lock"
        assert err.decode().strip() == (
            f"supervisor: bench 'sim' is already run by pid {first.pid} (lock {lock})"
        )
        assert out == b""
        assert await connected()
        assert (await asyncio.to_thread(_get, f"{url}/tags/ch4.state"))["value"] == "idle"
    finally:
        if first.returncode is None:
            first.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(first.wait(), 20)
            except TimeoutError:
                first.kill()
                await first.wait()
    assert first.returncode == 0
