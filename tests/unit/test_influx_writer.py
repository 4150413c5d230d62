"""The InfluxDB writer as the bench sees it: a publisher whose scan side only queues, the
influx.* status tags, its alarms through the bench's alarm model, bench events as
annotations, a clean stop that keeps what it could not send, and the ``influxdb:``
section of the I/O map (the token never in the file; a missing token file named with
file:line:col)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from influxrig import Reply, ScriptedInflux, parse_line

from supervisor.app import build_bench
from supervisor.cli.main import main
from supervisor.commands import Command
from supervisor.core.clock import RealClock, VirtualClock
from supervisor.core.records import BenchEvent
from supervisor.devices.registry import bench_from_data, load_bench
from supervisor.publish.influx import InfluxSettings, InfluxWriter
from supervisor.publish.influx.spool import Spool
from supervisor.publish.influx.writer import SpoolWriter
from supervisor.safety.alarms import AlarmState
from supervisor.tags import TagDB, TagSpec
from supervisor.testing import wait_until

ROOT = Path(__file__).resolve().parents[2]
LIMIT_S = 30.0


class Alarms:
    """The alarm hook's calls, in order."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, bool, str]] = []

    def __call__(self, alarm_id: str, active: bool, message: str) -> None:
        self.calls.append((alarm_id, active, message))

    def of(self, alarm_id: str) -> list[bool]:
        return [active for a, active, _ in self.calls if a == alarm_id]


def writer_for(
    tmp: Path, url: str, db: TagDB, clock: VirtualClock, alarms: Alarms, **kw: object
) -> InfluxWriter:
    settings = InfluxSettings(
        url=url,
        org="-",
        bucket="bench/autogen",
        token="user:password",
        spool_path=tmp / "influx-spool.sqlite",
        flush_interval_s=0.05,
        retry_max_s=0.2,
        alarm_after_s=0.0,
        commit_interval_s=0.02,
        **kw,  # type: ignore[arg-type]
    )
    return InfluxWriter(db, clock, settings, bench="b1", channels=["ch0"], alarm=alarms)


@pytest.fixture
def server() -> Iterator[ScriptedInflux]:
    srv = ScriptedInflux()
    yield srv
    srv.close()


@pytest.fixture
def db() -> TagDB:
    db = TagDB()
    db.add(TagSpec("ch0.voltage", unit="V"))
    db.add(TagSpec("pack.temp", unit="degC"))
    return db


def scan(writer: InfluxWriter, db: TagDB, clock: VirtualClock, **values: float) -> None:
    db.set_scan_time(clock.now())
    for name, v in values.items():
        db.update(db[name.replace("__", ".")], v)
    writer.on_scan(db, clock.now())


async def test_changes_reach_the_server_and_the_status_tags_follow(
    tmp_path: Path, server: ScriptedInflux, db: TagDB, virtual_clock: VirtualClock
) -> None:
    alarms = Alarms()
    w = writer_for(tmp_path, server.url, db, virtual_clock, alarms)
    w.start()
    try:
        scan(w, db, virtual_clock, ch0__voltage=1.2, pack__temp=25.0)
        virtual_clock.advance(0.1)
        scan(w, db, virtual_clock, ch0__voltage=1.3)
        await wait_until(lambda: w.status().spool.sent >= 3, "delivery", LIMIT_S)
        scan(w, db, virtual_clock)
        assert db["influx.sent"].value == w.status().spool.sent
        assert db["influx.connected"].value is True
        assert db["influx.spool_depth"].value == w.status().spool.waiting
        assert db["influx.last_error"].value == ""
        text = b"\n".join(server.accepted).decode()
        assert "channel,bench=b1,channel=ch0 voltage=1.2" in text
        assert "device,bench=b1,device=pack temp=25.0" in text
        assert alarms.calls == []  # nothing wrong: no alarm touched
    finally:
        w.close()


