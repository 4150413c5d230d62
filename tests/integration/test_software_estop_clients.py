"""The bench-wide software e-stop (seed 002 §1.5; issue 32, finding 7) from its clients:

- **HTTP** (``POST /api/estop``, ``POST /api/estop/reset``) with a real aiohttp client and
  logins, on the simulated seed 002 bench driven by the real drivers over loopback (ADAM
  Modbus TCP, EA SCPI, BMS CAN): a viewer is refused; an operator's press trips the EA
  channel while it charges at 2 A, and the outputs are what the answer says — no current in
  the pack, the supply's output off, the battery contactor open — on the simulated plant
  itself, not only on the alarm; the reset before the acknowledgement is refused with the
  reason, after it accepted, and nothing is energised again.
- **``supervisor ctl estop``** (and ``estop reset``) in a process of its own against the
  OPC UA server of a bench (opcuarig): the viewer refused, the operator's press recorded
  with the session's user, the reset refused until ``ctl ack estop``.

The OPC UA method from an independent client (node-opcua) is in
tests/interop/test_opcua_estop_interop.py; the button on the Overview in
tests/browser/test_estop_button.py.
"""

from __future__ import annotations

import asyncio
import os
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import pytest
import yaml
from hmirig import JSON, USERS, password
from opcuarig import PASSWORDS, Rig, opcua_rig

from supervisor.app import Bench, build_bench
from supervisor.app.hmi import build_screens
from supervisor.config.models import HmiConfig
from supervisor.config.users import add_user
from supervisor.core.clock import RealClock
from supervisor.devices import base
from supervisor.devices.registry import load_bench
from supervisor.hmi import HttpApi
from supervisor.publish.opcua import OpcUaSettings
from supervisor.safety import AlarmState
from supervisor.sim.plant import BenchPlant
from supervisor.testing import free_tcp_port, wait_until

ROOT = Path(__file__).resolve().parents[2]
# The bench and its three simulators share one event loop with device timeouts of 0.5 s
# (test_seed002_bench.py: the "quiet" marker).
pytestmark = [pytest.mark.integration, pytest.mark.quiet]


