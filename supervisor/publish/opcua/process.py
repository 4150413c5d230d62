"""The OPC UA server in a process of its own, seen from the bench (ADR 0029).

``OpcUaProcess`` is what ``OpcUaServer`` is to ``supervisor run`` (``start``, ``closing``,
``stop``, ``endpoint``), but the server, its clients' sessions, subscriptions, browsing and
history reads run in a child process (``child.py``) with an interpreter of its own: ten
clients browsing or subscribing cost the scan no interpreter lock and no turn of its loop.

On the bench's side, all of it runs on the scan's loop, between scans, and never waits:
- the scan hands its changes to the same ``OpcUaFeed`` as in process (sampled at the
  server's interval, one pending update per tag, drops counted); when woken, the link takes
  them and writes one frame. While the child does not read (hung, or restarting), nothing
  more is written and the feed conflates: the queue is bounded by the number of tags.
- a ``Request`` from the child runs through the one command path, as an in-process call
  would, and its ``Answer`` goes back; a request after ``closing`` is refused.
- the child's heartbeat (its clients) arrives every second. A child that exits is started
  again after a pause that doubles up to ``RESTART_MAX_S``; one silent for ``HANG_S`` is
  killed (by its process id) and started again. Each start sends the image as it is then.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Coroutine, Sequence
from pathlib import Path
from typing import Any, Final

from supervisor.core.logins import LoginThrottle
from supervisor.publish.opcua.feed import AlarmView, OpcUaFeed
from supervisor.publish.opcua.layout import Layout
from supervisor.publish.opcua.ports import Answer, Operate, Request
from supervisor.publish.opcua.settings import OpcUaSettings
from supervisor.publish.opcua.wire import Hello, frame, read_frame, tag_row
from supervisor.tags import TagDB

__all__ = ["HANG_S", "OpcUaProcess"]

log = logging.getLogger(__name__)

START_TIMEOUT_S: Final = 60.0
"""A child that has not said it listens after this long is killed (its imports and the
standard address space take 1–3 s on a Raspberry Pi class machine)."""
HANG_S: Final = 10.0
"""A child silent this long (its heartbeat is every second) is taken as hung: killed and
started again."""
RESTART_FIRST_S: Final = 1.0
RESTART_MAX_S: Final = 30.0
STOP_TIMEOUT_S: Final = 10.0
WRITE_BUFFER_MAX_BYTES: Final = 4 * 1024 * 1024
"""Written but not read by the child: beyond this the link stops taking from the feed (it
conflates meanwhile) until the child catches up."""


class OpcUaProcess:
    """The bench's end of the server's process: start, supervise, feed, answer, stop."""

    def __init__(
        self,
        settings: OpcUaSettings,
        db: TagDB,
        layout: Layout,
        feed: OpcUaFeed,
        operate: Operate,
        alarms: Callable[[], Sequence[AlarmView]],
        *,
        history_file: Path | None = None,
        throttle: LoginThrottle | None = None,
    ) -> None:
        self.settings = settings
        self.db = db
        self.layout = layout
        self.feed = feed
        feed.sampling_interval_s = settings.sampling_interval_s
        self.operate = operate
        self.alarms = alarms
        self.history_file = history_file
        self.throttle = throttle
        self.on_login: Callable[[str, str, str], None] | None = None
        """Told each password login's outcome (``failed``/``succeeded``, user, address):
        the bench's audit trail (``app/opcua.py``)."""
        self.endpoint = settings.endpoint
        self.namespace = layout.uri
        self.hang_s = HANG_S
        """Silent this long, the child is killed and started again."""
        self.starts = 0
        """Children started (1 after ``start``; each restart adds one)."""
        self.pid: int | None = None
        self.serving = False
        """The current child listens (False while it is being started again)."""
        self._closing = False
        self._stopping = False
        self._proc: subprocess.Popen[bytes] | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._wake = asyncio.Event()
        self._heard = 0.0
        self._supervisor: asyncio.Task[None] | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    # --- what supervisor run calls ------------------------------------------------------
    async def start(self) -> None:
        """Start the server's process and wait until it listens. ``OSError`` when it could
        not (the port taken: its errno and message, as an in-process server raises)."""
        link = await self._spawn()
        try:
            await asyncio.wait_for(link, START_TIMEOUT_S)  # raises what the child reported
        except BaseException:
            await self._end_child(ask=False)
            raise
        self._supervisor = asyncio.create_task(self._supervise(), name="opcua-process")
        log.info(
            "OPC UA server listening on %s (namespace %s; process %s)",
            self.endpoint,
            self.namespace,
            self.pid,
        )

    @property
    def idle(self) -> bool:
        """Nothing waits to be sent to the server's process."""
        writer = self._writer
        buffered = writer.transport.get_write_buffer_size() if writer is not None else 0
        return self.feed.empty() and buffered == 0

    def closing(self) -> None:
        """Refuse commands from now on (the bench is going to its safe state)."""
        self._closing = True

    async def stop(self) -> None:
        self._closing = self._stopping = True
        if self._supervisor is not None:
            self._supervisor.cancel()
            await asyncio.gather(self._supervisor, return_exceptions=True)
            self._supervisor = None
        await self._end_child(ask=True)
        self.feed.stop()
        log.info("OPC UA server stopped")

    def kill(self) -> None:
        """SIGKILL the server's process (tests and benchmarks: what a crash looks like)."""
        if self._proc is not None and self._proc.poll() is None:
            os.kill(self._proc.pid, signal.SIGKILL)

    # --- the child ------------------------------------------------------------------------
    async def _spawn(self) -> asyncio.Future[None]:
        """A child started and sent its hello; the future is done when it listens (or
        raises what stopped it)."""
        ours, theirs = socket.socketpair()
        try:
            # Spawned on the loop's thread (vfork and exec: about a millisecond), not in a
            # worker: the child's death signal follows the thread that started it.
            proc = subprocess.Popen(  # noqa: ASYNC220
                [sys.executable, "-m", "supervisor.publish.opcua.child", str(theirs.fileno())],
                pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL,  # the environment inherited, as the recipe checks'
            )
        finally:
            theirs.close()
        self._proc, self.pid = proc, proc.pid
        self.starts += 1
        self.feed.restarts = self.starts - 1  # a diagnostic tag (opcua.restarts)
        reader, writer = await asyncio.open_connection(sock=ours)
        self._writer = writer
        self._heard = time.monotonic()
        ready: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        # Every tag as it is now: the image the server starts from; changes queue from now.
        first = self.feed.start(self.db, self._wake.set)
        hello = Hello(
            settings=self.settings,
            specs=tuple(t.spec for t in self.db),
            layout=self.layout,
            first=tuple(tag_row(u) for u in first),
            alarms=tuple(self.alarms()),
            history_file=self.history_file,
            log_level=logging.getLogger().getEffectiveLevel(),
        )
        writer.write(frame(hello))
        self._track(self._read(reader, ready, proc))
        self._track(self._send(writer, proc))
        return ready

    async def _read(
        self,
        reader: asyncio.StreamReader,
        ready: asyncio.Future[None],
        proc: subprocess.Popen[bytes],
    ) -> None:
        try:
            while True:
                message = await read_frame(reader, safe=True)
                self._heard = time.monotonic()
                self._on_message(message, ready)
        except (EOFError, OSError) as exc:
            if not ready.done():
                code = await asyncio.to_thread(_wait, proc, STOP_TIMEOUT_S)
                ready.set_exception(
                    OSError(f"the OPC UA server's process ended (exit {code}) before listening")
                )
            elif not self._stopping:
                log.error("OPC UA server's process %d: pipe closed (%s)", proc.pid, exc)
        except Exception as exc:  # a frame the bench does not accept
            log.error("OPC UA server's process %d sent %s: killed", proc.pid, exc)
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGKILL)
            if not ready.done():
                ready.set_exception(OSError(f"the OPC UA server's process sent {exc}"))

    def _on_message(self, message: object, ready: asyncio.Future[None]) -> None:
        if not isinstance(message, tuple) or not message:
            raise ValueError(f"a message that is not a tuple: {type(message).__name__}")
        kind = message[0]
        if kind == "status":
            clients = message[1]
            self.feed.clients = clients if isinstance(clients, int) else 0
        elif kind == "op" and isinstance(message[2], Request):
            self._track(self._answer(message[1], message[2]))
        elif kind == "login" and (self.throttle is not None or self.on_login is not None):
            _, outcome, user, address = message
            self._login(str(outcome), str(user), str(address))
        elif kind == "ready":
            self.serving = True
            if not ready.done():
                ready.set_result(None)
        elif kind == "failed":
            if not ready.done():
                ready.set_exception(OSError(int(message[1]), str(message[2])))
        else:
            raise ValueError(f"an unknown message {kind!r}")

    def _login(self, outcome: str, user: str, address: str) -> None:
        if self.throttle is not None:
            if outcome == "failed":
                self.throttle.failed(user, address)
            else:
                self.throttle.succeeded(user, address)
        if self.on_login is not None:
            self.on_login(outcome, user, address)

    async def _answer(self, n: object, req: Request) -> None:
        if self._closing:
            answer = Answer(False, "the bench is stopping: outputs going safe", "refused")
        else:
            try:
                answer = await self.operate(req)
            except Exception as exc:  # never lost: the client gets an answer
                log.exception("OPC UA request %r failed", req)
                answer = Answer(False, f"{type(exc).__name__}: {exc}", "failed")
        writer = self._writer
        if writer is not None and not writer.is_closing():
            writer.write(frame(("answer", n, answer)))

    async def _send(self, writer: asyncio.StreamWriter, proc: subprocess.Popen[bytes]) -> None:
        """The feed's changes and events, one frame per wake-up, on the scan's loop."""
        wake = self._wake
        while not writer.is_closing():
            await wake.wait()
            wake.clear()
            if writer.transport.get_write_buffer_size() > WRITE_BUFFER_MAX_BYTES:
                continue  # the child is not reading: the feed conflates meanwhile
            updates = self.feed.take()
            events = self.feed.take_events()
            if updates or events:
                writer.write(frame(("data", [tag_row(u) for u in updates], events)))

    async def _supervise(self) -> None:
        """Start the child again when it ends; kill it when it stops answering."""
        pause_s = RESTART_FIRST_S
        while True:
            proc = self._proc
            assert proc is not None
            await asyncio.sleep(STATUS_CHECK_S)
            code = proc.poll()
            silent_s = time.monotonic() - self._heard
            if code is None and silent_s < self.hang_s:
                if silent_s < 2 * STATUS_CHECK_S:
                    pause_s = RESTART_FIRST_S  # healthy again: the next restart is quick
                continue
            if code is None:
                log.error(
                    "OPC UA server's process %d silent for %.0f s: killed, started again",
                    proc.pid,
                    silent_s,
                )
            else:
                log.error(
                    "OPC UA server's process %d ended (exit %s): started again in %g s",
                    proc.pid,
                    code,
                    pause_s,
                )
            await self._end_child(ask=False)
            await asyncio.sleep(pause_s)
            pause_s = min(2 * pause_s, RESTART_MAX_S)
            try:
                await asyncio.wait_for(await self._spawn(), START_TIMEOUT_S)
            except (OSError, TimeoutError) as exc:
                log.error("OPC UA server did not start again: %s", exc)
                await self._end_child(ask=False)
                continue
            log.info("OPC UA server started again (process %d)", self.pid)

    async def _end_child(self, *, ask: bool) -> None:
        proc, writer = self._proc, self._writer
        self._writer = None
        self.serving = False
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if writer is not None:
            if ask and not writer.is_closing():
                writer.write(frame(("stop",)))
                with contextlib.suppress(OSError, ConnectionError):
                    await asyncio.wait_for(writer.drain(), STOP_TIMEOUT_S)
            writer.close()
        if proc is None:
            return
        code = await asyncio.to_thread(_wait, proc, STOP_TIMEOUT_S if ask else 0.0)
        if code is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGKILL)
            await asyncio.to_thread(_wait, proc, STOP_TIMEOUT_S)

    def _track(self, coro: Coroutine[Any, Any, None]) -> None:
        task: asyncio.Task[None] = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)


STATUS_CHECK_S: Final = 1.0


def _wait(proc: subprocess.Popen[bytes], timeout_s: float) -> int | None:
    try:
        return proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        return None