async def test_a_refused_token_raises_the_config_alarm_once_and_clears_it_when_fixed(
    tmp_path: Path, server: ScriptedInflux, db: TagDB, virtual_clock: VirtualClock
) -> None:
    fixed = threading.Event()
    server.answer = lambda body: Reply() if fixed.is_set() else Reply(401, '{"error":"nope"}')
    alarms = Alarms()
    w = writer_for(tmp_path, server.url, db, virtual_clock, alarms)
    w.start()
    try:
        scan(w, db, virtual_clock, ch0__voltage=1.2)
        await wait_until(lambda: w.status().forwarder.failed_writes >= 2, "refusals", LIMIT_S)
        for _ in range(3):
            scan(w, db, virtual_clock)
        assert alarms.of("influx.config") == [True]
        assert "401 nope" in alarms.calls[0][2]
        assert "token refused: 401 nope" in str(db["influx.last_error"].value)
        assert db["influx.connected"].value is False
        assert w.status().spool.dead == 0
        fixed.set()
        await wait_until(lambda: w.status().spool.waiting == 0, "delivery once fixed", LIMIT_S)
        scan(w, db, virtual_clock)
        assert alarms.of("influx.config") == [True, False]
    finally:
        w.close()


async def test_an_unreachable_server_alarms_after_alarm_after_s_and_a_dead_letter_alarms(
    tmp_path: Path, server: ScriptedInflux, db: TagDB, virtual_clock: VirtualClock
) -> None:
    down = threading.Event()
    down.set()
    server.answer = lambda body: (
        Reply(503, "unavailable")
        if down.is_set()
        else Reply(400, '{"error":"field type conflict"}')
        if b"temp" in body
        else Reply()
    )
    alarms = Alarms()
    w = writer_for(tmp_path, server.url, db, virtual_clock, alarms)
    w.start()
    try:
        scan(w, db, virtual_clock, ch0__voltage=1.2, pack__temp=25.0)
        await wait_until(lambda: w.status().forwarder.failed_writes >= 1, "a 503", LIMIT_S)
        scan(w, db, virtual_clock)
        assert alarms.of("influx.unreachable") == [True]
        down.clear()
        await wait_until(lambda: w.status().spool.waiting == 0, "the batch settled", LIMIT_S)
        scan(w, db, virtual_clock)
        assert alarms.of("influx.unreachable") == [True, False]
        assert alarms.of("influx.dead_letters") == [True]
        assert db["influx.dead_letters"].value == 1
        ((_, status, reason, line),) = w.spool.dead_letters()
        assert (status, reason) == (400, "400 field type conflict") and "temp=25.0" in line
    finally:
        w.close()


async def test_the_scan_only_hands_its_samples_over_the_spool_writer_encodes_them(
    tmp_path: Path, server: ScriptedInflux, db: TagDB, virtual_clock: VirtualClock
) -> None:
    w = writer_for(tmp_path, server.url, db, virtual_clock, Alarms())
    scan(w, db, virtual_clock, ch0__voltage=1.2, pack__temp=25.0)
    assert w.encoder._routes == {}  # no line made on the scan's thread (issue 13)
    assert w.writer.queued >= 2
    w.start()
    try:
        await wait_until(lambda: w.status().spool.sent >= 2, "delivery", LIMIT_S)
        text = b"\n".join(server.accepted).decode()
        assert "channel,bench=b1,channel=ch0 voltage=1.2" in text
        assert "device,bench=b1,device=pack temp=25.0" in text
    finally:
        w.close()


async def test_a_full_queue_drops_its_oldest_points_counted_and_alarmed(
    tmp_path: Path, db: TagDB, virtual_clock: VirtualClock
) -> None:
    alarms = Alarms()
    w = writer_for(tmp_path, "http://127.0.0.1:9", db, virtual_clock, alarms, queue_max_points=2)
    # Not started: nothing moves the queue to the spool (as if the disk stalled).
    for k in range(5):
        scan(w, db, virtual_clock, ch0__voltage=1.0 + k, pack__temp=20.0 + k)
    assert w.writer.queued <= 2
    assert db["influx.dropped"].value == w.status().dropped > 0
    assert alarms.of("influx.spool_full") == [True]


