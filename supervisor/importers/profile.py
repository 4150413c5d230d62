"""Import a load profile CSV (seed 002 §2.3) as a recipe with one ``profile:`` step.

The file is read by :func:`supervisor.chains.profile_csv.read_profile_csv` — the same reader
a recipe's ``profile: {file: ...}`` uses — so the columns, separators and encodings it
accepts are exactly those: time (s), current (A, + charges), then optional V min/max,
I min/max and T min/max, each pair in two columns or one ``min/max`` cell; ``,`` ``;`` or
tab separated; an optional header line; UTF-8 or CP1252.

The rows are written inline (``profile: {rows: [...]}``) so the recipe stands alone, when
the recipe stays within a recipe's size limit (1 MiB, about 30,000 rows); a longer profile,
up to the CSV's own limits (README: Input limits), is named by the recipe instead
(``profile: {file: ...}``, relative to the recipe written with ``-o``, else absolute).
Times are seconds from the step start; the step ends when the last row's time is reached
(that row only marks the end).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from pathlib import Path

from supervisor.chains.compiler import Target, compile_recipe
from supervisor.chains.profile_csv import read_profile_csv
from supervisor.chains.program import ProfilePoint
from supervisor.config.limits import MAX_YAML_BYTES
from supervisor.config.recipe import ID_PATTERN, load_recipe_text
from supervisor.config.yamledit import yaml_float, yaml_scalar
from supervisor.core.errors import ConfigError, ConfigErrors

__all__ = ["import_profile"]

_FIELDS = ("v_min", "v_max", "i_min", "i_max", "t_min", "t_max")


def _name(path: Path, name: str | None) -> str:
    if name is not None:
        if not re.match(ID_PATTERN, name):
            raise ConfigError(
                f"--name {name!r}: a recipe name must match {ID_PATTERN}", "<command line>"
            )
        return name
    stem = re.sub(r"[^A-Za-z0-9_\-]+", "-", path.stem).strip("-") or "profile"
    return stem if re.match(r"^[A-Za-z_]", stem) else f"profile-{stem}"


def _row(p: ProfilePoint) -> str:
    items: list[tuple[str, float | None]] = [("t", p.t_s), ("current", p.current_a)]
    items += [(f, getattr(p, f)) for f in _FIELDS]
    return "{" + ", ".join(f"{k}: {yaml_float(v)}" for k, v in items if v is not None) + "}"


def _check_points(points: Sequence[ProfilePoint], file: str) -> None:
    """Every value finite and no time negative; raise ConfigErrors naming each bad row."""
    problems: list[ConfigError] = []
    for k, p in enumerate(points, start=1):
        values = [p.t_s, p.current_a, *(getattr(p, f) for f in _FIELDS)]
        if not all(math.isfinite(v) for v in values if v is not None):
            problems.append(ConfigError(f"profile row {k}: a value is not a finite number", file))
        elif p.t_s < 0:
            problems.append(ConfigError(f"profile row {k}: time {p.t_s:g} s is negative", file))
    if problems:
        raise ConfigErrors(problems)


def import_profile(
    csv_path: str | Path, *, name: str | None = None, output: str | Path | None = None
) -> str:
    """Recipe YAML (one ``profile:`` step with ``rows:``) from a load profile CSV.

    ``output``: where the recipe will be written (None: printed); a profile too long to be
    written inline is named relative to it.

    Raises ConfigErrors naming the CSV (with line) when it cannot be read or the rows do
    not make a valid profile (times not increasing, a negative time, non-finite values).
    """
    path = Path(csv_path)
    file = str(path)
    try:
        points = read_profile_csv(path)
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    _check_points(points, file)
    span = points[-1].t_s - points[0].t_s
    header = [
        "# Imported by supervisor.importers.profile from a load profile (seed 002 §2.3).",
        f"# source: {path}",
        "# t: s from the step start; current: A, + charges; v/i/t min/max: per-row window",
        "# (V, A, degC) that holds the chain with an alarm when crossed.",
        "# The step ends when the last row's time is reached.",
    ]
    body: list[str] = [
        f"recipe: {yaml_scalar(_name(path, name))}",
        f"description: {yaml_scalar(f'Load profile imported from {path.name}')}",
        "steps:",
        "  - id: profile",
        f"    comment: {yaml_scalar(f'{len(points)} rows, {span:g} s')}",
        "    profile:",
        "      rows:",
        *(f"        - {_row(p)}" for p in points),
    ]
    text = "\n".join(header + body) + "\n"
    where = "<imported profile>"
    if len(text.encode("utf-8")) > MAX_YAML_BYTES:
        # The CSV's limits are the ones that apply (issue 28: a 100,000-row profile within
        # them was refused as a recipe over 1 MiB): the recipe names the file instead.
        recipe_path = Path(output).absolute() if output is not None else Path.cwd() / "r.yaml"
        ref = os.path.relpath(path.absolute(), recipe_path.parent) if output else path.absolute()
        body[-len(points) - 1 :] = [f"      file: {yaml_scalar(str(ref))}"]
        text = "\n".join(header + body) + "\n"
        where = str(recipe_path)
    try:
        recipe, pos = load_recipe_text(text, where)
        compile_recipe(recipe, pos, where, Target())
    except ConfigErrors as exc:
        raise ConfigErrors(
            [ConfigError(f"the imported profile is refused: {e.message}", file) for e in exc.errors]
        ) from None
    return text
