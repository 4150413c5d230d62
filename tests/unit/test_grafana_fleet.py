"""The fleet dashboard (issue 35, hmi/grafana/dashboards/Fleet/fleet-benches.json): several
benches side by side, chosen in one multi-select variable. Its queries run against a real
InfluxDB in tests/integration/test_grafana_dashboards.py with every bench the run wrote."""

from __future__ import annotations

from grafanarig import DASHBOARDS, load, panels, queries, variables

FLEET = DASHBOARDS / "Fleet" / "fleet-benches.json"


def test_the_bench_variable_chooses_several_benches_from_influxdb() -> None:
    [bench] = variables(load(FLEET))
    assert bench["name"] == "bench"
    assert bench["multi"] is True and bench["includeAll"] is True
    assert 'measurement: "channel", tag: "bench"' in bench["query"]


def test_every_query_takes_every_chosen_bench() -> None:
    # A bench filter written for one bench (r.bench == "${bench}") would match none of
    # several: each query must use the regex form Grafana expands to all of them.
    for q in queries(FLEET):
        if q.where.startswith("variable"):
            continue
        assert "r.bench =~ /^${bench:regex}$/" in q.flux, q.where
        assert 'r.bench == "${bench}"' not in q.flux, q.where


def test_it_shows_channels_v_and_i_active_alarms_and_scan_health() -> None:
    titles = {p["title"] for p in panels(load(FLEET))}
    assert {"Voltage", "Current", "Active alarms", "Scan duration (max)"} <= titles
    assert "Scan overruns (total)" in titles