async def test_a_spool_that_cannot_be_written_is_alarmed_and_retried_until_it_can(
    tmp_path: Path, server: ScriptedInflux, db: TagDB, virtual_clock: VirtualClock
) -> None:
    alarms = Alarms()
    w = writer_for(tmp_path, server.url, db, virtual_clock, alarms)
    w.spool.path.mkdir()  # a folder where the spool file should be: cannot be opened
    w.start()
    try:
        scan(w, db, virtual_clock, ch0__voltage=1.2)
        await wait_until(lambda: w.status().spool_error != "", "the spool error", LIMIT_S)
        scan(w, db, virtual_clock)
        assert alarms.of("influx.spool") == [True]
        assert w.writer.queued > 0  # kept in memory meanwhile
        w.spool.path.rmdir()
        await wait_until(
            lambda: w.status().spool.sent == w.status().spool.produced > 0,
            "delivery after the fix",
            LIMIT_S,
        )
        scan(w, db, virtual_clock)
        assert alarms.of("influx.spool") == [True, False]
    finally:
        w.close()


def test_a_new_test_writes_every_current_field_of_its_channel_once_with_the_new_tags(
    tmp_path: Path, db: TagDB, virtual_clock: VirtualClock
) -> None:
    # A test that starts at the cycle number the last one ended at changes no chain_cycle:
    # without this its series would have no chain_cycle point (dashboards: per-cycle panels).
    db.add(TagSpec("ch0.chain.test_id", dtype="str", initial=""))
    db.add(TagSpec("ch0.chain.recipe", dtype="str", initial=""))
    db.add(TagSpec("ch0.chain.cycle", dtype="int", initial=1))
    db.add(TagSpec("ch0.eta_s", unit="s"))  # GOOD, never set: no field
    db.add(TagSpec("ch1.voltage", unit="V"))  # another channel's: not rewritten
    w = writer_for(tmp_path, "http://127.0.0.1:9", db, virtual_clock, Alarms())
    lines: list[str] = []
    w.writer.put = lambda measurement, batch: lines.extend(batch)  # type: ignore[method-assign]
    # Encoded on the spool writer's thread in the bench; here at once, to look at the lines.
    w.writer.put_deferred = lambda points, encode: [  # type: ignore[method-assign]
        lines.extend(batch) for batch in encode().values()
    ]
    scan(w, db, virtual_clock, ch0__voltage=3.5, ch1__voltage=3.6)
    virtual_clock.advance(0.1)
    scan(w, db, virtual_clock, ch0__voltage=3.6)
    lines.clear()

    virtual_clock.advance(0.1)
    db.set_scan_time(virtual_clock.now())
    db.update(db["ch0.chain.test_id"], "T-2")
    db.update(db["ch0.chain.recipe"], "cycle")
    w.on_scan(db, virtual_clock.now())
    [line] = [x for x in lines if x.startswith("channel,")]
    _, tags, fields, ts = parse_line(line)
    assert tags == {"bench": "b1", "channel": "ch0", "recipe": "cycle", "test_id": "T-2"}
    assert fields == {
        "voltage": 3.6,
        "chain_cycle": 1.0,
        "chain_test_id": "T-2",
        "chain_recipe": "cycle",
    }
    assert ts == round(virtual_clock.wall() * 1e9)

    lines.clear()  # once: the next scan writes only what changed
    virtual_clock.advance(0.1)
    scan(w, db, virtual_clock, ch0__voltage=3.7)
    assert [parse_line(x)[2] for x in lines if x.startswith("channel,")] == [{"voltage": 3.7}]


async def test_bench_events_become_event_lines(
    tmp_path: Path, server: ScriptedInflux, db: TagDB, virtual_clock: VirtualClock
) -> None:
    w = writer_for(tmp_path, server.url, db, virtual_clock, Alarms())
    w.start()
    try:
        w.on_event(BenchEvent(0.0, 1.7e9, "step", "ch0", "charge", "step charge", "recipe"))
        await wait_until(lambda: w.status().spool.sent == 1, "the event", LIMIT_S)
        (line,) = server.accepted
        assert line.startswith(b"event,bench=b1,channel=ch0,kind=step ")
        assert b'text="step charge"' in line
    finally:
        w.close()


async def test_a_clean_stop_spools_the_queue_and_keeps_what_it_could_not_send(
    tmp_path: Path, db: TagDB, virtual_clock: VirtualClock
) -> None:
    w = writer_for(tmp_path, "http://127.0.0.1:9", db, virtual_clock, Alarms(), stop_flush_s=0.2)
    w.start()
    scan(w, db, virtual_clock, ch0__voltage=1.2, pack__temp=25.0)
    w.close()
    again = writer_for(tmp_path, "http://127.0.0.1:9", TagDB(), virtual_clock, Alarms())
    again.spool.open()
    c = again.spool.counts()
    assert c.waiting == c.produced >= 2 and c.sent == 0  # on disk for the next run
    again.spool.close()


