"""``supervisor bench fleet`` (issue 35): simulated benches through a real Mosquitto into
the fleet's state code. The short mode runs end to end (its figures are printed and
recorded, never asserted: no timing assertions); the latency it reports is each data
sample's arrival minus its acquisition time, checked here on payloads of the edge node's
own session."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from supervisor.bench import report
from supervisor.bench.fleetsink import MeasuredFleet, percentile_ms
from supervisor.cli.main import main
from supervisor.core.quality import Quality
from supervisor.publish.sparkplug.node import Layout, Metric, Session

T0_MS = 1_767_225_600_000


def _metric(value: float, wall_ms: int) -> Metric:
    return Metric("float", "V", value, Quality.GOOD, wall_ms)


def _born(fleet: MeasuredFleet, session: Session) -> None:
    births = session.births(0, {"ch1.v": _metric(1.0, T0_MS)}, T0_MS)
    for m in births:
        assert fleet.receive(m.topic, m.payload, T0_MS) == []


def test_each_data_sample_counts_its_arrival_minus_its_acquisition_time() -> None:
    fleet = MeasuredFleet("lab")
    session = Session("lab", "bench-000", Layout(("ch1",), ()))
    _born(fleet, session)
    fleet.begin()
    changes = [("ch1.v", _metric(2.0, T0_MS + 1000)), ("ch1.v", _metric(3.0, T0_MS + 1500))]
    [ddata] = session.data(changes, T0_MS + 1500)
    assert fleet.receive(ddata.topic, ddata.payload, T0_MS + 1520) == []
    fleet.end()
    fleet.receive(ddata.topic, ddata.payload, T0_MS + 1600)  # after the window: not counted
    res = fleet.result()
    assert res["latency_ms"] == [(20, 1), (520, 1)]
    assert (res["messages"], res["samples"], res["online"]) == (1, 2, 1)
    assert res["window_s"] >= 0
    assert fleet.nodes["bench-000"].devices["ch1"].metrics["v"] == 3.0  # the fleet's picture


def test_nothing_is_counted_before_the_window_begins() -> None:
    fleet = MeasuredFleet("lab")
    session = Session("lab", "bench-000", Layout(("ch1",), ()))
    _born(fleet, session)
    [ddata] = session.data([("ch1.v", _metric(2.0, T0_MS))], T0_MS)
    fleet.receive(ddata.topic, ddata.payload, T0_MS + 5)
    assert fleet.result()["latency_ms"] == [] and fleet.result()["messages"] == 0


def test_percentiles_of_a_histogram_by_nearest_rank() -> None:
    hist = [(1, 50), (2, 49), (900, 1)]
    assert percentile_ms(hist, 0.50) == 1.0
    assert percentile_ms(hist, 0.99) == 2.0
    assert percentile_ms(hist, 1.0) == 900.0


def test_short_mode_runs_three_benches_through_mosquitto_and_records_the_figures(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results.jsonl"
    monkeypatch.setenv(report.ENV, str(results))
    main(["bench", "fleet", "--benches", "3", "--seconds", "3"])  # its exit: p99 on this machine
    out = capsys.readouterr().out
    assert "3 of 3 benches online" in out, out
    assert "broker CPU" in out and "fleet process CPU" in out and "same run" in out
    names = {json.loads(line)["figure"] for line in results.read_text().splitlines()}
    shape = "fleet 3 benches × 100 tags"
    for what in ("latency p99", "latency p50", "broker CPU", "fleet process CPU"):
        assert f"{shape}: {what}" in names, names
    assert f"{shape}: fleet process RSS" in names and f"{shape}: messages" in names
