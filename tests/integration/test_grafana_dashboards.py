"""Every Flux query of the Grafana dashboards returns data from a real InfluxDB holding a
simulated run, written in the schema the InfluxDB writer follows.

The run: the simulated bench of ``io_maps/sim.yaml`` on a virtual clock (every device in
process), two charge/discharge cycles of a short recipe on ``ch4`` (the seed 002 bench:
EA supply, ADAM, BMS), started by an operator through the command path, then the e-stop
pressed. Every query of every dashboard (panels, annotations, template variables) runs
with Grafana's macros substituted (``grafanarig.substitute``) and the variables given the
values their own queries return; a query that returns nothing fails, naming the
dashboard and the panel.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import yaml
from grafanarig import Query, dashboard_files, load, queries, substitute, variables
from influxdb_client import InfluxDBClient
from influxdb_client.client.write_api import SYNCHRONOUS
from influxdb_client.rest import ApiException
from influxrig import InfluxServer

from supervisor.app import build_bench
from supervisor.app.events import EventFeed
from supervisor.commands import Command, Verb
from supervisor.core.clock import VirtualClock
from supervisor.core.driver import Value
from supervisor.core.quality import Quality
from supervisor.core.records import BenchEvent
from supervisor.devices.registry import load_bench
from supervisor.publish.changes import ChangeFeed
from supervisor.tags import TagDB, TagSpec
from supervisor.testing import run_scans

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration

BENCH = "sim"
TEST_CHANNEL = "ch4"
CYCLES = 2
RECIPE = f"""recipe: short-cycle
chemistry: liion
capacity: 10 Ah
cycles: {CYCLES}
steps:
  - {{id: charge, charge: 2 A, duration: 20 s}}
  - {{id: rest1, rest: 5 s}}
  - {{id: discharge, discharge: 2 A, duration: 20 s}}
  - {{id: rest2, rest: 5 s}}
"""
RUN_S = 2 * 50.0 + 10.0  # the two cycles and a margin
WINDOW_S = 1


# --- stand-in for the InfluxDB writer -------------------------------------------------
# Replace by the writer (supervisor/publish/influx/) once merged: it follows the same
# schema (brief: measurements channel/device/diagnostics/event, tag keys bench, channel,
# device, source, kind, test_id, recipe; analog values as floats; BAD → no field).
DIAGNOSTIC_PREFIXES = ("scan", "influx", "historian")
WRITER_TAGS = {  # the writer's and historian's status tags the diagnostics dashboard reads
    "influx.spool_depth": 0.0,
    "influx.spool_bytes": 0.0,
    "influx.drain_rate": 0.0,
    "influx.dead_letters": 0.0,
    "influx.dropped": 0.0,
    "influx.failed_writes": 0.0,
    "influx.timeouts": 0.0,
    "influx.last_error": "",
    "historian.queue": 0.0,
    "historian.last_error": "",
}


def _tag_value(v: str) -> str:
    return v.replace("\\", "\\\\").replace(",", "\\,").replace("=", "\\=").replace(" ", "\\ ")


def _field_value(v: Value) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(float(v))  # analog values always float: an int would fix the field type
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'


def _line(measurement: str, tags: dict[str, str], fields: dict[str, str], wall: float) -> str:
    keys = ",".join(f"{k}={_tag_value(v)}" for k, v in tags.items() if v)
    values = ",".join(f"{k}={v}" for k, v in fields.items())
    return f"{measurement},{keys} {values} {round(wall * 1e9)}"


@dataclass
class StandInWriter:
    """Publisher and event sink: the change feed and the bench events as line protocol."""

    bench: str
    channels: list[str]
    clock: VirtualClock
    name: str = "influx-stand-in"
    lines: list[str] = field(default_factory=list)
    _feed: ChangeFeed | None = None
    _tests: dict[str, tuple[str, str]] = field(default_factory=dict)
    _event_ns: set[tuple[str, int]] = field(default_factory=set)
    _pending: int = 0

    def on_scan(self, db: TagDB, t: float) -> None:
        if self._feed is None:
            self._feed = ChangeFeed(db, self.clock)
        grouped: dict[tuple[str, tuple[tuple[str, str], ...], float], dict[str, str]] = {}
        for s in self._feed.take():
            if s.value is None:  # BAD: no field, a gap
                continue
            measurement, tags, name = self._place(db, s.name)
            key = (measurement, tuple(tags.items()), s.wall)
            grouped.setdefault(key, {})[name] = _field_value(s.value)
        # A channel's first point of a new test carries every field of the channel (its
        # counters' baseline and its cycle), so that a test's series start complete.
        for ch in self.channels:
            test = self._test_of(db, ch)
            if self._tests.get(ch) != test:
                self._tests[ch] = test
                tags = self._channel_tags(db, ch)
                fields = {
                    tag.name[len(ch) + 1 :].replace(".", "_"): _field_value(tag.value)
                    for tag in db
                    if tag.name.startswith(ch + ".")
                    and tag.quality is not Quality.BAD
                    and tag.value is not None  # e.g. no ETA yet
                }
                key = ("channel", tuple(tags.items()), self.clock.wall())
                grouped[key] = {**fields, **grouped.get(key, {})}
        for (measurement, tags_items, wall), fields in grouped.items():
            self.lines.append(_line(measurement, dict(tags_items), fields, wall))
        self._status(db, len(grouped))

    def on_event(self, e: BenchEvent) -> None:
        tags = {
            "bench": self.bench,
            "kind": e.kind,
            "channel": e.channel,
            "test_id": e.test_id,
            "recipe": e.recipe,
        }
        ns = round(e.wall * 1e9)
        series = ",".join(f"{k}={v}" for k, v in tags.items() if v)
        while (series, ns) in self._event_ns:  # same series and time would overwrite
            ns += 1
        self._event_ns.add((series, ns))
        fields = {
            "text": _field_value(e.text),
            "source": _field_value(e.source),
            "actor": _field_value(e.actor),
            "severity": _field_value(float(e.severity)),
        }
        self.lines.append(_line("event", tags, fields, ns / 1e9))

    def _place(self, db: TagDB, name: str) -> tuple[str, dict[str, str], str]:
        head, _, rest = name.partition(".")
        fieldname = (rest or "value").replace(".", "_")
        if head in self.channels:
            return "channel", self._channel_tags(db, head), fieldname
        if head in DIAGNOSTIC_PREFIXES:
            return "diagnostics", {"bench": self.bench, "source": head}, fieldname
        return "device", {"bench": self.bench, "device": head}, fieldname

    def _channel_tags(self, db: TagDB, ch: str) -> dict[str, str]:
        test_id, recipe = self._test_of(db, ch)
        return {"bench": self.bench, "channel": ch, "test_id": test_id, "recipe": recipe}

    @staticmethod
    def _test_of(db: TagDB, ch: str) -> tuple[str, str]:
        return str(db[f"{ch}.chain.test_id"].value or ""), str(db[f"{ch}.chain.recipe"].value or "")

    def _status(self, db: TagDB, lines: int) -> None:
        """The writer's status tags as a spool flushed every second would show them."""
        self._pending += lines
        flushed = round(self.clock.now() * 10) % 10 == 0
        db.update(db["influx.spool_depth"], float(self._pending))
        db.update(db["influx.spool_bytes"], float(self._pending * 120))
        if flushed:
            db.update(db["influx.drain_rate"], float(self._pending))
            self._pending = 0


