"""``supervisor run`` stops truthfully (finding 5): "stopped: all outputs safe" and exit 0
only when every device confirmed its safe state; an unreachable supply makes it say which
device and why, and exit 1. A clean stop gives the supply back to its front panel.

Wall clock: the supervisor is a real process talking SCPI over loopback to a simulated
supply in this process (bounded waits, no timing assertion). ``Bench.shutdown`` itself is
specified on virtual time in tests/unit/test_bench_shutdown.py.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import urllib.request
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import pytest
import yaml
from ea_rig import ea_only_io_map

from supervisor.core.clock import RealClock
from supervisor.devices.ea.sim import EaTcpSimulator
from supervisor.sim.battery import make_model
from supervisor.sim.plant import BenchPlant
from supervisor.testing import wait_until

pytestmark = pytest.mark.integration


def _put(url: str, body: object) -> None:
    req = urllib.request.Request(
        url,
        data=json.dumps(body).encode(),
        method="PUT",
        headers={"Content-Type": "application/json"},
    )
    with urllib.request.urlopen(req, timeout=5) as resp:
        resp.read()


@asynccontextmanager
async def supervised_supply(
    tmp_path: Path,
) -> AsyncIterator[tuple[EaTcpSimulator, str, subprocess.Popen[str]]]:
    """A simulated EA supply served here, ``supervisor run`` driving it from another process
    (its HTTP API URL); on exit the process is stopped by its pid and the supply stopped."""
    plant = BenchPlant(RealClock(), make_model("liion-pack", cells_series=4, capacity_ah=10.0))
    plant.set_contactor(True)  # no ADAM on this bench: the contactor is not part of it
    ea = EaTcpSimulator(plant)
    await ea.start()
    io_map = ea_only_io_map("stop", {"port": ea.port, "poll_period_s": 0.1, "watchdog_s": 1.0})
    io_map["hmi"] = {"port": 0}
    path = tmp_path / "stop.yaml"
    path.write_text(yaml.safe_dump(io_map), encoding="utf-8")
    proc = subprocess.Popen(  # noqa: ASYNC220 - Popen only starts it; waits go to threads
        [sys.executable, "-m", "supervisor.cli.main", "run", str(path)],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    try:
        assert proc.stdout is not None
        url = None
        while url is None:
            line = await asyncio.to_thread(proc.stdout.readline)
            assert line, "supervisor exited before listening"
            if m := re.search(r"HTTP API listening on (http://127\.0\.0\.1:\d+/api)", line):
                url = m.group(1)
        await wait_until(lambda: plant.supply.remote, "the supervisor took remote control")
        yield ea, url, proc
    finally:
        if proc.poll() is None:
            proc.kill()
            await asyncio.to_thread(proc.wait)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
        await ea.stop()


async def stop(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    proc.send_signal(signal.SIGTERM)
    out, err = await asyncio.to_thread(proc.communicate, None, 30)
    return proc.returncode, out, err


async def test_sigterm_with_the_supply_unreachable_says_so_and_exits_1(tmp_path: Path) -> None:
    async with supervised_supply(tmp_path) as (ea, _url, proc):
        await ea.stop()  # the supply drops off the network
        code, out, err = await stop(proc)
    assert code == 1, err
    assert "stopped: all outputs safe" not in out
    (line,) = [ln for ln in out.splitlines() if ln.startswith("stopped:")]
    assert line.startswith("stopped: safe state NOT confirmed for ea: ")
    assert "not connected" in line
    assert "Traceback" not in err


async def test_a_clean_sigterm_switches_the_supply_off_releases_its_lock_and_exits_0(
    tmp_path: Path,
) -> None:
    async with supervised_supply(tmp_path) as (ea, url, proc):
        await asyncio.to_thread(_put, f"{url}/tags/ch0.manual_current", {"value": 2.0})
        await asyncio.to_thread(_put, f"{url}/tags/ch0.enable", {"value": True})
        await wait_until(lambda: ea.plant.pack_current_a > 1.9, "charging")
        code, out, err = await stop(proc)
        assert code == 0, err
        assert out.splitlines()[-1] == "stopped: all outputs safe"
        await wait_until(lambda: not ea.remote, "the remote lock released")
        assert not ea.plant.supply.output_on
        assert ea.lines[-1] == "SYST:LOCK OFF"
        assert ea.watchdog_trips == 0  # released by the supervisor, not by the watchdog
