"""Nothing a channel does goes unrecorded (issue 26, finding 1 and its "Must show"): 20
start → Complete → reset → start cycles on one channel through the HTTP API and 5 through
OPC UA's channel methods give 25 tests, each in a folder of its own, each complete — a
final summary, a record every logging period of its whole duration. The bench scans on
the virtual clock; the HTTP API and the OPC UA server are real, on loopback."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from hmirig import hmi_bench
from opcuarig import call, opcua_rig, text

from supervisor.cli.main import main

pytestmark = pytest.mark.integration

SHORT = (
    "recipe: short\n"
    "logging: {period: 1 s}\n"
    "steps:\n"
    "  - {id: rest, rest: 1 s}\n"
    "  - {id: charge, charge: 300 mA, duration: 2 s}\n"
)
"""3 s of test at a record a second: records at 0, 1, 2 and 3 s."""
DURATION_S = 3


def assert_complete(folder: Path) -> None:
    """A final summary, the BDF rows it counts, a record every logging period, and
    ``supervisor results verify`` finds the folder complete and unmodified."""
    summary: dict[str, Any] = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    assert (summary["state"], summary["complete"]) == ("Complete", True), folder.name
    assert summary["duration_s"] == pytest.approx(DURATION_S, abs=0.2)
    with (folder / f"{folder.name}.bdf.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == summary["records"], folder.name
    times = {round(float(r["Test Time / s"])) for r in rows}
    assert times == set(range(DURATION_S + 1)), folder.name
    assert main(["results", "verify", str(folder)]) == 0, folder.name


async def test_twenty_runs_through_the_http_api_are_twenty_complete_tests(
    tmp_path: Path,
) -> None:
    path = tmp_path / "short.yaml"
    path.write_text(SHORT, encoding="utf-8")
    async with hmi_bench(tmp_path) as hmi:
        otto = await hmi.login("otto")
        status, body = await hmi.call(otto, "PUT", "/api/channels/ch1/recipe", {"file": str(path)})
        assert status == 200, body
        ids = []
        for _ in range(20):
            status, body = await hmi.call(otto, "POST", "/api/channels/ch1/commands/start", {})
            assert status == 200, body
            ids.append(body["test_id"])
            await hmi.scans(10 * DURATION_S + 5)
            assert hmi.bench.runners["ch1"].state.value == "Complete"
            status, body = await hmi.call(otto, "POST", "/api/channels/ch1/commands/reset", {})
            assert status == 200, body
            await hmi.scans(2)
        results = Path(hmi.bench.cfg.state_dir) / "results"
    assert len(set(ids)) == 20
    assert sorted(p.name for p in results.iterdir()) == sorted(ids)
    for test_id in ids:
        assert_complete(results / test_id)


async def test_five_runs_through_opcua_methods_are_five_complete_tests(tmp_path: Path) -> None:
    path = tmp_path / "short.yaml"
    path.write_text(SHORT, encoding="utf-8")
    async with opcua_rig(tmp_path) as rig, rig.client("alice") as c:
        ns = await rig.ns(c)
        node = ua.NodeId("/Bench/Channels/ch1", ns)

        async def method(name: str, *args: ua.Variant) -> ua.CallMethodResult:
            res = await call(c, node, ua.NodeId(f"/Bench/Channels/ch1/{name}", ns), *args)
            assert res.StatusCode.is_good(), text(res)
            return res

        test_id = c.get_node(ua.NodeId("ch1.chain.test_id", ns))
        ids = []
        for n in range(5):
            recipe = ua.Variant(str(path) if n == 0 else "", ua.VariantType.String)
            await method("Start", recipe, ua.Variant("", ua.VariantType.String))
            await rig.scans(10 * DURATION_S + 5)
            assert rig.bench.runners["ch1"].state.value == "Complete"
            ids.append(await test_id.read_value())
            await method("Reset")
            await rig.scans(2)
        results = Path(rig.bench.cfg.state_dir) / "results"
    assert len(set(ids)) == 5
    for test_id in ids:
        assert_complete(results / test_id)
