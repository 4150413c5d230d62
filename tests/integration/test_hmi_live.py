"""Live data (issue 12 "Live data"): ``/api/ws`` sends a snapshot, then at the publish rate
only the tags that changed; a client that never reads is closed ("too slow", 1008) and
counted, and neither the scan nor the other clients notice. Real server on loopback, the
bench on the virtual clock."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from hmirig import Hmi, hmi_bench

from supervisor.config.models import HmiConfig
from supervisor.tags import TagSpec
from supervisor.testing import wait_until

# It asserts the scan kept its timing (no stall, no overrun) under load it makes itself:
# it runs alone, after the tests that run in parallel (Makefile: the "quiet" marker).
pytestmark = [pytest.mark.integration, pytest.mark.quiet]


class Reader:
    """A page's WebSocket that reads everything, in a task of its own."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self.ws = ws
        self.messages: list[dict[str, Any]] = []
        self.task = asyncio.get_running_loop().create_task(self._read())

    async def _read(self) -> None:
        async for msg in self.ws:
            if msg.type is aiohttp.WSMsgType.TEXT:
                self.messages.append(json.loads(msg.data))

    def of(self, kind: str) -> list[dict[str, Any]]:
        return [m for m in self.messages if m["type"] == kind]

    @property
    def version(self) -> int:
        versions = [m["version"] for m in self.messages if "version" in m]
        return max(versions, default=0)

    async def close(self) -> None:
        await self.ws.close()
        await self.task


async def connect(hmi: Hmi, s: aiohttp.ClientSession) -> Reader:
    ws = await s.ws_connect(f"ws://127.0.0.1:{hmi.api.port}/api/ws")
    return Reader(ws)


async def test_a_page_gets_a_snapshot_then_only_the_tags_that_changed(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=True, publish_period_s=0.5)) as hmi:
        db = hmi.bench.db
        marker = db.add(TagSpec("lab.marker", unit="V", initial=1.0))
        page = await connect(hmi, await hmi.login("vera"))
        await wait_until(lambda: len(page.messages) >= 2, "the snapshot and the alarms")
        snapshot, alarms = page.messages[:2]
        assert snapshot["type"] == "snapshot"
        assert set(snapshot["tags"]) == {t.name for t in db}
        assert snapshot["tags"]["lab.marker"] == {
            "value": 1.0,
            "unit": "V",
            "quality": "UNCERTAIN",
            "reason": "initial value",
            "forced": False,
            "access": "read_only",
            "source_time": None,
            "version": marker.version,
        }
        assert alarms["type"] == "alarms"
        assert [a["id"] for a in alarms["alarms"]] == ["room.temp.H"]  # the rig's plain alarm

        db.update(marker, 2.5)
        await hmi.scans(5)  # 0.5 s: one publication
        await wait_until(lambda: page.of("delta"), "a delta")
        delta = page.of("delta")[0]
        assert delta["tags"]["lab.marker"]["value"] == 2.5
        assert delta["version"] > snapshot["version"]
        # Only what changed since the snapshot: each tag's version is newer, and a tag
        # that did not change (the channel's recipe name) is not sent again.
        assert all(t["version"] > snapshot["version"] for t in delta["tags"].values())
        assert "ch0.chain.recipe" not in delta["tags"]
        assert len(delta["tags"]) < len(snapshot["tags"])

        await hmi.scans(5)
        await wait_until(lambda: len(page.of("delta")) >= 2, "a second delta")
        second = page.of("delta")[1]
        assert "lab.marker" not in second["tags"]  # unchanged since the first delta
        assert all(t["version"] > delta["version"] for t in second["tags"].values())
        await page.close()


async def test_deltas_come_at_the_publish_rate_not_every_scan(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=True, publish_period_s=0.5)) as hmi:
        page = await connect(hmi, await hmi.login("vera"))
        await wait_until(lambda: len(page.messages) >= 2, "the snapshot")
        for _ in range(20):  # 2 s of scans at 0.1 s
            await hmi.scans(1)
        await hmi.scans(1)
        await wait_until(lambda: len(page.of("delta")) >= 4, "four deltas")
        assert len(page.of("delta")) in (4, 5)
        await page.close()


