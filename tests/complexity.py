"""The complexity budget of ``make lint``: no function over ruff's McCabe complexity 12
(``[tool.ruff.lint.mccabe]`` in pyproject.toml) or over 60 lines, but for the allow-list
``tests/complexity_budget.txt`` of the functions that were over it when the budget came in,
each with its figure then. The list only shrinks: the check fails when a function not
listed is over budget, when a listed one grew past its figure, and when a listed one is
within budget or gone (its line is to be removed). A listed one that shrank is noted:
``--update`` lowers its figure (so it cannot grow back), removes the lines of functions
within budget or gone, and renames the line of a function that moved (another file or
class, the same name, the only one): never a line added or a figure raised.

    python -m tests.complexity [--update] [paths ...]   (default: supervisor tests)

Complexity is ruff's (the rule C901, run with a budget of 0 so that every function's
figure is reported); a function's lines run from its ``def`` to its last line, comments
and docstring included, decorators not: what a reader has to scroll through.
"""

from __future__ import annotations

import argparse
import ast
import json
import shutil
import subprocess
import sys
import tomllib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ALLOW_LIST = ROOT / "tests" / "complexity_budget.txt"
DEFAULT_PATHS = ("supervisor", "tests")
MAX_LINES = 60
MEASURES = ("complexity", "lines")


def max_complexity(pyproject: Path = ROOT / "pyproject.toml") -> int:
    """The McCabe budget, kept where ruff reads it."""
    config = tomllib.loads(pyproject.read_text(encoding="utf-8"))
    return int(config["tool"]["ruff"]["lint"]["mccabe"]["max-complexity"])


@dataclass(frozen=True)
class Figures:
    """One function's figures; ``name`` is ``path::Outer.inner`` (path from the root)."""

    name: str
    complexity: int
    lines: int

    def of(self, measure: str) -> int:
        return int(getattr(self, measure))


@dataclass(frozen=True)
class Finding:
    name: str
    measure: str
    message: str
    failing: bool = True
    """False: a note (a listed figure that shrank; ``--update`` lowers it)."""

    def __str__(self) -> str:
        return f"{self.name}: {self.measure} {self.message}".replace(":  ", ": ")


# --- measuring ---------------------------------------------------------------------------


