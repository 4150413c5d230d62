"""Import a load profile CSV (seed 002 §2.3) as a recipe with one ``profile:`` step.

The file is read by :func:`supervisor.chains.profile_csv.read_profile_table` — the same
reader a recipe's ``profile: {file: ...}`` uses — so the columns, separators and encodings
it accepts are exactly those: columns by their header's names (``Time (s)``, ``Current
(A)``, ``V min``, ``Tension Min/Max``…; a name it does not know is refused), else by place
(time (s), current (A, + charges), then optional V min/max, I min/max and T min/max, each
pair in two columns or one ``min/max`` cell); ``,`` ``;`` or tab separated; UTF-8 or
CP1252. Unix timestamps (the seed's Tk HMI log, figures 21 and 26) are made relative to
the first row, with a note in the recipe.

The rows are written inline (``profile: {rows: [...]}``) so the recipe stands alone, when
the recipe stays within a recipe's size limit (1 MiB, about 30,000 rows); a longer profile,
up to the CSV's own limits (README: Input limits), is named by the recipe instead
(``profile: {file: ...}``, relative to the recipe written with ``-o``, else absolute).
Times are seconds from the step start; the step ends when the last row's time is reached
(that row only marks the end). The text is made by :mod:`supervisor.chains.profile_recipe`,
which the Recipes screen's profile upload shares.
"""

from __future__ import annotations

import os
from pathlib import Path

from supervisor.chains.profile_csv import read_profile_table
from supervisor.chains.profile_recipe import (
    check_points,
    compile_profile_recipe,
    profile_recipe_name,
    profile_recipe_text,
    too_long_inline,
)
from supervisor.core.errors import ConfigError, ConfigErrors

__all__ = ["import_profile", "import_profile_noting"]


def import_profile(
    csv_path: str | Path, *, name: str | None = None, output: str | Path | None = None
) -> str:
    """Recipe YAML (one ``profile:`` step with ``rows:``) from a load profile CSV.

    ``output``: where the recipe will be written (None: printed); a profile too long to be
    written inline is named relative to it.

    Raises ConfigErrors naming the CSV (with line) when it cannot be read or the rows do
    not make a valid profile (times not increasing, a negative time, non-finite values).
    """
    return import_profile_noting(csv_path, name=name, output=output)[0]


def import_profile_noting(
    csv_path: str | Path, *, name: str | None = None, output: str | Path | None = None
) -> tuple[str, tuple[str, ...]]:
    """:func:`import_profile`'s text and what the reader noticed (columns not used, Unix
    timestamps made relative), which the command line also prints."""
    path = Path(csv_path)
    file = str(path)
    try:
        recipe = profile_recipe_name(path.stem, name)
        table = read_profile_table(path)
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    check_points(table.points, file)
    where = "<imported profile>"
    ref = None
    if too_long_inline(table, file, recipe):
        # The CSV's limits are the ones that apply (issue 28: a 100,000-row profile within
        # them was refused as a recipe over 1 MiB): the recipe names the file instead.
        recipe_path = Path(output).absolute() if output is not None else Path.cwd() / "r.yaml"
        ref = os.path.relpath(path.absolute(), recipe_path.parent) if output else path.absolute()
        where = str(recipe_path)
    text = profile_recipe_text(table, file, recipe, None if ref is None else str(ref))
    compile_profile_recipe(text, where, file, None)
    return text, table.notices
