"""Our BDF files pass the Battery Data Format's reference reader (``batterydf`` from PyPI,
module ``bdf``; ADR 0025): a dry run and a real run on the simulated bench of the same
recipe, each with its metadata sidecar, and each folder verified."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from bdf.io import load as bdf_load
from bdf.validate import validate_df

from supervisor.app import build_bench
from supervisor.app.dryrun import dry_run
from supervisor.chains.states import State
from supervisor.commands import Command, Verb
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import REGISTRY
from supervisor.publish.provenance import BDF_METADATA_SUFFIX, verify
from supervisor.publish.results import BDF_COLUMNS

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "tests" / "browser" / "short-cycle.yaml"
pytestmark = pytest.mark.integration

NOT_IN_THE_READERS_LIST = {
    # BDF 1.3.0 names these (docs/recipes.md "Recipes", docs/adr/0025); batterydf
    # 0.1.0 reads them as columns it does not interpret ("extras"), which BDF allows.
    "Step ID",
    "Step Type",
    "Step Time / s",
    "Record Index / 1",
    "Cycle Charging Capacity / Ah",
    "Cycle Discharging Capacity / Ah",
    "Temperature T1 / degC",
}


def check_with_the_reference_reader(folder: Path) -> dict[str, Any]:
    (bdf,) = folder.glob("*.bdf.csv")
    df = bdf_load(bdf)
    report = validate_df(df)  # raises BDFValidationError on a missing required column
    assert report["ok"] and report["missing"] == []
    assert report["time_stats"]["monotonic"]
    assert set(report["extras"]) & set(BDF_COLUMNS) == NOT_IN_THE_READERS_LIST
    summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    assert len(df) == summary["records"] > 0
    assert df["Voltage / V"].notna().all() and df["Current / A"].abs().max() > 0.2
    sidecar = bdf.with_name(bdf.name.removesuffix(".bdf.csv") + BDF_METADATA_SUFFIX)
    meta = json.loads(sidecar.read_text(encoding="utf-8"))
    assert meta["identifier"] == summary["test_id"]
    checked = verify(folder)
    assert checked.ok, checked.problems
    return meta


async def test_a_dry_run_and_a_real_run_of_one_recipe_write_bdf_the_reference_reader_accepts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    res = await dry_run(RECIPE, results_dir=tmp_path / "dry")
    assert res.state is State.COMPLETE
    (dry_folder,) = (tmp_path / "dry").iterdir()
    check_with_the_reference_reader(dry_folder)

    monkeypatch.chdir(tmp_path)  # sim.yaml's recipe folder, recipes/, is relative
    (tmp_path / "recipes").mkdir()
    shutil.copyfile(RECIPE, tmp_path / "recipes" / RECIPE.name)
    b = build_bench(
        REGISTRY.load_bench(ROOT / "io_maps" / "sim.yaml"), VirtualClock(), in_process=True
    )
    try:
        await b.start()
        await b.engine.run_for(3.0)
        for verb, args in ((Verb.LOAD, {"recipe": RECIPE.stem}), (Verb.START, {"cell_id": "A1"})):
            r = b.commands.execute(Command.channel("ch1", verb, **args))
            assert r.accepted, r.reason
        for _ in range(120):
            await b.engine.run_for(1.0)
            if b.runners["ch1"].state is State.COMPLETE:
                break
        assert b.runners["ch1"].state is State.COMPLETE
        folder = b.results["ch1"].folder
        assert folder is not None
        meta = check_with_the_reference_reader(folder)
        assert meta["battery"]["identifier"] == "A1"
    finally:
        await b.shutdown()
