"""Every result row is written once (issue 26, 6c): the end of a test wrote its last record
twice (the end of the last cycle, then the end of the test, at the same instant)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from supervisor.cli.main import main

TWO_STEPS = (
    "recipe: t\nlogging: {period: 10 s}\nsteps:\n"
    "  - {id: c, charge: 100 mA, duration: 30 s}\n"
    "  - {id: d, discharge: 100 mA, duration: 30 s}\n"
)
END_STEP = (
    "recipe: t\nlogging: {period: 10 s}\nsteps:\n"
    "  - {id: c, charge: 100 mA, duration: 30 s}\n  - {id: e, end: true}\n"
)


@pytest.mark.parametrize(
    ("text", "rows"),
    [
        # 0..30 s in c, then d from 30 s to 60 s: a step change is the last row of one step
        # and the first of the next, at the same time (different step counts).
        (
            TWO_STEPS,
            [
                ("0", "c"),
                ("10", "c"),
                ("20", "c"),
                ("30", "c"),
                ("30", "d"),
                ("40", "d"),
                ("50", "d"),
                ("60", "d"),
            ],
        ),
        (END_STEP, [("0", "c"), ("10", "c"), ("20", "c"), ("30", "c")]),
    ],
    ids=["last-cycle-ends", "end-step"],
)
def test_a_finished_test_writes_its_last_row_once(
    tmp_path: Path, text: str, rows: list[tuple[str, str]], capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = tmp_path / "t.yaml"
    recipe.write_text(text, encoding="utf-8")
    assert main(["dry-run", str(recipe), "--results", str(tmp_path / "results")]) == 0
    capsys.readouterr()
    (bdf,) = (tmp_path / "results").rglob("*.bdf.csv")
    table = list(csv.DictReader(bdf.read_text(encoding="utf-8").splitlines()))
    got = [(f"{float(r['Test Time / s']):g}", r["Step ID"]) for r in table]
    assert got == rows
    assert [r["Record Index / 1"] for r in table] == [str(n) for n in range(1, len(rows) + 1)]
    keys = [(r["Test Time / s"], r["Step Count / 1"]) for r in table]
    assert len(set(keys)) == len(keys)
    (cha,) = (tmp_path / "results").rglob("*.chadeche.csv")
    lines = cha.read_text(encoding="utf-8").splitlines()
    assert len(lines) == len(rows) and len(set(lines)) == len(lines)
