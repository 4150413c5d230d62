"""The HTTP listener's connection cap, header timeout and idle timeout (issue 27, finding 3).

aiohttp accepts every connection and waits for its request for as long as the client
likes: 1000 idle TCP connections took every file descriptor of the process (soft limit
1024) and the devices could not reconnect. ``ConnectionGuard`` makes the protocol of each
accepted connection:

- at most ``max_connections`` open at once (``hmi.max_connections``, default 256); one more
  is answered at once ``503 Service Unavailable`` with a JSON body and
  ``Connection: close``, then closed — never left waiting, never handed to aiohttp;
- a connection that has not sent the complete headers of a request ``header_timeout_s``
  (``hmi.header_timeout_s``, default 10 s) after it opened, or after the first byte of its
  next request, is closed: one header byte a second (slowloris) holds it for that long,
  not for ever;
- a keep-alive connection idle for ``idle_timeout_s`` (``hmi.idle_timeout_s``, default 60 s)
  is closed by aiohttp (its ``keepalive_timeout``).

A WebSocket is one of these connections (its upgrade request completed its headers); the
screens' own cap on WebSockets is ``hmi.max_websockets`` (``supervisor.hmi.live``).
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

log = logging.getLogger(__name__)

MAX_CONNECTIONS: Final = 256
"""Open HTTP connections at most (screens, API clients, WebSockets together)."""
MAX_WEBSOCKETS: Final = 32
"""Screens (WebSocket clients) connected at most."""
HEADER_TIMEOUT_S: Final = 10.0
"""A request's headers must be complete this long after its first byte (or the connect)."""
IDLE_TIMEOUT_S: Final = 60.0
"""A keep-alive connection without a request for this long is closed."""
BACKLOG: Final = 128
"""The listening socket's accept queue (aiohttp's default)."""
LINGER_S: Final = 1.0
"""A refused connection is read (and its bytes thrown away) this long at most after its
503 before it is closed: closed with the client's request unread, the kernel would answer
a reset, and the client might lose the 503 before reading it."""
LINGER_MAX: Final = 32
"""Refused connections lingering at most; beyond, a refused connection is closed at once
(a flood must not hold descriptors through its refusals)."""


@dataclass(frozen=True, slots=True)
class ConnectionLimits:
    max_connections: int = MAX_CONNECTIONS
    max_websockets: int = MAX_WEBSOCKETS
    header_timeout_s: float = HEADER_TIMEOUT_S
    idle_timeout_s: float = IDLE_TIMEOUT_S
    backlog: int = BACKLOG

    @property
    def descriptors(self) -> int:
        """What the HTTP listener may hold at most: its open connections, an accept queue
        of connections to refuse, the refusals lingering."""
        return self.max_connections + self.backlog + LINGER_MAX


def refusal(reason: str) -> bytes:
    """A complete ``503`` answer with the JSON body ``{"accepted": false, "reason": ...}``."""
    body = json.dumps({"accepted": False, "reason": reason}).encode()
    head = (
        "HTTP/1.1 503 Service Unavailable\r\n"
        "Content-Type: application/json; charset=utf-8\r\n"
        f"Content-Length: {len(body)}\r\n"
        "Retry-After: 5\r\n"
        "Connection: close\r\n\r\n"
    )
    return head.encode() + body


class ConnectionGuard:
    """Counts the listener's connections and makes each one's protocol (``protocol``, the
    factory given to ``loop.create_server``) around aiohttp's (``factory``)."""

    def __init__(self, factory: Callable[[], asyncio.Protocol], limits: ConnectionLimits) -> None:
        self.factory = factory
        self.limits = limits
        self.open = 0
        """Connections open now (refused ones not counted)."""
        self.accepted = 0
        """Connections handed to aiohttp since the start."""
        self.refused = 0
        """Connections answered 503 since the start."""
        self.timed_out = 0
        """Connections closed for headers not complete in time."""
        self.lingering = 0
        self._answer = refusal(
            f"too many connections (hmi.max_connections: {limits.max_connections}); try again later"
        )

    def protocol(self) -> asyncio.Protocol:
        return _Guarded(self)


class _Guarded(asyncio.Protocol):
    """One connection: aiohttp's protocol inside, or a refusal."""

    def __init__(self, guard: ConnectionGuard) -> None:
        self.guard = guard
        self.inner: Any = None
        """aiohttp's ``RequestHandler`` (None: refused)."""
        self.transport: asyncio.Transport | None = None
        self._requests = 0
        self._timer: asyncio.TimerHandle | None = None
        self._lingering = False

    # --- asyncio's side ---------------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        guard = self.guard
        if guard.open >= guard.limits.max_connections:
            self._refuse(transport)
            return
        guard.open += 1
        guard.accepted += 1
        self.inner = guard.factory()
        self.inner.connection_made(transport)
        self._start_timer()

    def data_received(self, data: bytes) -> None:
        inner = self.inner
        if inner is None:
            return  # a refused connection's request: read to close cleanly, thrown away
        inner.data_received(data)
        count = inner._request_count  # complete request headers parsed so far
        if count != self._requests:
            self._requests = count
            self._stop_timer()
        elif self._timer is None and self._between_requests():
            self._start_timer()  # the first bytes of the next request

    def eof_received(self) -> bool | None:
        if self.inner is None:
            return False  # the refused client is done: close
        result: bool | None = self.inner.eof_received()
        return result

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_timer()
        if self.inner is None:
            if self._lingering:
                self._lingering = False
                self.guard.lingering -= 1
            return
        self.guard.open -= 1
        inner, self.inner = self.inner, None
        inner.connection_lost(exc)

    def pause_writing(self) -> None:
        if self.inner is not None:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.inner is not None:
            self.inner.resume_writing()

    # --- the limits -------------------------------------------------------------------------
    def _refuse(self, transport: asyncio.Transport) -> None:
        guard = self.guard
        guard.refused += 1
        log.warning(
            "hmi: %d HTTP connections open (hmi.max_connections): a new one answered 503",
            guard.open,
        )
        transport.write(guard._answer)
        if guard.lingering >= LINGER_MAX or not transport.can_write_eof():
            transport.close()
            return
        transport.write_eof()
        guard.lingering += 1
        self._lingering = True
        self._timer = asyncio.get_running_loop().call_later(LINGER_S, transport.close)

    def _between_requests(self) -> bool:
        inner = self.inner
        return (
            not inner._request_in_progress
            and not inner._messages
            and not inner._upgraded
            and inner._payload_parser is None
        )

    def _start_timer(self) -> None:
        self._timer = asyncio.get_running_loop().call_later(
            self.guard.limits.header_timeout_s, self._headers_late
        )

    def _stop_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _headers_late(self) -> None:
        self._timer = None
        if self.inner is None or self.transport is None:
            return
        if not self._between_requests():
            # A request is being answered: the timer was started by the last bytes of its
            # body, which came after aiohttp took its headers but before its handler ran
            # (issue 28: two of three slow validations of a 150 KB text were cut off at
            # 10 s without an answer). Its headers were complete; the next request's first
            # bytes start the timer again.
            return
        self.guard.timed_out += 1
        log.warning(
            "hmi: a connection sent no complete request headers within %g s"
            " (hmi.header_timeout_s): closed",
            self.guard.limits.header_timeout_s,
        )
        self.transport.abort()  # nothing to flush: it never had a request answered
