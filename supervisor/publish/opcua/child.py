"""The OPC UA server's own process (ADR 0029): ``python -m supervisor.publish.opcua.child FD``.

Started by ``OpcUaProcess`` (process.py) with one end of a socket pair as file descriptor
``FD``. It reads a ``Hello`` (the settings, every tag's spec and value, the layout, the
alarms), builds the same ``OpcUaServer`` as in process, on its own event loop, and serves:
the bench's changes arrive as frames and are handed to the server as the in-process feed
would; a method call or a write is sent to the bench as a ``Request`` and answered there by
the one command path. It never touches a device, the tag database or a file but the
historian's (read-only) and its PKI folder.

It ends when the bench says stop, when the pipe closes (the bench's process ended, or
killed it), or on SIGTERM. Whatever it does, the bench's scan runs on: a hung server is
killed and started again by its parent.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import errno
import gc
import itertools
import logging
import os
import signal
import socket
import sys
from collections.abc import Callable
from typing import Final

from supervisor.core.clock import RealClock
from supervisor.core.encoding import StorableFormatter
from supervisor.core.logins import LoginThrottle
from supervisor.publish.historian import HistoryQuery
from supervisor.publish.opcua.feed import OpcUaFeed, Update
from supervisor.publish.opcua.ports import Answer, Request
from supervisor.publish.opcua.server import OpcUaServer
from supervisor.publish.opcua.settings import OpcUaSettings
from supervisor.publish.opcua.wire import (
    STATUS_PERIOD_S,
    Hello,
    frame,
    read_frame,
    update_of,
)
from supervisor.tags import TagDB

log = logging.getLogger("supervisor.publish.opcua.child")

LOG_FORMAT: Final = "%(asctime)s %(levelname)-7s opcua[%(process)d] %(name)s: %(message)s"
PR_SET_PDEATHSIG: Final = 1


class MirrorFeed(OpcUaFeed):
    """The server's feed in its own process: filled from the pipe instead of by a scan.
    Its events queue is the in-process feed's; its updates arrive made (``wire.py``) and
    are conflated the same way: one per tag, a replaced one counted as dropped."""

    def __init__(self, db: TagDB, first: list[Update]) -> None:
        super().__init__(db)
        self._first = first
        self._pending: dict[int, Update] = {}

    def start(self, db: TagDB, wake: Callable[[], None]) -> list[Update]:
        self.wake = wake
        return self._first

    def deliver(self, updates: list[Update], events: list[object]) -> None:
        """A sampling interval's changes and the events since the last frame."""
        wake = self.wake
        if wake is None:
            return
        with self._lock:
            pending = self._pending
            for u in updates:
                if u.tag_index in pending:
                    self.replaced += 1
                pending[u.tag_index] = u
        for ev in events:
            self._events.append(ev)  # type: ignore[arg-type]  # BenchEvent | AlarmView
        wake()

    def take(self) -> list[Update]:
        with self._lock:
            out = list(self._pending.values())
            self._pending = {}
        return out

    def empty(self) -> bool:
        with self._lock:
            return not self._pending and not self._events


class SharedThrottle(LoginThrottle):
    """The server's login throttle: its own refusals, and every outcome told to the bench,
    whose throttle (shared with the HMI's logins) raises the burst alarm."""

    def __init__(self, tell: Callable[[object], None]) -> None:
        super().__init__(RealClock().now)
        self._tell = tell

    def failed(self, user: str, address: str) -> None:
        super().failed(user, address)
        self._tell(("login", "failed", user, address))

    def succeeded(self, user: str, address: str) -> None:
        super().succeeded(user, address)
        self._tell(("login", "succeeded", user, address))


