"""The battery contactor opens when the supervisor dies, over real protocols and real
processes (finding 3): ``supervisor sim`` serves the seed 002 devices in one process,
``supervisor run --no-sim`` drives them from another; the supervisor is SIGKILLed while
charging and the simulated plant (``GET /api/sim/state``) must see its contactor open.

Wall clock (bounded waits, never a timing assertion): the served units enforce their
watchdogs with checker tasks on the real clock. The same behaviour on virtual time, in
process: tests/unit/test_contactor_watchdogs.py.
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
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml
from adam_rig import AdamRig, open_rig, reconnect_on_every_poll
from rig_transports import TCP

from supervisor.core.clock import RealClock
from supervisor.testing import free_tcp_port, wait_until
from supervisor.testing.waiting import SETTLE_S

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration


# --- the served unit's host watchdog, on the real clock ---------------------------------------
@pytest.fixture
async def served(monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[AdamRig]:
    reconnect_on_every_poll(monkeypatch)
    async with open_rig(TCP, RealClock(), poll_period_s=0.1, host_watchdog_s=0.5) as rig:
        yield rig


async def test_a_served_unit_switches_its_relays_off_by_itself_when_the_host_goes_silent(
    served: AdamRig,
) -> None:
    await served.driver.poll()
    assert served.driver.connected, served.driver.last_error
    served.driver.write("slot3.do0", True)
    await served.driver.flush()
    assert served.unit.relay_state(3, 0)
    # Nothing is asked any more (the driver is not polled); the unit's checker acts.
    await wait_until(lambda: not served.unit.relay_state(3, 0), "the relay switched off")
    assert served.relay_calls[(3, 0)][-1] is False
    assert served.unit.host_watchdog_trips == 1


# --- two processes -----------------------------------------------------------------------------
def http(method: str, url: str, body: object | None = None) -> Any:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        url, data=data, method=method, headers={"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(req, timeout=5) as resp:
        return json.loads(resp.read())


def seed002_map(tmp_path: Path, change: Callable[[dict[str, Any]], None] | None = None) -> Path:
    """sim.yaml's seed 002 devices and their channel, on free loopback ports."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["hmi"]["login"] = False  # its HTTP clients do not log in
    del data["devices"]["chadeche"]
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    for name in ("adam", "ea", "bms"):
        data["devices"][name]["port"] = free_tcp_port()
    data["hmi"]["port"] = 0
    data.pop("opcua", None)  # not part of this test (and 4840 may be taken)
    data.pop("modbus_server", None)  # nor Modbus (1502 may be taken)
    if change is not None:
        change(data)
    path = tmp_path / "seed002.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


@dataclass
class Processes:
    sim: subprocess.Popen[str]
    supervisor: subprocess.Popen[str]
    control_url: str
    """``supervisor sim``'s control API (``…/api``)."""
    api_url: str
    """``supervisor run``'s HTTP API (``…/api``)."""

    async def plant(self) -> dict[str, Any]:
        state: dict[str, Any] = await asyncio.to_thread(
            http, "GET", f"{self.control_url}/sim/state"
        )
        return state

    async def wait_plant(
        self, what: str, condition: Callable[[dict[str, Any]], bool], limit_s: float = SETTLE_S
    ) -> None:
        """A bounded wait on the plant: reaching the bound fails the test (no timing claim)."""
        seen: dict[str, Any] = {}

        async def poll() -> None:
            while True:
                seen.update(await self.plant())
                if condition(seen):
                    return
                await asyncio.sleep(0.05)

        try:
            await asyncio.wait_for(poll(), timeout=limit_s)
        except TimeoutError:
            raise AssertionError(f"gave up waiting for {what}; plant: {seen}") from None


async def read_until(proc: subprocess.Popen[str], pattern: str) -> re.Match[str]:
    assert proc.stdout is not None
    while True:
        line = await asyncio.to_thread(proc.stdout.readline)
        assert line, f"process exited before printing {pattern!r}"
        if m := re.search(pattern, line):
            return m


