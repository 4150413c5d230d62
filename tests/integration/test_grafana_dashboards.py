"""Every Flux query of the Grafana dashboards returns data from a real InfluxDB holding a
simulated run, written by the product's own InfluxDB writer (the bench's ``influxdb:``).

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
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import yaml
from grafanarig import Query, dashboard_files, load, queries, substitute, variables
from influxdb_client import InfluxDBClient
from influxdb_client.rest import ApiException
from influxrig import InfluxServer

from supervisor.app import build_bench
from supervisor.commands import Command, Verb
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.publish.influx.spool import Spool
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


# --- the simulated run ----------------------------------------------------------------
@dataclass
class Run:
    test_id: str
    start: datetime
    stop: datetime
    summary: dict[str, Any]


def _simulate(tmp: Path, server: InfluxServer) -> Run:
    """The run, published by the bench's own InfluxDB writer (``influxdb:``) into
    ``server``, with the historian recording too (its status tags feed the diagnostics
    dashboard). The writer's threads run on real time beside the virtual scan; at shutdown
    it sends everything it spooled (checked: nothing left, nothing refused)."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["hmi"]["login"] = False  # its HTTP clients do not log in
    data["state_dir"] = str(tmp / "state")
    data["recipes"] = {"folders": [str(tmp)]}  # the test's recipe, written below
    token = tmp / "influx.token"
    token.write_text(server.token + "\n", encoding="utf-8")
    data["influxdb"] = {
        "url": server.url,
        "org": server.org,
        "bucket": server.bucket,
        "token_file": str(token),
        "flush_interval_s": 0.2,
        "stop_flush_s": 120.0,  # a bound for a loaded machine: shutdown sends all of it
    }
    data["history"] = {**data.get("history", {}), "enabled": True}
    io_map = tmp / "bench.yaml"
    io_map.write_text(yaml.safe_dump(data), encoding="utf-8")
    recipe = tmp / "short-cycle.yaml"
    recipe.write_text(RECIPE, encoding="utf-8")
    # Recent wall times: the variables list what was written in the last 30 days.
    epoch = float(int(time.time()) - 3600)
    clock = VirtualClock(wall_epoch_s=epoch)
    cfg = load_bench(io_map)

    async def scenario() -> tuple[str, Path, Path]:
        bench = build_bench(cfg, clock, in_process=True)
        assert bench.influx is not None
        bench.record_history()
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
            return test_id, bench.results[TEST_CHANNEL].folder, bench.influx.spool.path
        finally:
            await bench.shutdown()

    test_id, folder, spool_path = asyncio.run(scenario())
    spool = Spool(spool_path, 256 * 1024 * 1024)
    spool.open()
    try:
        counts = spool.counts()
    finally:
        spool.close()
    assert counts.sent > 0 and counts.waiting == 0 and counts.dead == 0, counts
    summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    return Run(
        test_id,
        # The time range starts after the first points, so that the "value in force at
        # the start of the range" parts of the queries are exercised too.
        datetime.fromtimestamp(epoch + 1.0, UTC),
        datetime.fromtimestamp(clock.wall() + 1.0, UTC),
        summary,
    )


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InfluxServer]:
    """One InfluxDB for the module (the queries only read what the run wrote)."""
    s = InfluxServer(tmp_path_factory.mktemp("influxdb"))
    s.start()
    try:
        yield s
    finally:
        s.stop()


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory, server: InfluxServer) -> Run:
    return _simulate(tmp_path_factory.mktemp("run"), server)


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
