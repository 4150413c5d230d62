"""``supervisor bench dry-run --bytecodes``: one scan's cost in bytecodes and calls, a
figure that does not depend on the machine's speed or load."""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.bench.dryruncost import scan_cost
from supervisor.cli.main import main


def test_a_scans_cost_is_the_difference_of_two_runs_and_the_same_each_time(root: Path) -> None:
    recipe = root / "recipes" / "nimh-25h-slow-cycle.yaml"
    # In one process after other tests, whose garbage (transports, tasks with finalizers)
    # the collector may free at any allocation: never counted in a scan's cost.
    first = scan_cost(recipe, hours=0.01)
    second = scan_cost(recipe, hours=0.01)
    assert first.scans == 36
    assert first.bytecodes == second.bytecodes > 0
    assert first.calls == second.calls > 0
    assert sum(row[1] for row in first.by_function) == pytest.approx(first.bytecodes)
    assert [row[1] for row in first.by_function] == sorted(
        (row[1] for row in first.by_function), reverse=True
    )
    # The scan's own work is in it, the start-up's is not.
    names = {where.rsplit(":", 1)[1] for where, _, _ in first.by_function}
    assert {"scan_once", "_copy_inputs", "evaluate", "update"} <= names
    assert "build_bench" not in names and "compile_recipe" not in names


def test_the_bench_command_prints_the_cost_by_function(
    root: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import supervisor.bench.dryruncost as cost

    real = cost.scan_cost
    monkeypatch.setattr(cost, "scan_cost", lambda recipe: real(recipe, hours=0.01))
    recipe = str(root / "recipes" / "nimh-25h-slow-cycle.yaml")
    assert main(["bench", "dry-run", "--recipe", recipe, "--bytecodes"]) == 0
    out = capsys.readouterr().out
    assert "bytecodes and" in out and "Python calls a scan" in out and "36 scans" in out
    assert "supervisor/scan/engine.py" in out
