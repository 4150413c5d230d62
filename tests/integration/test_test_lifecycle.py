"""Every start is a test of its own (issue 26, finding 1): a second run on a channel —
start, Complete, reset, start — is recorded in a new folder under a new id, and the first
test's files stay as it ended. Virtual clock, one simulated Chadèche channel."""

from __future__ import annotations

import csv
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from supervisor.app import Bench, build_bench
from supervisor.app.dryrun import dry_run_config
from supervisor.chains.states import State
from supervisor.core.clock import VirtualClock

pytestmark = pytest.mark.integration

SHORT = (
    "recipe: short\n"
    "logging: {period: 1 s}\n"
    "steps:\n"
    "  - {id: rest, rest: 3 s}\n"
    "  - {id: charge, charge: 300 mA, duration: 4 s}\n"
)
"""7 s of test: rest then a charge, a record a second."""

_OPEN: list[Bench] = []


@pytest.fixture(autouse=True)
async def _shutdown_benches() -> AsyncIterator[None]:
    yield
    while _OPEN:
        await _OPEN.pop().shutdown()


async def loaded(tmp_path: Path) -> Bench:
    path = tmp_path / "short.yaml"
    path.write_text(SHORT, encoding="utf-8")
    b = build_bench(dry_run_config("nimh-aa", 2.0, 0.5, 1.0), VirtualClock())
    _OPEN.append(b)
    b.load_recipe("ch0", path, results_dir=tmp_path / "results")
    await b.engine.run_for(1.0)
    return b


async def run_to_complete(b: Bench) -> str:
    runner = b.runners["ch0"]
    runner.command("start", actor="alice")
    await b.engine.run_for(10.0)
    assert runner.state is State.COMPLETE
    return runner.test_id


def summary(folder: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    return data


def bdf_rows(folder: Path) -> list[dict[str, str]]:
    (path,) = folder.glob("*.bdf.csv")
    with path.open(encoding="utf-8") as f:
        return list(csv.DictReader(f))


async def test_a_start_after_a_reset_is_a_new_test_with_its_own_complete_files(
    tmp_path: Path,
) -> None:
    b = await loaded(tmp_path)
    first = await run_to_complete(b)
    first_folder = tmp_path / "results" / first
    first_files = {p.name: p.read_bytes() for p in first_folder.iterdir()}
    b.runners["ch0"].command("reset", actor="alice")
    await b.engine.run_for(1.0)
    second = await run_to_complete(b)

    assert second != first  # was the first test's id, its files closed: nothing recorded
    second_folder = tmp_path / "results" / second
    s = summary(second_folder)
    assert (s["test_id"], s["state"], s["complete"]) == (second, "Complete", True)
    rows = bdf_rows(second_folder)
    assert len(rows) == s["records"] >= 7  # a record a second over the 7 s test
    assert float(rows[-1]["Test Time / s"]) == pytest.approx(7.0, abs=1.0)
    # The first test is as it ended.
    assert {p.name: p.read_bytes() for p in first_folder.iterdir()} == first_files
    assert b.db["ch0.chain.test_id"].value == second
    assert b.results["ch0"].test_id == second


async def test_twenty_runs_on_one_channel_are_twenty_complete_tests(tmp_path: Path) -> None:
    b = await loaded(tmp_path)
    ids = []
    for _ in range(20):
        ids.append(await run_to_complete(b))
        b.runners["ch0"].command("reset", actor="alice")
        await b.engine.run_for(0.5)
    assert len(set(ids)) == 20
    for test_id in ids:
        folder = tmp_path / "results" / test_id
        s = summary(folder)
        assert (s["state"], s["complete"]) == ("Complete", True), test_id
        rows = bdf_rows(folder)
        assert len(rows) == s["records"], test_id
        # A record every logging period (1 s) of the 7 s test, none missing.
        assert {float(r["Test Time / s"]) for r in rows} == {float(t) for t in range(8)}


async def test_a_stopped_test_and_the_next_start_each_keep_their_end(tmp_path: Path) -> None:
    b = await loaded(tmp_path)
    runner = b.runners["ch0"]
    runner.command("start", actor="alice")
    await b.engine.run_for(4.0)
    runner.command("stop", actor="bob")
    await b.engine.run_for(1.0)
    first = runner.test_id
    runner.command("reset", actor="bob")
    second = await run_to_complete(b)
    assert summary(tmp_path / "results" / first)["end_reason"] == "stopped: stop by bob"
    assert summary(tmp_path / "results" / second)["state"] == "Complete"
