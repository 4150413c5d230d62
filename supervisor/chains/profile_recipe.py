"""A load profile (seed 002 §2.3) as a recipe with one ``profile:`` step: the text that
``supervisor import profile`` writes and the Recipes screen's profile upload loads.

The rows are written inline (``profile: {rows: [...]}``) so the recipe stands alone; one
too long for a recipe's size limit (1 MiB, about 30,000 rows) names its CSV instead
(``profile: {file: ...}``; :func:`profile_recipe_text`'s ``csv_ref``). Times are seconds
from the step start; the step ends when the last row's time is reached (that row only
marks the end). What the reader noticed (columns not used, Unix timestamps made relative)
is written as comments at the top, so the recipe says how it was made.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Sequence
from typing import Final

from supervisor.chains.compiler import Target, compile_recipe
from supervisor.chains.profile_csv import ProfileTable
from supervisor.chains.program import ProfilePoint
from supervisor.config.limits import MAX_YAML_BYTES
from supervisor.config.recipe import ID_PATTERN, load_recipe_text
from supervisor.config.yamledit import yaml_float, yaml_scalar
from supervisor.core.errors import ConfigError, ConfigErrors

__all__ = [
    "check_points",
    "compile_profile_recipe",
    "log_period_s",
    "profile_recipe_name",
    "profile_recipe_text",
    "too_long_inline",
]

FIELDS: Final = ("v_min", "v_max", "i_min", "i_max", "t_min", "t_max")
LOG_PERIOD_S: Final = (0.25, 120.0)
"""A profile step's logging period, at least the seed's sampling (250 ms: a profile of
millisecond rows does not make a line per scan), at most a recipe's default."""


def profile_recipe_name(stem: str, name: str | None = None) -> str:
    """``name`` if given (``ConfigError`` when it is no recipe name), else one made of the
    CSV's file name without its suffix."""
    if name is not None:
        if not re.match(ID_PATTERN, name):
            raise ConfigError(
                f"--name {name!r}: a recipe name must match {ID_PATTERN}", "<command line>"
            )
        return name
    made = re.sub(r"[^A-Za-z0-9_\-]+", "-", stem).strip("-") or "profile"
    return made if re.match(r"^[A-Za-z_]", made) else f"profile-{made}"


def log_period_s(points: Sequence[ProfilePoint]) -> float:
    """The step's logging period: its rows' shortest spacing within ``LOG_PERIOD_S``."""
    gaps = [b.t_s - a.t_s for a, b in itertools.pairwise(points)]
    low, high = LOG_PERIOD_S
    return round(min(high, max(low, min(gaps, default=high))), 3)


def _row(p: ProfilePoint) -> str:
    items: list[tuple[str, float | None]] = [("t", p.t_s), ("current", p.current_a)]
    items += [(f, getattr(p, f)) for f in FIELDS]
    return "{" + ", ".join(f"{k}: {yaml_float(v)}" for k, v in items if v is not None) + "}"


def check_points(points: Sequence[ProfilePoint], file: str) -> None:
    """Every value finite and no time negative; raise ConfigErrors naming each bad row."""
    problems: list[ConfigError] = []
    for k, p in enumerate(points, start=1):
        values = [p.t_s, p.current_a, *(getattr(p, f) for f in FIELDS)]
        if not all(math.isfinite(v) for v in values if v is not None):
            problems.append(ConfigError(f"profile row {k}: a value is not a finite number", file))
        elif p.t_s < 0:
            problems.append(ConfigError(f"profile row {k}: time {p.t_s:g} s is negative", file))
    if problems:
        raise ConfigErrors(problems)


def _lines(
    table: ProfileTable, source: str, recipe: str, csv_ref: str | None
) -> tuple[list[str], list[str]]:
    points = table.points
    span = points[-1].t_s - points[0].t_s
    header = [
        "# Imported by supervisor.importers.profile from a load profile (seed 002 §2.3).",
        f"# source: {source}",
        *(f"# note: {n}" for n in table.notices),
        "# t: s from the step start; current: A, + charges; v/i/t min/max: per-row window",
        "# (V, A, degC) that holds the chain with an alarm when crossed.",
        "# The step ends when the last row's time is reached.",
    ]
    where = source.rsplit("/", 1)[-1]
    body = [
        f"recipe: {yaml_scalar(recipe)}",
        f"description: {yaml_scalar(f'Load profile imported from {where}')}",
        "steps:",
        "  - id: profile",
        f"    comment: {yaml_scalar(f'{len(points)} rows, {span:g} s')}",
        "    # A result line per row (its shortest spacing, 0.25 s to 120 s): the profile's",
        "    # own resolution in the results, as the seed's HMI logs it (every 250 ms).",
        f"    log: {{period: {log_period_s(points):g} s}}",
        "    profile:",
    ]
    if csv_ref is None:
        body += ["      rows:", *(f"        - {_row(p)}" for p in points)]
    else:
        body.append(f"      file: {yaml_scalar(csv_ref)}")
    return header, body


def too_long_inline(table: ProfileTable, source: str, recipe: str) -> bool:
    """Whether the rows inline would make a recipe over its size limit."""
    return len(profile_recipe_text(table, source, recipe).encode("utf-8")) > MAX_YAML_BYTES


def profile_recipe_text(
    table: ProfileTable, source: str, recipe: str, csv_ref: str | None = None
) -> str:
    """The recipe of ``table`` (read from ``source``, named ``recipe``): its rows inline,
    or ``csv_ref`` (the CSV as the recipe's ``profile: {file:}``) when given."""
    header, body = _lines(table, source, recipe, csv_ref)
    return "\n".join(header + body) + "\n"


def compile_profile_recipe(text: str, where: str, source: str, target: Target | None) -> None:
    """Compile the recipe made of a profile (``where``: the recipe's file, for a CSV it
    names); ConfigErrors naming ``source`` when the profile does not make a valid step."""
    try:
        recipe, pos = load_recipe_text(text, where)
        compile_recipe(recipe, pos, where, target or Target())
    except ConfigErrors as exc:
        raise ConfigErrors(
            [
                ConfigError(f"the imported profile is refused: {e.message}", source)
                for e in exc.errors
            ]
        ) from None
