"""The test metadata's checks, ``provenance.json`` frozen at start, the manifest and
``verify`` (supervisor/publish/provenance.py, ADR 0025), on a collector fed by hand."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from test_results import REC, WALL

from supervisor.core.records import ChainEvent
from supervisor.publish.provenance import (
    PROVENANCE_NAME,
    MetadataError,
    NotAResultFolder,
    Provenance,
    TestMetadata,
    metadata_from_arguments,
    utc_iso,
    verify,
)
from supervisor.publish.results import ResultCollector

TEXT = "recipe: r\nsteps:\n  - {id: c, charge: 300 mA, duration: 60 s}\n"


def provenance() -> Provenance:
    return Provenance(
        bench="b",
        channel="ch0",
        test_id="t1",
        recipe_name="r",
        recipe_file="recipes/r.yaml",
        recipe_text=TEXT,
        parameters_given={"i": "0.1C"},
        parameters_resolved={"i": 0.2},
        io_map_file="io_maps/b.yaml",
        io_map_sha256="ab" * 32,
        io_map_channel={"channel": {"name": "ch0"}},
    )


def finished(tmp_path: Path, **kw: Any) -> Path:
    c = ResultCollector("ch0", "r", "t1", tmp_path / "t1", provenance=provenance(), **kw)
    c.on_event(ChainEvent(3.0, WALL, "ch0", "state", "Idle → Running (start by operator)"))
    for i in range(3):
        c.on_record(replace(REC, t=3.0 + i, test_time_s=float(i), wall=WALL + i))
    c.on_event(ChainEvent(5.0, WALL + 2, "ch0", "state", "Running → Held (hold by bob)"))
    c.on_event(ChainEvent(6.0, WALL + 3, "ch0", "state", "Held → Running (resume by bob)"))
    c.close("done", "Complete", now=7.0)
    return tmp_path / "t1"


def test_metadata_are_checked_and_given_in_their_units() -> None:
    got = metadata_from_arguments(
        {"cell_id": " A-1/2 ", "nominal_capacity": "1300 mAh", "comment": "é\nline 2"}
    )
    assert got == {"cell_id": "A-1/2", "nominal_capacity_ah": 1.3, "comment": "é\nline 2"}
    assert metadata_from_arguments({"nominal_capacity": 2.5}) == {"nominal_capacity_ah": 2.5}
    assert metadata_from_arguments({"nominal_capacity": "2.5"}) == {"nominal_capacity_ah": 2.5}
    assert metadata_from_arguments({}) == {}


@pytest.mark.parametrize(
    ("args", "field", "message"),
    [
        ({"cell_id": "x" * 65}, "cell_id", "cell_id is 65 characters long, at most 64"),
        ({"cell_id": "a\tb"}, "cell_id", "cell_id 'a\\tb' has '\\t': one line of letters"),
        ({"chemistry": ["nimh"]}, "chemistry", "chemistry must be a text, not ['nimh']"),
        ({"comment": "\x1b[31mred"}, "comment", "comment has the control character '\\x1b'"),
        ({"comment": "\u202eevil"}, "comment", "control character '\\u202e'"),
        ({"nominal_capacity": True}, "nominal_capacity", "not True"),
        ({"nominal_capacity": "0 Ah"}, "nominal_capacity", "above 0"),
    ],
)
def test_bad_metadata_name_the_field_and_what_was_received(
    args: dict[str, Any], field: str, message: str
) -> None:
    with pytest.raises(MetadataError) as exc:
        metadata_from_arguments(args)
    assert exc.value.field == field and message in str(exc.value)


def test_provenance_is_written_at_the_first_record_with_the_recipe_and_its_hash(
    tmp_path: Path,
) -> None:
    c = ResultCollector("ch0", "r", "t1", tmp_path / "t1", provenance=provenance())
    c.on_event(ChainEvent(3.0, WALL, "ch0", "state", "Idle → Running (start by operator)"))
    assert not (tmp_path / "t1" / PROVENANCE_NAME).exists()
    c.on_record(replace(REC, t=3.5, test_time_s=0.5, wall=WALL + 0.5))
    prov = json.loads((tmp_path / "t1" / PROVENANCE_NAME).read_text(encoding="utf-8"))
    assert prov["recipe"]["sha256"] == hashlib.sha256(TEXT.encode()).hexdigest()
    assert prov["recipe"]["parameters_given"] == {"i": "0.1C"}
    assert prov["recipe"]["parameters_resolved"] == {"i": 0.2}
    assert prov["started_utc"] == utc_iso(WALL) and prov["started_utc"].endswith("Z")
    c.close("done", "Complete")


def test_the_final_summary_has_the_pauses_the_end_and_a_manifest_that_verifies(
    tmp_path: Path,
) -> None:
    folder = finished(tmp_path, metadata=TestMetadata(cell_id="C1", operator="alice"))
    summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    assert [p["text"] for p in summary["pauses"]] == [
        "Running → Held (hold by bob)",
        "Held → Running (resume by bob)",
    ]
    assert summary["ended_utc"] == utc_iso(WALL + 3)
    assert summary["metadata"]["cell_id"] == "C1"
    assert sorted(summary["manifest"]) == [
        "provenance.json",
        "t1.bdf.csv",
        "t1.bdf.metadata.json",
        "t1.chadeche.csv",
        "t1.cycles.jsonl",
        "t1.timeline.jsonl",
    ]
    assert verify(folder).ok, verify(folder).problems


def test_a_bdf_row_removed_is_found_by_its_count_and_its_hash(tmp_path: Path) -> None:
    folder = finished(tmp_path)
    bdf = folder / "t1.bdf.csv"
    bdf.write_text("".join(bdf.read_text(encoding="utf-8").splitlines(True)[:-1]))
    problems = verify(folder).problems
    assert "t1.bdf.csv: modified (SHA-256 differs from the manifest)" in problems
    assert "t1.bdf.csv: 2 rows, the summary counts 3 records" in problems


def test_a_folder_without_a_test_is_not_a_result_folder(tmp_path: Path) -> None:
    with pytest.raises(NotAResultFolder, match="not a test"):
        verify(tmp_path)
    with pytest.raises(NotAResultFolder, match="not a folder"):
        verify(tmp_path / "missing")
