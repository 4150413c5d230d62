"""Free loopback ports for servers a test starts (tests only ever bind 127.0.0.1): the
benchmarks' one function (``supervisor/bench/ports.py``: never the same port twice in a
process)."""

from __future__ import annotations

from supervisor.bench.ports import LOOPBACK, free_port


def free_tcp_port(host: str = LOOPBACK) -> int:
    """A TCP port nobody listens on right now, not handed out before by this process."""
    return free_port(host)