def _functions(tree: ast.AST) -> Iterator[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
    """Every function with its dotted name inside the module (classes and enclosing
    functions included); a name seen twice in one scope (a property's setter) gets
    ``#2``, ``#3``… in order of appearance."""
    seen: dict[str, int] = {}

    def walk(node: ast.AST, prefix: str) -> Iterator[tuple[str, ast.AST]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                name = prefix + child.name
                seen[name] = seen.get(name, 0) + 1
                if seen[name] > 1:
                    name = f"{name}#{seen[name]}"
                if not isinstance(child, ast.ClassDef):
                    yield name, child
                yield from walk(child, name + ".")
            else:
                yield from walk(child, prefix)

    for name, node in walk(tree, ""):
        assert isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        yield name, node


def measure_source(path: str, source: str, complexity_by_line: dict[int, int]) -> Iterator[Figures]:
    """The figures of every function of one module; ``complexity_by_line`` maps the line of
    a ``def`` to its complexity (ruff's C901 reports it at the function's name)."""
    for name, node in _functions(ast.parse(source, filename=path)):
        end = node.end_lineno if node.end_lineno is not None else node.lineno
        yield Figures(
            f"{path}::{name}",
            complexity_by_line.get(node.lineno, 1),
            end - node.lineno + 1,
        )


def _ruff() -> str:
    """The ruff of this environment (make lint's), else the one on the PATH."""
    beside = Path(sys.executable).with_name("ruff")
    return str(beside) if beside.exists() else shutil.which("ruff") or "ruff"


def _ruff_complexities(paths: Sequence[str]) -> dict[Path, dict[int, int]]:
    """Every function's McCabe complexity by file and line, from ruff's C901 at budget 0."""
    command = [
        _ruff(),
        "check",
        "--quiet",
        "--no-cache",
        "--select",
        "C901",
        "--config",
        "lint.mccabe.max-complexity = 0",
        "--output-format",
        "json",
        "--exit-zero",
        *paths,
    ]
    out = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=True).stdout
    found: dict[Path, dict[int, int]] = {}
    for item in json.loads(out):
        if item["code"] != "C901":
            continue  # a syntax error: ruff check, before, says where
        # "`name` is too complex (15 > 0)"
        figure = int(item["message"].rsplit("(", 1)[1].split(">", 1)[0])
        found.setdefault(Path(item["filename"]), {})[item["location"]["row"]] = figure
    return found


def _ruff_files(paths: Sequence[str]) -> list[Path]:
    """The files ruff checks (its excludes and .gitignore kept)."""
    command = [_ruff(), "check", "--show-files", *paths]
    out = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return [Path(line) for line in out.splitlines() if line.endswith(".py")]


def measure(paths: Sequence[str] = DEFAULT_PATHS) -> list[Figures]:
    """The figures of every function of the files ruff checks under ``paths``."""
    complexities = _ruff_complexities(paths)
    figures: list[Figures] = []
    for file in _ruff_files(paths):
        rel = file.resolve().relative_to(ROOT).as_posix()
        source = file.read_text(encoding="utf-8")
        figures.extend(measure_source(rel, source, complexities.get(file.resolve(), {})))
    return figures


# --- the allow-list ----------------------------------------------------------------------


def parse_allow_list(text: str) -> dict[str, dict[str, int]]:
    """``path::name  complexity=33  lines=219`` a line (a measure within budget left out);
    ``#`` starts a comment."""
    allowed: dict[str, dict[str, int]] = {}
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.split(" #", 1)[0].strip()
        if not line or line.startswith("#"):
            continue
        name, *pairs = line.split()
        if name in allowed:
            raise ValueError(f"line {number}: {name} listed twice")
        entry: dict[str, int] = {}
        for pair in pairs:
            measure_name, _, value = pair.partition("=")
            if measure_name not in MEASURES or not value.isdigit():
                raise ValueError(f"line {number}: {pair!r} is not complexity=N or lines=N")
            entry[measure_name] = int(value)
        if not entry:
            raise ValueError(f"line {number}: {name} has no figure")
        allowed[name] = entry
    return allowed


def format_allow_list(allowed: dict[str, dict[str, int]], header: str) -> str:
    lines = [header.rstrip("\n")] if header else []
    for name in sorted(allowed):
        figures = "  ".join(f"{m}={allowed[name][m]}" for m in MEASURES if m in allowed[name])
        lines.append(f"{name}  {figures}")
    return "\n".join(lines) + "\n"


def _header(text: str) -> str:
    """The comment lines the list starts with, kept by ``--update``."""
    head: list[str] = []
    for line in text.splitlines():
        if not line.startswith("#") and line.strip():
            break
        head.append(line)
    return "\n".join(head)


# --- the check ---------------------------------------------------------------------------


def _path(name: str) -> str:
    return name.split("::", 1)[0]


def _in_scope(name: str, scope: Sequence[str] | None) -> bool:
    """Whether the listed function's file lies under one of the paths checked."""
    if scope is None:
        return True
    path = _path(name)
    return any(path == p or path.startswith(p.rstrip("/") + "/") for p in scope)


def _judge(value: int, listed: int | None, limit: int) -> tuple[str | None, bool, int | None]:
    """One measure of one function: (the message or None, whether it fails, the figure the
    allow-list keeps or None)."""
    if listed is None:
        if value > limit:
            return f"{value} > {limit}: over budget, make it simpler", True, None
        return None, False, None
    if value > listed:
        return f"grew from {listed} to {value} (budget {limit})", True, listed
    if value <= limit:
        return f"is {value}, within budget: remove it from the list", True, None
    if value < listed:
        return f"shrank from {listed} to {value}: --update lowers its figure", False, value
    return None, False, listed


def _moves(
    by_name: dict[str, Figures],
    allowed: dict[str, dict[str, int]],
    gone: list[str],
    budget: dict[str, int],
) -> dict[str, str]:
    """New name → listed name of the functions that moved (another file or class): a
    listed function gone and one function of the same name, not listed, that is over
    budget, each the only one of that name. Its figures carry over: a move is no growth."""

    def short(name: str) -> str:
        return name.rsplit("::", 1)[1].rsplit(".", 1)[-1]

    claimants: dict[str, list[str]] = {}
    for name, function in by_name.items():
        if name not in allowed and any(function.of(m) > budget[m] for m in MEASURES):
            claimants.setdefault(short(name), []).append(name)
    olds: dict[str, list[str]] = {}
    for name in gone:
        olds.setdefault(short(name), []).append(name)
    return {
        claimants[key][0]: old[0]
        for key, old in olds.items()
        if len(old) == 1 and len(claimants.get(key, [])) == 1
    }


def check(
    figures: Iterable[Figures],
    allowed: dict[str, dict[str, int]],
    budget: dict[str, int],
    scope: Sequence[str] | None = None,
) -> tuple[list[Finding], dict[str, dict[str, int]]]:
    """The findings, and the allow-list as it should be (``--update``): a figure lowered
    to what it is, a function within budget or gone removed, a moved one renamed; never
    one added or a figure raised. ``scope``: the paths checked (from the root; None: all),
    so that a listed function of a file not checked this time is not taken for gone."""
    by_name = {f.name: f for f in figures}
    gone = [n for n in allowed if n not in by_name and _in_scope(n, scope)]
    moved = _moves(by_name, allowed, gone, budget)
    findings: list[Finding] = []
    updated: dict[str, dict[str, int]] = {}
    for function in by_name.values():
        old = moved.get(function.name)
        entry = allowed.get(old if old is not None else function.name, {})
        for m in MEASURES:
            message, failing, keep = _judge(function.of(m), entry.get(m), budget[m])
            if message is not None:
                findings.append(Finding(function.name, m, message, failing))
            if keep is not None:
                updated.setdefault(function.name, {})[m] = keep
        if old is not None:
            findings.append(Finding(function.name, "", f"moved from {old}: --update renames it"))
    for name in gone:
        if name not in moved.values():
            findings.append(Finding(name, "", "is listed but no such function: remove it"))
    for name, entry in allowed.items():
        if not _in_scope(name, scope):
            updated[name] = dict(entry)  # a file not checked this time
    return findings, updated


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.complexity", description=__doc__)
    parser.add_argument("paths", nargs="*", default=list(DEFAULT_PATHS))
    parser.add_argument(
        "--update",
        action="store_true",
        help="lower the figures that shrank, remove the functions within budget or gone,"
        " rename those that moved",
    )
    args = parser.parse_args(argv)
    budget = {"complexity": max_complexity(), "lines": MAX_LINES}
    text = ALLOW_LIST.read_text(encoding="utf-8")
    allowed = parse_allow_list(text)
    figures = measure(args.paths)
    scope = [Path(p).resolve().relative_to(ROOT).as_posix() for p in args.paths]
    findings, updated = check(figures, allowed, budget, scope)
    if args.update and updated != allowed:
        ALLOW_LIST.write_text(format_allow_list(updated, _header(text)), encoding="utf-8")
        print(f"{ALLOW_LIST.relative_to(ROOT)}: {len(allowed)} -> {len(updated)} functions")
        findings, _ = check(figures, updated, budget, scope)
    failing = [f for f in findings if f.failing]
    for finding in findings:
        print(finding, file=sys.stderr if finding.failing else sys.stdout)
    if failing:
        print(
            f"complexity budget (complexity {budget['complexity']}, {MAX_LINES} lines): "
            f"{len(failing)} finding(s); the allow-list is {ALLOW_LIST.relative_to(ROOT)}",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