async def test_alarm_changes_and_commands_reach_the_page(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.login("otto")
        page = await connect(hmi, s)
        await wait_until(lambda: len(page.messages) >= 2, "the snapshot")
        status, body = await hmi.call(s, "POST", "/api/alarms/room.temp.H/acknowledge", {})
        assert status == 200, body
        await hmi.scans(3)
        await wait_until(lambda: len(page.of("alarms")) >= 2, "the alarms after the ack")
        acked = page.of("alarms")[-1]["alarms"][0]
        assert (acked["id"], acked["acked_by"]) == ("room.temp.H", "hmi:otto")
        await wait_until(lambda: page.of("event"), "the command's event")
        events = [m["event"] for m in page.of("event")]
        assert any(e["kind"] == "command" and e["actor"] == "hmi:otto" for e in events), events
        assert "t" not in events[0] and isinstance(events[0]["wall"], float)
        await page.close()


async def test_the_websocket_needs_a_session_when_anonymous_read_is_off(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=True, anonymous_read=False)) as hmi:
        s = await hmi.client()
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await s.ws_connect(f"ws://127.0.0.1:{hmi.api.port}/api/ws")
        assert refused.value.status == 401
        page = await connect(hmi, await hmi.login("vera"))
        await wait_until(lambda: page.of("snapshot"), "the snapshot")
        await page.close()


async def test_a_websocket_closes_when_its_session_expires(tmp_path: Path) -> None:
    cfg = HmiConfig(login=True, anonymous_read=False, session_timeout_s=2.0)
    async with hmi_bench(tmp_path, cfg) as hmi:
        page = await connect(hmi, await hmi.login("vera"))
        await wait_until(lambda: page.of("snapshot"), "the snapshot")
        await hmi.scans(25)
        await wait_until(lambda: page.task.done(), "the page's socket closed")
        assert page.ws.close_code == 1008
        assert not hmi.screens.live.clients


# --- a client that never reads -----------------------------------------------------------
def frames(data: bytes) -> list[tuple[int, bytes]]:
    """(opcode, payload) of the server's frames (RFC 6455 §5.2; unmasked, no extension)."""
    out, i = [], 0
    while i + 2 <= len(data):
        opcode, n = data[i] & 0x0F, data[i + 1] & 0x7F
        i += 2
        if n == 126:
            (n,) = struct.unpack("!H", data[i : i + 2])
            i += 2
        elif n == 127:
            (n,) = struct.unpack("!Q", data[i : i + 8])
            i += 8
        if i + n > len(data):
            break
        out.append((opcode, data[i : i + n]))
        i += n
    return out


class DeafClient:
    """A WebSocket client that upgrades, then never reads (a frozen tab, a dead tablet):
    a tiny receive buffer, a reader that stops at 1 KiB."""

    async def open(self, port: int, cookie: str) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
        self.reader, self.writer = await asyncio.open_connection(sock=sock, limit=1024)
        self.writer.write(
            (
                "GET /api/ws HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
                "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                f"Sec-WebSocket-Version: 13\r\nCookie: {cookie}\r\n\r\n"
            ).encode()
        )
        head = await self.reader.readuntil(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 101"), head

    async def read_all(self) -> bytes:
        chunks = []
        while chunk := await self.reader.read(65536):
            chunks.append(chunk)
        self.writer.close()
        return b"".join(chunks)


async def test_a_client_that_never_reads_is_dropped_without_slowing_the_scan(
    tmp_path: Path,
) -> None:
    async with hmi_bench(tmp_path, queue_size=4) as hmi:
        db, live, engine = hmi.bench.db, hmi.screens.live, hmi.bench.engine
        # Enough changes per publication (about 100 kB) to fill the deaf client's socket.
        load = [db.add(TagSpec(f"lab.load{i:03d}", dtype="str", initial="")) for i in range(300)]
        s = await hmi.login("vera")
        cookie = "; ".join(f"{c.key}={c.value}" for c in s.cookie_jar)
        deaf = DeafClient()
        await deaf.open(hmi.api.port, cookie)
        page = await connect(hmi, s)
        await wait_until(lambda: len(live.clients) == 2, "both clients connected")
        overruns, stalls = engine.stats.overruns, engine.stats.stalls
        for n in range(400):
            for i, tag in enumerate(load):
                db.update(tag, f"{n:04d}-{i:03d}-" + "x" * 300)
            await hmi.scans(2)  # one publication
            # The reading page keeps up (as a real one does between two publications).
            await wait_until(lambda: page.version >= live.version, "the page reads")
            if live.dropped:
                break
        assert live.dropped == 1, "the deaf client was never dropped"
        assert len(live.clients) == 1
        deltas_before = len(page.of("delta"))
        await hmi.scans(10)
        assert db["hmi.ws_dropped"].value == 1
        assert db["hmi.ws_clients"].value == 1
        await wait_until(lambda: len(page.of("delta")) >= deltas_before + 4, "more deltas")
        # The scan never waited: no overrun, no stall, while a client would not read.
        assert engine.stats.overruns == overruns == 0
        assert engine.stats.stalls == stalls == 0
        # What the deaf client finally reads ends with the close frame: 1008 "too slow".
        data = await asyncio.wait_for(deaf.read_all(), 30)
        opcode, payload = frames(data)[-1]
        assert opcode == 0x8
        assert struct.unpack("!H", payload[:2])[0] == 1008 and payload[2:] == b"too slow"
        await page.close()
