"""The bench's Modbus TCP server (pymodbus), for panel HMIs and SCADA that speak only Modbus
(issue 36, docs/adr/0032-modbus-server.md).

Never on the scan's time: the scan's publisher (``ModbusFeed``) keeps the scan's one copy of
its changes by reference (``publish/changes.py``, ADR 0030) and counts the scan (the
HEARTBEAT); the server, on **its own thread with its own event loop** that waits at the
scan gate (``core/gate.py``), encodes them into its register image (``image.py``) when a
request comes in or at its drain period. The bench and the server meet in three places:

- ``ModbusFeed``: batches appended, never a wake-up, never a wait;
- writes: handed to the bench's loop and run there between two scans, through the one
  command path (``Write``, wired by ``app/modbus.py``) with the actor
  ``modbus:<client address>``; a refusal answers exception 03 (a value the tag does not
  take) or 04 (anything else) and its reason code goes to the REFUSAL register;
- start and stop, awaited by the bench's loop (``start`` raises ``OSError`` for a taken
  port).

Exceptions (Modbus Application Protocol v1.1b3 §7): 01 a function it does not serve, or a
write while ``writes`` is off; 02 an address no point holds, a write to a read-only one,
or a write that cuts a float in half; 03 a count beyond the function's limit, or a value
the point cannot hold; 04 a write the command path refused.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import contextvars
import logging
import struct
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.exceptions import ModbusIOException, NoSuchIdException
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.transaction import TransactionManager

from supervisor.core.driver import Value
from supervisor.core.gate import ScanGate
from supervisor.core.loops import await_thread_end, run_gated
from supervisor.fieldbus.modbus import quiet_pymodbus
from supervisor.publish.changes import ChangeBatch, ChangeSnapshots, ChangeSource
from supervisor.publish.modbus.image import Decoded, RegisterImage, decode, encode
from supervisor.publish.modbus.regmap import REFUSALS, Point, RegisterMap, Table
from supervisor.tags import TagDB

__all__ = ["ACTOR_PREFIX", "ModbusFeed", "ModbusServer", "Write", "WriteAnswer"]

log = logging.getLogger(__name__)

ACTOR_PREFIX: Final = "modbus:"
"""A write's actor on the command path: ``modbus:<client address>``."""
DRAIN_PERIOD_S: Final = 0.2
"""The server applies the scan's batches at least this often, polled or not (the batches
it keeps meanwhile are the scan's own copies, by reference)."""
STOP_TIMEOUT_S: Final = 5.0
WRITE_TIMEOUT_S: Final = 10.0
"""A write waits at most this for the bench's loop (the command path answers in a scan)."""
MAX_REGISTERS: Final = 125  # FC 03/04: registers a read may ask for (MAP v1.1b3 §6.3)
MAX_BITS: Final = 2000  # FC 01/02
MAX_WRITE_REGISTERS: Final = 123  # FC 16
MAX_WRITE_BITS: Final = 1968  # FC 15

_READ_TABLE: Final = {
    1: Table.COIL,
    2: Table.DISCRETE_INPUT,
    3: Table.HOLDING_REGISTER,
    4: Table.INPUT_REGISTER,
}
_WRITE_TABLE: Final = {
    5: Table.COIL,
    15: Table.COIL,
    6: Table.HOLDING_REGISTER,
    16: Table.HOLDING_REGISTER,
    # FC 23 (read/write multiple) writes holding registers too.
    23: Table.HOLDING_REGISTER,
}

_peer: contextvars.ContextVar[str] = contextvars.ContextVar("modbus_peer", default="")
"""The client address of the request being handled (set by ``_Handler``)."""


@dataclass(frozen=True, slots=True)
class WriteAnswer:
    """The command path's answer to a write (``kind``: a refusal's kind, ``REFUSALS``)."""

    accepted: bool
    reason: str
    kind: str = ""


Write = Callable[[str, Value, str], Awaitable[WriteAnswer]]
"""Write ``value`` to the tag named so, as ``actor``, through the one command path: run on
the bench's loop (``app/modbus.py``)."""


