"""The complexity budget of ``make lint`` (tests/complexity.py): over budget only what the
allow-list names, at most its figure, and the list only shrinks."""

from __future__ import annotations

from pathlib import Path

import pytest
from complexity import (
    ALLOW_LIST,
    Figures,
    _ruff_complexities,
    check,
    format_allow_list,
    max_complexity,
    measure_source,
    parse_allow_list,
)

BUDGET = {"complexity": 12, "lines": 60}


def findings_of(
    figures: list[Figures], allowed: dict[str, dict[str, int]]
) -> list[tuple[str, str]]:
    """The failing findings, as (function, measure)."""
    found, _ = check(figures, allowed, BUDGET)
    return [(f.name, f.measure) for f in found if f.failing]


def test_a_function_within_budget_and_not_listed_passes() -> None:
    assert findings_of([Figures("a.py::f", 12, 60)], {}) == []


def test_a_function_over_budget_and_not_listed_fails_on_each_measure_over() -> None:
    assert findings_of([Figures("a.py::f", 13, 60)], {}) == [("a.py::f", "complexity")]
    assert findings_of([Figures("a.py::f", 12, 61)], {}) == [("a.py::f", "lines")]
    assert findings_of([Figures("a.py::f", 20, 80)], {}) == [
        ("a.py::f", "complexity"),
        ("a.py::f", "lines"),
    ]


def test_a_listed_function_at_its_figure_passes() -> None:
    allowed = {"a.py::f": {"complexity": 33, "lines": 219}}
    assert findings_of([Figures("a.py::f", 33, 219)], allowed) == []


def test_a_listed_function_fails_when_it_grows() -> None:
    allowed = {"a.py::f": {"complexity": 33, "lines": 219}}
    assert findings_of([Figures("a.py::f", 34, 219)], allowed) == [("a.py::f", "complexity")]
    assert findings_of([Figures("a.py::f", 33, 220)], allowed) == [("a.py::f", "lines")]


def test_a_listed_measure_covers_only_itself() -> None:
    # Listed for its length only: its complexity keeps the budget.
    allowed = {"a.py::f": {"lines": 100}}
    assert findings_of([Figures("a.py::f", 13, 100)], allowed) == [("a.py::f", "complexity")]


def test_a_listed_function_that_shrank_but_is_still_over_is_noted_and_its_figure_lowered() -> None:
    allowed = {"a.py::f": {"complexity": 33, "lines": 219}}
    found, updated = check([Figures("a.py::f", 20, 219)], allowed, BUDGET)
    assert [(f.name, f.measure, f.failing) for f in found] == [("a.py::f", "complexity", False)]
    assert "shrank from 33 to 20" in found[0].message
    assert updated == {"a.py::f": {"complexity": 20, "lines": 219}}
    # Once lowered, growing back to the old figure fails.
    assert findings_of([Figures("a.py::f", 33, 219)], updated) == [("a.py::f", "complexity")]


def test_a_listed_function_now_within_budget_fails_until_removed_from_the_list() -> None:
    allowed = {"a.py::f": {"complexity": 33, "lines": 219}}
    found, shrunk = check([Figures("a.py::f", 12, 40)], allowed, BUDGET)
    assert {(f.name, f.measure) for f in found} == {
        ("a.py::f", "complexity"),
        ("a.py::f", "lines"),
    }
    assert all("within budget" in f.message for f in found)
    assert shrunk == {}
    found, _ = check([Figures("a.py::f", 12, 40)], shrunk, BUDGET)
    assert found == []


def test_a_listed_function_that_is_gone_fails_until_removed_from_the_list() -> None:
    allowed = {"a.py::gone": {"lines": 70}}
    found, updated = check([Figures("a.py::f", 1, 3)], allowed, BUDGET)
    assert [(f.name, f.failing) for f in found] == [("a.py::gone", True)]
    assert updated == {}


def test_a_listed_function_that_moved_keeps_its_figures_under_its_new_name() -> None:
    allowed = {"supervisor/app/bench.py::Bench.shutdown": {"complexity": 17, "lines": 64}}
    moved = Figures("supervisor/bench/rig.py::Rig.shutdown", 17, 64)
    found, updated = check([moved], allowed, BUDGET)
    assert [(f.name, f.failing) for f in found] == [(moved.name, True)]
    assert "moved from supervisor/app/bench.py::Bench.shutdown" in found[0].message
    assert updated == {moved.name: {"complexity": 17, "lines": 64}}
    assert check([moved], updated, BUDGET)[0] == []
    # A move is no licence to grow.
    grown = Figures(moved.name, 18, 64)
    assert ("complexity" in {f.measure for f in check([grown], allowed, BUDGET)[0]}) is True
    assert check([grown], allowed, BUDGET)[1] == {moved.name: {"complexity": 17, "lines": 64}}


