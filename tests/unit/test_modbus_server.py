"""The Modbus TCP server, at the protocol: a hand-rolled client (tests/modbus_rig.py) against
a register map built by hand over a small tag database (issue 36; ADR 0032).

The server runs on its own thread on a loopback port; the scan is played by calling the
feed's ``on_scan`` on the test's loop, as the engine does at each scan's end.
"""

from __future__ import annotations

import asyncio
import logging
import struct
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml
from commandrig import chadeche_map
from modbus_rig import ModbusException, RawClient, float_of, words_of

from supervisor.app import Bench, build_bench
from supervisor.app.modbus import build_modbus
from supervisor.commands import Command
from supervisor.core.clock import VirtualClock
from supervisor.core.driver import Value
from supervisor.core.quality import Quality, Reason
from supervisor.devices.registry import load_bench
from supervisor.publish.modbus.image import BIT, RegisterImage, decode, encode
from supervisor.publish.modbus.regmap import REFUSALS, Kind, Point, RegisterMap, Table
from supervisor.publish.modbus.server import (
    ModbusFeed,
    ModbusServer,
    WriteAnswer,
    exception_of,
    refusal_code,
)
from supervisor.tags import Access, TagDB, TagSpec
from supervisor.testing import free_tcp_port, wait_until

IR, HR, CO, DI = (
    Table.INPUT_REGISTER,
    Table.HOLDING_REGISTER,
    Table.COIL,
    Table.DISCRETE_INPUT,
)


def a_map(word_order: str = "big") -> RegisterMap:
    return RegisterMap(
        (
            Point(IR, 0, Kind.FLOAT32, "ch0.voltage", "ch0", "V"),
            Point(IR, 2, Kind.FLOAT32, "ch0.current", "ch0", "A"),
            Point(IR, 4, Kind.INT16, "ch0.temperature", "ch0", "degC", scale=10.0),
            Point(IR, 5, Kind.CODE, "ch0.state", "ch0", codes=("idle", "running", "tripped")),
            Point(IR, 6, Kind.STATUS, "", "ch0"),
            Point(IR, 7, Kind.HEARTBEAT, ""),
            Point(IR, 8, Kind.REFUSAL, ""),
            Point(IR, 9, Kind.STATUS, ""),
            Point(HR, 0, Kind.FLOAT32, "ch0.manual_current", "ch0", "A", writable=True),
            Point(HR, 2, Kind.CODE, "ch0.mode", "ch0", codes=("auto", "manual"), writable=True),
            Point(HR, 3, Kind.UINT16, "ch0.setpoint_ma", "ch0", "mA", writable=True),
            Point(HR, 4, Kind.FLOAT32, "ch0.limit", "ch0", "A"),  # read-only holding
            Point(CO, 0, Kind.BOOL, "ch0.enable", "ch0", writable=True),
            Point(DI, 0, Kind.BOOL, "ch0.armed", "ch0"),
        ),
        word_order=word_order,  # type: ignore[arg-type]
    )


def a_db() -> TagDB:
    db = TagDB()
    for name, dtype, initial in (
        ("ch0.voltage", "float", 1.25),
        ("ch0.current", "float", -0.5),
        ("ch0.temperature", "float", 23.4),
        ("ch0.state", "str", "idle"),
        ("ch0.manual_current", "float", 0.0),
        ("ch0.mode", "str", "auto"),
        ("ch0.setpoint_ma", "float", 0.0),
        ("ch0.limit", "float", 2.0),
        ("ch0.enable", "bool", False),
        ("ch0.armed", "bool", True),
    ):
        tag = db.add(TagSpec(name, dtype=dtype, initial=initial, access=Access.OPERATOR))  # type: ignore[arg-type]
        db.update(tag, initial)
    return db


@dataclass
class PathStub:
    """The command path as the server sees it: records each write, refuses what it is told."""

    db: TagDB
    refuse: dict[str, WriteAnswer] = field(default_factory=dict)
    writes: list[tuple[str, Value, str]] = field(default_factory=list)

    async def __call__(self, tag: str, value: Value, actor: str) -> WriteAnswer:
        self.writes.append((tag, value, actor))
        if tag in self.refuse:
            return self.refuse[tag]
        self.db.update(self.db[tag], value)
        return WriteAnswer(True, f"{tag} := {value!r}")


