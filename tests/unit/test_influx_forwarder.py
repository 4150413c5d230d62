"""The forwarder against replies a real InfluxDB cannot be made to give on demand (a tiny
HTTP server on loopback, ``influxrig.ScriptedInflux``): each failure kind is retried or
set aside as it deserves, reported once, counted, and nothing leaves the spool unless the
server took it or refused that very line for good."""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from influxrig import Reply, ScriptedInflux

from supervisor.publish.influx import Delivery, Failure, Forwarder, Spool, WriteClient
from supervisor.testing import free_tcp_port

LIMIT_S = 30.0  # a bound for a loaded machine, not a timing claim


def wait_for(condition: Callable[[], bool], what: str, limit_s: float = LIMIT_S) -> None:
    deadline = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up after {limit_s:g} s waiting for {what}")
        time.sleep(0.01)


def lines(first: int, n: int, bad: set[int] = frozenset()) -> list[str]:  # type: ignore[assignment]
    return [f"m,bench=b v={'BAD' if k in bad else f'{k}.0'} {k}" for k in range(first, first + n)]


class Rig:
    """A spool with points, a forwarder and its recorded waits."""

    def __init__(self, tmp: Path, url: str, *, timeout_s: float = 5.0, batch: int = 10) -> None:
        self.spool = Spool(tmp / "spool.sqlite", 1 << 30)
        self.spool.open()
        self.client = WriteClient(url, "-", "bench/autogen", "user:password", timeout_s)
        self.waits: list[float] = []
        self.deliveries: list[Delivery] = []
        rig = self

        class Recording(Forwarder):
            def _wait(self, delay_s: float, until_kicked: bool = False) -> None:
                if not until_kicked:
                    rig.waits.append(delay_s)
                super()._wait(min(delay_s, 0.05), until_kicked)  # recorded, not waited out

        self.forwarder = Recording(
            self.spool, self.client, batch_size=batch, flush_interval_s=0.01, retry_max_s=7.0
        )
        self.forwarder.listeners.append(self.deliveries.append)

    def put(self, body: list[str]) -> None:
        self.spool.append([("m", body)], 10)
        self.forwarder.notify()

    def close(self) -> None:
        self.forwarder.stop(0.5)
        self.spool.close()


@pytest.fixture
def server() -> Iterator[ScriptedInflux]:
    srv = ScriptedInflux()
    yield srv
    srv.close()


@pytest.fixture
def rig(tmp_path: Path, server: ScriptedInflux) -> Iterator[Rig]:
    r = Rig(tmp_path, server.url)
    yield r
    r.close()


def errors(caplog: pytest.LogCaptureFixture, text: str) -> int:
    return sum(1 for r in caplog.records if r.levelno >= logging.ERROR and text in r.getMessage())


def test_points_go_out_oldest_first_and_leave_the_spool_once_acknowledged(
    rig: Rig, server: ScriptedInflux
) -> None:
    rig.put(lines(0, 10))
    rig.put(lines(10, 10))
    rig.put(lines(20, 5))
    rig.forwarder.start()
    wait_for(lambda: rig.spool.counts().sent == 25, "every point acknowledged")
    assert server.accepted == [x.encode() for x in lines(0, 25)]
    ids = [i for d in rig.deliveries for i in d.ids]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    assert rig.spool.counts().waiting == 0
    assert rig.forwarder.status().connected


def test_a_kept_alive_connection_closed_by_the_server_is_reopened_without_a_failure(
    rig: Rig, server: ScriptedInflux
) -> None:
    server.answer = lambda body: Reply(hang_up=True)  # as an idle timeout of a proxy does
    rig.forwarder.start()
    for k in range(3):
        rig.put(lines(10 * k, 10))
        wait_for(lambda k=k: rig.spool.counts().sent == 10 * (k + 1), f"batch {k}")
    assert rig.forwarder.status().failed_writes == 0
    assert len(server.requests) == 3


def test_a_500_is_retried_with_backoff_reported_once_and_the_batch_delivered_after(
    rig: Rig, server: ScriptedInflux, caplog: pytest.LogCaptureFixture
) -> None:
    failures = iter(range(3))
    server.answer = lambda body: (
        Reply(500, '{"error":"engine: cache maximum memory size exceeded"}')
        if next(failures, None) is not None
        else Reply()
    )
    rig.put(lines(0, 10))
    rig.forwarder.start()
    wait_for(lambda: rig.spool.counts().sent == 10, "delivery after the 500s")
    st = rig.forwarder.status()
    assert st.failed_writes == 3 and st.failure is None and st.connected
    assert "500 engine: cache maximum memory size exceeded" in st.last_error
    assert errors(caplog, "server error") == 1  # reported once, not three times
    assert any("accepted again" in r.getMessage() for r in caplog.records)
    assert rig.waits[:3] == sorted(rig.waits[:3])  # backing off
    assert server.accepted == [x.encode() for x in lines(0, 10)]


