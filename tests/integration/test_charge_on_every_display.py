"""Issue 26 "Must show": the charge shown by the Overview tile, the channel screen,
``supervisor ctl status``, ``supervisor ctl watch``, OPC UA and the Chadèche display line
agree within one count at the same moment.

One bench (sim.yaml's Chadèche channels in process, virtual clock: it scans only when the
test says so) with its real OPC UA server and its real HTTP API and screens on loopback;
``supervisor ctl`` runs on its own thread as a separate process would. ``nimh-ds2710`` with
``q_init`` 1300 mAh on ch3, started and taken past its first rest with ``ctl``, discharges
for 30 s and is held: the figure stops moving, and the display line is written again while
the test is held. Then each display is read as it reads it and printed to its own
resolution: one count is 0.1 mAh for every one of them (the tile and the channel screen
print Ah to four decimals)."""

from __future__ import annotations

import asyncio
import re
import shutil
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from asyncua import ua
from opcuarig import PASSWORDS, Rig, opcua_rig

from supervisor.app.hmi import build_screens
from supervisor.cli.main import main
from supervisor.config.models import HmiConfig
from supervisor.hmi import HttpApi

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
DS2710 = ROOT / "recipes" / "nimh-ds2710.yaml"
COUNT_MAH = 0.1


@pytest.fixture(autouse=True)
def config_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """ctl's per-user folder (its client certificate) in the test's own folder."""
    home = tmp_path / "xdg"
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home))
    return home


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[tuple[Rig, HttpApi]]:
    # The shipped recipe, in the rig's recipe folder (its temporary folder): ctl names it.
    shutil.copyfile(DS2710, tmp_path / DS2710.name)
    async with opcua_rig(tmp_path) as r:
        api = HttpApi(r.bench.db, r.bench.clock, "127.0.0.1", 0, commands=r.bench.commands)
        build_screens(r.bench, api, root=tmp_path / "no-hmi", cfg=HmiConfig(login=False))
        await api.start()
        try:
            yield r, api
        finally:
            await api.stop()


async def ctl(rig: Rig, capsys: pytest.CaptureFixture[str], *argv: str) -> list[str]:
    """``supervisor ctl`` as operator alice: its output lines (exit 0, nothing on stderr)."""
    login = ["--user", "alice", "--password", PASSWORDS["alice"]]
    code = await asyncio.to_thread(main, ["ctl", "--url", rig.server.endpoint, *login, *argv])
    out, err = capsys.readouterr()
    assert (code, err) == (0, ""), (argv, out, err)
    return out.splitlines()


async def screen_figure(api: HttpApi, channel: str) -> tuple[str, float]:
    """What the Overview tile and the channel screen show: the tag /api/bench names as the
    channel's ``charge``, from the live snapshot the page starts from, printed as the page
    prints it (``data-fmt="n4"``: Ah to four decimals)."""
    base = f"http://127.0.0.1:{api.port}"
    async with aiohttp.ClientSession() as s:
        async with s.get(f"{base}/api/bench") as resp:
            assert resp.status == 200
            bench = await resp.json()
        tags = next(c for c in bench["channels"] if c["name"] == channel)["tags"]
        async with s.ws_connect(f"{base}/api/ws") as ws:
            snapshot: dict[str, Any] = await ws.receive_json(timeout=10)
    assert snapshot["type"] == "snapshot"
    tag = snapshot["tags"][tags["charge"]]
    assert tag["unit"] == "Ah"
    return tags["charge"], float(f"{tag['value']:.4f}")


async def test_the_tile_the_channel_screen_ctl_opcua_and_the_display_line_show_one_charge(
    rig: tuple[Rig, HttpApi], capsys: pytest.CaptureFixture[str]
) -> None:
    r, api = rig
    bench = r.bench
    out = await ctl(r, capsys, "start", "ch3", DS2710.stem, "-p", "q_init=1300 mAh")
    assert "started" in out[0]
    await r.scans(10)
    await ctl(r, capsys, "advance", "ch3")  # past the 60 s rest: 200 mA out
    await r.scans(300)  # 30 s
    assert bench.db["ch3.chain.step"].value == "discharge"
    await ctl(r, capsys, "hold", "ch3")
    await r.scans(10)
    assert bench.db["ch3.chain.state"].value == "Held"
    # The display writes its line every minute while a test is under way (held too).
    display = bench.displays["ch3"]
    before = display.last_line
    await r.scans(610)
    assert display.last_line != before

    # The same moment (held: nothing moves), every display as it reads the figure.
    (mah,) = re.findall(r"mAh=(-?[\d.]+),", display.last_line)
    figures: dict[str, float] = {"display line": float(mah)}
    screen_tag, ah = await screen_figure(api, "ch3")
    figures["Overview tile and channel screen"] = ah * 1000
    lines = await ctl(r, capsys, "status")
    (row,) = [line for line in lines if line.startswith("ch3 ")]
    figures["ctl status"] = float(row.split()[-1]) * 1000
    (line,) = await ctl(r, capsys, "watch", "ch3", "--count", "1")
    (mah,) = re.findall(r"mAh=(-?[\d.]+) ", line)
    figures["ctl watch"] = float(mah)
    async with r.client() as c:
        ns = await r.ns(c)
        channel = c.get_node(ua.NodeId("/Bench/Channels/ch3", ns))
        (charge,) = [
            n for n in await channel.get_children() if (await n.read_browse_name()).Name == "Charge"
        ]
        figures["OPC UA Charge"] = float(await charge.read_value()) * 1000
        units = c.get_node(ua.NodeId(f"{charge.nodeid.Identifier}.EngineeringUnits", ns))
        assert (await units.read_value()).DisplayName.Text == "Ah"
    print(figures)

    # 1300 mAh less 30 s at 200 mA (1.7 mAh), and every display within one count of it.
    reference = figures["OPC UA Charge"]
    assert reference == pytest.approx(1300 - 200 * 30 / 3600, abs=0.2)
    for where, shown in figures.items():
        assert shown == pytest.approx(reference, abs=COUNT_MAH + 1e-9), (where, figures)
    # One tag behind them: chN.chain.charge_ah. The raw counter stays under its own name,
    # labelled as a counter.
    assert screen_tag == charge.nodeid.Identifier == "ch3.chain.charge_ah"
    assert re.split(r"\s{2,}", lines[0])[-1] == "charge (Ah)"
    assert bench.db["ch3.charge_ah"].as_float() * 1000 == pytest.approx(reference - 1300, abs=0.2)
    assert "counter" in bench.db["ch3.charge_ah"].spec.description
