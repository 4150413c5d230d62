"""One free-port function for benchmarks and tests (``supervisor/bench/ports.py``): the OS
may give a closed socket's port to the next bind, and two services of one map given one
port fail to start (a load benchmark in the unit suite did)."""

from __future__ import annotations

import socket
from typing import Any

import pytest

from supervisor.bench import ports
from supervisor.testing import free_tcp_port


def test_a_port_the_os_offers_again_is_not_handed_out_twice(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    offered = iter([41001, 41001, 41001, 41002])

    class Socket:
        def __enter__(self) -> Socket:
            return self

        def __exit__(self, *exc: Any) -> None:
            return None

        def bind(self, address: tuple[str, int]) -> None:
            self.port = next(offered)

        def getsockname(self) -> tuple[str, int]:
            return ("127.0.0.1", self.port)

    monkeypatch.setattr(ports, "_given", set())
    monkeypatch.setattr(ports.socket, "socket", Socket)
    assert [ports.free_port(), ports.free_port()] == [41001, 41002]


def test_ports_handed_out_one_after_the_other_are_distinct_and_bindable() -> None:
    picked = [free_tcp_port() for _ in range(50)]
    assert len(set(picked)) == 50
    with socket.socket() as s:
        s.bind(("127.0.0.1", picked[-1]))