# --- the simulated run ----------------------------------------------------------------
@dataclass
class Run:
    lines: list[str]
    test_id: str
    start: datetime
    stop: datetime
    summary: dict[str, Any]


def _simulate(tmp: Path) -> Run:
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["state_dir"] = str(tmp / "state")
    io_map = tmp / "bench.yaml"
    io_map.write_text(yaml.safe_dump(data), encoding="utf-8")
    recipe = tmp / "short-cycle.yaml"
    recipe.write_text(RECIPE, encoding="utf-8")
    # Recent wall times: the variables list what was written in the last 30 days.
    epoch = float(int(time.time()) - 3600)
    clock = VirtualClock(wall_epoch_s=epoch)
    cfg = load_bench(io_map)
    writer = StandInWriter(BENCH, [c.name for c in cfg.channels], clock)

    async def scenario() -> tuple[str, Path]:
        bench = build_bench(cfg, clock, [writer], in_process=True)
        for name, initial in WRITER_TAGS.items():
            dtype = "str" if isinstance(initial, str) else "float"
            bench.db.add(TagSpec(name, dtype=dtype, initial=initial))
        feed = EventFeed()
        feed.sinks.append(writer)
        feed.attach(bench)
        try:
            await bench.start()
            await run_scans(bench.engine, 30)
            start = Command.channel(TEST_CHANNEL, Verb.START, "alice", recipe=str(recipe))
            result = bench.commands.execute(start)
            assert result.accepted, result.reason
            test_id = bench.runners[TEST_CHANNEL].test_id
            await run_scans(bench.engine, round(RUN_S / bench.engine.period_s))
            assert bench.runners[TEST_CHANNEL].state.value == "Complete"
            assert bench.sim is not None
            bench.sim.press_estop(True)  # an alarm for the annotations
            await run_scans(bench.engine, 20)
            return test_id, bench.results[TEST_CHANNEL].folder
        finally:
            await bench.shutdown()

    test_id, folder = asyncio.run(scenario())
    summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    return Run(
        writer.lines,
        test_id,
        # The time range starts after the first points, so that the "value in force at
        # the start of the range" parts of the queries are exercised too.
        datetime.fromtimestamp(epoch + 1.0, UTC),
        datetime.fromtimestamp(clock.wall() + 1.0, UTC),
        summary,
    )


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    return _simulate(tmp_path_factory.mktemp("run"))


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, run: Run) -> Iterator[InfluxServer]:
    """One InfluxDB for the module, holding the run (the queries only read)."""
    s = InfluxServer(tmp_path_factory.mktemp("influxdb"))
    s.start()
    try:
        with InfluxDBClient(url=s.url, token=s.token, org=s.org) as client:
            write = client.write_api(write_options=SYNCHRONOUS)
            for i in range(0, len(run.lines), 5000):
                write.write(bucket=s.bucket, record=run.lines[i : i + 5000])
        yield s
    finally:
        s.stop()