@dataclass
class Rig:
    server: ModbusServer
    feed: ModbusFeed
    db: TagDB
    path: PathStub

    def client(self, unit: int = 1) -> RawClient:
        return RawClient(self.server.host, self.server.port, unit)

    def scan(self) -> None:
        self.feed.on_scan(self.db, 0.0)


async def serving(
    *, writes: bool = True, max_clients: int = 8, word_order: str = "big"
) -> AsyncIterator[Rig]:
    db = a_db()
    feed = ModbusFeed(db)
    path = PathStub(db)
    server = ModbusServer(
        a_map(word_order),
        db,
        feed,
        path,
        host="127.0.0.1",
        port=free_tcp_port(),
        writes=writes,
        max_clients=max_clients,
    )
    await server.start()
    try:
        yield Rig(server, feed, db, path)
    finally:
        await server.stop()


@pytest.fixture
async def rig() -> AsyncIterator[Rig]:
    async for r in serving():
        yield r


def call(fn, *args, **kw):  # type: ignore[no-untyped-def]
    """A blocking client call off the test's loop (the writes run on that loop)."""
    return asyncio.to_thread(fn, *args, **kw)


# --- reads ----------------------------------------------------------------------------------
async def test_measurements_read_as_their_tags_hold_them(rig: Rig) -> None:
    with rig.client() as c:
        words = await call(c.read_registers, 0, 6)
    assert float_of(words[0:2]) == pytest.approx(1.25)
    assert float_of(words[2:4]) == pytest.approx(-0.5)
    assert struct.unpack(">h", struct.pack(">H", words[4]))[0] == 234  # 23.4 °C × 10
    assert words[5] == 0  # "idle", code 0


async def test_a_change_of_the_scan_reaches_the_registers(rig: Rig) -> None:
    rig.db.update(rig.db["ch0.voltage"], 3.5)
    rig.db.update(rig.db["ch0.state"], "running")
    rig.scan()
    with rig.client() as c:
        words = await call(c.read_registers, 0, 6)
    assert float_of(words[0:2]) == pytest.approx(3.5)
    assert words[5] == 1


async def test_little_word_order_swaps_the_two_registers_of_a_float() -> None:
    async for rig in serving(word_order="little"):
        with rig.client() as c:
            words = await call(c.read_registers, 0, 2)
        assert words == words_of(1.25, "little")
        assert float_of(words, "little") == pytest.approx(1.25)


async def test_a_bad_value_keeps_its_last_registers_and_sets_the_status_bit(rig: Rig) -> None:
    with rig.client() as c:
        status = (await call(c.read_registers, 6, 1))[0]
        assert status & BIT["bad"] == 0
        rig.db.update(rig.db["ch0.voltage"], None, Quality.BAD, Reason.COMM_FAILURE)
        rig.scan()
        words = await call(c.read_registers, 0, 2)
        status = (await call(c.read_registers, 6, 1))[0]
        bench = (await call(c.read_registers, 9, 1))[0]
    assert float_of(words) == pytest.approx(1.25)  # the last value, never a silent 0
    assert status & BIT["bad"]
    assert bench & BIT["bad"]  # the bench's status says some input reads BAD


async def test_a_sensor_not_fitted_reads_bad_without_setting_the_bit(rig: Rig) -> None:
    rig.db.update(rig.db["ch0.temperature"], None, Quality.BAD, Reason.NOT_FITTED)
    rig.scan()
    with rig.client() as c:
        status = (await call(c.read_registers, 6, 1))[0]
    assert not status & BIT["bad"]  # no thermocouple on this channel: not a fault


async def test_an_uncertain_input_sets_its_bit_and_its_value(rig: Rig) -> None:
    rig.db.update(rig.db["ch0.current"], 0.75, Quality.UNCERTAIN, Reason.STALE)
    rig.scan()
    with rig.client() as c:
        words = await call(c.read_registers, 2, 1 + 4)
    assert float_of(words[0:2]) == pytest.approx(0.75)
    assert words[4] & BIT["uncertain"]
    assert not words[4] & BIT["bad"]


