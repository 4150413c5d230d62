"""Every result folder says which cell, recipe, I/O map and software produced it, and
``supervisor results verify`` tells a complete, unmodified folder from one that is not
(issue 26: test metadata, provenance). The simulated bench of ``io_maps/sim.yaml`` on the
virtual clock, its devices in process; commands through the bench's command path (what
HTTP, the screens, OPC UA and ``ctl`` call)."""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from supervisor.app import Bench, build_bench
from supervisor.chains.states import State
from supervisor.cli.main import main
from supervisor.commands import Command, Verb
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import REGISTRY
from supervisor.publish.provenance import PROVENANCE_NAME, verify

ROOT = Path(__file__).resolve().parents[2]
SIM_MAP = ROOT / "io_maps" / "sim.yaml"
SHORT_CYCLE = ROOT / "tests" / "browser" / "short-cycle.yaml"
RECIPE = Path("recipes") / SHORT_CYCLE.name
"""As the bench finds it: in sim.yaml's recipe folder (``recipes/``, relative to the working
directory: each test's own, where ``sim_bench`` puts a copy)."""
pytestmark = pytest.mark.integration

_OPEN: list[Bench] = []


@pytest.fixture(autouse=True)
async def _shutdown_benches() -> AsyncIterator[None]:
    yield
    while _OPEN:
        await _OPEN.pop().shutdown()


