"""Embedding a supervisor is one call (issue 29, finding 6): ``serve`` builds what
``supervisor run`` serves — the bench, its HTTP API, screens and OPC UA server — from an
I/O map, runs it for the block's duration and stops it with every output safe. Here the
default simulated bench (io_maps/sim.yaml) on loopback and free ports, its simulators in
this process."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import yaml

from supervisor.app.lock import BenchBusy, BenchLock
from supervisor.app.service import serve
from supervisor.bench.subject import prepare
from supervisor.devices.registry import load_bench

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
READ_WAIT_S = 30.0  # how long the first GOOD reading may take on a loaded machine


def sim_bench(tmp: Path) -> Path:
    """sim.yaml on free ports, its state in ``tmp``, its screens without logins."""
    copy, _, _ = prepare(ROOT / "io_maps" / "sim.yaml", tmp)
    data = yaml.safe_load(copy.read_text(encoding="utf-8"))
    data["hmi"]["login"] = False
    copy.write_text(yaml.safe_dump(data, allow_unicode=True, sort_keys=False), encoding="utf-8")
    return copy


async def good_reading(session: aiohttp.ClientSession, url: str) -> dict[str, Any]:
    """The tag at ``url`` once it reads GOOD (its device's first poll came)."""
    deadline = asyncio.get_running_loop().time() + READ_WAIT_S
    while True:
        async with session.get(url) as resp:
            assert resp.status == 200
            body: dict[str, Any] = await resp.json()
        if body["quality"] == "GOOD" or asyncio.get_running_loop().time() > deadline:
            return body
        await asyncio.sleep(0.05)


async def test_one_call_runs_a_whole_supervisor_whose_tags_read_over_http(tmp_path: Path) -> None:
    cfg = load_bench(sim_bench(tmp_path))
    async with serve(cfg) as sup:
        assert sup.api.port == cfg.hmi.port
        assert sup.opcua is not None  # sim.yaml enables OPC UA
        # The bench is this supervisor's while it runs.
        with pytest.raises(BenchBusy):
            BenchLock(cfg.state_dir, cfg.bench).acquire()
        async with aiohttp.ClientSession() as session:
            # The ADAM's pack voltage, polled over Modbus TCP from its simulator.
            tag = await good_reading(session, f"{sup.api.url}/tags/pack.voltage")
    assert tag["name"] == "pack.voltage" and tag["unit"] == "V"
    assert tag["quality"] == "GOOD" and tag["value"] > 0
    # Stopped: every output safe, the bench released for the next supervisor.
    assert sup.unconfirmed == {}
    BenchLock(cfg.state_dir, cfg.bench).acquire().release()
    # Nothing of it left running in the embedding process: the recipe checks' spare
    # processes were killed *and reaped* (an unreaped one's pipes were an unclosed
    # transport that failed the next test in this process).
    assert [t for t in asyncio.all_tasks() if t is not asyncio.current_task()] == []
