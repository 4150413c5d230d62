"""Simulated BMS on a python-can bus, and a minimal socketcand server to cross processes.

``BmsSimulator`` sends the three BMS frames (protocols/bms.py) at their own periods on any
``can.BusABC``: a python-can ``virtual`` bus inside one process, or the sink of a
``SocketcandServer`` so that a supervisor in another process (or task) can connect with
python-can's own client, ``can.Bus(interface="socketcand", channel="can0", host=..., port=...)``.
These machines have no ``vcan`` module and python-can's ``udp_multicast`` does not stay on
loopback (reference/devices.md), hence the socketcand server.

socketcand ASCII protocol as spoken here (and as python-can 4.6.1's client expects it: it
reads each handshake answer with a single ``recv(256)`` and compares it exactly)::

    server: < hi >
    client: < open can0 >        server: < ok >      (other channel: < error ... >, close)
    client: < rawmode >          server: < ok >
    server: < frame 2B0 1767225600.000000 42C80000 >     (id: 3 hex digits, 8 if extended)
    client: < send 2B0 4 42 c8 0 0 >                     (id, length, bytes, all hex)

After the last ``< ok >`` the server waits ``handshake_settle_s`` before streaming, so that
the client's handshake ``recv`` cannot receive the ``< ok >`` glued to a frame.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any, Final, Protocol

import can

from supervisor.core.clock import Clock
from supervisor.devices.bms.protocol import FRAME_IDS, BmsValues, encode_values, period_s
from supervisor.sim.plant import BenchPlant

log = logging.getLogger(__name__)


class FrameSink(Protocol):
    """Where the simulator sends its frames: a python-can bus, or the in-process pipe."""

    def send(self, msg: can.Message, timeout: float | None = None) -> None: ...


class BmsSimulator:
    """Send the BMS frames on ``bus``, each at its own period, values from ``source()``.

    Deadlines are absolute on ``clock`` (an overrun skips the missed periods, no burst);
    ``source`` is called at most once per deadline instant. ``paused`` (for tests) keeps the
    task running but sends nothing, as a BMS that went silent. ``send_raw`` injects any frame
    (wrong length, unknown id) right away. The bus belongs to the caller: ``stop()`` does not
    shut it down.
    """

    def __init__(
        self,
        bus: FrameSink,
        clock: Clock,
        source: Callable[[], BmsValues],
        *,
        periods_s: Mapping[int, float] | None = None,
    ) -> None:
        self._bus = bus
        self._clock = clock
        self._source = source
        self._periods = dict(periods_s) if periods_s is not None else {}
        for frame_id in FRAME_IDS:
            self._periods.setdefault(frame_id, period_s(frame_id))
        for frame_id, p in self._periods.items():
            if frame_id not in FRAME_IDS:
                raise ValueError(f"BMS simulator: unknown frame id 0x{frame_id:X}")
            if p <= 0:
                raise ValueError(f"BMS simulator: period of 0x{frame_id:03X} must be > 0")
        self.paused = False
        self.frames_sent = 0
        self.send_errors = 0
        self._task: asyncio.Task[None] | None = None
        self._error_logged = False
        self._deadlines: dict[int, float] | None = None

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    async def start(self) -> None:
        if self.running:
            return
        self._task = asyncio.create_task(self._run(), name="bms-simulator")

    async def stop(self) -> None:
        """Stop sending; re-raises an unexpected error of the sending task."""
        task, self._task = self._task, None
        if task is None:
            return
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    def send_raw(self, frame_id: int, data: bytes, *, extended: bool | None = None) -> None:
        """Send one frame now, whatever its content (``extended`` default: id > 0x7FF)."""
        is_extended = frame_id > 0x7FF if extended is None else extended
        self._bus.send(
            can.Message(
                arbitration_id=frame_id,
                data=bytes(data),
                is_extended_id=is_extended,
                timestamp=self._clock.to_wall(self._clock.now()),
            )
        )

    def pump(self, now: float) -> float:
        """Send the frames due at ``now``; the next deadline. The sending task calls it after
        each sleep; in process (no task: a virtual clock moves only when the scan sleeps) the
        driver's end of the link calls it before it reads."""
        deadlines = self._deadlines
        if deadlines is None:
            deadlines = self._deadlines = dict.fromkeys(self._periods, now)
        due = [frame_id for frame_id, t in deadlines.items() if t <= now]
        if due and not self.paused:
            self._send_frames(due, now)
        for frame_id in due:
            period = self._periods[frame_id]
            t = deadlines[frame_id] + period
            if t <= now:  # overrun: skip the missed periods
                t = now + period
            deadlines[frame_id] = t
        return min(deadlines.values())

    async def _run(self) -> None:
        nxt = self.pump(self._clock.now())
        while True:
            await self._clock.sleep_until(nxt)
            nxt = self.pump(self._clock.now())

    def _send_frames(self, due: list[int], now: float) -> None:
        try:
            frames = encode_values(self._source())
        except ValueError as exc:
            self._log_error_once("values out of the DBC range: %s", exc)
            return
        wall = self._clock.to_wall(now)
        for frame_id in sorted(due):
            msg = can.Message(
                arbitration_id=frame_id,
                data=frames[frame_id],
                is_extended_id=False,
                timestamp=wall,
            )
            try:
                self._bus.send(msg)
            except (can.CanError, OSError) as exc:
                self.send_errors += 1
                self._log_error_once("send failed: %s", exc)
            else:
                self.frames_sent += 1

    def _log_error_once(self, fmt: str, exc: Exception) -> None:
        if not self._error_logged:
            log.warning("BMS simulator: " + fmt, exc)
            self._error_logged = True


