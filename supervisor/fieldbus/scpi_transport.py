"""The line transport an SCPI driver speaks over: whole lines out, whole lines in.

:class:`ScpiTransport` opens connections (:class:`ScpiConnection`); the kind's registration
chooses the implementation (an injected backend, as ophyd-async does):

- :class:`TcpScpiTransport`: raw-socket SCPI on ``host:port`` (the I/O map's ``host``/
  ``port``; most units listen on 5025). Timeouts are wall-clock
  ``asyncio.timeout``: right for a real network;
- :class:`InProcessScpiTransport`: hands every line to a simulated unit's SCPI interpreter
  in this process (dry runs, virtual-clock tests). A reply that does not come (a muted
  unit) times out on the INJECTED clock, so a timeout on a virtual clock is deterministic
  and takes no wall time.

Both report failures as the project's typed errors, naming the device and the line whose
reply was awaited: :class:`~supervisor.core.errors.DeviceTimeout` (no reply in time),
:class:`~supervisor.core.errors.DeviceIOError` (cannot connect, connection closed or
dropped), :class:`~supervisor.core.errors.ProtocolError` (a reply line longer than
:data:`~supervisor.fieldbus.scpi.MAX_LINE_BYTES`, with the bytes received). A
connection that raised must be closed by its user and not reused: the driver does, so a
late reply can never be read as the answer to the next question.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections import deque
from typing import Protocol

from supervisor.core.clock import Clock
from supervisor.core.errors import DeviceIOError, DeviceTimeout, ProtocolError
from supervisor.fieldbus.scpi import LINE_END, MAX_LINE_BYTES

_CONTEXT_CHARS = 64
"""Received bytes kept in a ProtocolError for an over-long line."""


class ScpiConnection(Protocol):
    """One open connection to a unit."""

    async def send_line(self, data: bytes, timeout_s: float) -> None:
        """Send one complete command line (``data`` ends with ``\\n``) in one write."""
        ...

    async def receive_line(self, timeout_s: float) -> bytes:
        """The next reply line, with its ``\\n``; waits at most ``timeout_s``."""
        ...

    async def close(self) -> None:
        """Close the connection (idempotent; never raises)."""
        ...


class ScpiTransport(Protocol):
    """Where the driver's unit is, and how to reach it."""

    @property
    def address(self) -> str:
        """For messages: ``host:port`` or which in-process simulator."""
        ...

    async def connect(self, device: str, timeout_s: float) -> ScpiConnection:
        """Open a connection; errors name ``device``."""
        ...


def _text(data: bytes) -> str:
    """A sent line as the driver wrote it (for error messages)."""
    return data.decode("ascii", "replace").rstrip("\r\n")


# --- TCP -----------------------------------------------------------------------------------
class TcpScpiTransport:
    """Raw-socket SCPI to ``host:port`` (asyncio streams, wall-clock timeouts)."""

    def __init__(self, host: str, port: int) -> None:
        self.host = host
        self.port = port

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    async def connect(self, device: str, timeout_s: float) -> ScpiConnection:
        try:
            async with asyncio.timeout(timeout_s):
                reader, writer = await asyncio.open_connection(
                    self.host, self.port, limit=MAX_LINE_BYTES
                )
        except TimeoutError:
            raise DeviceTimeout(
                device, f"no TCP connection to {self.address} in {timeout_s} s"
            ) from None
        except OSError as exc:
            raise DeviceIOError(device, f"cannot connect to {self.address}: {exc}") from exc
        return _TcpConnection(device, reader, writer, timeout_s)