def test_a_429_is_retried_no_sooner_than_its_retry_after(rig: Rig, server: ScriptedInflux) -> None:
    answers = iter([Reply(429, "too many requests", {"Retry-After": "5"})])
    server.answer = lambda body: next(answers, Reply())
    rig.put(lines(0, 10))
    rig.forwarder.start()
    wait_for(lambda: rig.spool.counts().sent == 10, "delivery after the 429")
    assert rig.waits[0] >= 5.0
    assert rig.forwarder.status().failed_writes == 1


def test_a_400_isolates_the_bad_lines_as_dead_letters_and_delivers_the_rest(
    rig: Rig, server: ScriptedInflux
) -> None:
    conflict = '{"error":"partial write: field type conflict: input field \\"v\\" is type float"}'
    server.answer = lambda body: Reply(400, conflict) if b"BAD" in body else Reply()
    body = lines(0, 10, bad={3, 7})
    rig.put(body)
    rig.forwarder.start()
    wait_for(lambda: rig.spool.counts().waiting == 0, "the batch settled")
    c = rig.spool.counts()
    assert (c.sent, c.dead, c.dropped) == (8, 2, 0)
    dead = sorted(line for _, _, _, line in rig.spool.dead_letters())
    assert dead == sorted([body[3], body[7]])
    reasons = {reason for _, _, reason, _ in rig.spool.dead_letters()}
    assert reasons == {'400 partial write: field type conflict: input field "v" is type float'}
    good = [x.encode() for k, x in enumerate(body) if k not in (3, 7)]
    assert sorted(set(server.accepted)) == sorted(good)
    assert rig.forwarder.status().dead_alarm
    (delivery,) = rig.deliveries
    assert delivery.body.split(b"\n") == good and delivery.points == 8


@pytest.mark.parametrize(
    ("status", "message", "failure"),
    [
        (401, '{"error":"authorization failed"}', Failure.AUTH),
        (403, '{"error":"forbidden"}', Failure.AUTH),
        (404, '{"error":"database not found: \\"bench\\""}', Failure.BUCKET),
    ],
)
def test_a_refused_token_or_bucket_keeps_every_point_and_retries_slowly_until_fixed(
    rig: Rig,
    server: ScriptedInflux,
    caplog: pytest.LogCaptureFixture,
    status: int,
    message: str,
    failure: Failure,
) -> None:
    fixed = threading.Event()
    server.answer = lambda body: Reply() if fixed.is_set() else Reply(status, message)
    rig.put(lines(0, 10))
    rig.forwarder.start()
    wait_for(lambda: rig.forwarder.status().failed_writes >= 3, "a few refusals")
    st = rig.forwarder.status()
    assert st.failure is failure and not st.connected
    c = rig.spool.counts()
    assert (c.waiting, c.dead, c.dropped) == (10, 0, 0)  # never dead-lettered
    assert all(w == 7.0 for w in rig.waits)  # retry_max_s, no fast retries
    assert errors(caplog, failure.value) == 1
    fixed.set()
    wait_for(lambda: rig.spool.counts().sent == 10, "delivery once the server accepts")
    assert rig.forwarder.status().failure is None


def test_a_server_that_is_not_there_is_retried_until_it_is(tmp_path: Path) -> None:
    port = free_tcp_port()
    rig = Rig(tmp_path, f"http://127.0.0.1:{port}")
    try:
        rig.put(lines(0, 10))
        rig.forwarder.start()
        wait_for(lambda: rig.forwarder.status().failed_writes >= 2, "refused connections")
        st = rig.forwarder.status()
        assert st.failure is Failure.UNREACHABLE and rig.spool.counts().waiting == 10
        server = ScriptedInflux(port=port)
        try:
            wait_for(lambda: rig.spool.counts().sent == 10, "delivery once it listens")
        finally:
            server.close()
    finally:
        rig.close()


def test_a_server_that_accepts_and_never_answers_times_out_is_counted_and_retried(
    tmp_path: Path,
) -> None:
    silent = threading.Event()
    silent.set()
    server = ScriptedInflux(lambda body: Reply(silent=silent.is_set()))
    rig = Rig(tmp_path, server.url, timeout_s=0.3)
    try:
        rig.put(lines(0, 10))
        rig.forwarder.start()
        wait_for(lambda: rig.forwarder.status().timeouts >= 2, "timed-out requests")
        st = rig.forwarder.status()
        assert st.failure is Failure.TIMEOUT and "timed out" in st.last_error
        assert rig.spool.counts().waiting == 10
        silent.clear()
        wait_for(lambda: rig.spool.counts().sent == 10, "delivery once it answers")
    finally:
        rig.close()
        server.close()


def test_a_stop_during_an_outage_is_bounded_and_leaves_the_points_spooled(tmp_path: Path) -> None:
    with socket.socket() as listener:  # accepts (the kernel does), never answers
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)
        rig = Rig(tmp_path, f"http://127.0.0.1:{listener.getsockname()[1]}", timeout_s=60.0)
        rig.put(lines(0, 10))
        rig.forwarder.start()
        wait_for(
            lambda: rig.forwarder.status().failed_writes == 0 and rig.spool._inflight,
            "a request in flight",
        )
        assert rig.forwarder.stop(0.3)  # aborted at the deadline, not after its 60 s timeout
        assert rig.spool.counts().waiting == 10
        rig.spool.close()
