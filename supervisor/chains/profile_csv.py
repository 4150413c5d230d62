"""Load profiles in CSV (seed 002 §2.3), read for a recipe's ``profile: {file: ...}``."""

from __future__ import annotations

import csv
from pathlib import Path

from supervisor.chains.program import ProfilePoint
from supervisor.core.errors import ConfigError

__all__ = ["read_profile_csv"]


def read_profile_csv(path: Path) -> tuple[ProfilePoint, ...]:
    """A load profile (seed 002 §2.3): time, current, then optional V/I/T min/max columns.

    Accepts ``,`` ``;`` or tab separators, a header line, UTF-8 or CP1252, and
    ``min/max`` pairs written in one cell as ``3.0/4.2``.
    """
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read profile: {exc.strerror or exc}", path) from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("cp1252")
    lines = text.splitlines()
    if not lines:
        raise ConfigError("profile is empty", path, 1, 1)
    # On a tie prefer ";" and tab: "0;1,5" is a French decimal comma, not two fields.
    dialect_sep = max((";", "\t", ","), key=lambda c: lines[0].count(c))
    rows = list(csv.reader(lines, delimiter=dialect_sep))
    out: list[ProfilePoint] = []
    last_t = -1.0
    for ln, row in enumerate(rows, start=1):
        cells = [c.strip() for c in row]
        if not any(cells):
            continue
        if dialect_sep != ",":
            # Spreadsheets in French locales write decimal commas (seed 002 profiles).
            cells = [c.replace(",", ".") for c in cells]
        try:
            t = float(cells[0])
        except ValueError:
            if ln == 1:
                continue  # header
            raise ConfigError(f"time {cells[0]!r} is not a number", path, ln, 1) from None
        vals: list[float | None] = []
        for c in cells[1:]:
            for part in c.split("/") if "/" in c else [c]:
                part = part.strip()
                try:
                    vals.append(float(part) if part else None)
                except ValueError:
                    raise ConfigError(f"{part!r} is not a number", path, ln, 1) from None
        if not vals or vals[0] is None:
            raise ConfigError("each row needs a current after the time", path, ln, 1)
        if t <= last_t:
            raise ConfigError(f"time {t:g} s does not increase", path, ln, 1)
        last_t = t
        vals += [None] * (7 - len(vals))
        cur = vals[0]
        out.append(ProfilePoint(t, cur, *vals[1:7]))
    if not out:
        raise ConfigError("profile has no rows", path, 1, 1)
    return tuple(out)
