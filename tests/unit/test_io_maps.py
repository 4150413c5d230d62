"""I/O maps: the shipped files load; broken ones get one clear file:line:col message."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from supervisor.cli.main import main
from supervisor.config.schema import bench_schema
from supervisor.core.errors import ConfigErrors
from supervisor.devices.registry import BENCH_MODEL, load_bench

ROOT = Path(__file__).resolve().parents[2]
BAD = ROOT / "tests" / "data" / "bad_io_maps"


@pytest.mark.parametrize("path", sorted((ROOT / "io_maps").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_io_map_loads_and_checks(path: Path) -> None:
    cfg = load_bench(path)
    assert cfg.bench


# (file, line, col, words the message must contain)
CASES = [
    ("duplicate_tag.yaml", 9, 12, "duplicate tag name 'cell.v'"),
    ("missing_point.yaml", 10, 12, "has no point 'b3.voltage'"),
    ("zero_span.yaml", 11, 14, "raw span is zero"),
    ("unknown_driver.yaml", 4, 13, "unknown value 'siemens-s7'"),
    ("unknown_key.yaml", 3, 3, "did you mean 'period_s'"),
    ("board_owned_twice.yaml", 13, 13, "one owner per board"),
    ("limit_beyond_hardware.yaml", 11, 25, "at most 0.4 A"),
    ("board_not_on_bus.yaml", 7, 18, "board address 0 is already used"),
    ("bad_yaml.yaml", 5, 12, "YAML syntax error"),
]


@pytest.mark.parametrize(("name", "line", "col", "words"), CASES, ids=[c[0] for c in CASES])
def test_a_broken_io_map_is_refused_with_file_line_and_column(
    name: str, line: int, col: int, words: str
) -> None:
    with pytest.raises(ConfigErrors) as info:
        load_bench(BAD / name)
    first = info.value.errors[0]
    assert (first.file, first.line, first.col) == (str(BAD / name), line, col)
    assert words in first.message


def test_every_broken_file_in_the_corpus_has_a_case() -> None:
    assert {p.name for p in BAD.glob("*.yaml")} == {c[0] for c in CASES}


def test_check_exits_2_and_prints_one_line_per_error_without_traceback(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code = main(["check", str(BAD / "unknown_key.yaml"), str(ROOT / "io_maps" / "sim.yaml")])
    out, err = capsys.readouterr()
    assert code == 2
    assert "Traceback" not in err
    assert err.strip().splitlines() == [
        f"{BAD / 'unknown_key.yaml'}:3:3: unknown key 'perod_s' in scan"
        " (did you mean 'period_s'? expected one of: period_s)"
    ]
    assert "sim.yaml: OK" in out


def test_check_of_good_files_exits_0(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", *map(str, sorted((ROOT / "io_maps").glob("*.yaml")))]) == 0


def test_the_installed_command_reports_a_missing_file_with_exit_2() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "supervisor.cli.main", "check", "no/such/file.yaml"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert "no/such/file.yaml" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_the_committed_json_schema_matches_the_models() -> None:
    committed = json.loads((ROOT / "io_maps" / "bench.schema.json").read_text(encoding="utf-8"))
    assert committed == json.loads(json.dumps(bench_schema(BENCH_MODEL)))


def test_the_schema_rejects_unknown_keys_for_editors() -> None:
    schema = bench_schema(BENCH_MODEL)
    assert schema["additionalProperties"] is False
    assert "period_s" in json.dumps(schema)