def refusal_code(kind: str) -> int:
    """The REFUSAL register's code of a refusal's kind (``REFUSALS``; "failed" for any
    kind the table does not name)."""
    try:
        return REFUSALS.index(kind) if kind else REFUSALS.index("failed")
    except ValueError:
        return REFUSALS.index("failed")


def exception_of(kind: str) -> ExcCodes:
    """03 for a value the tag does not take, 04 for any other refusal."""
    if kind in ("bad argument", "out of range"):
        return ExcCodes.ILLEGAL_VALUE
    return ExcCodes.DEVICE_FAILURE


class ModbusFeed:
    """The scan's publisher: keeps its copies of its changes for the server, by reference."""

    name = "modbus"

    def __init__(self, db: TagDB, changes: ChangeSource | None = None) -> None:
        self._source: ChangeSource = (
            changes if changes is not None else ChangeSnapshots(db, None, since=db.version)
        )
        # Appended by the scan, popped by the server's thread: a deque's two ends are
        # thread-safe without a lock (a list swapped by the server could lose a batch the
        # scan appended to the old list after the swap).
        self._held: deque[ChangeBatch] = deque()
        self.serving = False
        self.scans = 0
        """Scans since the start (an int, read by the server: the HEARTBEAT)."""

    def on_scan(self, db: TagDB, t: float) -> None:
        batches = self._source.batches()
        self.scans += 1
        if not self.serving:
            return  # not serving: the server reads every tag when it starts
        held = self._held
        for b in batches:
            if b.changes:
                held.append(b)

    # --- the server's side ---------------------------------------------------------------
    def take(self) -> list[ChangeBatch]:
        """The batches since the last take, oldest first (never blocks the scan)."""
        held, out = self._held, []
        while held:
            out.append(held.popleft())
        return out


class _Context(ModbusServerContext):
    """pymodbus's datastore calls, answered from the register image (or the command path,
    for writes). Never raises: an exception would be a traceback in pymodbus's log."""

    def __init__(self, server: ModbusServer) -> None:
        # Not ModbusServerContext.__init__: no simulator device, no deprecation warning.
        self._server = server
        self.old_simulator = True  # pymodbus's base server then calls these methods
        self.simdevices = []

    def device_ids(self) -> list[int]:
        return [self._server.regmap.unit_id]

    def _check_unit(self, device_id: int) -> None:
        if device_id not in (self._server.regmap.unit_id, 0, 255):
            raise NoSuchIdException(f"unit {device_id} is not served")

    async def async_getValues(
        self, device_id: int, func_code: int, address: int, count: int = 1
    ) -> list[int] | list[bool] | ExcCodes:
        self._check_unit(device_id)
        try:
            return self._server.read(func_code, address, count)
        except Exception:  # a bug must not become pymodbus's traceback in the log
            log.exception("Modbus read of %d at %d failed", count, address)
            return ExcCodes.DEVICE_FAILURE

    async def async_setValues(
        self, device_id: int, func_code: int, address: int, values: Sequence[int] | Sequence[bool]
    ) -> ExcCodes | None:
        self._check_unit(device_id)
        try:
            return await self._server.write(func_code, address, list(values), _peer.get())
        except Exception:
            log.exception("Modbus write at %d failed", address)
            return ExcCodes.DEVICE_FAILURE


