"""Free loopback ports for the servers a benchmark (or a test) starts: one function.

The OS picks a free port for a bind to port 0; once that socket is closed, the next bind
may be given the same port. A map whose HMI, OPC UA, Modbus and device ports are picked one
after the other could so give one port to two services, and the second failed to start
("address already in use": a load benchmark in the unit suite, 2026-12-05). A port handed
out here is never handed out again by this process."""

from __future__ import annotations

import socket
import threading
from typing import Final

LOOPBACK: Final = "127.0.0.1"
_TRIES: Final = 100

_given: set[int] = set()
_lock = threading.Lock()


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port nobody listens on right now and that this process has not handed out
    before (another process could still take it before it is bound: loopback benchmarks
    and tests on one machine accept that)."""
    with _lock:
        for _ in range(_TRIES):
            with socket.socket() as s:
                s.bind((host, 0))
                port = int(s.getsockname()[1])
            if port not in _given:
                _given.add(port)
                return port
    raise OSError(f"no free TCP port on {host} that was not handed out before")
