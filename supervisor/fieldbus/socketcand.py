"""socketcand's raw mode read as a TCP stream: a python-can bus over a socketcand daemon.

socketcand (linux-can) serves a CAN interface over TCP in ASCII elements ``< … >``:
the daemon greets ``< hi >``; ``< open can0 >`` and ``< rawmode >`` are each answered
``< ok >`` (or ``< error … >``, and the daemon closes); in raw mode every frame of the bus
arrives as ``< frame 1B0 1733412345.123456 00C350A0030005F0 >`` (identifier of 3 hex
digits for a standard frame, 8 for an extended one; data as hex, none for DLC 0), an error
frame as ``< error CLASS SEC.USEC >``; the client sends ``< send 2B0 4 42 C8 00 00 >``.

TCP is a stream, not a sequence of messages: a daemon on a busy bus writes ``< ok >`` and the
first frames in one segment, an element may be split across two segments, and the reader
must not care. python-can's own client does one ``recv`` and compares it with ``< ok >``,
so it fails against such a daemon (issue 32). :class:`ElementSplitter` cuts the byte stream
into elements whatever the segments, and :class:`SocketcandBus` uses it for the handshake
as well as for the frames. Text outside ``< … >`` (garbage, a truncated element followed by
a new one) is skipped and counted, never fatal.

Kernel SocketCAN (``can.Bus(interface="socketcan")``, a USB-CAN adapter on the host) needs
none of this and is the preferred wiring (docs/deployment.md); this transport is for a CAN
interface on another machine (a Raspberry Pi next to the pack running socketcand).
"""

from __future__ import annotations

import logging
import select
import socket
import time
from collections import deque
from typing import Any, Final

import can

log = logging.getLogger(__name__)

MAX_ELEMENT_BYTES: Final = 512
"""Longest element accepted (a CAN FD frame of 64 bytes is about 160): a ``<`` without its
``>`` within this many bytes is garbage, not a reason to buffer without bound."""
RECV_BYTES: Final = 65536
CONNECT_TIMEOUT_S: Final = 5.0


class ElementSplitter:
    """Bytes in, complete ``< … >`` elements out (their text between the brackets, stripped).

    Pure and incremental: feeding a stream in any cut gives the same elements. What lies
    outside elements is counted in ``garbage_bytes`` (whitespace between elements is not).
    """

    def __init__(self, max_element_bytes: int = MAX_ELEMENT_BYTES) -> None:
        self.max_element_bytes = max_element_bytes
        self.garbage_bytes = 0
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[str]:
        self._buf += data
        out: list[str] = []
        while True:
            start = self._buf.find(b"<")
            if start < 0:
                self._discard(len(self._buf))
                return out
            self._discard(start)
            end = self._buf.find(b">", 1)
            restart = self._buf.find(b"<", 1)
            if restart > 0 and (end < 0 or restart < end):
                self._discard(restart)  # an element cut short by a new one
                continue
            if end < 0:
                if len(self._buf) > self.max_element_bytes:
                    self._discard(len(self._buf))
                return out
            out.append(self._buf[1:end].decode("ascii", errors="replace").strip())
            del self._buf[: end + 1]

    def _discard(self, n: int) -> None:
        if n:
            self.garbage_bytes += len(bytes(self._buf[:n]).strip())
            del self._buf[:n]


def parse_frame(element: str) -> can.Message:
    """``frame ID SEC.USEC [DATA]`` (an element's text) as a received message.

    Raises ``ValueError`` for anything else or a malformed field.
    """
    parts = element.split()
    if not parts or parts[0] != "frame" or len(parts) not in (3, 4):
        raise ValueError(f"not a frame element: {element!r}")
    ident, stamp = parts[1], parts[2]
    if len(ident) not in (3, 8):
        raise ValueError(f"frame id {ident!r}: 3 hex digits (standard) or 8 (extended)")
    data = bytes.fromhex(parts[3]) if len(parts) == 4 else b""
    if len(data) > 8:
        raise ValueError(f"frame with {len(data)} data bytes (classic CAN: at most 8)")
    extended = len(ident) == 8
    arbitration_id = int(ident, 16)
    if arbitration_id > (0x1FFFFFFF if extended else 0x7FF):
        raise ValueError(f"frame id {ident!r} out of range")
    return can.Message(
        timestamp=float(stamp),
        arbitration_id=arbitration_id,
        is_extended_id=extended,
        data=data,
        is_rx=True,
    )


def parse_error_frame(element: str) -> can.Message:
    """``error CLASS SEC.USEC`` (an error frame in raw mode) as an error message."""
    parts = element.split()
    if len(parts) != 3 or parts[0] != "error":
        raise ValueError(f"not an error frame element: {element!r}")
    return can.Message(
        timestamp=float(parts[2]),
        arbitration_id=int(parts[1], 16) & 0x1FFFFFFF,
        is_error_frame=True,
        is_rx=True,
    )


def send_element(msg: can.Message) -> str:
    """``< send ID DLC B0 B1 … >`` for a classic frame (the daemon reads DLC in decimal)."""
    if msg.is_fd or msg.is_remote_frame or msg.is_error_frame or len(msg.data) > 8:
        raise ValueError("socketcand raw mode sends classic data frames only")
    ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    data = "".join(f" {b:02X}" for b in msg.data)
    return f"< send {ident} {len(msg.data)}{data} >"


