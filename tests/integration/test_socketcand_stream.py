"""The product's socketcand client against a daemon it did not write (tests/socketcand_peer.py,
from linux-can/socketcand's source): TCP is a stream, and the client reads it as one
(issue 32, finding 1). Kernel vcan where the machine has it."""

from __future__ import annotations

import asyncio
import math
import shutil
import subprocess
from collections.abc import AsyncIterator
from pathlib import Path

import can
import pytest

from supervisor.core.clock import RealClock
from supervisor.core.quality import Quality, Reason
from supervisor.devices.bms.driver import FAULT_PACK_VOLTAGE, BmsDriver, socketcand_bus_factory
from supervisor.fieldbus.socketcand import SocketcandBus
from tests.socketcand_peer import SocketcandPeer, frame_element

pytestmark = pytest.mark.integration

CURRENT_FRAME = frame_element(0x2B0, bytes.fromhex("C0A0000000000000"))  # -5.0 A, padded
MAX_POLLS = 300


@pytest.fixture
async def peer() -> AsyncIterator[SocketcandPeer]:
    daemon = SocketcandPeer()
    await daemon.start()
    yield daemon
    await daemon.stop()


async def open_bus(peer: SocketcandPeer, channel: str = "can0") -> SocketcandBus:
    return await asyncio.to_thread(SocketcandBus, channel, "127.0.0.1", peer.port, 2.0)


async def recv(bus: can.BusABC, timeout_s: float = 2.0) -> can.Message | None:
    return await asyncio.to_thread(bus.recv, timeout_s)


# python-can's client leaves its socket open when its handshake fails.
@pytest.mark.filterwarnings("ignore::ResourceWarning")
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
async def test_python_cans_own_client_fails_when_a_frame_shares_the_segment_of_ok(
    peer: SocketcandPeer,
) -> None:
    # The finding as it was: one recv, an exact comparison with '< ok >'.
    peer.with_ok = CURRENT_FRAME
    with pytest.raises(can.CanError, match=r"Expected '< ok >' got: '< ok >< frame 2B0"):
        await asyncio.to_thread(
            can.Bus, interface="socketcand", channel="can0", host="127.0.0.1", port=peer.port
        )


async def test_a_frame_in_the_same_segment_as_ok_is_received(peer: SocketcandPeer) -> None:
    peer.with_ok = CURRENT_FRAME
    bus = await open_bus(peer)
    try:
        msg = await recv(bus)
        assert msg is not None
        assert (msg.arbitration_id, bytes(msg.data), msg.is_extended_id) == (
            0x2B0,
            bytes.fromhex("C0A0000000000000"),
            False,
        )
        assert msg.timestamp == pytest.approx(1733412345.5)
    finally:
        bus.shutdown()


async def test_a_frame_just_after_ok_is_received(peer: SocketcandPeer) -> None:
    bus = await open_bus(peer)
    try:
        await peer.wait_raw()
        await peer.write(CURRENT_FRAME)
        msg = await recv(bus)
        assert msg is not None
        assert msg.arbitration_id == 0x2B0
    finally:
        bus.shutdown()


async def test_elements_split_across_segments_are_put_back_together(
    peer: SocketcandPeer,
) -> None:
    peer.segment_bytes = 3  # '< h', 'i >', … the greeting and the replies too
    peer.with_ok = frame_element(0x1B0, bytes.fromhex("00003900 0E6A0E7E"))
    bus = await open_bus(peer)
    try:
        got = [await recv(bus)]  # the one with the < ok >
        await peer.wait_raw()
        await peer.write(CURRENT_FRAME + frame_element(0x12345678, b"\x01", extended=True))
        got += [await recv(bus), await recv(bus)]
        assert [(m.arbitration_id, m.is_extended_id) for m in got if m is not None] == [
            (0x1B0, False),
            (0x2B0, False),
            (0x12345678, True),
        ]
        assert bus.garbage_bytes == 0
    finally:
        bus.shutdown()


async def test_garbage_between_elements_is_skipped_and_the_next_frame_decodes(
    peer: SocketcandPeer,
) -> None:
    bus = await open_bus(peer)
    try:
        await peer.write(
            b"garbage\r\n< frame 2B0 17334"  # an element cut short by the next one
            + b"< frame 2B0 notatime C0A00000 >"  # malformed: skipped
            + b"< frame 7FF0 1.000000 00 >"  # an id of 4 digits: neither kind, skipped
            + CURRENT_FRAME
        )
        msg = await recv(bus)
        assert msg is not None
        assert bytes(msg.data) == bytes.fromhex("C0A0000000000000")
        assert bus.garbage_bytes > 0
    finally:
        bus.shutdown()