async def test_the_heartbeat_moves_every_scan_and_alive_is_set(rig: Rig) -> None:
    with rig.client() as c:
        first = (await call(c.read_registers, 7, 1))[0]
        for _ in range(3):
            rig.scan()
        second, _, status = await call(c.read_registers, 7, 3)
    assert second == (first + 3) & 0xFFFF
    assert status & BIT["alive"]


async def test_alive_clears_when_the_scan_stops_moving(rig: Rig) -> None:
    # No real time waited: the window the scan count must have moved in is made 0 (every
    # scan is then too old), then wide again.
    with rig.client() as c:
        rig.server.alive_window_s = 0.0
        assert not (await call(c.read_registers, 6, 1))[0] & BIT["alive"]
        rig.server.alive_window_s = 3600.0
        rig.scan()
        assert (await call(c.read_registers, 6, 1))[0] & BIT["alive"]


async def test_trips_and_unacknowledged_alarms_set_their_bits(rig: Rig) -> None:
    with rig.client() as c:
        rig.server.on_alarms({"": BIT["tripped"] | BIT["unacked"]})
        ch0, _, _, bench = await call(c.read_registers, 6, 4)
    assert bench & BIT["tripped"] and bench & BIT["unacked"]
    assert ch0 & BIT["tripped"]  # a bench trip (the e-stop) holds every channel
    assert not ch0 & BIT["unacked"]  # its own alarms only


async def test_bits_read_as_discrete_inputs_and_coils(rig: Rig) -> None:
    with rig.client() as c:
        assert await call(c.read_bits, 0, 1) == [True]
        assert await call(c.read_bits, 0, 1, coils=True) == [False]


# --- exceptions -----------------------------------------------------------------------------
async def test_an_address_no_point_holds_answers_02(rig: Rig) -> None:
    with rig.client() as c:
        with pytest.raises(ModbusException) as e:
            await call(c.read_registers, 9, 2)  # 10 is nobody's
        assert e.value.code == 2
        with pytest.raises(ModbusException) as e:
            await call(c.read_registers, 65535, 1)
        assert e.value.code == 2


async def test_a_count_beyond_the_function_limit_answers_03(rig: Rig) -> None:
    with rig.client() as c:
        with pytest.raises(ModbusException) as e:
            await call(c.request, 4, struct.pack(">HH", 0, 126))
        assert e.value.code == 3
        with pytest.raises(ModbusException) as e:
            await call(c.request, 4, struct.pack(">HH", 0, 0))
        assert e.value.code == 3


async def test_a_function_it_does_not_serve_answers_01(rig: Rig) -> None:
    with rig.client() as c:
        for function, data in (
            (0x41, b"\x00\x00"),  # nobody's
            (0x08, b"\x00\x04\x00\x00"),  # diagnostics: force listen only mode
            (0x11, b""),  # report server id
            (0x2B, b"\x0e\x01\x00"),  # read device identification
            (0x16, b"\x00\x64\xff\xff\x00\x00"),  # mask write register
        ):
            with pytest.raises(ModbusException) as e:
                await call(c.request, function, data)
            assert e.value.code == 1, hex(function)
        assert len(await call(c.read_registers, 0, 2)) == 2  # still serving


async def test_writes_off_answer_01() -> None:
    async for rig in serving(writes=False):
        with rig.client() as c:
            with pytest.raises(ModbusException) as e:
                await call(c.write_registers, 0, words_of(0.5))
            assert e.value.code == 1
            with pytest.raises(ModbusException) as e:
                await call(c.write_coil, 0, True)
            assert e.value.code == 1
        assert rig.path.writes == []


async def test_a_write_to_a_read_only_address_answers_02(rig: Rig) -> None:
    with rig.client() as c:
        with pytest.raises(ModbusException) as e:
            await call(c.write_registers, 4, words_of(1.0))  # ch0.limit: read-only
        assert e.value.code == 2
        with pytest.raises(ModbusException) as e:
            await call(c.write_register, 0, 0x3F00)  # half of a float
        assert e.value.code == 2
    assert rig.path.writes == []


