"""A channel's result file carries every measurement its I/O map gives it (issue 26,
finding 7; seed 002 §2.3 "Save Data"): BDF's columns, then one auxiliary column per tag of
the channel's ``record:`` list, each headed "Name / unit", with the tag's value read in
the scan of the record's V and I."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import pytest

from supervisor.app import build_bench
from supervisor.config.bench import record_columns
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigErrors
from supervisor.devices.registry import bench_from_data, load_bench
from supervisor.publish.results import BDF_COLUMNS

ROOT = Path(__file__).resolve().parents[2]
EPOCH = 1_767_254_400.0
RECIPE = (
    "recipe: aux\n"
    "logging: {period: 1 s}\n"
    "steps:\n"
    "  - {id: charge, charge: 300 mA, duration: 5 s}\n"
    "  - {id: rest, rest: 3 s}\n"
)


def bench_data(record: list[Any] | None) -> dict[str, Any]:
    ch: dict[str, Any] = {
        "name": "ch0",
        "source": {"device": "chadeche", "board": 0},
        "capacity_ah": 2.0,
        "limits": {"current_a": [-0.4, 0.4], "voltage_v": [0.2, 2.0]},
    }
    if record is not None:
        ch["record"] = record
    return {
        "bench": "aux",
        "scan": {"period_s": 0.1},
        "devices": {
            "chadeche": {
                "driver": "chadeche",
                "poll_period_s": 0.1,
                "boards": [{"address": 0, "sim": {"model": "nimh-aa", "capacity_ah": 2.0}}],
            }
        },
        # The board's own readings published once more as tags: recorded, they must show
        # the values of the BDF columns of the same row (the same scan).
        "tags": [
            {"name": "cell.v", "device": "chadeche", "point": "b0.voltage", "unit": "V"},
            {"name": "cell.charging", "device": "chadeche", "point": "b0.charging"},
        ],
        "channels": [ch],
    }


async def run_recipe(tmp_path: Path, record: list[Any] | None) -> list[list[str]]:
    b = build_bench(bench_from_data(bench_data(record)), VirtualClock(wall_epoch_s=EPOCH))
    try:
        recipe = tmp_path / "aux.yaml"
        recipe.write_text(RECIPE, encoding="utf-8")
        runner = b.load_recipe("ch0", recipe, results_dir=tmp_path, test_id="t1")
        await b.engine.run_for(1.0)
        runner.command("start")
        await b.engine.run_for(12.0)
        assert runner.state.value == "Complete"
    finally:
        await b.shutdown()
    with (tmp_path / "t1" / "t1.bdf.csv").open(encoding="utf-8", newline="") as f:
        return list(csv.reader(f))


async def test_the_recorded_tags_follow_the_bdf_columns_with_their_values_at_the_record(
    tmp_path: Path,
) -> None:
    rows = await run_recipe(
        tmp_path,
        ["cell.v", {"tag": "cell.charging", "label": "Charging / 1"}, "ch0.fault"],
    )
    header, data = rows[0], rows[1:]
    assert tuple(header) == (*BDF_COLUMNS, "cell.v / V", "Charging / 1", "Fault")
    assert len(data) >= 8
    n = len(BDF_COLUMNS)
    volts = header.index("Voltage / V")
    for row in data:
        assert len(row) == n + 3
        assert row[n] == row[volts]  # the same reading, the same scan
        assert row[n + 2] == ""  # no trip
    charging = [row[n + 1] for row in data]
    assert "1" in charging and set(charging) <= {"0", "1"}  # a boolean as 1 or 0
    assert len({row[volts] for row in data}) > 1  # the voltage moved: not a constant


async def test_a_channel_with_nothing_more_to_record_keeps_the_bdf_columns(
    tmp_path: Path,
) -> None:
    rows = await run_recipe(tmp_path, [])
    assert tuple(rows[0]) == BDF_COLUMNS
    assert all(len(r) == len(BDF_COLUMNS) for r in rows)


def test_the_ea_channel_of_the_simulated_bench_records_the_pack_and_its_bms() -> None:
    cfg = load_bench(ROOT / "io_maps" / "sim.yaml")
    ch4 = next(c for c in cfg.channels if c.name == "ch4")
    labels = [c.label for c in record_columns(cfg, ch4)]
    for want in (
        "ea.voltage / V",
        "bms.voltage / V",
        "pack.current / A",
        "bms.cell_min / V",
        "bms.cell_max / V",
        "bms.temp_min / degC",
        "bms.temp_max / degC",
        "Fault",
    ):
        assert want in labels
    # Its voltage board and thermocouple are the BDF columns already.
    assert "pack.voltage / V" not in labels and "pack.temp / degC" not in labels
    ch0 = next(c for c in cfg.channels if c.name == "ch0")
    assert record_columns(cfg, ch0) == []


@pytest.mark.parametrize(
    ("record", "message"),
    [
        (["no.such"], "record: 'no.such' is not a tag declared under tags:"),
        (["cell.v", "cell.v"], "record: 'cell.v' is listed twice"),
        (
            ["cell.v", {"tag": "cell.charging", "label": "cell.v / V"}],
            "record: header 'cell.v / V' used twice",
        ),
    ],
)
def test_a_record_list_naming_an_unknown_or_repeated_tag_is_refused(
    record: list[Any], message: str
) -> None:
    with pytest.raises(ConfigErrors) as err:
        bench_from_data(bench_data(record))
    assert message in str(err.value)