class _Handler(ServerRequestHandler):
    """One client's connection: closed at once beyond ``max_clients``; its requests carry
    its address (a write's actor)."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        peer = transport.get_extra_info("peername")
        self.peer = str(peer[0]) if peer else ""
        server: _TcpServer = self.server
        if len(server.active_connections) > server.max_clients:
            log.warning(
                "Modbus: connection from %s closed: %d clients already (max_clients)",
                self.peer,
                server.max_clients,
            )
            self.close()

    async def handle_request(self) -> None:
        _peer.set(getattr(self, "peer", ""))
        await super().handle_request()  # type: ignore[no-untyped-call]

    def data_received(self, data: bytes) -> None:
        if not _frames_well_formed(self.recv_buffer + data):
            # Not Modbus TCP (a protocol id other than 0, a length no PDU has): nothing
            # in the stream can be trusted to start a frame after it. Closed (pymodbus
            # would drop an oversize buffer silently and leave the client waiting).
            log.warning("Modbus: a malformed frame from %s: connection closed", self.peer)
            self.close()
            return
        super().data_received(data)

    def callback_data(self, data: bytes, addr: tuple[Any, ...] | None = None) -> int:
        # pymodbus answers a frame its decoder refuses as function 0x00, exception 01: a
        # client cannot tell which request failed nor why. Here it is answered with the
        # request's own function code: 01 for a function it does not serve, 03 for a
        # served function whose fields are wrong (a count beyond its limit, MAP §6).
        try:
            used: int = TransactionManager.callback_data(self, data, addr)
        except ModbusIOException as exc:
            function = data[7] if len(data) > 7 else 0
            served = function in self.server.decoder.pdu_table
            code = ExcCodes.ILLEGAL_VALUE if served else ExcCodes.ILLEGAL_FUNCTION
            answer = ExceptionResponse(
                function & 0x7F,
                exception_code=code,
                device_id=exc.dev_id,
                transaction=exc.transaction_id,
            )
            self.server_send(answer, addr)  # type: ignore[no-untyped-call]
            return len(data)
        if self.last_pdu:
            self.loop.call_soon(self.handle_later)
        return used


MAX_PDU: Final = 253
"""A Modbus PDU's bytes at most (MAP v1.1b3 §4.1): an MBAP length beyond 1 + this is not
Modbus."""


def _frames_well_formed(data: bytes) -> bool:
    """Every MBAP header in ``data`` (complete or not) says protocol 0 and a length a PDU
    can have."""
    pos, n = 0, len(data)
    while pos + 6 <= n:
        protocol, length = struct.unpack_from(">HH", data, pos + 2)
        if protocol != 0 or not 2 <= length <= 1 + MAX_PDU:
            return False
        pos += 6 + length
    return True


SERVED_FUNCTIONS: Final = frozenset({1, 2, 3, 4, 5, 6, 15, 16, 23})
"""The four tables' functions. pymodbus also decodes the serial line's diagnostics (08, 11,
12, 17) and device identification (43), and would answer them from state of its own (a
"listen only" flag, counters, an empty identity): any function not here answers 01."""


class _TcpServer(ModbusTcpServer):
    max_clients = 8

    def __init__(self, context: ModbusServerContext, *, address: tuple[str, int]) -> None:
        super().__init__(context, address=address)
        # An instance's own table: the class's is shared with every pymodbus decoder in
        # the process (the ADAM's simulator among them).
        self.decoder.pdu_table = {
            fc: pdus for fc, pdus in self.decoder.pdu_table.items() if fc in SERVED_FUNCTIONS
        }

    def callback_new_connection(self) -> _Handler:
        return _Handler(self, self.trace_packet, self.trace_pdu, self.trace_connect)  # type: ignore[no-untyped-call]


class ModbusServer:
    """The register map served over Modbus TCP on ``host:port`` (see the module's doc)."""

    def __init__(
        self,
        regmap: RegisterMap,
        db: TagDB,
        feed: ModbusFeed,
        write: Write | None,
        *,
        host: str,
        port: int,
        writes: bool = False,
        max_clients: int = 8,
        gate: ScanGate | None = None,
        period_s: float = 0.1,
    ) -> None:
        self.regmap = regmap
        self.db = db
        self.feed = feed
        self.write_tag = write
        self.host = host
        self.port = port
        self.writes = writes
        self.max_clients = max_clients
        self.gate = gate
        self.alive_window_s = max(1.0, 5 * period_s)
        """The alive bit clears when no scan ran for this long (a stalled scan)."""
        self.image = RegisterImage(regmap)
        self._closing = False
        self._bench_loop: asyncio.AbstractEventLoop | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._done: concurrent.futures.Future[None] | None = None
        self._last_scans = -1
        self._last_scan_t = 0.0
        self.bound_port = 0
        self._tcp: _TcpServer | None = None

    @property
    def clients(self) -> int:
        """Connections open now (diagnostics; read from any thread)."""
        tcp = self._tcp
        return 0 if tcp is None else len(tcp.active_connections)

    @property
    def endpoint(self) -> str:
        """``host:port`` (a panel's Modbus TCP settings)."""
        return f"{self.host}:{self.bound_port or self.port}"

    # --- the bench's side ------------------------------------------------------------------
    async def start(self) -> None:
        """Listen and serve until ``stop``; ``OSError`` when the port cannot be bound."""
        self._bench_loop = asyncio.get_running_loop()
        quiet_pymodbus()
        # Every tag as it is now, read between two scans; from now on the scan's batches.
        self.feed.take()
        self.image.load({t.spec.name: (t.value, t.quality, t.reason) for t in self.db})
        self.feed.serving = True
        ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._done = concurrent.futures.Future()
        self._thread = threading.Thread(
            target=self._thread_main, args=(ready,), name=THREAD_NAME, daemon=True
        )
        self._thread.start()
        try:
            await asyncio.wrap_future(ready)
        except BaseException:
            await self._wait_done()
            raise
        log.info("Modbus TCP server listening on %s (unit %d)", self.endpoint, self.regmap.unit_id)

    def closing(self) -> None:
        """Refuse writes from now on (the bench is going to its safe state)."""
        self._closing = True

    def on_alarms(self, flags: dict[str, int]) -> None:
        """Each group's tripped/unacked bits (``image.BIT``), from the alarm model's listener
        (on the bench's loop: one dict replaced, read by the server's thread)."""
        self.image.flags = flags

    async def stop(self) -> None:
        self._closing = True
        self.feed.serving = False
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        await self._wait_done()
        self.feed.take()

    async def _wait_done(self) -> None:
        await await_thread_end(self._done, self._thread, STOP_TIMEOUT_S, "Modbus server")
        self._thread = None
        self._done = None

    # --- the server's thread ----------------------------------------------------------------
    def _thread_main(self, ready: concurrent.futures.Future[None]) -> None:
        try:
            run_gated(self._main(ready), ready, self.gate, "Modbus server")
        finally:
            if self._done is not None and not self._done.done():
                self._done.set_result(None)

    async def _main(self, ready: concurrent.futures.Future[None]) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        _quiet_pymodbus()
        server = _TcpServer(_Context(self), address=(self.host, self.port))
        server.max_clients = self.max_clients
        self._tcp = server
        # pymodbus's listen() logs and answers False for a taken port: bind ourselves first
        # so the bench hears the OSError (as from the HTTP API and OPC UA).
        await _probe(self.host, self.port)
        await server.serve_forever(background=True)
        transport = server.transport
        sockets = getattr(transport, "sockets", None) or ()
        self.bound_port = sockets[0].getsockname()[1] if sockets else self.port
        drain = asyncio.create_task(self._drain(), name="modbus-drain")
        try:
            ready.set_result(None)
            await self._stop.wait()
        finally:
            drain.cancel()
            await asyncio.gather(drain, return_exceptions=True)
            await server.shutdown()  # type: ignore[no-untyped-call]
            self._tcp = None
            self._loop = None
            log.info("Modbus TCP server stopped")

    async def _drain(self) -> None:
        while True:
            await asyncio.sleep(DRAIN_PERIOD_S)
            self._refresh()

    def _refresh(self) -> None:
        """The scan's batches into the image; the heartbeat and the alive bit."""
        self.image.apply(self.feed.take())
        scans, now = self.feed.scans, time.monotonic()
        if scans != self._last_scans:
            self._last_scans, self._last_scan_t = scans, now
        self.image.heartbeat = scans
        self.image.alive = now - self._last_scan_t < self.alive_window_s

    # --- the requests (on the server's thread) ------------------------------------------
    def read(self, func_code: int, address: int, count: int) -> list[int] | list[bool] | ExcCodes:
        table = _READ_TABLE.get(func_code) or _WRITE_TABLE.get(func_code)
        if table is None:
            return ExcCodes.ILLEGAL_FUNCTION
        bits = table in (Table.COIL, Table.DISCRETE_INPUT)
        if not 1 <= count <= (MAX_BITS if bits else MAX_REGISTERS):
            return ExcCodes.ILLEGAL_VALUE
        if not self.image.served(table, address, count):
            return ExcCodes.ILLEGAL_ADDRESS
        self._refresh()
        words = self.image.read(table, address, count)
        if bits:
            return [bool(w) for w in words]
        return words

    async def write(
        self, func_code: int, address: int, values: list[int] | list[bool], peer: str
    ) -> ExcCodes | None:
        table = _WRITE_TABLE.get(func_code)
        if table is None or not self.writes:
            return ExcCodes.ILLEGAL_FUNCTION
        limit = MAX_WRITE_BITS if table is Table.COIL else MAX_WRITE_REGISTERS
        if not 1 <= len(values) <= limit:
            return ExcCodes.ILLEGAL_VALUE
        image = self.image
        points = image.points_in(table, address, len(values))
        if points is None or not all(p.writable for p in points):
            return ExcCodes.ILLEGAL_ADDRESS
        actor = ACTOR_PREFIX + peer
        words = [int(v) for v in values]
        offset = 0
        for p in points:
            raw = tuple(words[offset : offset + p.words])
            offset += p.words
            try:
                value = decode(p, raw, image.word_order)
            except Decoded as exc:
                return self._refused(p, actor, "bad argument", str(exc))
            if self._closing:
                return self._refused(p, actor, "closing", "the bench is going to its safe state")
            answer = await self._write_on_bench(p.tag, value, actor)
            if not answer.accepted:
                return self._refused(p, actor, answer.kind, answer.reason)
            image.put(p, encode(p, value, image.word_order) or raw)  # the echo reads it
            log.info("Modbus write %s := %r by %s accepted", p.tag, value, actor)
        return None

    def _refused(self, p: Point, actor: str, kind: str, reason: str) -> ExcCodes:
        self.image.refusal = refusal_code(kind)
        log.info("Modbus write to %s by %s refused (%s): %s", p.tag, actor, kind, reason)
        return exception_of(kind)

    async def _write_on_bench(self, tag: str, value: Value, actor: str) -> WriteAnswer:
        bench, write = self._bench_loop, self.write_tag
        if bench is None or write is None:
            return WriteAnswer(False, "writes are not wired", "failed")

        async def run() -> WriteAnswer:
            return await write(tag, value, actor)

        fut = asyncio.run_coroutine_threadsafe(run(), bench)
        try:
            return await asyncio.wait_for(asyncio.wrap_future(fut), WRITE_TIMEOUT_S)
        except TimeoutError:
            return WriteAnswer(False, "the bench did not answer in time", "timeout")


async def _probe(host: str, port: int) -> None:
    """``OSError`` when ``host:port`` cannot be bound (closed at once: pymodbus binds it)."""
    loop = asyncio.get_running_loop()
    probe = await loop.create_server(asyncio.Protocol, host, port, reuse_address=True)
    probe.close()
    await probe.wait_closed()


THREAD_NAME: Final = "modbus-server"


class _ServerThreadOnly(logging.Filter):
    """Drops what pymodbus logs on the server's thread: it logs a refused request (an
    unknown unit, a frame it cannot decode) at WARNING or ERROR, a datastore failure with
    its stack in the message. The server's own log says what matters (a refused write, a
    closed client, a bug of its own); pymodbus's client elsewhere is not silenced."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.threadName != THREAD_NAME


_FILTER = _ServerThreadOnly()


def _quiet_pymodbus() -> None:
    pm = logging.getLogger("pymodbus.logging")  # pymodbus's one logger (``pymodbus.logging.Log``)
    if _FILTER not in pm.filters:
        pm.addFilter(_FILTER)