async def sim_bench(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Bench:
    monkeypatch.chdir(tmp_path)  # the I/O map's state_dir and recipe folder are relative
    RECIPE.parent.mkdir(exist_ok=True)
    shutil.copyfile(SHORT_CYCLE, RECIPE)
    b = build_bench(REGISTRY.load_bench(SIM_MAP), VirtualClock(), in_process=True)
    _OPEN.append(b)
    await b.start()
    await b.engine.run_for(3.0)
    return b


def ok(b: Bench, channel: str, verb: Verb, actor: str = "operator", **args: Any) -> str:
    r = b.commands.execute(Command.channel(channel, verb, actor, **args))
    assert r.accepted, r.reason
    return str(r.data.get("test_id", ""))


async def run_to_end(b: Bench, channel: str) -> None:
    for _ in range(120):
        await b.engine.run_for(1.0)
        if b.runners[channel].state is State.COMPLETE:
            return
    raise AssertionError(f"{channel}: {b.runners[channel].state} after 120 s")


def folder_of(b: Bench, channel: str) -> Path:
    folder = b.results[channel].folder
    assert folder is not None
    return folder


async def test_a_test_records_its_cell_comment_and_operator_in_its_summary_and_bdf_sidecar(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    b = await sim_bench(tmp_path, monkeypatch)
    ok(b, "ch1", Verb.LOAD, recipe=str(RECIPE), cell_id="NIMH-0042", nominal_capacity="2000 mAh")
    test_id = ok(b, "ch1", Verb.START, "hmi:alice", chemistry="nimh", comment="after storage")
    await run_to_end(b, "ch1")
    folder = folder_of(b, "ch1")
    summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    assert summary["metadata"] == {
        "cell_id": "NIMH-0042",
        "chemistry": "nimh",
        "nominal_capacity_ah": 2.0,
        "operator": "hmi:alice",
        "comment": "after storage",
    }
    assert summary["started_utc"].endswith("Z") and summary["ended_utc"].endswith("Z")
    assert b.db["ch1.chain.cell_id"].value == "NIMH-0042"  # historian, InfluxDB, OPC UA
    sidecar = json.loads((folder / f"{test_id}.bdf.metadata.json").read_text(encoding="utf-8"))
    assert sidecar["battery"]["identifier"] == "NIMH-0042"
    assert (sidecar["creator"], sidecar["description"]) == ("hmi:alice", "after storage")


async def test_provenance_names_the_recipe_text_parameters_io_map_and_software(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    b = await sim_bench(tmp_path, monkeypatch)
    ok(b, "ch1", Verb.LOAD, recipe=str(RECIPE), parameters={})
    ok(b, "ch1", Verb.START)
    await run_to_end(b, "ch1")
    prov = json.loads((folder_of(b, "ch1") / PROVENANCE_NAME).read_text(encoding="utf-8"))
    text = RECIPE.read_text(encoding="utf-8")
    assert prov["recipe"]["text"] == text
    assert prov["recipe"]["sha256"] == hashlib.sha256(text.encode()).hexdigest()
    assert prov["recipe"]["file"] == str(RECIPE)
    assert prov["io_map"]["file"] == str(SIM_MAP)
    assert prov["io_map"]["sha256"] == hashlib.sha256(SIM_MAP.read_bytes()).hexdigest()
    section = prov["io_map"]["channel"]
    assert section["channel"]["name"] == "ch1" and "limits" in section["channel"]
    assert section["source_device"]  # its calibration, where the device has one
    assert prov["software"]["name"] == "bench-supervisor" and prov["software"]["version"]
    assert (prov["bench"], prov["channel"], prov["host"]) != ("", "", "")
    assert prov["started_utc"].endswith("Z")


async def test_a_finished_folder_verifies_and_a_modified_or_missing_file_does_not(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    b = await sim_bench(tmp_path, monkeypatch)
    ok(b, "ch1", Verb.LOAD, recipe=str(RECIPE))
    test_id = ok(b, "ch1", Verb.START)
    await run_to_end(b, "ch1")
    folder = folder_of(b, "ch1")
    checked = verify(folder)
    assert checked.ok, checked.problems
    summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    assert set(summary["manifest"]) >= {
        f"{test_id}.bdf.csv",
        f"{test_id}.chadeche.csv",
        f"{test_id}.timeline.jsonl",
        f"{test_id}.cycles.jsonl",
        PROVENANCE_NAME,
    }
    bdf = folder / f"{test_id}.bdf.csv"
    bdf.write_text(bdf.read_text(encoding="utf-8").replace(",", ";", 1), encoding="utf-8")
    assert any("bdf.csv: modified" in p for p in verify(folder).problems)
    (folder / f"{test_id}.cycles.jsonl").unlink()
    problems = verify(folder).problems
    assert any("cycles.jsonl: listed in the manifest, missing" in p for p in problems)


async def test_a_folder_whose_recipe_text_was_edited_or_whose_test_is_under_way_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    b = await sim_bench(tmp_path, monkeypatch)
    ok(b, "ch1", Verb.LOAD, recipe=str(RECIPE))
    ok(b, "ch1", Verb.START)
    await b.engine.run_for(4.0)
    folder = folder_of(b, "ch1")
    assert any("not final" in p for p in verify(folder).problems)
    await run_to_end(b, "ch1")
    prov_path = folder / PROVENANCE_NAME
    prov = json.loads(prov_path.read_text(encoding="utf-8"))
    prov["recipe"]["text"] = prov["recipe"]["text"].replace("300 mA", "3 A")
    prov_path.write_text(json.dumps(prov), encoding="utf-8")
    problems = verify(folder).problems
    assert any("recipe text does not match" in p for p in problems)


async def test_a_start_with_a_cell_under_test_on_another_channel_is_refused_naming_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    b = await sim_bench(tmp_path, monkeypatch)
    ok(b, "ch1", Verb.LOAD, recipe=str(RECIPE), cell_id="C-7")
    test_id = ok(b, "ch1", Verb.START)
    ok(b, "ch0", Verb.LOAD, recipe=str(RECIPE))
    r = b.commands.execute(Command.channel("ch0", Verb.START, cell_id="C-7"))
    assert (r.accepted, r.http_status) == (False, 409)
    assert r.reason == (
        f"ch0: cell 'C-7' is under test on ch1 (test {test_id}); end that test first or give"
        " another cell_id"
    )
    assert b.runners["ch0"].state is State.IDLE
    assert b.test_metadata["ch0"].cell_id == ""  # the refused start left nothing behind
    ok(b, "ch0", Verb.START, cell_id="C-8")  # another cell starts


@pytest.mark.parametrize(
    ("args", "field", "received"),
    [
        ({"cell_id": "a" * 65}, "cell_id", "65 characters long, at most 64"),
        ({"cell_id": "A\nB"}, "cell_id", "'A\\nB' has '\\n'"),
        ({"cell_id": 42}, "cell_id", "must be a text, not 42"),
        ({"comment": "x" * 501}, "comment", "501 characters long, at most 500"),
        ({"comment": "bell\x07"}, "comment", "control character '\\x07'"),
        ({"nominal_capacity": "2 V"}, "nominal_capacity", "not '2 V'"),
        ({"nominal_capacity": -1}, "nominal_capacity", "not -1"),
        ({"cell_": "x"}, "unknown argument cell_", "expected: recipe"),
    ],
)
async def test_bad_metadata_is_refused_with_the_field_and_what_was_received(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    args: dict[str, Any],
    field: str,
    received: str,
) -> None:
    b = await sim_bench(tmp_path, monkeypatch)
    for verb in (Verb.LOAD, Verb.START):
        r = b.commands.execute(Command.channel("ch1", verb, recipe=str(RECIPE), **args))
        assert (r.accepted, r.http_status) == (False, 400)
        assert field in r.reason and received in r.reason, r.reason
    assert b.runners["ch1"].state is State.IDLE


async def test_a_resumed_test_keeps_its_metadata_and_its_provenance_as_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    b = await sim_bench(tmp_path, monkeypatch)
    ok(b, "ch1", Verb.LOAD, recipe=str(RECIPE), cell_id="R-1")
    ok(b, "ch1", Verb.START, "hmi:bob")
    await b.engine.run_for(4.0)
    folder = folder_of(b, "ch1")
    prov_before = (folder / PROVENANCE_NAME).read_bytes()
    c = b.results["ch1"]
    c.close("supervisor stopped", "Running", complete=False)
    again = b.new_collector("ch1", "browser-short-cycle", c.test_id, folder)
    again.resume(b.clock.now() - 4.0)
    assert again.metadata.cell_id == "R-1" and again.metadata.operator == "hmi:bob"
    assert len(again.restarts) == 1
    again.close("done", "Complete")
    assert (folder / PROVENANCE_NAME).read_bytes() == prov_before


async def test_results_verify_exits_0_when_verified_1_when_not_and_2_on_a_bad_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    b = await sim_bench(tmp_path, monkeypatch)
    ok(b, "ch1", Verb.LOAD, recipe=str(RECIPE))
    test_id = ok(b, "ch1", Verb.START)
    await run_to_end(b, "ch1")
    folder = folder_of(b, "ch1")
    assert main(["results", "verify", str(folder)]) == 0
    assert "OK, complete and unmodified" in capsys.readouterr().out
    with (folder / f"{test_id}.chadeche.csv").open("a", encoding="utf-8") as f:
        f.write("C;01;01;0;300; 1; 1; 1; 0;1.300;0.0;Mon May 22 03:21:43 2017\n")
    assert main(["results", "verify", str(folder)]) == 1
    out = capsys.readouterr().out
    assert "NOT verified" in out and f"{test_id}.chadeche.csv: modified" in out
    assert main(["results", "verify", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert err == f"supervisor results verify: {tmp_path / 'nowhere'}: not a folder\n"
    assert main(["results", "verify", str(tmp_path)]) == 2
    assert "not a test" in capsys.readouterr().err
