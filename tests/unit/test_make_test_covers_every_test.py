"""`make test` runs the suite in parts (Makefile ``unit``: tests/unit, then the folders of
``WALL``): a folder of tests left out of every part would never run, silently."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_every_folder_holding_tests_is_in_a_part_of_make_test() -> None:
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    wall = re.search(r"^WALL\s*:=\s*(.+)$", makefile, re.MULTILINE)
    assert wall is not None, "the Makefile names the wall-time test folders in WALL"
    parts = {"tests/unit", *wall.group(1).split()}
    holding = {
        str(p.parent.relative_to(ROOT).parts[0] + "/" + p.parent.relative_to(ROOT).parts[1])
        for p in (ROOT / "tests").rglob("test_*.py")
        if "node_modules" not in p.parts
    }
    assert holding <= parts, f"test folders run by no part of make test: {holding - parts}"


def test_no_hypothesis_example_has_a_wall_clock_deadline() -> None:
    # A deadline is a timing assertion: on a loaded machine a line fit took 976 ms against
    # hypothesis's default 200 ms and failed the suite (tests/conftest.py's profile).
    from hypothesis import settings

    assert settings().deadline is None