# --- the I/O map and the composition root -----------------------------------------------------
def sim_data(tmp: Path, influxdb: dict[str, object] | None) -> dict[str, object]:
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["devices"] = {"chadeche": data["devices"]["chadeche"]}
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "chadeche"]
    for key in ("tags", "simulation", "safety"):
        data.pop(key, None)
    data["state_dir"] = str(tmp / "var")
    if influxdb is not None:
        data["influxdb"] = influxdb
    return data


async def test_an_io_map_with_influxdb_wires_the_writer_its_alarms_and_its_events(
    tmp_path: Path, server: ScriptedInflux
) -> None:
    token = tmp_path / "token"
    token.write_text("user:password\n")
    cfg = bench_from_data(
        sim_data(
            tmp_path,
            {
                "url": server.url,
                "bucket": "bench/autogen",
                "token_file": str(token),
                "flush_interval_s": 0.05,
            },
        )
    )
    bench = build_bench(cfg, VirtualClock(), in_process=True)
    assert bench.influx is not None and bench.influx in bench.engine.publishers
    assert bench.influx.settings.spool_path == Path(cfg.state_dir) / "influx-spool.sqlite"
    assert bench.influx.settings.token == "user:password"
    assert bench.alarms is not None and "influx.config" in bench.alarms
    await bench.start()
    try:
        await bench.engine.run_for(2.0)
        result = bench.commands.execute(Command.write("ch0.mode", "manual", actor="tester"))
        assert result.accepted
        await bench.engine.run_for(1.0)
        await wait_until(lambda: bench.influx.status().spool.waiting == 0, "drained", LIMIT_S)  # type: ignore[union-attr]
    finally:
        await bench.shutdown()
    text = b"\n".join(server.accepted).decode()
    assert "channel,bench=sim,channel=ch0 " in text
    assert "diagnostics,bench=sim,source=scan " in text
    events = [x for x in text.splitlines() if x.startswith("event,")]
    assert any(",kind=command " in x and 'actor="tester"' in x for x in events), events
    assert bench.alarms["influx.config"].state is AlarmState.NORMAL


def test_without_influxdb_there_is_no_writer(tmp_path: Path) -> None:
    bench = build_bench(bench_from_data(sim_data(tmp_path, None)), VirtualClock(), in_process=True)
    assert bench.influx is None and "influx.sent" not in bench.db


def test_a_missing_token_file_is_a_config_error_naming_file_line_and_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = sim_data(tmp_path, None)
    path = tmp_path / "bench.yaml"
    text = yaml.safe_dump(data, sort_keys=False)
    text += "influxdb:\n  url: http://127.0.0.1:8086\n  bucket: bench/autogen\n"
    text += f"  token_file: {tmp_path / 'no-such-token'}\n"
    path.write_text(text, encoding="utf-8")
    line = text.count("\n")  # the token_file line is the last
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"{path}:{line}:15: influxdb.token_file: token file" in err
    assert "not found" in err


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"token": "secret"}, "unknown key 'token' in influxdb"),
        ({}, "give exactly one of token_file or token_env (never the token itself)"),
    ],
)
def test_the_token_itself_is_not_a_key_and_one_token_source_is_required(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], section: dict[str, str], message: str
) -> None:
    data = sim_data(tmp_path, {"url": "http://h:8086", "bucket": "b/rp", **section})
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    assert main(["check", str(path)]) == 2
    assert message in capsys.readouterr().err


def test_a_token_from_the_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BENCH_INFLUX_TOKEN", " user:password ")
    data = sim_data(
        tmp_path, {"url": "http://h:8086", "bucket": "b/rp", "token_env": "BENCH_INFLUX_TOKEN"}
    )
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    cfg = load_bench(path)
    assert cfg.influxdb is not None and cfg.influxdb.token() == "user:password"
    monkeypatch.delenv("BENCH_INFLUX_TOKEN")
    with pytest.raises(Exception, match="BENCH_INFLUX_TOKEN is not set"):
        load_bench(path)


