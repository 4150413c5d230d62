"""EA-PSB 10000 over real TCP on loopback (real clock): what is about TCP itself.

The driver's behaviour is specified in tests/unit/test_ea_driver.py, in process on the
virtual clock. Here: the TCP transport (connect, reply, timeout, closed and over-long lines),
the driver through it, the simulator's server (restart on the same port, raw sessions,
several queries on one line, dropped clients) and its watchdog after a silent socket close.
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest

from supervisor.core.clock import RealClock
from supervisor.core.errors import DeviceIOError, DeviceTimeout, ProtocolError
from supervisor.core.quality import Quality, Reason
from supervisor.devices.ea.driver import EaDriver
from supervisor.devices.ea.protocol import MAX_LINE_BYTES
from supervisor.devices.ea.sim import EaTcpSimulator
from supervisor.devices.ea.transport import TcpScpiTransport
from supervisor.sim.battery import make_model
from supervisor.sim.plant import BenchPlant

pytestmark = pytest.mark.integration

V_MIN = 12.0
V_MAX = 16.8
INPUTS = ("voltage", "current", "power", "output_on", "remote", "ques", "error")

MakeDriver = Callable[..., EaDriver]
Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


@pytest.fixture
def clock() -> RealClock:
    return RealClock()


@pytest.fixture
def plant(clock: RealClock) -> BenchPlant:
    battery = make_model("liion-pack", cells_series=4, capacity_ah=10.0, soc=0.5)
    p = BenchPlant(clock, battery)
    p.set_contactor(True)
    return p


@pytest.fixture
async def sim(plant: BenchPlant) -> AsyncIterator[EaTcpSimulator]:
    s = EaTcpSimulator(plant)
    await s.start()
    yield s
    await s.stop()


@pytest.fixture
async def make_driver(sim: EaTcpSimulator, clock: RealClock) -> AsyncIterator[MakeDriver]:
    drivers: list[EaDriver] = []

    def make(**overrides: Any) -> EaDriver:
        params: dict[str, Any] = {
            "v_min": V_MIN,
            "v_max": V_MAX,
            "i_charge_max_a": 5.0,
            "i_discharge_max_a": 5.0,
            "poll_period_s": 0.1,
            "watchdog_s": 2.0,
            "timeout_s": 1.0,
        }
        params.update(overrides)
        driver = EaDriver("psu", clock, TcpScpiTransport("127.0.0.1", sim.port), **params)
        drivers.append(driver)
        return driver

    yield make
    for driver in drivers:
        await driver.close()


@pytest.fixture
async def driver(make_driver: MakeDriver) -> EaDriver:
    d = make_driver()
    await d.poll()
    assert d.connected, d.last_error
    return d


@pytest.fixture
async def raw_server() -> AsyncIterator[Callable[[Handler], Awaitable[int]]]:
    """A loopback server with a hand-written handler (misbehaving devices); its port."""
    servers: list[asyncio.Server] = []

    async def serve(handler: Handler) -> int:
        server = await asyncio.start_server(handler, "127.0.0.1", 0)
        servers.append(server)
        return int(server.sockets[0].getsockname()[1])

    yield serve
    for server in servers:
        server.close()
        await server.wait_closed()


def value(driver: EaDriver, point: str) -> Any:
    return driver.image()[point].value


def assert_all_good(driver: EaDriver) -> None:
    for point in INPUTS:
        sample = driver.image()[point]
        assert sample.quality is Quality.GOOD, (point, sample)


def assert_all_bad_comm_failure(driver: EaDriver) -> None:
    for point in INPUTS:
        sample = driver.image()[point]
        assert (sample.quality, sample.reason) == (Quality.BAD, Reason.COMM_FAILURE), point


async def wait_for(condition: Callable[[], bool], timeout_s: float = 5.0) -> None:
    """Poll ``condition`` until true; a generous upper bound, not a duration assertion."""
    step_s = 0.02
    for _ in range(round(timeout_s / step_s)):
        if condition():
            return
        await asyncio.sleep(step_s)
    assert condition(), f"condition still false after {timeout_s} s"


async def charge(driver: EaDriver, current_a: float) -> None:
    driver.write("current_set", current_a)
    driver.write("output", True)
    await driver.poll()
    assert driver.connected, driver.last_error


async def raw_session(sim: EaTcpSimulator) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    return await asyncio.open_connection("127.0.0.1", sim.port)


# --- the TCP transport -----------------------------------------------------------------------
async def test_tcp_a_line_sent_gets_its_reply_line(sim: EaTcpSimulator) -> None:
    link = await TcpScpiTransport("127.0.0.1", sim.port).connect("psu", 1.0)
    try:
        await link.send_line(b"OUTP?;SYST:LOCK:OWN?\n", 1.0)
        assert await link.receive_line(1.0) == b"OFF;NONE\n"
    finally:
        await link.close()


async def test_tcp_nothing_listening_is_a_device_io_error_naming_the_address() -> None:
    with socket.socket() as s:  # a free loopback port, closed again: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    with pytest.raises(DeviceIOError, match=rf"psu: cannot connect to 127\.0\.0\.1:{port}: "):
        await TcpScpiTransport("127.0.0.1", port).connect("psu", 1.0)


async def test_tcp_a_silent_device_times_out_naming_the_line(sim: EaTcpSimulator) -> None:
    link = await TcpScpiTransport("127.0.0.1", sim.port).connect("psu", 1.0)
    sim.mute = True
    try:
        await link.send_line(b"*IDN?\n", 0.1)
        with pytest.raises(DeviceTimeout, match=r"psu: no reply to '\*IDN\?' within 0.1 s"):
            await link.receive_line(0.1)
    finally:
        await link.close()


async def test_tcp_a_device_closing_the_socket_is_a_device_io_error(
    sim: EaTcpSimulator,
) -> None:
    link = await TcpScpiTransport("127.0.0.1", sim.port).connect("psu", 1.0)
    try:
        await sim.drop_clients()
        await link.send_line(b"OUTP?\n", 1.0)
        with pytest.raises(DeviceIOError, match="connection closed by the device while waiting"):
            await link.receive_line(1.0)
    finally:
        await link.close()


async def test_tcp_a_reply_line_too_long_is_a_protocol_error_with_the_bytes(
    raw_server: Callable[[Handler], Awaitable[int]],
) -> None:
    async def babble(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readline()
        writer.write(b"Y" * (2 * MAX_LINE_BYTES))
        await writer.drain()
        await reader.read()  # until the client closes
        writer.close()

    port = await raw_server(babble)
    link = await TcpScpiTransport("127.0.0.1", port).connect("psu", 1.0)
    try:
        await link.send_line(b"*IDN?\n", 1.0)
        with pytest.raises(ProtocolError, match="at most 4096 bytes") as info:
            await link.receive_line(1.0)
        assert info.value.raw.startswith(b"YYYY")
    finally:
        await link.close()


async def test_the_driver_charges_over_tcp(
    driver: EaDriver, sim: EaTcpSimulator, plant: BenchPlant
) -> None:
    await charge(driver, 2.0)
    assert plant.pack_current_a == pytest.approx(2.0, abs=0.01)
    assert value(driver, "current") == pytest.approx(2.0, abs=0.01)
    assert "CURR 2.0000; VOLT 16.8000; SINK:CURR 0" in sim.lines
    assert_all_good(driver)


# --- the server --------------------------------------------------------------------------------
async def test_stopping_the_device_marks_inputs_bad_and_restarting_makes_them_good(
    driver: EaDriver, sim: EaTcpSimulator, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("supervisor.devices.base.BACKOFF_START_S", 0.0)
    port = sim.port
    await sim.stop()
    await driver.poll()
    assert_all_bad_comm_failure(driver)
    await sim.start()
    assert sim.port == port
    driver._next_connect_t = float("-inf")
    await driver.poll()
    assert driver.connected, driver.last_error
    assert_all_good(driver)


async def test_the_unit_switches_off_when_the_socket_closes_silently(
    make_driver: MakeDriver, sim: EaTcpSimulator, plant: BenchPlant
) -> None:
    d = make_driver(watchdog_s=0.3, poll_period_s=0.1)
    await d.poll()
    await charge(d, 2.0)
    await d.close()
    await wait_for(lambda: not plant.supply.output_on)
    assert not sim.remote


async def test_sim_disconnect_alone_does_not_switch_the_output_off(
    sim: EaTcpSimulator, plant: BenchPlant
) -> None:
    reader, writer = await raw_session(sim)
    writer.write(b"SYST:LOCK ON;VOLT 16.8;CURR 1;OUTP ON\nOUTP?\n")
    await writer.drain()
    assert await reader.readline() == b"ON\n"
    writer.close()
    await writer.wait_closed()
    await asyncio.sleep(0.1)
    assert plant.supply.output_on
    assert plant.pack_current_a == pytest.approx(1.0, abs=0.01)


async def test_sim_answers_several_queries_on_one_line(sim: EaTcpSimulator) -> None:
    reader, writer = await raw_session(sim)
    try:
        writer.write(b"*IDN?; OUTP? ;SYST:LOCK:OWN?\r\n")
        await writer.drain()
        reply = (await reader.readline()).decode()
    finally:
        writer.close()
        await writer.wait_closed()
    idn, outp, owner = reply.rstrip("\n").split(";")
    assert idn.startswith("EA Elektro-Automatik GmbH & Co. KG, PSB 10060-60, ")
    assert (outp, owner) == ("OFF", "NONE")


async def test_sim_restarts_on_the_same_port(sim: EaTcpSimulator) -> None:
    port = sim.port
    await sim.stop()
    assert not sim.running
    await sim.start()
    assert sim.port == port
    reader, writer = await raw_session(sim)
    try:
        writer.write(b"OUTP?\n")
        await writer.drain()
        assert await reader.readline() == b"OFF\n"
    finally:
        writer.close()
        await writer.wait_closed()


async def test_sim_drop_clients_closes_connections(sim: EaTcpSimulator) -> None:
    reader, writer = await raw_session(sim)
    await sim.drop_clients()
    try:
        assert await reader.read() == b""
    finally:
        writer.close()
        await writer.wait_closed()


def test_sim_served_lists_its_address_and_keeps_its_name(plant: BenchPlant) -> None:
    sim = EaTcpSimulator(plant, port=5025, name="psu1")
    assert sim.name == "psu1"
    assert sim.addresses() == ["EA supply psu1: scpi tcp 127.0.0.1:5025"]
    assert not sim.reachable  # not listening before start()
