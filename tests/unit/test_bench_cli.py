"""``supervisor bench cli`` (issue 30): the command line's wall time beside the same run's
references. Its figures are printed and recorded, never asserted: only that it runs, what
it records, and that a failing command stops it instead of timing an error."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from supervisor.bench import cli, report
from supervisor.cli.main import main

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.chdir(ROOT)  # the benchmark names the shipped files, as make runs it
    path = tmp_path / "results.jsonl"
    monkeypatch.setenv(report.ENV, str(path))
    return path


def test_bench_cli_records_the_checks_median_with_the_interpreters_start_beside_it(
    results: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "cli", "--runs", "1"]) == 0
    (fig,) = report.read(results)
    assert fig.figure == "`supervisor check recipes/nimh-ds2710.yaml` wall time"
    assert fig.unit == "s" and fig.target == "<= 0.3"
    assert fig.measured > 0
    assert "python -c pass" in fig.reference and "import supervisor" in fig.reference
    assert fig.command == "supervisor bench cli --runs 1"
    out = capsys.readouterr().out
    for label in cli.cli_commands():
        assert label in out


def test_each_command_is_timed_as_often_as_asked_in_a_fresh_process() -> None:
    timed = cli.time_commands({"bare": (sys.executable, "-c", "pass")}, runs=3)
    assert [t.label for t in timed] == ["bare"]
    assert len(timed[0].walls_s) == len(timed[0].cpus_s) == 3
    assert all(cpu >= 0 for cpu in timed[0].cpus_s)


def test_a_command_that_fails_stops_the_benchmark_with_its_message() -> None:
    failing = (sys.executable, "-c", "import sys; sys.exit('no such recipe')")
    with pytest.raises(RuntimeError, match="exit 1: no such recipe"):
        cli.time_commands({"failing": failing}, runs=1)


def test_the_commands_run_with_their_bytecode_written(monkeypatch: pytest.MonkeyPatch) -> None:
    """A checkout run under ``PYTHONDONTWRITEBYTECODE`` would compile every module at each
    start: not the command's time, nor what an installed package does."""
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    monkeypatch.setenv("SOME_SETTING", "kept")
    env = cli._environment()
    assert "PYTHONDONTWRITEBYTECODE" not in env
    assert env["SOME_SETTING"] == "kept"
