"""Free loopback ports for servers a test starts (tests only ever bind 127.0.0.1)."""

from __future__ import annotations

import socket

LOOPBACK = "127.0.0.1"


def free_tcp_port(host: str = LOOPBACK) -> int:
    """A TCP port nobody listens on right now (the OS picks it; another process could take
    it before the test binds it, which loopback tests on one machine accept)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])