async def test_an_accepted_write_goes_through_the_command_path_with_its_actor(rig: Rig) -> None:
    with rig.client() as c:
        await call(c.write_registers, 0, words_of(0.25))
        await call(c.write_register, 2, 1)  # mode: manual
        await call(c.write_coil, 0, True)
        await call(c.write_register, 3, 1500)
        rig.scan()
        words = await call(c.read_registers, 0, 4, holding=True)
    assert rig.path.writes == [
        ("ch0.manual_current", 0.25, "modbus:127.0.0.1"),
        ("ch0.mode", "manual", "modbus:127.0.0.1"),
        ("ch0.enable", True, "modbus:127.0.0.1"),
        ("ch0.setpoint_ma", 1500.0, "modbus:127.0.0.1"),
    ]
    assert float_of(words[0:2]) == pytest.approx(0.25)
    assert words[2] == 1


async def test_a_refused_write_answers_04_or_03_and_sets_the_refusal_register(
    rig: Rig,
) -> None:
    rig.path.refuse["ch0.manual_current"] = WriteAnswer(False, "not a writer", "forbidden")
    rig.path.refuse["ch0.setpoint_ma"] = WriteAnswer(False, "beyond 2 A", "out of range")
    with rig.client() as c:
        assert (await call(c.read_registers, 8, 1)) == [0]
        with pytest.raises(ModbusException) as e:
            await call(c.write_registers, 0, words_of(0.25))
        assert e.value.code == 4
        assert (await call(c.read_registers, 8, 1)) == [REFUSALS.index("forbidden")]
        with pytest.raises(ModbusException) as e:
            await call(c.write_register, 3, 9000)
        assert e.value.code == 3
        assert (await call(c.read_registers, 8, 1)) == [REFUSALS.index("out of range")]
        with pytest.raises(ModbusException) as e:
            await call(c.write_register, 2, 7)  # no mode has code 7
        assert e.value.code == 3
        assert (await call(c.read_registers, 8, 1)) == [REFUSALS.index("bad argument")]


def test_every_refusal_kind_has_its_code_and_exception() -> None:
    for code, kind in enumerate(REFUSALS[1:], start=1):
        assert refusal_code(kind) == code
        assert exception_of(kind) in (3, 4)
    assert refusal_code("something new") == REFUSALS.index("failed")


# --- robustness -----------------------------------------------------------------------------
async def test_one_client_beyond_max_clients_is_closed() -> None:
    async for rig in serving(max_clients=2):
        a, b = rig.client(), rig.client()
        try:
            assert len(await call(a.read_registers, 0, 2)) == 2
            assert len(await call(b.read_registers, 0, 2)) == 2
            with rig.client() as third, pytest.raises((ConnectionError, OSError)):
                await call(third.read_registers, 0, 2)
            assert len(await call(a.read_registers, 0, 2)) == 2  # the others go on
        finally:
            a.close()
            b.close()
        # A place freed is a place again, once the server has seen the two leave.
        await wait_until(lambda s=rig.server: s.clients == 0, "the two clients gone")
        with rig.client() as again:
            assert len(await call(again.read_registers, 0, 2)) == 2