class Child:
    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer
        self.ids = itertools.count(1)
        self.asked: dict[int, asyncio.Future[Answer]] = {}
        self.server: OpcUaServer | None = None
        self.feed: MirrorFeed | None = None

    def tell(self, message: object) -> None:
        if not self.writer.is_closing():
            self.writer.write(frame(message))

    async def operate(self, req: Request) -> Answer:
        """A method call or a write: run by the bench's command path, its answer awaited."""
        n = next(self.ids)
        fut: asyncio.Future[Answer] = asyncio.get_running_loop().create_future()
        self.asked[n] = fut
        try:
            self.tell(("op", n, req))
            return await fut
        finally:
            self.asked.pop(n, None)

    async def build(self, hello: Hello) -> OpcUaServer:
        settings: OpcUaSettings = hello.settings
        db = TagDB()
        for spec in hello.specs:
            db.add(spec)  # the same order: the same indexes as the bench's
        feed = MirrorFeed(db, [update_of(r) for r in hello.first])
        alarms = list(hello.alarms)
        history = HistoryQuery(hello.history_file) if hello.history_file is not None else None
        server = OpcUaServer(
            settings,
            db,
            RealClock(),
            hello.layout,
            feed,
            self.operate,
            _users(settings),
            lambda: alarms,
            threaded=False,
            history=history,
            throttle=SharedThrottle(self.tell),
        )
        self.server, self.feed = server, feed
        return server

    async def pump(self) -> None:
        """The bench's frames, until it says stop or closes the pipe."""
        while True:
            message = await read_frame(self.reader, safe=False)
            kind = message[0]
            if kind == "data":
                assert self.feed is not None
                self.feed.deliver([update_of(r) for r in message[1]], message[2])
            elif kind == "answer":
                fut = self.asked.get(message[1])
                if fut is not None and not fut.done():
                    fut.set_result(message[2])
            elif kind == "stop":
                return

    async def status(self) -> None:
        while True:
            server, feed = self.server, self.feed
            if server is not None and feed is not None:
                self.tell(("status", feed.clients, server.written))
            await asyncio.sleep(STATUS_PERIOD_S)


def _users(settings: OpcUaSettings):  # type: ignore[no-untyped-def]
    from supervisor.config.users import UserStore

    return UserStore(settings.users_file)


async def serve(fd: int) -> int:
    sock = socket.socket(fileno=fd)
    reader, writer = await asyncio.open_connection(sock=sock)
    child = Child(reader, writer)
    try:
        hello = await read_frame(reader, safe=False)
    except EOFError:
        return 1
    assert isinstance(hello, Hello)
    logging.getLogger().setLevel(hello.log_level)
    server = await child.build(hello)
    try:
        await server.start()
    except OSError as exc:
        child.tell(("failed", exc.errno or errno.EIO, str(exc)))
        await writer.drain()
        return 3
    except Exception as exc:  # a bad users file, a PKI folder it cannot write
        log.exception("OPC UA server could not start")
        child.tell(("failed", errno.EIO, f"{type(exc).__name__}: {exc}"))
        await writer.drain()
        return 3
    child.tell(("ready", server.endpoint))
    status = asyncio.create_task(child.status(), name="opcua-status")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    pump = asyncio.create_task(child.pump(), name="opcua-pipe")
    stopped = asyncio.create_task(stop.wait())
    try:
        await asyncio.wait({pump, stopped}, return_when=asyncio.FIRST_COMPLETED)
        failed = pump.exception() if pump.done() and not pump.cancelled() else None
        if failed is not None and not isinstance(failed, EOFError | ConnectionError):
            log.error("OPC UA server's pipe failed: %r", failed)
    finally:
        for task in (status, pump, stopped):
            task.cancel()
        await asyncio.gather(status, pump, stopped, return_exceptions=True)
        server.closing()
        await server.stop()
        with contextlib.suppress(OSError):
            writer.close()
    return 0


def _normal_priority() -> None:
    """Started by the scan's thread after a restart, the child would inherit its real-time
    policy (ADR 0023): the server runs at normal priority, like any other client of the
    bench."""
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def _die_with_parent() -> None:
    """SIGTERM when the bench's process ends, even killed: a server must not outlive the
    bench whose values it shows (the pipe's end is the other way it learns it)."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or not args[0].isdigit():
        sys.stderr.write("usage: python -m supervisor.publish.opcua.child FD\n")
        return 2
    _normal_priority()
    _die_with_parent()
    # Ctrl-C in a terminal reaches the whole process group: the bench stops its server
    # itself once its outputs are safe (clients see them go), so the child waits for that.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(StorableFormatter(LOG_FORMAT))
    logging.getLogger().addHandler(handler)
    gc.freeze()  # the imports live as long as the process (ADR 0018)
    try:
        return asyncio.run(serve(int(args[0])))
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    sys.exit(main())