def test_influx_is_a_namespace_the_supervisor_generates(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = sim_data(tmp_path, None)
    data["tags"] = [{"name": "influx.sent", "device": "chadeche", "point": "b0.voltage"}]
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    assert main(["check", str(path)]) == 2
    assert "tag name 'influx.sent' is in a namespace the supervisor generates" in (
        capsys.readouterr().err
    )


async def test_a_put_wakes_the_spool_writer_only_when_it_waits_for_work(tmp_path: Path) -> None:
    # A wake-up per scan would cost the scan's thread a system call and a turn of the
    # interpreter lock 100 times a second (issue 13): while the writer sleeps out its
    # commit interval, what is put waits for it.
    spool = Spool(tmp_path / "spool.sqlite", 10_000_000)
    writer = SpoolWriter(spool, commit_interval_s=3600.0, chunk_points=100, max_queue_points=10_000)
    writer.start()
    try:
        writer.put("channel", ["channel,bench=b1 v=1 1"])  # idle: woken, committed at once
        await wait_until(lambda: writer.commits == 1, "the first commit", LIMIT_S)
        notified: list[int] = []
        original = writer._cond.notify_all

        def counting() -> None:
            notified.append(1)
            original()

        writer._cond.notify_all = counting  # type: ignore[method-assign]
        for k in range(100):  # a second of 10 ms scans
            writer.put_deferred(1, lambda k=k: {"channel": [f"channel,bench=b1 v={k} {k + 2}"]})
        assert notified == [] and writer.queued == 100
    finally:
        writer.stop()  # wakes it: what was queued is committed at the stop
    assert writer.commits == 2 and spool.counts().produced == 101


def published_at(w: InfluxWriter, db: TagDB, times: list[float]) -> list[float]:
    """The scan times at which ``w`` brought its status tags up to date."""
    calls: list[int] = []
    w._publish_status = lambda _db: calls.append(1)  # type: ignore[method-assign]
    out = []
    for t in times:
        before = len(calls)
        w.on_scan(db, t)
        if len(calls) > before:
            out.append(t)
    return out


def test_on_a_real_clock_the_status_tags_are_brought_up_to_date_ten_times_a_second(
    tmp_path: Path, db: TagDB
) -> None:
    """Diagnostics, not process values: at a 10 ms scan, every tenth scan (on a virtual
    clock, every scan: dry runs and these tests step it)."""
    times = [100.0, 100.01, 100.05, 100.09, 100.1, 100.15]
    url = "http://127.0.0.1:9"
    real = writer_for(tmp_path / "real", url, db, RealClock(), Alarms())  # type: ignore[arg-type]
    virtual = writer_for(tmp_path / "virtual", url, db, VirtualClock(), Alarms())
    try:
        assert published_at(real, db, times) == [100.0, 100.1]
        assert published_at(virtual, db, times) == times
    finally:
        real.close()
        virtual.close()


async def test_a_spool_writer_thread_that_crashes_is_started_again_and_says_why(
    tmp_path: Path,
) -> None:
    # Issue 28: an exception escaping the writer's loop ended it for good, silently.
    class OnceBroken(Spool):  # a fake collaborator: a bug the loop does not expect
        broken = True

        def append(self, *args: Any, **kw: Any) -> tuple[int, int]:
            if self.broken:
                self.broken = False
                raise RuntimeError("injected fault")
            return super().append(*args, **kw)

    spool = OnceBroken(tmp_path / "spool.sqlite", 10_000_000)
    writer = SpoolWriter(spool, commit_interval_s=0.01, chunk_points=100, max_queue_points=10_000)
    writer.start()
    try:
        writer.put("channel", ["channel,bench=b1 v=1 1", "channel,bench=b1 v=2 2"])
        await wait_until(lambda: writer.crashes == 1, "the crash counted", LIMIT_S)
        assert writer.error is not None and "injected fault" in writer.error
        writer.put("channel", ["channel,bench=b1 v=3 3"])
        await wait_until(lambda: writer.commits >= 1, "a commit after the crash", 10 * LIMIT_S)
        assert writer.error is None  # written again
    finally:
        writer.stop()
    counts = spool.counts()
    assert counts.produced == 3 and counts.dropped == 2 and counts.waiting == 1
