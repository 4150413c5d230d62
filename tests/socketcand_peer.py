"""A socketcand daemon for tests, written from linux-can/socketcand's source (state_nobus.c,
state_raw.c, socketcand.c), not from the project's simulator (``SocketcandServer``).

What it does as the daemon does: greets ``< hi >``; ``< open BUS >`` answers ``< ok >``
for a bus it serves, ``< error could not open bus >`` and closes otherwise; ``< rawmode >``
answers ``< ok >``; in raw mode a frame goes out as ``< frame %03X %lld.%06lld DATA >``
(``%08X`` for an extended id, data bytes ``%02X`` back to back), ``< echo >`` is echoed,
``< send ID DLC B0 … >`` is taken (recorded here), anything else answers
``< error unknown command >``. Commands are read as the daemon reads them: the bytes from
one ``<`` to the next ``>``, whatever the segments.

What a test controls, to reproduce what TCP does to a real daemon's output: ``with_ok``
(bytes written in the same ``write`` as the raw mode's ``< ok >``, so in one segment),
``segment_bytes`` (every write cut into pieces of that many bytes, each sent on its own:
elements split across segments), and :meth:`write` (any bytes, garbage included).
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Iterable

MAX_COMMAND_BYTES = 4096


def frame_element(
    frame_id: int, data: bytes, t: float = 1733412345.5, *, extended: bool = False
) -> bytes:
    """One received frame as the daemon's ``state_raw`` prints it."""
    ident = f"{frame_id:08X}" if extended else f"{frame_id:03X}"
    sec, usec = int(t), round((t - int(t)) * 1e6)
    return f"< frame {ident} {sec}.{usec:06d} {data.hex().upper()} >".encode("ascii")


class SocketcandPeer:
    def __init__(self, buses: Iterable[str] = ("can0",)) -> None:
        self.buses = set(buses)
        self.with_ok = b""
        self.segment_bytes: int | None = None
        self.received: list[str] = []  # commands taken in raw mode (``send ...``)
        self._server: asyncio.Server | None = None
        self._raw: list[asyncio.StreamWriter] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self.port = 0

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
        for w in self._writers:
            w.close()  # the session reads EOF and ends
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()

    async def wait_raw(self, clients: int = 1) -> None:
        """Until ``clients`` clients are in raw mode and their ``< ok >`` is written."""
        for _ in range(1000):
            if len(self._raw) >= clients:
                return
            await asyncio.sleep(0.005)
        raise TimeoutError(f"{len(self._raw)} clients in raw mode, not {clients}")

    async def write(self, data: bytes) -> None:
        """To every client in raw mode, cut as ``segment_bytes`` says."""
        for w in list(self._raw):
            await self._send(w, data)

    async def close_clients(self) -> None:
        for w in self._raw:
            w.close()
        self._raw.clear()

    async def _send(self, w: asyncio.StreamWriter, data: bytes) -> None:
        step = self.segment_bytes or len(data) or 1
        for i in range(0, len(data), step):
            if i:
                await asyncio.sleep(0.005)  # TCP_NODELAY: each piece its own segment
            w.write(data[i : i + step])
            await w.drain()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        self._writers.add(writer)
        sock = writer.get_extra_info("socket")
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            await self._session(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError):
            pass  # the client went away: as the daemon, end the session
        finally:
            self._tasks.discard(task)
            self._writers.discard(writer)
            if writer in self._raw:
                self._raw.remove(writer)
            writer.close()

    async def _session(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await self._send(writer, b"< hi >")
        state = "nobus"
        buf = b""
        while True:
            start = buf.find(b"<")
            end = buf.find(b">", start) if start >= 0 else -1
            if end < 0:
                chunk = await reader.read(MAX_COMMAND_BYTES)
                if not chunk:
                    return
                buf += chunk
                continue
            command, buf = buf[start : end + 1].decode("ascii"), buf[end + 1 :]
            state = await self._command(writer, state, command)
            if state == "closed":
                return

    async def _command(self, writer: asyncio.StreamWriter, state: str, command: str) -> str:
        words = command.strip("<> ").split()
        if state == "nobus":
            if words[:1] == ["open"] and len(words) == 2:
                if words[1] not in self.buses:
                    await self._send(writer, b"< error could not open bus >")
                    return "closed"
                await self._send(writer, b"< ok >")
                return "bcm"
        elif command == "< rawmode >":
            await self._send(writer, b"< ok >" + self.with_ok)
            self._raw.append(writer)
            return "raw"
        elif state == "raw" and command == "< echo >":
            await self._send(writer, b"< echo >")
            return state
        elif state == "raw" and words[:1] == ["send"]:
            self.received.append(" ".join(words))
            return state
        await self._send(writer, b"< error unknown command >")
        return state