async def test_an_error_frame_arrives_as_an_error_message(peer: SocketcandPeer) -> None:
    bus = await open_bus(peer)
    try:
        await peer.write(b"< error 004 1733412345.000001 >")  # state_raw: CAN_ERR_FLAG
        msg = await recv(bus)
        assert msg is not None
        assert msg.is_error_frame
        assert msg.arbitration_id == 0x004
    finally:
        bus.shutdown()


async def test_a_bus_the_daemon_does_not_serve_is_refused_with_its_error_text(
    peer: SocketcandPeer,
) -> None:
    with pytest.raises(can.CanInitializationError, match="error could not open bus"):
        await open_bus(peer, "can7")


async def test_a_connection_the_daemon_closes_raises_instead_of_looking_quiet(
    peer: SocketcandPeer,
) -> None:
    bus = await open_bus(peer)
    try:
        await peer.wait_raw()
        await peer.close_clients()
        with pytest.raises(can.CanOperationError, match="closed the connection"):
            await recv(bus)
    finally:
        bus.shutdown()


async def test_a_sent_frame_reaches_the_daemon_as_its_send_command(peer: SocketcandPeer) -> None:
    bus = await open_bus(peer)
    try:
        bus.send(
            can.Message(arbitration_id=0x2B0, data=bytes.fromhex("42C80000"), is_extended_id=False)
        )
        bus.send(can.Message(arbitration_id=0x1ABCDEF0, data=b"", is_extended_id=True))
        for _ in range(MAX_POLLS):
            if len(peer.received) == 2:
                break
            await asyncio.sleep(0.01)
        # What state_raw.c's sscanf("< %*s %x %hhu %hhx …") takes.
        assert peer.received == ["send 2B0 4 42 C8 00 00", "send 1ABCDEF0 0"]
    finally:
        bus.shutdown()


async def test_the_bms_driver_reads_the_annex_frames_through_the_daemon(
    peer: SocketcandPeer,
) -> None:
    annex_voltage = frame_element(0x1B0, bytes.fromhex("00C350A0030005F0"))  # 12 800.16 V
    peer.with_ok = CURRENT_FRAME + annex_voltage  # a busy bus: frames with the < ok >
    driver = BmsDriver(
        "bms",
        RealClock(),
        socketcand_bus_factory("127.0.0.1", peer.port),
        silence_timeout_s=math.inf,
    )
    try:
        for _ in range(MAX_POLLS):
            await driver.poll()
            if driver.image()["pack_voltage"].value is not None:
                break
            await asyncio.sleep(0.01)
        image = driver.image()
        assert driver.connected
        assert image["pack_current"].value == pytest.approx(-5.0)
        assert image["pack_current"].quality is Quality.GOOD
        assert image["pack_voltage"].value == pytest.approx(12800.16)
        assert (image["pack_voltage"].quality, image["pack_voltage"].reason) == (
            Quality.BAD,
            Reason.OUT_OF_RANGE,
        )
        assert image["faults"].value & FAULT_PACK_VOLTAGE
    finally:
        await driver.close()


# --- kernel SocketCAN (the preferred wiring) ----------------------------------------------


def _vcan() -> tuple[str, bool]:
    """An existing vcan interface, or one made here (name, made); skips with why not."""
    for path in sorted(Path("/sys/class/net").glob("vcan*")):
        return path.name, False
    ip = shutil.which("ip")
    if ip is None:
        pytest.skip("no vcan interface and no ip command to make one")
    proc = subprocess.run(
        [ip, "link", "add", "dev", "vcansup0", "type", "vcan"],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        pytest.skip(f"kernel vcan not available (ip link add … type vcan: {proc.stderr.strip()})")
    subprocess.run([ip, "link", "set", "up", "vcansup0"], check=True)
    return "vcansup0", True


async def test_the_bms_driver_on_kernel_vcan() -> None:
    name, made = _vcan()
    sender = can.Bus(interface="socketcan", channel=name)
    driver = BmsDriver(
        "bms",
        RealClock(),
        lambda: can.Bus(interface="socketcan", channel=name),
        silence_timeout_s=math.inf,
    )
    try:
        await driver.poll()
        sender.send(
            can.Message(
                arbitration_id=0x2B0, data=bytes.fromhex("C0A0000000000000"), is_extended_id=False
            )
        )
        for _ in range(MAX_POLLS):
            await driver.poll()
            if driver.image()["pack_current"].value is not None:
                break
            await asyncio.sleep(0.01)
        assert driver.image()["pack_current"].value == pytest.approx(-5.0)
    finally:
        await driver.close()
        sender.shutdown()
        if made:
            await asyncio.to_thread(subprocess.run, ["ip", "link", "delete", name], check=False)