class _TcpConnection:
    def __init__(
        self,
        device: str,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        close_timeout_s: float,
    ) -> None:
        self._device = device
        self._reader = reader
        self._writer = writer
        self._close_timeout_s = close_timeout_s
        self._last_line = ""

    async def send_line(self, data: bytes, timeout_s: float) -> None:
        self._last_line = line = _text(data)
        try:
            async with asyncio.timeout(timeout_s):
                self._writer.write(data)  # one write per complete line
                await self._writer.drain()
        except TimeoutError:
            raise DeviceTimeout(
                self._device, f"no reply to {line!r} within {timeout_s:g} s"
            ) from None
        except OSError as exc:
            raise DeviceIOError(self._device, f"{line!r}: {exc}") from exc

    async def receive_line(self, timeout_s: float) -> bytes:
        line = self._last_line
        try:
            async with asyncio.timeout(timeout_s):
                return await self._reader.readuntil(LINE_END)
        except TimeoutError:
            raise DeviceTimeout(
                self._device, f"no reply to {line!r} within {timeout_s:g} s"
            ) from None
        except asyncio.IncompleteReadError as exc:
            raise DeviceIOError(
                self._device, f"connection closed by the device while waiting for {line!r}"
            ) from exc
        except asyncio.LimitOverrunError as exc:
            # The start of the over-long line is still buffered: keep it for diagnosis.
            raw = await self._reader.read(min(exc.consumed, _CONTEXT_CHARS) or _CONTEXT_CHARS)
            raise ProtocolError(
                self._device, f"a reply line to {line!r} of at most {MAX_LINE_BYTES} bytes", raw
            ) from exc
        except OSError as exc:
            raise DeviceIOError(self._device, f"{line!r}: {exc}") from exc

    async def close(self) -> None:
        self._writer.close()
        with contextlib.suppress(OSError, TimeoutError):
            async with asyncio.timeout(self._close_timeout_s):
                await self._writer.wait_closed()


# --- in process ------------------------------------------------------------------------------
class UnitSession(Protocol):
    """One in-process client connection, as the simulated unit sees it."""

    @property
    def open(self) -> bool:
        """False once the unit dropped it (``drop_clients()``, ``stop()``) or it was closed."""
        ...

    def close(self) -> None: ...


class ScpiUnit(Protocol):
    """What the in-process transport needs of a simulated unit (its SCPI interpreter, e.g.
    :class:`supervisor.devices.ea.sim.EaSimulator`)."""

    @property
    def name(self) -> str: ...

    @property
    def mute(self) -> bool:
        """True: the unit executes lines but sends no reply (a hung interface)."""
        ...

    def open_session(self) -> UnitSession:
        """A new client connection; ConnectionRefusedError while the link is unplugged."""
        ...

    def handle_line(self, raw: bytes) -> str | None:
        """Execute one command line; its reply line (without ``\\n``) or None."""
        ...


class InProcessScpiTransport:
    """SCPI lines handed to a simulated unit in this process; waits on ``clock``."""

    def __init__(self, unit: ScpiUnit, clock: Clock) -> None:
        self.unit = unit
        self.clock = clock

    @property
    def address(self) -> str:
        return f"in-process simulator {self.unit.name}"

    async def connect(self, device: str, timeout_s: float) -> ScpiConnection:
        try:
            session = self.unit.open_session()
        except ConnectionRefusedError as exc:
            raise DeviceIOError(device, f"cannot connect to {self.address}: {exc}") from exc
        return _InProcessConnection(device, self.unit, session, self.clock)


class _InProcessConnection:
    """Like a socket to the simulator: replies queue up until read, a dropped session fails
    every later exchange, and an awaited reply that never comes times out on the clock."""

    def __init__(self, device: str, unit: ScpiUnit, session: UnitSession, clock: Clock) -> None:
        self._device = device
        self._unit = unit
        self._session = session
        self._clock = clock
        self._replies: deque[bytes] = deque()
        self._last_line = b""  # decoded only for an error message (dry runs send millions)

    async def send_line(self, data: bytes, timeout_s: float) -> None:
        self._last_line = data
        if not self._session.open:
            line = _text(data)
            raise DeviceIOError(self._device, f"{line!r}: connection closed by the simulator")
        reply = self._unit.handle_line(data)
        if reply is not None and not self._unit.mute:
            self._replies.append(reply.encode("ascii") + LINE_END)

    async def receive_line(self, timeout_s: float) -> bytes:
        if not self._replies and self._session.open:
            # Nothing in this process will produce it later: a reply that is not here
            # now never comes. Wait out the timeout on the injected clock (a virtual
            # clock jumps) so the caller sees exactly what a silent device costs.
            await self._clock.sleep_until(self._clock.now() + timeout_s)
        if self._replies:
            raw = self._replies.popleft()
            if len(raw) > MAX_LINE_BYTES:  # as the TCP stream's line limit
                line = _text(self._last_line)
                raise ProtocolError(
                    self._device,
                    f"a reply line to {line!r} of at most {MAX_LINE_BYTES} bytes",
                    raw[:_CONTEXT_CHARS],
                )
            return raw
        line = _text(self._last_line)
        if not self._session.open:
            raise DeviceIOError(
                self._device, f"connection closed by the device while waiting for {line!r}"
            )
        raise DeviceTimeout(self._device, f"no reply to {line!r} within {timeout_s:g} s")

    async def close(self) -> None:
        self._session.close()
        self._replies.clear()