class SocketcandBus(can.BusABC):
    """A python-can bus on a socketcand daemon's raw mode, the TCP stream read as a stream.

    The constructor connects, opens ``channel`` and enters raw mode within
    ``connect_timeout_s`` or raises :class:`can.CanInitializationError` (with the daemon's
    ``< error … >`` text when it gave one). A connection the daemon closes raises
    :class:`can.CanOperationError` from ``recv`` (python-can's client returns ``None``
    forever instead, indistinguishable from a quiet bus). Not thread-safe: one reader.
    """

    def __init__(
        self,
        channel: str,
        host: str,
        port: int,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
        **kwargs: Any,
    ) -> None:
        self._splitter = ElementSplitter()
        self._queue: deque[can.Message] = deque()
        self._pending: deque[str] = deque()  # elements read during the handshake
        self._logged: set[str] = set()
        self.channel_info = f"socketcand {channel} on {host}:{port}"
        deadline = time.monotonic() + connect_timeout_s
        try:
            self._sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        except OSError as exc:
            raise can.CanInitializationError(f"{self.channel_info}: {exc}") from exc
        try:
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._handshake(channel, deadline)
            self._sock.setblocking(False)
            while self._pending:  # what came in the same segment as the last < ok >
                self._take(self._pending.popleft())
        except BaseException:
            self._sock.close()
            raise
        super().__init__(channel=channel, **kwargs)

    # --- handshake -------------------------------------------------------------------
    def _handshake(self, channel: str, deadline: float) -> None:
        self._expect("hi", deadline)
        self._sock.sendall(f"< open {channel} >".encode("ascii"))
        self._expect("ok", deadline)
        self._sock.sendall(b"< rawmode >")
        self._expect("ok", deadline)

    def _expect(self, word: str, deadline: float) -> None:
        """Read elements until the next reply; a frame that comes first is queued, what
        comes after the reply in the same read stays pending for the next call."""
        while True:
            while self._pending:
                element = self._pending.popleft()
                if element == word:
                    return
                if element.startswith("frame "):
                    self._take(element)
                    continue
                raise can.CanInitializationError(
                    f"{self.channel_info}: expected '< {word} >', got '< {element} >'"
                )
            left = deadline - time.monotonic()
            if left <= 0:
                raise can.CanInitializationError(
                    f"{self.channel_info}: no '< {word} >' from the daemon in time"
                )
            self._pending.extend(self._elements(left, initial=True))

    # --- reading ---------------------------------------------------------------------
    def _elements(self, timeout_s: float, *, initial: bool = False) -> list[str]:
        """The elements completed by what arrives within ``timeout_s`` (one read at most)."""
        readable, _, _ = select.select([self._sock], [], [], timeout_s)
        if not readable:
            return []
        try:
            chunk = self._sock.recv(RECV_BYTES)
        except BlockingIOError:
            return []
        except OSError as exc:
            error = can.CanInitializationError if initial else can.CanOperationError
            raise error(f"{self.channel_info}: {exc}") from exc
        if not chunk:
            error = can.CanInitializationError if initial else can.CanOperationError
            raise error(f"{self.channel_info}: the daemon closed the connection")
        before = self._splitter.garbage_bytes
        elements = self._splitter.feed(chunk)
        if self._splitter.garbage_bytes > before:
            self._log_once("garbage", "skipping bytes outside '< … >' elements")
        return elements

    def _take(self, element: str) -> None:
        kind = element.split(" ", 1)[0]
        try:
            if kind == "frame":
                self._queue.append(parse_frame(element))
            elif kind == "error":
                self._queue.append(parse_error_frame(element))
            elif kind not in ("ok", "echo"):
                self._log_once(kind, f"ignoring '< {element} >'")
        except ValueError as exc:
            if kind == "error":  # a reply (``< error unknown command >``), not an error frame
                self._log_once(f"said {element}", f"the daemon says '< {element} >'")
            else:
                self._log_once(f"bad {kind}", f"ignoring a malformed element: {exc}")

    def _log_once(self, key: str, text: str) -> None:
        if key not in self._logged:
            self._logged.add(key)
            log.warning("%s: %s (logged once)", self.channel_info, text)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._queue:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            for element in self._elements(60.0 if left is None else left):
                self._take(element)
            if deadline is not None and time.monotonic() >= deadline:
                break
        if self._queue:
            return self._queue.popleft(), False
        return None, False

    @property
    def garbage_bytes(self) -> int:
        """Bytes received outside elements since the connection opened."""
        return self._splitter.garbage_bytes

    # --- writing, closing ------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        data = send_element(msg).encode("ascii")
        try:
            self._sock.setblocking(True)
            self._sock.settimeout(timeout)
            self._sock.sendall(data)
        except OSError as exc:
            raise can.CanOperationError(f"{self.channel_info}: send failed: {exc}") from exc
        finally:
            self._sock.setblocking(False)

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()


__all__ = [
    "CONNECT_TIMEOUT_S",
    "MAX_ELEMENT_BYTES",
    "ElementSplitter",
    "SocketcandBus",
    "parse_error_frame",
    "parse_frame",
    "send_element",
]