@asynccontextmanager
async def running(
    tmp_path: Path, change: Callable[[dict[str, Any]], None] | None = None
) -> AsyncIterator[Processes]:
    """``supervisor sim`` and ``supervisor run --no-sim`` on sim.yaml's seed 002 bench
    (``change`` edits it first); on exit both are stopped by their pid."""
    path = seed002_map(tmp_path, change)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cli = [sys.executable, "-m", "supervisor.cli.main"]
    started: list[subprocess.Popen[str]] = []

    def start(*args: str) -> subprocess.Popen[str]:
        proc = subprocess.Popen(
            [*cli, *args],
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            env=env,
        )
        started.append(proc)
        return proc

    try:
        sim = start("sim", str(path), "--control-port", "0")
        control = (await read_until(sim, r"e-stop button: PUT (http://127\.0\.0\.1:\d+/api)"))[1]
        supervisor = start("run", str(path), "--no-sim", "--http-port", "0")
        api = (
            await read_until(supervisor, r"HTTP API listening on (http://127\.0\.0\.1:\d+/api)")
        )[1]
        await read_until(supervisor, r"^Ctrl-C")
        yield Processes(sim, supervisor, control, api)
    finally:
        for proc in reversed(started):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    await asyncio.to_thread(proc.wait, 20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    await asyncio.to_thread(proc.wait)
            if proc.stdout is not None:
                proc.stdout.close()


async def charge_and_sigkill(p: Processes) -> None:
    """Charge 2 A on ch4 until the plant has its contactor closed and the supply on, then
    kill the supervisor without a chance to clean up (SIGKILL, by its pid)."""
    await asyncio.to_thread(http, "PUT", f"{p.api_url}/tags/ch4.manual_current", {"value": 2.0})
    await asyncio.to_thread(http, "PUT", f"{p.api_url}/tags/ch4.enable", {"value": True})
    await p.wait_plant("charging", lambda s: s["contactor_closed"] and s["supply"]["output_on"])
    os.kill(p.supervisor.pid, signal.SIGKILL)
    await asyncio.to_thread(p.supervisor.wait, 10)
    assert p.supervisor.returncode == -signal.SIGKILL


async def test_sigkill_of_the_supervisor_lets_the_adam_host_watchdog_open_the_contactor(
    tmp_path: Path,
) -> None:
    """sim.yaml as shipped: the watchdog relay (1.5 s), the ADAM's host watchdog (2 s)
    and the EA's (2 s) — each layer on its own opens the power path."""
    async with running(tmp_path) as p:
        await charge_and_sigkill(p)
        await p.wait_plant("the contactor open", lambda s: not s["contactor_closed"])
        await p.wait_plant("the unit let its relay go", lambda s: not s["contactor_coil_on"])
        await p.wait_plant("the supply off", lambda s: not s["supply"]["output_on"])
        assert (await p.plant())["pack"]["current_a"] == 0.0


def relay_only(data: dict[str, Any]) -> None:
    """The hardware watchdog relay fitted, the ADAM host watchdog off: the relay alone."""
    wd = {"device": "adam", "point": "slot3.do5", "timeout_s": 1.5}
    data["simulation"]["watchdog_relay"] = wd
    data["devices"]["adam"].pop("host_watchdog_s", None)


async def test_sigkill_of_the_supervisor_lets_the_watchdog_relay_open_the_contactor(
    tmp_path: Path,
) -> None:
    async with running(tmp_path, relay_only) as p:
        await p.wait_plant("the heartbeat", lambda s: s["heartbeat_toggles"] >= 2, limit_s=5.0)
        await charge_and_sigkill(p)
        await p.wait_plant("the contactor open", lambda s: not s["contactor_closed"])
        state = await p.plant()
        assert state["contactor_coil_on"] is True  # the ADAM relay never moved...
        assert state["watchdog_relay_closed"] is False  # ...the watchdog relay opened it
