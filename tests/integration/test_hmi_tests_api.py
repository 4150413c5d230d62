"""The Tests screen's endpoints against the real aiohttp server on loopback (issue 12): a
test run through the HTTP API on a simulated Chadèche channel (virtual clock) is listed
while it runs and after, with its capacity and efficiency per cycle, and its result files
download as attachments; nothing else under the state directory can be fetched."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from commandrig import recipe, started_bench
from yarl import URL

from supervisor.app import Bench
from supervisor.chains.states import State
from supervisor.hmi import HttpApi
from supervisor.hmi.tests_api import TestsConfig
from supervisor.publish.results import BDF_COLUMNS
from supervisor.testing import run_scans

JSON = {"Content-Type": "application/json"}
"""What every command declares, a body or not (supervisor.hmi.csrf)."""

pytestmark = pytest.mark.integration

TWO_CYCLES = (
    "recipe: two-cycles\ncycles: 2\nsteps:\n"
    "  - {id: c, charge: 300 mA, duration: 60 s}\n"
    "  - {id: d, discharge: 300 mA, duration: 60 s}\n"
)


@dataclass
class Client:
    bench: Bench
    api: HttpApi
    session: aiohttp.ClientSession
    results: Path

    async def call(self, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        kw: dict[str, Any] = {"headers": JSON} if body is None else {"json": body}
        url = URL(self.api.url + path, encoded=True)
        async with self.session.request(method, url, **kw) as resp:
            return resp.status, await resp.json()

    async def download(self, path: str) -> tuple[int, dict[str, str], bytes]:
        url = URL(self.api.url + path, encoded=True)
        async with self.session.get(url) as resp:
            return resp.status, dict(resp.headers), await resp.read()

    async def start(self, tmp_path: Path, text: str = TWO_CYCLES) -> str:
        status, body = await self.call(
            "POST", "/channels/ch0/commands/start", {"recipe": recipe(tmp_path, text)}
        )
        assert status == 200 and body["accepted"] is True, body
        await run_scans(self.bench.engine, 5)
        return self.bench.runners["ch0"].test_id


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[Client]:
    bench = await started_bench(tmp_path)
    results = Path(bench.cfg.state_dir) / "results"
    tests = TestsConfig(results, bench.results, bench.runners)
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, commands=bench.commands, tests=tests)
    await api.start()
    try:
        async with aiohttp.ClientSession() as session:
            yield Client(bench, api, session, results)
    finally:
        await api.stop()
        await bench.shutdown()


async def run_to_the_end(c: Client) -> None:
    runner = c.bench.runners["ch0"]
    for _ in range(20):
        await c.bench.engine.run_for(30.0)
        if runner.state is State.COMPLETE:
            return
    raise AssertionError(f"the test did not complete: {runner.state}")


async def test_no_test_yet_is_an_empty_list(client: Client) -> None:
    assert await client.call("GET", "/tests") == (200, {"tests": []})


async def test_a_running_test_is_listed_with_its_state_from_the_chain(
    client: Client, tmp_path: Path
) -> None:
    test_id = await client.start(tmp_path)
    await client.bench.engine.run_for(90.0)  # past the first step change (a record)
    status, body = await client.call("GET", "/tests")
    assert status == 200
    (test,) = body["tests"]
    assert test["id"] == test_id
    assert (test["channel"], test["recipe"], test["state"]) == ("ch0", "two-cycles", "Running")
    assert test["running"] is True and test["complete"] is False and test["ended"] is None
    assert test["started"] == pytest.approx(client.bench.clock.wall() - 90.0, abs=2.0)
    assert test["duration_s"] == pytest.approx(90.0, abs=2.0)  # now, not at the last record
    kinds = {f["kind"] for f in test["files"]}
    assert {"bdf", "chadeche"} <= kinds
    status, detail = await client.call("GET", f"/tests/{test_id}")
    assert status == 200 and detail["cycles"][0]["cycle"] == 1
    assert detail["cycles"][0]["charge_ah"] > 0


async def test_a_finished_test_has_its_files_and_capacity_and_efficiency_per_cycle(
    client: Client, tmp_path: Path
) -> None:
    test_id = await client.start(tmp_path)
    await run_to_the_end(client)
    status, body = await client.call("GET", "/tests")
    (test,) = body["tests"]
    assert (test["state"], test["running"], test["complete"]) == ("Complete", False, True)
    assert test["end_reason"].startswith("complete after step d of cycle 2")
    assert test["ended"] == pytest.approx(test["started"] + test["duration_s"])
    assert test["duration_s"] == pytest.approx(240.0, abs=2.0)
    files = {f["kind"]: f for f in test["files"]}
    # ADR 0022: the timeline and the cycles have files of their own, every row in them;
    # ADR 0025: the BDF metadata sidecar and the provenance.
    assert sorted(files) == [
        "bdf",
        "bdf-metadata",
        "chadeche",
        "cycles",
        "provenance",
        "summary",
        "timeline",
    ]
    assert files["timeline"]["name"] == f"{test_id}.timeline.jsonl"
    assert files["bdf"]["name"] == f"{test_id}.bdf.csv"
    for f in files.values():
        assert f["bytes"] == (client.results / test_id / f["name"]).stat().st_size > 0

    status, detail = await client.call("GET", f"/tests/{test_id}")
    assert status == 200 and detail["id"] == test_id
    assert [c["cycle"] for c in detail["cycles"]] == [1, 2]
    for c in detail["cycles"]:
        # 300 mA for 60 s each way: 5 mAh in, 5 mAh out.
        assert c["charge_ah"] == pytest.approx(0.005, rel=0.05)
        assert c["discharge_ah"] == pytest.approx(0.005, rel=0.05)
        assert c["efficiency"] == pytest.approx(1.0, abs=0.05)
    starts = [e for e in detail["timeline"] if e["text"].startswith("starting step")]
    assert [(e["cycle"], e["step"]) for e in starts] == [(1, "c"), (1, "d"), (2, "c"), (2, "d")]
    assert [e["t_s"] for e in starts] == sorted(e["t_s"] for e in starts)


async def test_a_result_file_downloads_as_an_attachment(client: Client, tmp_path: Path) -> None:
    test_id = await client.start(tmp_path)
    await run_to_the_end(client)
    name = f"{test_id}.bdf.csv"
    status, headers, data = await client.download(f"/tests/{test_id}/files/{name}")
    assert status == 200
    assert headers["Content-Disposition"] == f'attachment; filename="{name}"'
    assert headers["Content-Type"].startswith("text/csv")
    assert data == (client.results / test_id / name).read_bytes()
    rows = list(csv.reader(io.StringIO(data.decode("utf-8"))))
    assert tuple(rows[0]) == BDF_COLUMNS and len(rows) > 2
    status, headers, data = await client.download(f"/tests/{test_id}/files/summary.json")
    assert status == 200 and headers["Content-Type"].startswith("application/json")
    name = f"{test_id}.timeline.jsonl"
    status, headers, data = await client.download(f"/tests/{test_id}/files/{name}")
    assert status == 200 and headers["Content-Type"].startswith("application/x-ndjson")
    events = [json.loads(line) for line in data.decode("utf-8").splitlines()]
    summary = json.loads((client.results / test_id / "summary.json").read_text("utf-8"))
    assert events == summary["timeline"] and summary["timeline_omitted"] == 0


async def test_unknown_tests_and_files_are_404(client: Client, tmp_path: Path) -> None:
    test_id = await client.start(tmp_path)
    await run_to_the_end(client)
    (client.results / test_id / "summary.json.tmp").write_text("{}", encoding="utf-8")
    assert (await client.call("GET", "/tests/no-such-test"))[0] == 404
    for path in (
        "/tests/no-such-test/files/summary.json",
        f"/tests/{test_id}/files/nothing.csv",
        f"/tests/{test_id}/files/summary.json.tmp",  # a temporary is not a result
    ):
        assert (await client.download(path))[0] == 404, path


@pytest.mark.parametrize(
    "path",
    [
        "/tests/..%2F..%2Fbench.yaml",
        "/tests/%2E%2E/files/bench.yaml",
        "/tests/{id}/files/..%2F..%2F..%2Fbench.yaml",
        "/tests/{id}/files/%2E%2E%2Fstate.sqlite",
        "/tests/..%2Fresults/files/state.sqlite",
    ],
)
async def test_no_path_leaves_the_results_directory(
    client: Client, tmp_path: Path, path: str
) -> None:
    test_id = await client.start(tmp_path)
    await run_to_the_end(client)
    status, _, data = await client.download(path.replace("{id}", test_id))
    assert status in (400, 404), status
    assert b"safety" not in data and b"SQLite" not in data  # nothing of bench.yaml, state


async def test_the_tests_of_a_cell_are_found_by_its_id(client: Client, tmp_path: Path) -> None:
    status, body = await client.call(
        "POST",
        "/channels/ch0/commands/start",
        {"recipe": recipe(tmp_path, TWO_CYCLES), "cell_id": "NIMH 7", "comment": "first"},
    )
    assert status == 200, body
    await run_to_the_end(client)
    first = client.bench.runners["ch0"].test_id
    status, body = await client.call("GET", "/tests?cell=NIMH%207")
    assert status == 200 and [t["id"] for t in body["tests"]] == [first]
    assert body["tests"][0]["metadata"]["comment"] == "first"
    assert await client.call("GET", "/tests?cell=OTHER") == (200, {"tests": []})


async def test_a_bad_cell_query_or_an_unknown_one_is_400(client: Client) -> None:
    status, body = await client.call("GET", "/tests?cell=" + "x" * 65)
    assert status == 400 and "cell is 65 characters long, at most 64" in body["reason"]
    status, body = await client.call("GET", "/tests?channel=ch0")
    assert (status, body["reason"]) == (400, "unknown query channel (expected: cell)")


# --- tests compared (issue 33 finding 10) -------------------------------------------------
async def two_tests_of_one_cell(client: Client, tmp_path: Path, cell: str = "C-1") -> list[str]:
    ids = []
    for comment in ("first", "second"):
        status, body = await client.call(
            "POST",
            "/channels/ch0/commands/start",
            {"recipe": recipe(tmp_path, TWO_CYCLES), "cell_id": cell, "comment": comment},
        )
        assert status == 200 and body["accepted"] is True, body
        await run_scans(client.bench.engine, 5)
        await run_to_the_end(client)
        ids.append(client.bench.runners["ch0"].test_id)
    assert ids[0] != ids[1]
    return ids


async def test_a_tests_cycles_are_voltage_against_charge_per_half(
    client: Client, tmp_path: Path
) -> None:
    first, _ = await two_tests_of_one_cell(client, tmp_path)
    status, body = await client.call("GET", f"/tests/{first}/curves")
    assert status == 200, body
    assert (body["id"], body["cycles"], body["cycles_total"]) == (first, [1, 2], 2)
    halves = [(c["cycle"], c["half"], c["index"]) for c in body["curves"]]
    assert halves == [(1, "charge", 1), (1, "discharge", 1), (2, "charge", 1), (2, "discharge", 1)]
    for c in body["curves"]:
        assert 2 <= len(c["ah"]) == len(c["v"]) <= body["points_max"]
        assert c["ah"] == sorted(c["ah"]) and c["ah"][0] < 0.001  # from the half's start
        # 300 mA for 60 s: 5 mAh each way, as the summary counts it.
        assert c["ah"][-1] == pytest.approx(0.005, rel=0.05)
        assert all(0.5 < v < 2.0 for v in c["v"])  # a NiMH cell's volts
    charge = body["curves"][0]["v"]
    assert charge[-1] > charge[0]  # a charge raises the voltage
    status, body = await client.call("GET", f"/tests/{first}/curves?cycles=2")
    assert status == 200 and {c["cycle"] for c in body["curves"]} == {2}


async def test_a_cells_fade_is_its_discharge_capacity_per_cumulative_cycle(
    client: Client, tmp_path: Path
) -> None:
    first, second = await two_tests_of_one_cell(client, tmp_path)
    status, body = await client.call("GET", "/fade?cell=C-1")
    assert status == 200, body
    assert body["cell"] == "C-1"
    assert [t["id"] for t in body["tests"]] == [first, second]  # oldest first
    a, b = body["tests"]
    assert (a["offset"], a["cycle"], a["cumulative_cycle"]) == (0, [1, 2], [1, 2])
    assert (b["offset"], b["cycle"], b["cumulative_cycle"]) == (2, [1, 2], [3, 4])
    for t in body["tests"]:
        assert t["discharge_ah"] == pytest.approx([0.005, 0.005], rel=0.05)
        assert isinstance(t["started"], float)


async def test_curves_and_fade_refuse_what_they_cannot_answer(
    client: Client, tmp_path: Path
) -> None:
    first, _ = await two_tests_of_one_cell(client, tmp_path)
    status, body = await client.call("GET", "/tests/no-such-test/curves")
    assert (status, body["reason"]) == (404, "no test 'no-such-test'")
    status, body = await client.call("GET", "/fade?cell=OTHER")
    assert status == 404 and "no finished or running test of cell 'OTHER'" in body["reason"]
    for query, words in (
        ("cycles=abc", "'abc' is not a cycle number"),
        ("cycles=0", "'0' is not a cycle number"),
        ("cycles=" + ",".join(str(n) for n in range(1, 30)), "at most 24 cycles"),
        ("cycle=1", "unknown query cycle"),
    ):
        status, body = await client.call("GET", f"/tests/{first}/curves?{query}")
        assert status == 400 and words in body["reason"], (query, body)
    for query in ("", "?cell=", "?cell=" + "x" * 65, "?cell=C-1&channel=ch0"):
        assert (await client.call("GET", f"/fade{query}"))[0] == 400, query
    # A BDF file gone (or a link out of the results): 404 with the reason, nothing read.
    bdf = client.results / first / f"{first}.bdf.csv"
    outside = tmp_path / "elsewhere.bdf.csv"
    outside.write_bytes(bdf.read_bytes())
    bdf.unlink()
    status, body = await client.call("GET", f"/tests/{first}/curves")
    assert (status, body["reason"]) == (404, f"test {first!r} has no BDF file")
    bdf.symlink_to(outside)
    status, body = await client.call("GET", f"/tests/{first}/curves")
    assert (status, body["reason"]) == (404, f"test {first!r} has no BDF file")


async def test_no_curve_comes_from_outside_the_results_directory(
    client: Client, tmp_path: Path
) -> None:
    test_id = await client.start(tmp_path)
    await run_to_the_end(client)
    assert (await client.call("GET", f"/tests/{test_id}/curves"))[0] == 200
    for path in ("/tests/..%2F..%2Fstate/curves", "/tests/%2E%2E/curves", "/tests/.hidden/curves"):
        status, body = await client.call("GET", path)
        assert status in (400, 404), (path, status)
        assert "curves" not in body and "cycle" not in str(body), body
