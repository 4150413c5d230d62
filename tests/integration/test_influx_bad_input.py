"""Bad input against the real InfluxDB (issue 10, "Bad input"): a wrong URL, a wrong token,
a wrong bucket and a field whose type changes — each reported once with its cause,
counted, the points kept in the spool (never dropped silently) and delivered once the
cause is gone, without a human restarting anything; and the line protocol's escaping
as the real server reads it back. (A 500, a 429 and a server that never answers cannot be
had from InfluxDB on demand: tests/unit/test_influx_forwarder.py gets them from a scripted
server.)"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from itertools import count
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from influxdb_client.client.influxdb_client import InfluxDBClient
from influxdb_client.client.write_api import SYNCHRONOUS
from influxrig import InfluxServer

from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality
from supervisor.publish.changes import Sample
from supervisor.publish.influx import (
    Failure,
    InfluxSettings,
    InfluxWriter,
    LineEncoder,
    WriteClient,
)
from supervisor.tags import TagDB, TagSpec
from supervisor.testing import free_tcp_port

LIMIT_S = 60.0  # a bound for a loaded machine, not a timing claim
WALL = 1_760_000_000.0
pytestmark = pytest.mark.integration
_databases = count()


def wait_for(condition: Callable[[], bool], what: str, limit_s: float = LIMIT_S) -> None:
    deadline = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up after {limit_s:g} s waiting for {what}")
        time.sleep(0.02)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InfluxServer]:
    """One InfluxDB for the module (no test here stops it): a database per test."""
    srv = InfluxServer(tmp_path_factory.mktemp("influxdb"))
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture
def database(server: InfluxServer) -> str:
    name = f"t{next(_databases)}"
    server.query(f"CREATE DATABASE {name}")
    return name


class Alarms:
    def __init__(self) -> None:
        self.calls: list[tuple[str, bool, str]] = []

    def __call__(self, alarm_id: str, active: bool, message: str) -> None:
        self.calls.append((alarm_id, active, message))

    def of(self, alarm_id: str) -> list[bool]:
        return [a for i, a, _ in self.calls if i == alarm_id]


class Bench:
    """A tag database with a few tags, scanned by hand, published by a real writer."""

    def __init__(self, tmp: Path, url: str, bucket: str, token: str = "user:password") -> None:
        self.clock = VirtualClock(wall_epoch_s=WALL)
        self.db = TagDB()
        for name, unit in (("pack.voltage", "V"), ("pack.temp", "degC"), ("ch0.current", "A")):
            self.db.add(TagSpec(name, unit=unit))
        self.alarms = Alarms()
        settings = InfluxSettings(
            url=url,
            org="-",
            bucket=bucket,
            token=token,
            spool_path=tmp / "influx-spool.sqlite",
            flush_interval_s=0.05,
            retry_max_s=0.3,
            timeout_s=5.0,
            commit_interval_s=0.02,
        )
        self.writer = InfluxWriter(
            self.db, self.clock, settings, bench="b1", channels=["ch0"], alarm=self.alarms
        )
        self.writer.start()

    def scan(self, **values: float) -> None:
        self.clock.advance(0.1)
        self.db.set_scan_time(self.clock.now())
        for name, v in values.items():
            self.db.update(self.db[name.replace("__", ".")], v)
        self.writer.on_scan(self.db, self.clock.now())

    def run(self, scans: int = 5) -> None:
        for k in range(scans):
            self.scan(pack__voltage=14.0 + k / 10, ch0__current=0.1 * k)

    def close(self) -> None:
        self.writer.close(0.5)


@pytest.fixture
def make_bench(tmp_path: Path) -> Iterator[Callable[..., Bench]]:
    made: list[Bench] = []

    def make(url: str, bucket: str, token: str = "user:password") -> Bench:
        b = Bench(tmp_path / f"b{len(made)}", url, bucket, token)
        made.append(b)
        return b

    yield make
    for b in made:
        b.close()


def errors(caplog: pytest.LogCaptureFixture, text: str) -> int:
    return sum(1 for r in caplog.records if r.levelno >= logging.ERROR and text in r.getMessage())


def test_a_wrong_url_keeps_every_point_counts_the_attempts_and_says_so_once(
    make_bench: Callable[..., Bench], caplog: pytest.LogCaptureFixture
) -> None:
    bench = make_bench(f"http://127.0.0.1:{free_tcp_port()}", "bench/autogen")
    bench.run()
    w = bench.writer
    wait_for(lambda: w.status().forwarder.failed_writes >= 3, "refused connections")
    st = w.status()
    assert st.forwarder.failure is Failure.UNREACHABLE
    assert "Connection refused" in st.forwarder.last_error
    assert st.spool.waiting == st.spool.produced > 0 and st.spool.dropped == 0
    assert errors(caplog, "unreachable") == 1


def test_a_wrong_bucket_keeps_every_point_alarms_and_drains_once_the_database_exists(
    server: InfluxServer, make_bench: Callable[..., Bench], caplog: pytest.LogCaptureFixture
) -> None:
    missing = f"late{next(_databases)}"
    bench = make_bench(server.url, f"{missing}/autogen")
    bench.run()
    w = bench.writer
    wait_for(lambda: w.status().forwarder.failed_writes >= 2, "404s")
    bench.scan()  # the status reaches the tags and the alarm model
    st = w.status()
    assert st.forwarder.failure is Failure.BUCKET
    assert f'404 database not found: "{missing}"' in st.forwarder.last_error
    assert st.spool.dead == 0 and st.spool.waiting == st.spool.produced  # never dead-lettered
    assert bench.alarms.of("influx.config") == [True]
    assert errors(caplog, "bucket not found") == 1
    server.query(f"CREATE DATABASE {missing}")  # someone fixes it; nobody restarts anything
    wait_for(lambda: w.status().spool.waiting == 0, "the spool drained")
    bench.scan()
    assert bench.alarms.of("influx.config") == [True, False]
    assert len(server.points("device", missing)) == 5
    assert len(server.points("channel", missing)) == 5


def test_a_wrong_token_gets_a_401_keeps_every_point_and_drains_once_the_user_exists(
    influx_auth: InfluxServer, make_bench: Callable[..., Bench], caplog: pytest.LogCaptureFixture
) -> None:
    bench = make_bench(influx_auth.url, influx_auth.bucket, token="writer:s3cret")
    bench.run()
    w = bench.writer
    wait_for(lambda: w.status().forwarder.failed_writes >= 2, "401s")
    bench.scan()
    st = w.status()
    assert st.forwarder.failure is Failure.AUTH
    assert "401 authorization failed" in st.forwarder.last_error
    assert st.spool.dead == 0 and st.spool.waiting == st.spool.produced
    assert bench.alarms.of("influx.config") == [True]
    assert errors(caplog, "token refused") == 1
    influx_auth.query("CREATE USER writer WITH PASSWORD 's3cret'")
    influx_auth.query("GRANT WRITE ON bench TO writer")
    wait_for(lambda: w.status().spool.waiting == 0, "the spool drained")
    assert len(influx_auth.points("device")) == 5


def test_a_field_whose_type_changed_goes_to_the_dead_letters_and_the_rest_is_delivered(
    server: InfluxServer, database: str, make_bench: Callable[..., Bench]
) -> None:
    # Someone wrote pack.temp as an integer field first (a Point with an int, 21i), in the
    # same shard (1.8 keeps field types per shard: the same week).
    with InfluxDBClient(url=server.url, token="user:password", org="-") as client:
        client.write_api(write_options=SYNCHRONOUS).write(
            bucket=f"{database}/autogen",
            record=f"device,bench=b1,device=pack temp=21i {int((WALL - 1) * 1e9)}",
        )
    bench = make_bench(server.url, f"{database}/autogen")
    bench.scan(pack__temp=25.0)  # our float: refused for good
    bench.run()  # voltage and current: fine
    w = bench.writer
    wait_for(lambda: w.status().spool.waiting == 0 and w.status().spool.sent > 0, "settled")
    st = w.status()
    assert st.spool.dead == 1 and st.spool.dropped == 0
    assert st.spool.sent + st.spool.dead == st.spool.produced
    ((_, status, reason, line),) = w.spool.dead_letters()
    assert status == 400 and "field type conflict" in reason and "temp=25.0" in line
    bench.scan()
    assert bench.alarms.of("influx.dead_letters")[0] is True
    points = server.points("device", database)
    assert sum(1 for f in points.values() if "voltage" in f) == 5
    assert sum(1 for f in server.points("channel", database).values() if "current" in f) == 5


TEXT = st.text(st.characters(blacklist_categories=("Cs",)), min_size=1, max_size=30)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(test_id=TEXT, recipe=TEXT, text=st.text(max_size=60))
def test_the_real_server_reads_back_any_test_id_recipe_and_text_as_encoded(
    server: InfluxServer, database: str, test_id: str, recipe: str, text: str
) -> None:
    enc = LineEncoder("b1", ["ch0"], lambda name: "str")
    ts = time.time_ns()
    sample = Sample("ch0.chain.last_event", text, Quality.GOOD, 0.0, ts / 1e9)
    (line,) = enc.encode([sample], {"ch0": (test_id, recipe)})["channel"]
    client = WriteClient(server.url, "-", f"{database}/autogen", "user:password", 10.0)
    try:
        assert client.write(line.encode()).status == 204, line
    finally:
        client.close()
    stamp = int(line.rsplit(" ", 1)[1])
    (tags, _), fields = next(
        (k, f) for k, f in server.points("channel", database).items() if k[1] == stamp
    )
    as_written = {  # the lineproto docstring: line breaks → space, backslash → "/" in tags
        "test_id": test_id.replace("\\", "/").replace("\n", " ").replace("\r", " "),
        "recipe": recipe.replace("\\", "/").replace("\n", " ").replace("\r", " "),
    }
    assert dict(tags) == {"bench": "b1", "channel": "ch0", **as_written}
    assert fields == {"chain_last_event": text.replace("\n", " ").replace("\r", " ")}