def test_a_move_is_not_guessed_between_functions_of_the_same_name() -> None:
    allowed = {"a.py::run": {"lines": 70}}
    figures = [Figures("b.py::run", 1, 70), Figures("c.py::X.run", 1, 70)]
    found, updated = check(figures, allowed, BUDGET)
    assert {(f.name, f.measure) for f in found} == {
        ("a.py::run", ""),
        ("b.py::run", "lines"),
        ("c.py::X.run", "lines"),
    }
    assert updated == {}


def test_a_listed_function_of_a_path_not_checked_this_time_is_not_taken_for_gone() -> None:
    allowed = {"b.py::g": {"lines": 70}}
    found, shrunk = check([Figures("a.py::f", 1, 3)], allowed, BUDGET, ["a.py"])
    assert found == []
    assert shrunk == allowed
    # A file deleted under a folder checked is gone, not "not checked".
    allowed = {"pkg/old.py::g": {"lines": 70}}
    found, shrunk = check([Figures("pkg/new.py::f", 1, 3)], allowed, BUDGET, ["pkg"])
    assert [(f.name, f.failing) for f in found] == [("pkg/old.py::g", True)]
    assert shrunk == {}


def test_the_update_never_adds_a_function_nor_raises_a_figure() -> None:
    allowed = {"a.py::f": {"complexity": 20}}
    figures = [Figures("a.py::f", 25, 10), Figures("a.py::new", 40, 100)]
    found, shrunk = check(figures, allowed, BUDGET)
    assert {(f.name, f.measure) for f in found} == {
        ("a.py::f", "complexity"),
        ("a.py::new", "complexity"),
        ("a.py::new", "lines"),
    }
    assert shrunk == {"a.py::f": {"complexity": 20}}


def test_the_allow_list_reads_back_what_it_writes() -> None:
    allowed = {"a.py::C.m": {"complexity": 14}, "a.py::f": {"complexity": 33, "lines": 219}}
    text = format_allow_list(allowed, "# header")
    assert text.splitlines() == [
        "# header",
        "a.py::C.m  complexity=14",
        "a.py::f  complexity=33  lines=219",
    ]
    assert parse_allow_list(text) == allowed


@pytest.mark.parametrize(
    "line", ["a.py::f", "a.py::f  size=3", "a.py::f  lines=x", "a.py::f lines=3\na.py::f lines=4"]
)
def test_an_allow_list_line_without_a_figure_or_twice_is_refused(line: str) -> None:
    with pytest.raises(ValueError, match="line"):
        parse_allow_list(line)


def test_the_shipped_allow_list_reads_and_names_only_functions_over_budget() -> None:
    allowed = parse_allow_list(ALLOW_LIST.read_text(encoding="utf-8"))
    budget = {"complexity": max_complexity(), "lines": 60}
    assert allowed
    for entry in allowed.values():
        assert all(figure > budget[m] for m, figure in entry.items())


SOURCE = '''
def top():
    def inner():
        pass

class C:
    @property
    def x(self):
        return 1

    @x.setter
    def x(self, value):
        pass

    async def run(self):
        """Doc."""

        return 2
'''


def test_functions_are_named_by_their_path_through_classes_and_functions() -> None:
    figures = {f.name: f for f in measure_source("m.py", SOURCE, {2: 5})}
    assert set(figures) == {
        "m.py::top",
        "m.py::top.inner",
        "m.py::C.x",
        "m.py::C.x#2",
        "m.py::C.run",
    }
    # Lines from the def to the last line, decorators left out; complexity by the def's line.
    assert figures["m.py::top"] == Figures("m.py::top", 5, 3)
    assert figures["m.py::C.x"].lines == 2
    assert figures["m.py::C.run"] == Figures("m.py::C.run", 1, 4)


def test_the_complexity_is_ruffs(tmp_path: Path) -> None:
    branches = "\n".join(f"    if x == {i}:\n        return {i}" for i in range(13))
    module = tmp_path / "m.py"
    module.write_text(f"def f(x):\n{branches}\n    return -1\n\n\ndef g():\n    pass\n")
    g_line = 1 + 2 * 13 + 1 + 3
    assert _ruff_complexities([str(module)]) == {module.resolve(): {1: 14, g_line: 1}}