async def test_malformed_requests_never_put_a_traceback_in_the_log(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    answered = {  # the frame → its exception answer (function | 0x80, code), or closed
        struct.pack(">HHHB", 1, 0, 2, 1) + b"\x04": b"\x84\x03",  # no address nor count
        struct.pack(">HHHB", 2, 0, 5, 1) + b"\x03\x00\x00\x7d": b"\x83\x03",  # cut short
        struct.pack(">HHHB", 3, 0, 300, 1) + b"\x03" + b"\x00" * 299: None,  # oversize
        struct.pack(">HHHB", 4, 7, 6, 1) + b"\x03\x00\x00\x00\x01": None,  # not protocol 0
        struct.pack(">HHHB", 5, 0, 1, 1): None,  # a length without a function code
        b"\xff" * 64: None,  # noise
    }
    for frame, expected in answered.items():
        with rig.client() as c:
            c.send_raw(frame)
            if expected is None:
                with pytest.raises(ConnectionError):
                    await call(c.recv_frame)
            else:
                assert (await call(c.recv_frame))[2] == expected
    with rig.client() as c:  # and it serves the next client
        assert len(await call(c.read_registers, 0, 2)) == 2
    assert not [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]


async def test_a_unit_it_is_not_answers_as_a_gateway_would(rig: Rig) -> None:
    with rig.client(unit=7) as c:
        with pytest.raises(ModbusException) as e:
            await call(c.read_registers, 0, 2)
        assert e.value.code == 0x0B
    with rig.client(unit=0) as c:  # 0 and 255 are answered too
        assert len(await call(c.read_registers, 0, 2)) == 2


# --- the encoding -----------------------------------------------------------------------------
@pytest.mark.parametrize("order", ["big", "little"])
def test_every_kind_decodes_what_it_encodes(order: str) -> None:
    cases: list[tuple[Point, Value]] = [
        (Point(HR, 0, Kind.FLOAT32, "f", writable=True), 0.1875),
        (Point(HR, 0, Kind.INT16, "i", scale=10.0, writable=True), -12.5),
        (Point(HR, 0, Kind.UINT16, "u", scale=1000.0, writable=True), 1.5),
        (Point(HR, 0, Kind.CODE, "c", codes=("auto", "manual"), writable=True), "manual"),
        (Point(CO, 0, Kind.BOOL, "b", writable=True), True),
        (Point(CO, 0, Kind.BOOL, "b", writable=True), False),
    ]
    for point, value in cases:
        words = encode(point, value, order)
        assert words is not None
        assert decode(point, words, order) == value


def test_integers_saturate_and_texts_out_of_the_table_read_as_ffff() -> None:
    assert encode(Point(IR, 0, Kind.INT16, "i"), 1e9, "big") == (32767,)
    assert encode(Point(IR, 0, Kind.INT16, "i"), -1e9, "big") == (0x8000,)
    assert encode(Point(IR, 0, Kind.UINT16, "u"), -3.0, "big") == (0,)
    assert encode(Point(IR, 0, Kind.INT16, "i"), float("nan"), "big") is None
    assert encode(Point(IR, 0, Kind.CODE, "c", codes=("a",)), "zz", "big") == (0xFFFF,)
    assert encode(Point(IR, 0, Kind.FLOAT32, "f"), "text", "big") is None


def test_the_image_serves_only_what_the_map_holds() -> None:
    image = RegisterImage(a_map())
    assert image.served(IR, 0, 10)
    assert not image.served(IR, 0, 11)
    assert image.points_in(HR, 0, 2) is not None
    assert image.points_in(HR, 1, 1) is None


# --- the wiring (app/modbus.py) -----------------------------------------------------------
def chadeche_bench(tmp: Path, modbus: dict[str, object] | None) -> Bench:
    path = Path(chadeche_map(tmp))
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    if modbus is not None:
        data["modbus_server"] = modbus
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return build_bench(load_bench(path), VirtualClock())


def test_no_modbus_server_section_builds_no_server(tmp_path: Path) -> None:
    bench = chadeche_bench(tmp_path, None)
    publishers = list(bench.engine.publishers)
    assert build_modbus(bench) is None
    assert bench.engine.publishers == publishers  # nothing added to the scan


def test_the_server_is_a_publisher_of_the_bench_and_writers_are_its_role_hook(
    tmp_path: Path,
) -> None:
    bench = chadeche_bench(
        tmp_path, {"port": free_tcp_port(), "writes": True, "writers": ["127.0.0.5"]}
    )
    server = build_modbus(bench)
    assert server is not None and server.writes
    assert server.feed in bench.engine.publishers
    assert any(p.tag == "ch0.voltage" for p in server.regmap.points)
    roles = bench.commands.roles
    mine = Command.write("ch0.manual_current", 0.1, "modbus:127.0.0.5")
    theirs = Command.write("ch0.manual_current", 0.1, "modbus:127.0.0.6")
    assert roles.refuses(mine) == ""
    assert "not a Modbus writer" in roles.refuses(theirs)
    assert roles.refuses(Command.write("ch0.manual_current", 0.1, "operator")) == ""
    refused = bench.commands.execute(theirs)
    assert not refused.accepted and refused.kind.value == "forbidden"
    assert bench.commands.log[-1].actor == "modbus:127.0.0.6"  # recorded with its actor
