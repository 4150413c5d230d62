"""EA-PSB 10000 over real TCP on loopback (real clock): what only TCP has.

The driver's contract (connect, current, device errors, a malformed reply, the unit stopped
and started again on the same port, the safe state, a line and its reply, a silent device)
runs on both transports in tests/unit/test_ea_driver.py (class
``TestDriverOnBothTransports``; its TCP runs are marked ``integration`` too). Here: nothing
listening, a socket closed by the device, an over-long line from a raw server, the
simulator's server (raw sessions, several queries on one line, dropped clients, restart on
the same port) and its watchdog after a silent socket close.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest
from ea_rig import EaRig, charge, make_plant, open_rig
from rig_transports import TCP

from supervisor.core.clock import RealClock
from supervisor.core.errors import DeviceIOError, ProtocolError
from supervisor.devices.ea.sim import EaTcpSimulator
from supervisor.fieldbus.scpi import MAX_LINE_BYTES
from supervisor.fieldbus.scpi_transport import TcpScpiTransport
from supervisor.testing import free_tcp_port, wait_until

pytestmark = pytest.mark.integration

Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


@pytest.fixture
async def rig() -> AsyncIterator[EaRig]:
    """The unit served on a loopback port the OS picks (real clock)."""
    async with open_rig(TCP, RealClock()) as r:
        yield r


@pytest.fixture
def sim(rig: EaRig) -> EaTcpSimulator:
    assert isinstance(rig.sim, EaTcpSimulator)
    return rig.sim


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


async def raw_session(sim: EaTcpSimulator) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    return await asyncio.open_connection("127.0.0.1", sim.port)


# --- the TCP transport -----------------------------------------------------------------------
async def test_tcp_nothing_listening_is_a_device_io_error_naming_the_address() -> None:
    port = free_tcp_port()  # closed again at once: nothing listens there
    with pytest.raises(DeviceIOError, match=rf"psu: cannot connect to 127\.0\.0\.1:{port}: "):
        await TcpScpiTransport("127.0.0.1", port).connect("psu", 1.0)


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


# --- the server --------------------------------------------------------------------------------
async def test_the_unit_switches_off_when_the_socket_closes_silently(
    rig: EaRig, sim: EaTcpSimulator
) -> None:
    d = rig.make_driver(watchdog_s=0.3, poll_period_s=0.1)
    await d.poll()
    await charge(d, 2.0)
    # The socket goes away without a word (a crash): not close(), which now switches the
    # output off and releases the lock itself (test_ea_driver.py).
    await d._drop_transport()
    await wait_until(lambda: not rig.plant.supply.output_on, "the watchdog switched the output off")
    assert not sim.remote
    assert sim.watchdog_trips == 1


async def test_sim_disconnect_alone_does_not_switch_the_output_off(
    sim: EaTcpSimulator, rig: EaRig
) -> None:
    reader, writer = await raw_session(sim)
    writer.write(b"SYST:LOCK ON;VOLT 16.8;CURR 1;OUTP ON\nOUTP?\n")
    await writer.drain()
    assert await reader.readline() == b"ON\n"
    writer.close()
    await writer.wait_closed()
    await asyncio.sleep(0.1)
    assert rig.plant.supply.output_on
    assert rig.plant.pack_current_a == pytest.approx(1.0, abs=0.01)


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


def test_sim_served_lists_its_address_and_keeps_its_name() -> None:
    sim = EaTcpSimulator(make_plant(RealClock()), port=5025, name="psu1")
    assert sim.name == "psu1"
    assert sim.addresses() == ["EA supply psu1: scpi tcp 127.0.0.1:5025"]
    assert not sim.reachable  # not listening before start()