def _rows(server: InfluxServer, flux: str) -> list[dict[str, Any]]:
    with InfluxDBClient(url=server.url, token=server.token, org=server.org, timeout=60_000) as c:
        tables = c.query_api().query(flux)
    return [r.values for t in tables for r in t.records]


def _run_query(server: InfluxServer, q: Query, text: str) -> list[dict[str, Any]]:
    try:
        return _rows(server, text)
    except ApiException as exc:
        pytest.fail(f"{q.dashboard}: {q.where}: InfluxDB refused the query: {exc.body}\n{text}")


@pytest.fixture(scope="module")
def values(server: InfluxServer, run: Run) -> dict[str, dict[str, list[str]]]:
    """Per dashboard, each template variable's values as its own query returns them (in
    the order Grafana evaluates them), the single ones set to the run's bench, channel and
    test."""
    chosen = {"bench": BENCH, "channel": TEST_CHANNEL, "test": run.test_id}
    out: dict[str, dict[str, list[str]]] = {}
    for path in dashboard_files():
        vals: dict[str, list[str]] = {}
        for v in variables(load(path)):
            q = Query(path.name, f"variable {v['name']!r}", v["query"])
            text = _substituted(q, run, vals)
            found = [str(r["_value"]) for r in _run_query(server, q, text)]
            if v.get("multi"):
                vals[v["name"]] = found
            else:
                want = chosen[v["name"]]
                assert want in found, f"{path.name}: variable {v['name']!r}: {want} not in {found}"
                vals[v["name"]] = [want]
        out[path.name] = vals
    return out


def _substituted(q: Query, run: Run, vals: dict[str, list[str]]) -> str:
    return substitute(
        q.flux,
        start=run.start,
        stop=run.stop,
        window_s=WINDOW_S,
        bucket="bench/autogen",
        values=vals,
    )


ALL_QUERIES = [q for path in dashboard_files() for q in queries(path)]


@pytest.mark.parametrize("q", ALL_QUERIES, ids=[f"{q.dashboard}:{q.where}" for q in ALL_QUERIES])
def test_every_query_returns_data(
    q: Query, server: InfluxServer, run: Run, values: dict[str, dict[str, list[str]]]
) -> None:
    text = _substituted(q, run, values[q.dashboard])
    rows = _run_query(server, q, text)
    assert rows, f"{q.dashboard}: {q.where} returned no data\n{text}"


def test_the_variables_list_the_bench_its_channels_and_the_test(
    values: dict[str, dict[str, list[str]]], run: Run
) -> None:
    overview = values["bench-overview.json"]
    assert overview["bench"] == [BENCH]
    assert set(overview["channel"]) == {"ch0", "ch1", "ch2", "ch3", "ch4"}
    assert values["test-detail.json"]["test"] == [run.test_id]


def _panel_rows(server: InfluxServer, run: Run, values: Any, title: str) -> list[dict[str, Any]]:
    [q] = [q for q in ALL_QUERIES if q.dashboard == "test-detail.json" and f"{title!r}" in q.where]
    return _run_query(server, q, _substituted(q, run, values["test-detail.json"]))


def test_capacity_energy_and_efficiency_per_cycle_agree_with_the_test_summary(
    server: InfluxServer, run: Run, values: dict[str, dict[str, list[str]]]
) -> None:
    cycles = {c["cycle"]: c for c in run.summary["cycles"]}
    assert sorted(cycles) == list(range(1, CYCLES + 1))
    capacity = _panel_rows(server, run, values, "Capacity per cycle")
    energy = _panel_rows(server, run, values, "Energy per cycle")
    efficiency = _panel_rows(server, run, values, "Efficiencies per cycle")
    assert [r["cycle"] for r in capacity] == [str(n) for n in sorted(cycles)]
    # One stored sample (one 100 ms scan at 2 A) is the resolution at a cycle boundary.
    sample_ah = 2.0 * 0.1 / 3600
    for r, e, eff in zip(capacity, energy, efficiency, strict=True):
        c = cycles[int(r["cycle"])]
        assert math.isclose(r["charged_ah"], c["charge_capacity_ah"], abs_tol=2 * sample_ah)
        assert math.isclose(r["discharged_ah"], c["discharge_capacity_ah"], abs_tol=2 * sample_ah)
        assert math.isclose(e["charged_wh"], c["charge_energy_wh"], rel_tol=0.02)
        assert math.isclose(e["discharged_wh"], c["discharge_energy_wh"], rel_tol=0.02)
        assert math.isclose(eff["coulombic"], c["coulombic_efficiency"], rel_tol=0.02)
        assert math.isclose(eff["energy"], c["energy_efficiency"], rel_tol=0.02)