class SocketcandServerBus(can.BusABC):
    """The server side of a :class:`SocketcandServer` as a python-can bus.

    ``send()`` pushes a frame to every client in raw mode (dropped while the server is stopped
    or has no client, as on a bus nobody listens to); ``recv()`` returns the frames clients
    sent with ``< send ... >``. Lives as long as its server, across ``stop()``/``start()``;
    call ``shutdown()`` when done with it.
    """

    def __init__(self, server: SocketcandServer, channel: str, **kwargs: Any) -> None:
        self._server = server
        self._rx: queue.Queue[can.Message] = queue.Queue()
        self.channel_info = f"socketcand server, channel {channel}"
        super().__init__(channel=channel, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._is_shutdown:
            raise can.CanOperationError("socketcand server bus is shut down")
        self._server.broadcast(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._is_shutdown:
            raise can.CanOperationError("socketcand server bus is shut down")
        try:
            return self._rx.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def _deliver(self, msg: can.Message) -> None:
        if not self._is_shutdown:
            self._rx.put(msg)


class _Client:
    __slots__ = ("peer", "writer")

    def __init__(self, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        self.peer = writer.get_extra_info("peername")


class SocketcandServer:
    """Minimal socketcand server (raw mode only) for python-can's socketcand client.

    ``port=0`` picks a free port at the first ``start()``; later ``start()`` calls (after
    ``stop()``) listen on the same port again, so a client can reconnect. ``stop()`` closes
    the listening socket and every client connection.
    """

    MAX_CLIENT_BUFFER = 1 << 20
    """A client whose unsent data exceeds this many bytes is disconnected (not reading)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        channel: str = "can0",
        handshake_settle_s: float = 0.1,
    ) -> None:
        self.host = host
        self._port = port
        self.channel = channel
        self.handshake_settle_s = handshake_settle_s
        self.bus = SocketcandServerBus(self, channel)
        self._server: asyncio.Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._clients: set[_Client] = set()
        self._handlers: set[asyncio.Task[Any]] = set()

    @property
    def port(self) -> int:
        """TCP port (the chosen one once started with ``port=0``)."""
        return self._port

    @property
    def serving(self) -> bool:
        return self._server is not None

    @property
    def clients(self) -> int:
        """Clients currently in raw mode (receiving frames)."""
        return len(self._clients)

    async def start(self) -> None:
        if self._server is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._server = await asyncio.start_server(self._handle, self.host, self._port)
        self._port = self._server.sockets[0].getsockname()[1]
        log.info("socketcand server on %s:%d (%s)", self.host, self._port, self.channel)

    async def stop(self) -> None:
        server, self._server = self._server, None
        if server is None:
            return
        server.close()
        for client in list(self._clients):
            client.writer.close()
        self._clients.clear()
        handlers = list(self._handlers)
        for task in handlers:
            task.cancel()
        await asyncio.gather(*handlers, return_exceptions=True)
        await server.wait_closed()

    def broadcast(self, msg: can.Message, exclude: _Client | None = None) -> None:
        """Push ``msg`` to every raw-mode client (thread-safe)."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        if threading.get_ident() != self._loop_thread:
            loop.call_soon_threadsafe(self.broadcast, msg, exclude)
            return
        line = _frame_line(msg)
        for client in list(self._clients):
            if client is not exclude:
                self._push(client, line)

    def _push(self, client: _Client, line: bytes) -> None:
        writer = client.writer
        if writer.is_closing():
            self._clients.discard(client)
            return
        if writer.transport.get_write_buffer_size() > self.MAX_CLIENT_BUFFER:
            log.warning("socketcand server: client %s does not read, dropping it", client.peer)
            self._clients.discard(client)
            writer.close()
            return
        writer.write(line)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._handlers.add(task)
        client = _Client(writer)
        try:
            await self._serve(client, reader)
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError):
            pass  # client went away or sent garbage
        except asyncio.CancelledError:
            # stop() ends the handlers; finishing normally keeps asyncio's stream callback,
            # which asks the task for its exception, from logging the cancellation as an error.
            pass
        finally:
            self._clients.discard(client)
            writer.close()
            with contextlib.suppress(OSError, asyncio.CancelledError):
                await writer.wait_closed()
            if task is not None:
                self._handlers.discard(task)

    async def _serve(self, client: _Client, reader: asyncio.StreamReader) -> None:
        writer = client.writer
        writer.write(b"< hi >")
        await writer.drain()
        words = await _read_command(reader)
        if words is None:
            return
        if len(words) != 2 or words[0] != "open":
            writer.write(b"< error expected open >")
            return
        if words[1] != self.channel:
            writer.write(b"< error could not open bus >")
            return
        writer.write(b"< ok >")
        await writer.drain()
        words = await _read_command(reader)
        if words != ["rawmode"]:
            if words is not None:
                writer.write(b"< error only rawmode is supported >")
            return
        writer.write(b"< ok >")
        await writer.drain()
        await asyncio.sleep(self.handshake_settle_s)
        self._clients.add(client)
        while (words := await _read_command(reader)) is not None:
            if words and words[0] == "send":
                msg = _parse_send(words, self.channel)
                if msg is None:
                    log.warning("socketcand server: bad send command %r", " ".join(words))
                    continue
                self.bus._deliver(msg)
                self.broadcast(msg, exclude=client)
            else:
                # Raw mode knows only "send"; never answer "< error ... >" here: python-can
                # would parse it as a CAN error frame.
                log.debug("socketcand server: ignored command %r", " ".join(words))


async def _read_command(reader: asyncio.StreamReader) -> list[str] | None:
    """Words between ``<`` and ``>`` of the next command; ``None`` at end of stream."""
    try:
        chunk = await reader.readuntil(b">")
    except asyncio.IncompleteReadError:
        return None
    text = chunk.decode("ascii", errors="replace")
    start = text.find("<")
    if start == -1:
        return []
    return text[start + 1 : -1].split()


def _parse_send(words: list[str], channel: str) -> can.Message | None:
    # send <id> <len> <b0> ... : every field hex; 8-digit id = extended (socketcand rule).
    if len(words) < 3:
        return None
    try:
        frame_id = int(words[1], 16)
        length = int(words[2], 16)
        data = bytes(int(b, 16) for b in words[3:])
    except ValueError:
        return None
    if length != len(data) or frame_id > 0x1FFFFFFF:
        return None
    return can.Message(
        arbitration_id=frame_id,
        data=data,
        is_extended_id=len(words[1]) != 3,
        timestamp=time.time(),
        channel=channel,
        is_rx=True,
    )


def _frame_line(msg: can.Message) -> bytes:
    if msg.is_extended_id:
        can_id = f"{msg.arbitration_id & 0x1FFFFFFF:08X}"
    else:
        can_id = f"{msg.arbitration_id & 0x7FF:03X}"
    stamp = msg.timestamp if msg.timestamp else time.time()
    return f"< frame {can_id} {stamp:.6f} {bytes(msg.data).hex().upper()} >".encode("ascii")


# --- wiring from an I/O map --------------------------------------------------------------
CELL_SPREAD_V: Final = 0.004
"""Simulated spread between the lowest and the highest cell of the pack."""


def plant_values(plant: BenchPlant, cells_series: int) -> Callable[[], BmsValues]:
    """What the BMS of the plant's pack reports, read from the plant at each frame."""

    def values() -> BmsValues:
        v = plant.pack_voltage_v
        cell = v / cells_series
        t = plant.pack_temperature_c
        return BmsValues(
            pack_voltage_v=v,
            min_cell_v=cell - CELL_SPREAD_V / 2,
            max_cell_v=cell + CELL_SPREAD_V / 2,
            pack_current_a=plant.pack_current_a,
            min_temp_c=t - 0.5,
            max_temp_c=t + 0.5,
            avg_temp_c=t,
        )

    return values


class InProcessCanBus(can.BusABC):
    """The driver's end of an in-process link to a :class:`BmsSimulator`: each read first
    lets the simulator send what is due at ``clock.now()`` — deterministic on a virtual
    clock, where no simulator task may sleep on its own."""

    MAX_QUEUED = 10_000

    def __init__(self, clock: Clock, **kwargs: Any) -> None:
        self._clock = clock
        self._frames: deque[can.Message] = deque(maxlen=self.MAX_QUEUED)
        self.sender: BmsSimulator | None = None
        self.channel_info = "in-process BMS link"
        super().__init__(channel="in-process", **kwargs)

    def deliver(self, msg: can.Message, timeout: float | None = None) -> None:
        """The simulator's side (a ``FrameSink``)."""
        self._frames.append(msg)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        return None  # the BMS only broadcasts; nothing listens to the supervisor here

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._is_shutdown:
            raise can.CanOperationError("in-process BMS link is shut down")
        if not self._frames and self.sender is not None:
            self.sender.pump(self._clock.now())
        return (self._frames.popleft() if self._frames else None), False


class _Sink:
    """The simulator's side of the in-process link: frames go to the driver's current
    reader (none before the driver opens its bus, as on a bus nobody listens to)."""

    def __init__(self) -> None:
        self.reader: InProcessCanBus | None = None

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        reader = self.reader
        if reader is not None and not reader._is_shutdown:
            reader.deliver(msg)


class SimulatedBms:
    """A BMS on the plant's pack, sending on python-can's ``virtual`` bus, through a
    :class:`SocketcandServer` on loopback (another process connects with python-can's
    socketcand client), or — ``in_process`` — straight to the driver's
    :class:`InProcessCanBus` (``link()``)."""

    def __init__(
        self,
        name: str,
        clock: Clock,
        source: Callable[[], BmsValues],
        *,
        interface: str,
        channel: str,
        host: str = "127.0.0.1",
        port: int = 0,
        in_process: bool = False,
    ) -> None:
        self.name = name
        self.clock = clock
        self.server: SocketcandServer | None = None
        self._virtual_bus: can.BusABC | None = None
        self._sink: _Sink | None = None
        bus: FrameSink
        if in_process:
            bus = self._sink = _Sink()
        elif interface == "virtual":
            bus = self._virtual_bus = can.Bus(interface="virtual", channel=channel)
        else:
            self.server = SocketcandServer(host, port, channel=channel)
            bus = self.server.bus
        self.sender = BmsSimulator(bus, clock, source)

    def link(self) -> InProcessCanBus:
        """A new driver's bus in process (the driver shuts its bus down at each reconnect)."""
        if self._sink is None:
            raise RuntimeError(f"BMS simulator {self.name} is not in process")
        reader = InProcessCanBus(self.clock)
        reader.sender = self.sender
        self._sink.reader = reader
        return reader

    async def start(self) -> None:
        if self._sink is not None:
            return  # in process: frames are pumped by the driver's reads, no task
        if self.server is not None:
            await self.server.start()
        await self.sender.start()

    async def stop(self) -> None:
        await self.sender.stop()
        if self.server is not None:
            await self.server.stop()
        if self._virtual_bus is not None:
            self._virtual_bus.shutdown()
            self._virtual_bus = None

    def release(self) -> None:
        """Done with it for good (the process ends): shut the socketcand server's bus,
        which outlives ``stop()`` so that an unplugged BMS can be plugged in again."""
        if self.server is not None:
            self.server.bus.shutdown()

    def addresses(self) -> list[str]:
        if self.server is None:
            return []
        return [f"BMS {self.name}: socketcand {self.server.host}:{self.server.port}"]