def seed002_map(tmp_path: Path) -> Path:
    """sim.yaml's seed 002 bench alone (ch4 on the EA, the ADAM, the BMS), free ports,
    logins on."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    del data["devices"]["chadeche"]
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    for name in ("adam", "ea", "bms"):
        data["devices"][name]["port"] = free_tcp_port()
    data["hmi"]["port"] = 0
    data.pop("opcua", None)
    data.pop("modbus_server", None)
    data["state_dir"] = str(tmp_path / "state")
    path = tmp_path / "seed002.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


class Http:
    """The seed 002 bench running on the real clock, its HTTP API with logins."""

    def __init__(self, bench: Bench, api: HttpApi) -> None:
        self.bench = bench
        self.api = api
        self.base = f"http://127.0.0.1:{api.port}"

    async def login(self, s: aiohttp.ClientSession, user: str) -> None:
        body = {"user": user, "password": password(user)}
        async with s.post(self.base + "/api/login", json=body) as resp:
            assert resp.status == 200, await resp.text()

    async def post(
        self, s: aiohttp.ClientSession, path: str, body: object = None
    ) -> tuple[int, dict[str, object]]:
        kw: dict[str, object] = {"headers": JSON} if body is None else {"json": body}
        async with s.post(self.base + path, **kw) as resp:  # type: ignore[arg-type]
            return resp.status, await resp.json()

    async def put(self, s: aiohttp.ClientSession, tag: str, value: object) -> None:
        async with s.put(f"{self.base}/api/tags/{tag}", json={"value": value}) as resp:
            assert resp.status == 200, await resp.text()


@pytest.fixture
async def http(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[Http]:
    monkeypatch.setattr(base, "BACKOFF_START_S", 0.2)
    monkeypatch.setattr(base, "BACKOFF_MAX_S", 1.0)
    bench = build_bench(load_bench(seed002_map(tmp_path)), RealClock())
    users = OpcUaSettings.of(bench.cfg).users_file
    for user, role in USERS.items():
        add_user(users, user, role, password(user))
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, commands=bench.commands)
    build_screens(bench, api, root=tmp_path / "no-hmi", cfg=HmiConfig(login=True))
    stop = asyncio.Event()
    await bench.start()
    task = asyncio.create_task(bench.run(stop))
    await api.start()
    try:
        db = bench.db
        await wait_until(
            lambda: (
                all(db[f"{d}.connected"].value is True for d in ("adam", "ea", "bms"))
                and db["pack.voltage"].good
                and db["bms.current"].good
                and db["estop.ok"].value is True
            ),
            "all devices connected",
        )
        yield Http(bench, api)
    finally:
        await api.stop()
        stop.set()
        await task
        await bench.shutdown()


def jar() -> aiohttp.ClientSession:
    # unsafe=True: aiohttp keeps no cookie of an IP host otherwise (browsers do).
    return aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True))


def pack_safe(plant: BenchPlant) -> bool:
    """The simulated plant itself: no current in the pack, supply output off, contactor open."""
    return plant.pack_current_a == 0.0 and not plant.supply.output_on and not plant.contactor_closed


def estop_commands(bench: Bench) -> list[tuple[str, str, bool]]:
    """The e-stop's commands in the command path's record: (actor, command, accepted)."""
    return [(e.actor, e.command, e.accepted) for e in bench.commands.log if "estop" in e.command]


async def test_http_press_makes_the_charging_pack_safe_and_reset_needs_the_acknowledgement(
    http: Http,
) -> None:
    bench, db = http.bench, http.bench.db
    plant = bench.sim.plant if bench.sim is not None else None
    assert plant is not None
    async with jar() as vera, jar() as otto:
        await http.login(vera, "vera")
        await http.login(otto, "otto")
        await http.put(otto, "ch4.manual_current", 2.0)
        await http.put(otto, "ch4.enable", True)
        await wait_until(lambda: abs(plant.pack_current_a - 2.0) < 0.01, "2 A into the pack")
        assert plant.contactor_closed and plant.supply.output_on

        # A viewer's press is refused, and the pack charges on.
        status, body = await http.post(vera, "/api/estop")
        assert (status, body["accepted"], body["kind"]) == (403, False, "forbidden")
        assert "viewer" in str(body["reason"])
        assert bench.alarms["estop"].state is AlarmState.NORMAL

        status, body = await http.post(otto, "/api/estop")
        assert (status, body["accepted"], body["alarm"]) == (200, True, "estop"), body
        assert str(body["reason"]).startswith("software e-stop pressed by hmi:otto")
        # What the answer says is true of the hardware: no current, supply off, contactor open.
        await wait_until(lambda: pack_safe(plant), "the pack disconnected and the supply off")
        assert db["ch4.current_cmd"].value == 0.0 and db["contactor.cmd"].value is False
        assert "Software e-stop pressed by hmi:otto" in str(db["ch4.fault"].value)
        assert db["estop.ok"].value is True  # the hardware button was never pressed

        # Reset before the acknowledgement: refused, with the reason, and nothing moves.
        status, body = await http.post(otto, "/api/estop/reset", {})
        assert (status, body["kind"]) == (409, "refused")
        assert "acknowledge the e-stop first" in str(body["reason"])
        assert (await http.post(otto, "/api/alarms/estop/acknowledge"))[0] == 200
        status, body = await http.post(otto, "/api/estop/reset")
        assert (status, body["accepted"]) == (200, True), body

        # Released: nothing energised again on its own (the channel's enable dropped).
        t_reset = bench.clock.now()
        await wait_until(lambda: bench.clock.now() > t_reset + 1.0, "a second after the reset")
        assert pack_safe(plant) and db["ch4.enable"].value is False

        # The record: who pressed, who acknowledged and reset, and the refusals.
        async with otto.get(http.base + "/api/alarms") as resp:
            history = (await resp.json())["history"]
    transitions = [(e["transition"], e["actor"]) for e in history if e["alarm"] == "estop"]
    assert transitions == [
        ("activated", ""),
        ("acknowledged", "hmi:otto"),
        ("cleared", ""),
        ("reset", "hmi:otto"),
    ]
    assert estop_commands(bench) == [
        ("hmi:vera", "estop", False),
        ("hmi:otto", "estop", True),
        ("hmi:otto", "estop_reset", False),
        ("hmi:otto", "estop_reset", True),
    ]


# --- supervisor ctl, a process of its own -------------------------------------------------
@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path) as r:
        yield r


async def ctl(rig: Rig, user: str, *argv: str) -> tuple[int, str, str]:
    """``supervisor ctl --url <the rig's server> --user U --password P argv`` as a child
    process: (exit code, stdout, stderr)."""
    env = {**os.environ, "XDG_CONFIG_HOME": str(rig.tmp / "xdg")}
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "supervisor.cli.main",
        "ctl",
        "--url",
        rig.server.endpoint,
        "--user",
        user,
        "--password",
        PASSWORDS[user],
        *argv,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env=env,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 120)
    assert proc.returncode is not None
    return proc.returncode, out.decode().strip(), err.decode().strip()


async def test_ctl_estop_presses_it_as_the_session_user_and_its_reset_waits_for_ack(
    rig: Rig,
) -> None:
    bench, db = rig.bench, rig.bench.db
    channels = [c.name for c in bench.cfg.channels]
    code, out, err = await ctl(rig, "bob", "estop")  # a viewer
    assert code == 2 and "BadUserAccessDenied" in err, (out, err)
    assert bench.alarms["estop"].state is AlarmState.NORMAL

    code, out, err = await ctl(rig, "alice", "estop")
    assert (code, err) == (0, ""), err
    assert out.startswith("software e-stop pressed by opcua:alice: every channel tripped")
    await rig.scans(3)
    for ch in channels:
        assert db[f"{ch}.state"].value == "faulted", ch
        assert db[f"{ch}.current_cmd"].value == 0.0 and db[f"{ch}.enable"].value is False

    code, out, err = await ctl(rig, "alice", "estop", "reset")
    assert code == 2
    assert err.startswith("supervisor ctl: estop reset refused (BadInvalidState): e-stop reset")
    assert "acknowledge the e-stop first" in err
    code, out, err = await ctl(rig, "alice", "ack", "estop")
    assert code == 0, err
    code, out, err = await ctl(rig, "alice", "estop", "reset")
    assert (code, err) == (0, ""), err
    assert out.startswith("e-stop reset by opcua:alice")
    await rig.scans(3)
    assert bench.alarms["estop"].state is AlarmState.NORMAL
    assert all(db[f"{ch}.enable"].value is False for ch in channels)
    assert estop_commands(bench) == [
        ("opcua:bob", "estop", False),
        ("opcua:alice", "estop", True),
        ("opcua:alice", "estop_reset", False),
        ("opcua:alice", "estop_reset", True),
    ]
