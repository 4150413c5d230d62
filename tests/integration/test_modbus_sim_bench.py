"""The simulated bench served over Modbus TCP, as ``supervisor run`` serves it (issue 36,
Must show 1): a client that is not the project's code (tests/modbus_rig.py: an MBAP header
and a PDU over a socket) reads every channel's voltage and current within one LSB of
``/api/tags``, sees the status bits change on an e-stop, and commands ch0's manual setpoint
from an allowed address (accepted, recorded with its actor) and from another (refused, 04,
the refusal register set).

Wall clock: io_maps/sim.yaml on free loopback ports, its simulators in this process. Bounded
waits only, never a timing assertion.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import struct
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import yaml
from modbus_rig import ModbusException, RawClient, float_of, words_of

from supervisor.app.service import Supervisor, serve
from supervisor.bench.subject import prepare
from supervisor.cli.main import _banner
from supervisor.devices.registry import load_bench
from supervisor.publish.modbus.image import BIT
from supervisor.publish.modbus.regmap import REFUSALS, Kind, Point, Table
from supervisor.testing import wait_until

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
WRITER = "127.0.0.1"
OTHER = "127.0.0.2"  # loopback too: a client bound to it writes from another address
WAIT_S = 30.0


def sim_bench(tmp: Path, **modbus: Any) -> Path:
    """sim.yaml on free ports (its Modbus server's too), screens without logins, Modbus
    writes from ``WRITER`` only."""
    tmp.mkdir(parents=True, exist_ok=True)
    copy, _, _ = prepare(ROOT / "io_maps" / "sim.yaml", tmp)
    data = yaml.safe_load(copy.read_text(encoding="utf-8"))
    data["hmi"]["login"] = False
    data["modbus_server"].update({"writes": True, "writers": [WRITER], **modbus})
    copy.write_text(yaml.safe_dump(data, allow_unicode=True, sort_keys=False), encoding="utf-8")
    return copy


@pytest.fixture
async def sup(tmp_path: Path) -> AsyncIterator[Supervisor]:
    async with serve(load_bench(sim_bench(tmp_path))) as s:
        assert s.modbus is not None
        await wait_until(lambda: s.bench.db["ch0.voltage"].quality.name == "GOOD", "ch0 read")
        yield s


def point(sup: Supervisor, tag: str, kind: Kind | None = None) -> Point:
    assert sup.modbus is not None
    for p in sup.modbus.regmap.points:
        if p.tag == tag and (kind is None or p.kind is kind):
            return p
    raise AssertionError(f"{tag} is not in the map")


def status_point(sup: Supervisor, channel: str) -> Point:
    assert sup.modbus is not None
    for p in sup.modbus.regmap.points:
        if p.kind is Kind.STATUS and p.channel == channel:
            return p
    raise AssertionError(f"no status register for {channel!r}")


def client(sup: Supervisor, source: str = WRITER) -> RawClient:
    assert sup.modbus is not None
    return RawClient(sup.modbus.host, sup.modbus.bound_port, source=source)


def lsb32(x: float) -> float:
    """The float32 spacing at ``x``: one LSB of a value served in two registers."""
    f = struct.unpack(">f", struct.pack(">f", x))[0]
    return math.ulp(f) * 2.0**29 if f else 2.0**-149  # a double's ulp × 2^(52-23)


async def api_values(session: aiohttp.ClientSession, url: str, names: list[str]) -> dict[str, Any]:
    async with session.get(f"{url}/tags") as resp:
        assert resp.status == 200
        body = await resp.json()
    tags = body["tags"] if isinstance(body, dict) and "tags" in body else body
    return {t["name"]: t["value"] for t in tags if t["name"] in names}


async def test_every_channel_voltage_and_current_read_within_one_lsb_of_the_api(
    sup: Supervisor,
) -> None:
    names = [f"{ch}.{q}" for ch in sup.bench.channels for q in ("voltage", "current")]
    points = {n: point(sup, n) for n in names}
    assert all(p.table is Table.INPUT_REGISTER for p in points.values())
    order = sup.bench.cfg.modbus_server.word_order  # type: ignore[union-attr]
    pending = set(names)
    async with aiohttp.ClientSession() as session:
        with client(sup) as c:
            # A value read between two reads of the API that agree is that value; a moving
            # one is read again (bounded), never compared across a change.
            for _ in range(50):
                before = await api_values(session, sup.api.url, names)
                served = {
                    n: float_of(await asyncio.to_thread(c.read_registers, p.address, 2), order)
                    for n, p in points.items()
                    if n in pending
                }
                after = await api_values(session, sup.api.url, names)
                for n, x in served.items():
                    if before[n] == after[n] and before[n] is not None:
                        assert abs(x - before[n]) <= lsb32(before[n]), (n, x, before[n])
                        pending.discard(n)
                if not pending:
                    break
    assert not pending, f"never still long enough to compare: {sorted(pending)}"


async def test_the_status_bits_change_on_an_e_stop(sup: Supervisor) -> None:
    bench_status, ch0_status = status_point(sup, ""), status_point(sup, "ch0")
    assert sup.bench.sim is not None

    def read(c: RawClient, p: Point) -> int:
        return c.read_registers(p.address, 1)[0]

    with client(sup) as c:
        await wait_until(
            lambda: read(c, bench_status) & BIT["tripped"] == 0, "no trip before", WAIT_S
        )
        assert read(c, bench_status) & BIT["alive"]
        # Every input GOOD (a channel's thermocouple that is not fitted is no fault).
        assert read(c, ch0_status) & (BIT["bad"] | BIT["uncertain"] | BIT["tripped"]) == 0
        heartbeat = point_heartbeat(sup)
        first = c.read_registers(heartbeat.address, 1)[0]
        await wait_until(
            lambda: c.read_registers(heartbeat.address, 1)[0] != first, "heartbeat", WAIT_S
        )
        sup.bench.sim.press_estop()
        await wait_until(
            lambda: read(c, bench_status) & BIT["tripped"], "the e-stop's trip", WAIT_S
        )
        bench = read(c, bench_status)
        ch0 = read(c, ch0_status)
    assert bench & BIT["unacked"]  # the e-stop's alarm waits for its acknowledge
    assert ch0 & BIT["tripped"]  # the bench's trip holds every channel
    assert bench & BIT["alive"]


def point_heartbeat(sup: Supervisor) -> Point:
    assert sup.modbus is not None
    return next(p for p in sup.modbus.regmap.points if p.kind is Kind.HEARTBEAT)


async def test_a_manual_setpoint_from_a_writer_is_accepted_and_from_another_refused(
    sup: Supervisor,
) -> None:
    mode, setpoint = point(sup, "ch0.mode"), point(sup, "ch0.manual_current")
    refusal = next(p for p in sup.modbus.regmap.points if p.kind is Kind.REFUSAL)  # type: ignore[union-attr]
    order = sup.bench.cfg.modbus_server.word_order  # type: ignore[union-attr]
    log = sup.bench.commands.log
    with client(sup) as c:
        await asyncio.to_thread(c.write_register, mode.address, mode.codes.index("manual"))
        await asyncio.to_thread(c.write_registers, setpoint.address, words_of(0.125, order))
        await wait_until(
            lambda: sup.bench.db["ch0.manual_current"].value == pytest.approx(0.125),
            "the setpoint",
        )
        assert c.read_registers(refusal.address, 1) == [0]
    accepted = [e for e in log if e.actor == f"modbus:{WRITER}" and e.accepted]
    assert [e.command for e in accepted] == ["mode manual", "manual_current 0.125 A"]
    assert all(e.channel == "ch0" for e in accepted)

    with client(sup, OTHER) as other:
        with pytest.raises(ModbusException) as e:
            await asyncio.to_thread(other.write_registers, setpoint.address, words_of(0.5, order))
        assert e.value.code == 4
        assert other.read_registers(refusal.address, 1) == [REFUSALS.index("forbidden")]
    # A chain command by its code, refused by the state table (no recipe loaded): 04, and
    # the refusal register holds the kind the command path recorded.
    command = point(sup, "ch0.command")
    with client(sup) as c:
        with pytest.raises(ModbusException) as e:
            await asyncio.to_thread(c.write_register, command.address, command.codes.index("start"))
        assert e.value.code == 4
        last = [e for e in log if e.actor == f"modbus:{WRITER}"][-1]
        assert not last.accepted and last.command == "start"
        assert c.read_registers(refusal.address, 1) == [REFUSALS.index(last.kind.value)]
    refused = [e for e in log if e.actor == f"modbus:{OTHER}"]
    assert len(refused) == 1 and not refused[0].accepted
    assert "not a Modbus writer" in refused[0].reason
    assert sup.bench.db["ch0.manual_current"].value == pytest.approx(0.125)  # unchanged


async def test_writes_off_answer_01_and_an_address_of_no_point_02(tmp_path: Path) -> None:
    async with serve(load_bench(sim_bench(tmp_path / "off", writes=False))) as s:
        with client(s) as c:
            with pytest.raises(ModbusException) as e:
                await asyncio.to_thread(
                    c.write_registers, point(s, "ch0.manual_current").address, words_of(0.1)
                )
            assert e.value.code == 1
        with client(s) as c:
            with pytest.raises(ModbusException) as e:
                await asyncio.to_thread(c.write_register, 60000, 1)  # nobody's address
            assert e.value.code in (1, 2)  # writes off: 01 before any address is looked at
    async with serve(load_bench(sim_bench(tmp_path / "on"))) as s:
        with client(s) as c:
            with pytest.raises(ModbusException) as e:
                await asyncio.to_thread(c.write_register, 60000, 1)  # nobody's address
            assert e.value.code == 2
            with pytest.raises(ModbusException) as e:  # holding register 104: nobody's either
                await asyncio.to_thread(c.write_register, 104, 1)
            assert e.value.code == 2


async def test_the_run_banner_says_where_modbus_listens(
    sup: Supervisor, capsys: pytest.CaptureFixture[str]
) -> None:
    _banner(argparse.Namespace(io_map="sim.yaml"), sup.bench.cfg, sup)
    out = capsys.readouterr().out
    assert sup.modbus is not None
    line = (
        f"Modbus TCP server listening on 127.0.0.1:{sup.modbus.bound_port}"
        f" (unit 1, writes from {WRITER})"
    )
    assert line in out.splitlines()
