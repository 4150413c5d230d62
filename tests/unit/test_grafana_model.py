"""The dashboards in hmi/grafana/dashboards/ follow Grafana's dashboard model, so that the
provisioned Grafana loads every one of them without an error (there is no Grafana binary
here to load them). Their queries are run against a
real InfluxDB in tests/integration/test_grafana_dashboards.py."""

from __future__ import annotations

from itertools import combinations
from pathlib import Path
from typing import Any

import pytest
import yaml
from grafanarig import (
    PROVISIONING,
    dashboard_files,
    datasource_refs,
    load,
    panels,
    provisioned_datasource_uids,
    queries,
    used_variables,
    variables,
)

FILES = dashboard_files()
IDS = [p.name for p in FILES]

# The unit ids the dashboards may use: Grafana's own ids (its value formats). The bench's
# units map onto them (V volt, A amp, degC celsius, Ah amph, Wh watth, W watt, s s).
GRAFANA_UNITS = {
    "volt", "amp", "celsius", "amph", "watth", "watt", "s", "ms", "percentunit", "percent",
    "short", "none", "bytes", "decbytes", "ohm", "wps",
}  # fmt: skip
# What each schema field is measured in: a panel that shows one must say so.
FIELD_UNITS = {
    "voltage": "volt",
    "current": "amp",
    "temperature": "celsius",
    "power": "watt",
    "charged_ah": "amph",
    "discharged_ah": "amph",
    "charged_wh": "watth",
    "discharged_wh": "watth",
    "duration_s": "s",
}


def test_there_are_the_four_dashboards_with_unique_uids() -> None:
    uids = {p.name: load(p)["uid"] for p in FILES}
    assert set(uids) == {
        "bench-overview.json",
        "test-detail.json",
        "diagnostics.json",
        "fleet-benches.json",  # issue 35: several benches at once
    }
    assert len(set(uids.values())) == len(uids), uids
    for name, uid in uids.items():
        # Grafana: at most 40 characters, letters, digits, '-' and '_'.
        assert len(uid) <= 40 and uid.replace("-", "").replace("_", "").isalnum(), name


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_the_dashboard_has_a_title_a_schema_version_and_no_instance_id(path: Path) -> None:
    d = load(path)
    assert d.get("title")
    assert isinstance(d.get("schemaVersion"), int) and d["schemaVersion"] >= 36
    # A provisioned dashboard must not carry the database id of the Grafana it came from.
    assert d.get("id") is None


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_panel_ids_are_unique_within_the_dashboard(path: Path) -> None:
    ids = [p["id"] for p in panels(load(path))]
    assert all(isinstance(i, int) for i in ids)
    assert len(ids) == len(set(ids)), sorted(ids)


def _box(p: dict[str, Any]) -> tuple[int, int, int, int]:
    g = p["gridPos"]
    return g["x"], g["y"], g["w"], g["h"]


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_panels_lie_within_the_24_columns_and_do_not_overlap(path: Path) -> None:
    top = load(path)["panels"]  # collapsed rows' panels have their own positions
    for p in top:
        x, y, w, h = _box(p)
        assert x >= 0 and y >= 0 and w >= 1 and h >= 1, p["title"]
        assert x + w <= 24, f"{p['title']!r} ends at column {x + w}"
    for a, b in combinations(top, 2):
        ax, ay, aw, ah = _box(a)
        bx, by, bw, bh = _box(b)
        apart = ax + aw <= bx or bx + bw <= ax or ay + ah <= by or by + bh <= ay
        assert apart, f"{a['title']!r} and {b['title']!r} overlap"


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_every_data_source_is_the_provisioned_one(path: Path) -> None:
    provisioned = provisioned_datasource_uids()
    refs = list(datasource_refs(load(path)))
    assert refs
    for where, ds in refs:
        assert isinstance(ds, dict), f"{where}: a data source by name, not by uid: {ds!r}"
        assert ds.get("uid") in provisioned, f"{where}: data source {ds!r} not provisioned"
        assert ds.get("type") == "influxdb", where


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_every_variable_a_query_uses_is_defined_before_it(path: Path) -> None:
    defined = [v["name"] for v in variables(load(path))]
    assert len(defined) == len(set(defined))
    for q in queries(path):
        missing = used_variables(q.flux) - set(defined)
        assert not missing, f"{q.where} uses undefined {sorted(missing)}"
    # A variable's query may only use the variables above it (Grafana evaluates in order).
    for i, v in enumerate(variables(load(path))):
        assert used_variables(v["query"]) <= set(defined[:i]), v["name"]


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_every_panel_with_a_query_has_a_flux_query_and_a_valid_unit(path: Path) -> None:
    for p in panels(load(path)):
        if p["type"] == "row":
            continue
        assert p.get("targets"), p["title"]
        assert all(t.get("query", "").strip() and t.get("refId") for t in p["targets"])
        units = [p["fieldConfig"]["defaults"].get("unit")]
        for o in p["fieldConfig"].get("overrides", []):
            units += [prop["value"] for prop in o["properties"] if prop["id"] == "unit"]
        for unit in units:
            assert unit in GRAFANA_UNITS, f"{p['title']!r}: unit {unit!r}"


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_a_panel_of_one_measured_quantity_carries_its_unit(path: Path) -> None:
    for p in panels(load(path)):
        if p["type"] == "row":
            continue
        text = "\n".join(t["query"] for t in p["targets"])
        shown = {f for f in FIELD_UNITS if f'r._field == "{f}"' in text}
        units = {FIELD_UNITS[f] for f in shown}
        if len(units) == 1 and p["type"] in ("timeseries", "barchart"):
            assert p["fieldConfig"]["defaults"]["unit"] in units, p["title"]


def test_the_bench_and_channel_variables_come_from_tag_values() -> None:
    """Queries that work on InfluxDB 1.8 and 2.x (no ``schema`` package on 1.8)."""
    for path in FILES:
        for v in variables(load(path)):
            assert 'import "influxdata/influxdb/v1"' in v["query"], (path.name, v["name"])
            assert "v1.tagValues" in v["query"] or "v1.measurementTagValues" in v["query"]


def test_the_datasource_provisioning_pins_the_uid_and_takes_the_token_from_the_environment() -> (
    None
):
    doc = yaml.safe_load((PROVISIONING / "datasources" / "influxdb.yaml").read_text("utf-8"))
    [ds] = doc["datasources"]
    assert ds["type"] == "influxdb" and ds["uid"] == "bench-influxdb"
    assert ds["jsonData"]["version"] == "Flux"
    assert ds["jsonData"]["organization"] and ds["jsonData"]["defaultBucket"]
    assert ds["secureJsonData"] == {"token": "$INFLUX_TOKEN"}, "never a token in the file"


def test_the_dashboard_provider_reads_the_folders_of_hmi_grafana_dashboards() -> None:
    doc = yaml.safe_load((PROVISIONING / "dashboards" / "bench.yaml").read_text("utf-8"))
    [provider] = doc["providers"]
    assert provider["type"] == "file"
    assert provider["options"]["foldersFromFilesStructure"] is True
    # deploy/compose.yaml mounts hmi/grafana/dashboards there.
    assert provider["options"]["path"] == "/etc/grafana/dashboards"
