"""Import a Chadèche sequence file (seed 000 §III.D) and its ``chadecheN.prm`` as a recipe.

The sequence file is tab separated, with a mandatory header line (the program ignores it,
so a file without one silently loses its first sequence) and eleven columns::

    ADR  C/D  mA  SD  TL  TH  LmAh  HmAh  TRUE  CTRLZ  COMMENT

Mapping (every row becomes one step, id ``s<ADR>``, in file order):

* ``C``/``D`` + ``mA`` → ``charge: N mA`` / ``discharge: N mA``; ``mA`` 0 → ``rest: true``
  (with 0 mA the letter only sets the relay); ``SD`` → ``duration: N s`` (0 → ``0 s``);
* the condition columns, in column order (the program evaluates them left to right and the
  first true non-``I`` one acts, which is what ``until`` does): TL ``voltage <= v_min``,
  TH ``voltage >= v_max``, LmAh ``charge <= q_min``, HmAh ``charge >= q_max``, TRUE
  ``true``; actions ``S`` → ``next``, ``C`` → ``next_cycle``, ``N`` → ``s<N>`` (a goto),
  ``HH:MM`` (sleep until then, then the next step), ``+HH:MM`` (sleep that long, then the
  next step); ``I`` entries are dropped;
* ``CTRLZ`` → ``advance:`` (``I`` → ``advance: false``, other actions mapped as above);
* ``COMMENT`` (without its ``#``) → ``comment:``; the source row is repeated as a YAML
  comment above its step, so nothing of the file is lost.

Instant rows (``simplify=True``, the default): a 0 mA row whose first acting condition is
TRUE ends at its first evaluation, whatever its SD says; it is written as the step kind
that means the same thing — ``goto: s<N>``, ``end_cycle: true``, ``sleep_until: "HH:MM"``
or ``sleep: N min`` — and a last row at 0 mA, SD 0, with no condition (the end of the
cycle) as ``end_cycle: true``. This is how ``recipes/nimh-ds2710.yaml`` writes the seed's
figure 10 by hand. ``simplify=False`` keeps every row a rest/charge/discharge step.

Parameters: program defaults < ``chadecheN.prm`` < ``overrides`` (the command line), like
the program itself (seed §III.D.4). ``-m -M -c -C -i`` become the recipe parameters
``v_min v_max q_min q_max q_init`` (``initial_charge: q_init``), ``-n`` the ``cycles``,
``-p`` the ``logging.period``. ``-1 -2 -s -o`` are the board's calibration (they belong in
the I/O map, not in a recipe): see :attr:`ImportResult.calibration_snippet`. ``-2`` is an
offset in mA: the seed's current fit is setpoint mA against measured mA (§III.F.1, its
example ``-2 0.0008`` comes from a 0–250 mA staircase), so it lands in
``current_offset_ma``; ``-o`` is in volts (``voltage_offset_v``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from supervisor.chains.compiler import Target, compile_recipe
from supervisor.config.recipe import ID_PATTERN, STEP_KINDS, load_recipe_text
from supervisor.config.text import DecodedText, decode_text
from supervisor.config.yamledit import yaml_comment, yaml_float, yaml_scalar
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.devices.chadeche.config import MAX_CURRENT_A

__all__ = [
    "COLUMNS",
    "DEFAULTS",
    "ImportResult",
    "import_chadeche",
]

COLUMNS = ("ADR", "C/D", "mA", "SD", "TL", "TH", "LmAh", "HmAh", "TRUE", "CTRLZ", "COMMENT")
_MAX_MA = round(MAX_CURRENT_A * 1000)  # the board maximum (seed §III.D.1), in the file's mA

# Condition columns (index in COLUMNS) → the recipe condition.
CONDITIONS: tuple[tuple[int, str], ...] = (
    (4, "voltage <= v_min"),
    (5, "voltage >= v_max"),
    (6, "charge <= q_min"),
    (7, "charge >= q_max"),
    (8, "true"),
)


@dataclass(frozen=True)
class _Option:
    letter: str
    target: str  # recipe parameter name, or "cycles" / "logging.period"
    unit: str
    default: float
    source: str  # where the default comes from
    assumed: bool = False  # the seed does not state this default


# The options that are recipe matters, in the order they are written out.
OPTIONS: dict[str, _Option] = {
    "m": _Option("m", "v_min", "V", 1.0, "default, seed §IV (TL 1 V)"),
    "M": _Option("M", "v_max", "V", 1.75, "default, seed §IV (TH 1.75 V)"),
    "c": _Option("c", "q_min", "mAh", 100.0, "default, seed §IV (LmAh 100 mAh)"),
    "C": _Option("C", "q_max", "mAh", 1300.0, "default, seed §IV (HmAh 1300 mAh)"),
    "i": _Option(
        "i", "q_init", "mAh", 0.0, "assumed default: the program's CINIT, 0 mAh", assumed=True
    ),
    "n": _Option("n", "cycles", "", 1.0, "assumed default: one cycle", assumed=True),
    "p": _Option("p", "logging.period", "s", 120.0, "default, seed §III.E.2 (120 s)"),
}
DEFAULTS: dict[str, float] = {k: o.default for k, o in OPTIONS.items()}

# Calibration options (seed §III.D.6, §III.F) → the I/O map's board calibration keys.
CALIBRATION: dict[str, tuple[str, str]] = {
    "1": ("current_slope", "current slope, setpoint mA per measured mA"),
    "2": ("current_offset_ma", "current offset in mA"),
    "s": ("voltage_slope", "voltage slope, meter V per ADC V"),
    "o": ("voltage_offset_v", "voltage offset in V"),
}
_POSITIVE_CAL = {"1", "s"}

# Ignored in a parameter file (seed §III.D.6).
IGNORED_IN_PRM = {"a": "board address", "h": "help"}
# Options of the program that have no meaning in a recipe.
NOT_RECIPE = {
    "v": "verbose display",
    "t": "test mode",
    "f": "results file name",
    "g": "sequence file name",
    "l": "message language",
}
_FLAGS = {"v", "t", "h"}  # options without a value

_INT = re.compile(r"^\d+$")
_HHMM = re.compile(r"^(\d{1,2}):(\d{2})$")
_PLUS_HHMM = re.compile(r"^\+(\d{1,3}):(\d{2})$")


@dataclass(frozen=True)
class ImportResult:
    """What :func:`import_chadeche` produced."""

    yaml_text: str
    """A complete recipe file, with a comment header saying where it came from."""
    recipe: dict[str, Any]
    """The same recipe as plain data (what loading ``yaml_text`` gives)."""
    calibration: dict[str, float] | None
    """``-1 -2 -s -o`` as I/O-map calibration keys (only those given), or None."""
    calibration_snippet: str | None
    """YAML lines to paste under the board's ``calibration:`` in the I/O map."""
    warnings: list[str] = field(default_factory=list)


def _num(value: float) -> str:
    """A number for a quantity string: ``1``, ``1.75``, ``0.5``."""
    if float(value).is_integer() and abs(value) < 1e15:
        return str(int(value))
    return yaml_float(value)


# --------------------------------------------------------------------------------------------
# Reading


def _split_fields(line: str) -> list[tuple[str, int]]:
    """Tab-separated fields with the 1-based column where each starts (a tab is one column)."""
    out: list[tuple[str, int]] = []
    start = 0
    for part in line.split("\t"):
        out.append((part, start + 1))
        start += len(part) + 1
    return out


@dataclass(frozen=True)
class _Act:
    """One action cell: I, S, C, N (goto ADR), HH:MM, +HH:MM."""

    kind: str  # "I" "S" "C" "N" "HHMM" "PLUS"
    value: str  # normalised text (ADR number, "20:00", "+01:30")
    col: int

    def recipe_action(self) -> str:
        if self.kind == "S":
            return "next"
        if self.kind == "C":
            return "next_cycle"
        if self.kind == "N":
            return f"s{self.value}"
        return self.value


@dataclass
class _Row:
    line: int
    adr: int
    letter: str
    ma: int
    sd: int
    conditions: list[tuple[str, _Act]]  # (recipe condition, action), I included
    ctrlz: _Act
    comment: str
    cells: list[str]


def _parse_action(text: str, col: int) -> _Act | str:
    """An action cell, or an error message."""
    t = text.strip()
    up = t.upper()
    if up in ("I", "S", "C"):
        return _Act(up, up, col)
    if _INT.match(t):
        return _Act("N", str(int(t)), col)
    m = _HHMM.match(t)
    if m and int(m[1]) < 24 and int(m[2]) < 60:
        return _Act("HHMM", f"{int(m[1]):02d}:{m[2]}", col)
    m = _PLUS_HHMM.match(t)
    if m and int(m[2]) < 60:
        return _Act("PLUS", f"+{int(m[1]):02d}:{m[2]}", col)
    if not t:
        return "empty action: expected I, S, C, an ADR number, HH:MM or +HH:MM"
    return (
        f"unknown action {t!r}: expected I (ignore), S (next sequence), C (next cycle), "
        "an ADR number (goto), HH:MM (sleep until) or +HH:MM (sleep for)"
    )


def _read_text(path: Path, not_found: str) -> DecodedText:
    """The file's text: UTF-8 (BOM allowed), else CP1252, what Excel writes on Windows."""
    file = str(path)
    try:
        return decode_text(path.read_bytes(), file)
    except FileNotFoundError:
        raise ConfigErrors([ConfigError(not_found, file)]) from None
    except OSError as exc:
        raise ConfigErrors([ConfigError(f"cannot read: {exc.strerror or exc}", file)]) from None
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None


def _read_rows(path: Path) -> tuple[list[_Row], list[str], str]:
    """Parse the sequence file; raise ConfigErrors listing every problem."""
    file = str(path)
    decoded = _read_text(path, "file not found")
    about = f"{decoded.encoding}, {decoded.newline_style}"
    lines = decoded.lines()
    while lines and not lines[-1].strip(" \t"):
        lines.pop()  # trailing empty lines (and a final line break)
    errors: list[ConfigError] = []
    warnings: list[str] = []

    def err(line: int, col: int, msg: str) -> None:
        errors.append(ConfigError(msg, file, line, col))

    if not lines:
        raise ConfigErrors([ConfigError("file is empty: expected a header line", file, 1, 1)])

    # --- header ------------------------------------------------------------------------------
    header = lines[0].rstrip(" \t")
    hfields = _split_fields(header)
    expected = "\t".join(COLUMNS)
    first_row = 1  # 2: the header is missing
    if _INT.match(hfields[0][0].strip()):
        err(
            1,
            1,
            "missing header line: the first line must be the column titles "
            f"({' '.join(COLUMNS)}); the Chadèche program ignores the first line, "
            "so this sequence would be lost",
        )
        first_row = 2  # still check the rows below
    elif len(hfields) < len(COLUMNS):
        missing = " ".join(COLUMNS[len(hfields) :])
        err(
            1,
            len(header) + 1,
            f"short header: {len(hfields)} of {len(COLUMNS)} columns (missing {missing}); "
            f"expected {expected!r}",
        )
    elif len(hfields) > len(COLUMNS):
        err(
            1,
            hfields[len(COLUMNS)][1],
            f"header has {len(hfields)} columns, expected {len(COLUMNS)}: {expected!r}",
        )
    else:
        odd = [
            f"{got.strip()!r} for {want}"
            for (got, _), want in zip(hfields, COLUMNS, strict=True)
            if got.strip().upper() != want.upper()
        ]
        if odd:
            warnings.append(f"{file}:1: unusual column titles ({', '.join(odd)}); read as usual")

    # --- rows --------------------------------------------------------------------------------
    rows: list[_Row] = []
    prev_adr: tuple[int, int] | None = None  # (adr, line)
    adrs: set[int] = set()
    actions: list[tuple[int, str, _Act]] = []  # (line, column title, action) for goto checks
    body = list(enumerate(lines, start=1))
    if first_row == 1:
        body = body[1:]  # else no header: line 1 is a row too, check it
    if not body:
        err(len(lines) + 1, 1, "no sequence rows after the header")
    for ln, raw in body:
        line = raw.rstrip(" \t")
        if not line.strip():
            err(ln, 1, "empty line among the sequences (the Chadèche program stops reading here)")
            continue
        fields = _split_fields(line)
        n = len(COLUMNS)
        if len(fields) < n:
            last, last_col = fields[-1]
            if len(fields) > 1 and last.lstrip().startswith("#"):
                err(
                    ln,
                    last_col,
                    f"row has {len(fields)} fields, expected {n}: the comment is in the "
                    f"{COLUMNS[len(fields) - 1]} column, so a column before it is missing",
                )
            else:
                missing = " ".join(COLUMNS[len(fields) :])
                err(
                    ln,
                    len(line) + 1,
                    f"row has {len(fields)} fields, expected {n} (missing {missing})",
                )
            continue
        if len(fields) > n and not fields[n - 1][0].lstrip().startswith("#"):
            err(ln, fields[n][1], f"row has {len(fields)} fields, expected {n}")
            continue
        cells = [f for f, _ in fields[: n - 1]] + ["\t".join(f for f, _ in fields[n - 1 :])]
        cols = [c for _, c in fields[:n]]
        bad = False

        adr_text = cells[0].strip()
        adr = -1
        if not _INT.match(adr_text):
            err(ln, cols[0], f"ADR {adr_text!r} is not a whole number")
            bad = True
        else:
            adr = int(adr_text)
            adrs.add(adr)
            if prev_adr is not None and adr <= prev_adr[0]:
                err(
                    ln,
                    cols[0],
                    f"ADR {adr} does not increase (line {prev_adr[1]} has ADR {prev_adr[0]}); "
                    "addresses must always increase",
                )
                bad = True
            else:
                prev_adr = (adr, ln)

        letter = cells[1].strip().upper()
        if letter not in ("C", "D"):
            err(
                ln,
                cols[1],
                f"unknown C/D letter {cells[1].strip()!r}: expected C (charge) or D (discharge)",
            )
            bad = True

        ma_text = cells[2].strip()
        ma = 0
        if not _INT.match(ma_text):
            err(ln, cols[2], f"mA {ma_text!r} is not a whole number of mA")
            bad = True
        else:
            ma = int(ma_text)
            if ma > _MAX_MA:
                err(ln, cols[2], f"{ma} mA is over the board's {_MAX_MA} mA maximum")
                bad = True

        sd_text = cells[3].strip()
        sd = 0
        if not _INT.match(sd_text):
            err(ln, cols[3], f"SD {sd_text!r} is not a whole number of seconds")
            bad = True
        else:
            sd = int(sd_text)

        acts: list[_Act] = []
        for k in range(4, 10):
            parsed = _parse_action(cells[k], cols[k])
            if isinstance(parsed, str):
                err(ln, cols[k], f"{COLUMNS[k]}: {parsed}")
                bad = True
            else:
                acts.append(parsed)
                actions.append((ln, COLUMNS[k], parsed))

        comment = cells[10].strip()
        if not comment.startswith("#"):
            err(ln, cols[10], f"comment {comment!r} must start with '#'")
            bad = True
        if bad:
            continue
        rows.append(
            _Row(
                line=ln,
                adr=adr,
                letter=letter,
                ma=ma,
                sd=sd,
                conditions=[(cond, acts[k - 4]) for k, cond in CONDITIONS],
                ctrlz=acts[5],
                comment=comment[1:].strip(),
                cells=[c.strip() for c in cells],
            )
        )

    # --- goto targets (any row with a whole-number ADR counts, even one with other errors) ---
    for ln, name, act in actions:
        if act.kind == "N" and int(act.value) not in adrs:
            known = ", ".join(str(a) for a in sorted(adrs)[:30])
            err(ln, act.col, f"{name}: goto to a missing ADR {act.value} (this file has: {known})")
        if act.kind == "PLUS":
            warnings.append(
                f"{file}:{ln}:{act.col}: {act.value} (sleep for) was not implemented in"
                " the Chadèche program (seed §III.D.1); here it sleeps, then goes on"
            )
    if errors:
        errors.sort(key=lambda e: (e.line or 0, e.col or 0))
        raise ConfigErrors(errors)
    return rows, warnings, about


# --------------------------------------------------------------------------------------------
# Parameters


@dataclass
class _Param:
    value: float
    source: str


def _convert(letter: str, raw: str) -> float | str:
    """The value of option ``letter``, or an error message."""
    t = raw.strip()
    if letter == "n":
        if not _INT.match(t) or int(t) < 1:
            return f"-n needs a whole number of cycles >= 1, got {t!r}"
        return float(int(t))
    try:
        v = float(t)
    except ValueError:
        return f"-{letter} needs a number, got {t!r}"
    if not math.isfinite(v):
        return f"-{letter} needs a finite number, got {t!r}"
    if letter == "p" and v <= 0:
        return f"-p (logging period) must be > 0 s, got {t!r}"
    if letter in _POSITIVE_CAL and v <= 0:
        return f"-{letter} (a calibration slope) must be > 0, got {t!r}"
    return v


def _read_prm(
    path: Path,
    params: dict[str, _Param],
    calibration: dict[str, _Param],
    warnings: list[str],
) -> None:
    file = str(path)
    decoded = _read_text(path, "parameter file not found")
    errors: list[ConfigError] = []
    ignored: list[str] = []
    not_recipe: list[str] = []
    for ln, raw in enumerate(decoded.lines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        col = len(raw) - len(raw.lstrip()) + 1
        m = re.match(r"^-(.)(.*)$", line)
        if m is None:
            errors.append(
                ConfigError(f"expected an option such as '-m 1.1', got {line!r}", file, ln, col)
            )
            continue
        letter, value = m[1], m[2].strip()
        vcol = col + 2 + (len(m[2]) - len(m[2].lstrip()))
        if letter in IGNORED_IN_PRM:
            ignored.append(f"-{letter} ({IGNORED_IN_PRM[letter]}, line {ln})")
            continue
        if letter in NOT_RECIPE:
            not_recipe.append(f"-{letter} ({NOT_RECIPE[letter]}, line {ln})")
            continue
        if letter not in OPTIONS and letter not in CALIBRATION:
            known = " ".join(f"-{k}" for k in [*OPTIONS, *CALIBRATION])
            other = " ".join(f"-{k}" for k in [*IGNORED_IN_PRM, *NOT_RECIPE])
            errors.append(
                ConfigError(
                    f"unknown option -{letter} (recipe and calibration options: {known};"
                    f" ignored: {other})",
                    file,
                    ln,
                    col,
                )
            )
            continue
        if not value:
            errors.append(ConfigError(f"-{letter} needs a value", file, ln, col))
            continue
        got = _convert(letter, value)
        if isinstance(got, str):
            errors.append(ConfigError(got, file, ln, vcol))
            continue
        target = params if letter in OPTIONS else calibration
        target[letter] = _Param(got, f"{path.name}:{ln}")
    if errors:
        raise ConfigErrors(errors)
    if ignored:
        warnings.append(
            f"{file}: {', '.join(ignored)} ignored: a parameter file cannot set them "
            "(seed §III.D.6)"
        )
    if not_recipe:
        warnings.append(f"{file}: {', '.join(not_recipe)} ignored: not a recipe matter")


def _apply_overrides(
    overrides: Mapping[str, str | float | int],
    params: dict[str, _Param],
    calibration: dict[str, _Param],
    warnings: list[str],
) -> None:
    errors: list[ConfigError] = []
    skipped: list[str] = []
    for key, raw in overrides.items():
        letter = str(key)[1:] if str(key).startswith("-") else str(key)
        if letter in IGNORED_IN_PRM or letter in NOT_RECIPE:
            what = IGNORED_IN_PRM.get(letter) or NOT_RECIPE[letter]
            skipped.append(f"-{letter} ({what})")
            continue
        if letter not in OPTIONS and letter not in CALIBRATION:
            known = " ".join(f"-{k}" for k in [*OPTIONS, *CALIBRATION])
            errors.append(ConfigError(f"unknown option {key!r} (known: {known})", "<overrides>"))
            continue
        got = _convert(letter, str(raw))
        if isinstance(got, str):
            errors.append(ConfigError(got, "<overrides>"))
            continue
        (params if letter in OPTIONS else calibration)[letter] = _Param(got, "override")
    if errors:
        raise ConfigErrors(errors)
    if skipped:
        warnings.append(f"overrides: {', '.join(skipped)} ignored: not a recipe matter")


# --------------------------------------------------------------------------------------------
# Rows → steps


def _instant_step(row: _Row, last: bool) -> tuple[str, Any, str] | None:
    """(kind, value, why) when a 0 mA row ends at its first evaluation, else None."""
    if row.ma != 0:
        return None
    acting = [(cond, act) for cond, act in row.conditions if act.kind != "I"]
    if not acting:
        if last and row.sd == 0:
            return "end_cycle", True, "last row, 0 mA, SD 0, no condition: the end of the cycle"
        return None
    cond, act = acting[0]
    if cond != "true":
        return None
    why = "0 mA and TRUE acts first, so the row ends at once whatever SD says"
    if act.kind == "N":
        return "goto", f"s{act.value}", why
    if act.kind == "C":
        return "end_cycle", True, why
    if act.kind == "HHMM":
        return "sleep_until", act.value, why
    if act.kind == "PLUS":
        hh, mm = act.value[1:].split(":")
        return "sleep", f"{int(hh) * 60 + int(mm)} min", why
    return None  # TRUE → S: an empty step; keep it as written


def _step_kind(step: Mapping[str, Any]) -> str:
    return next(k for k in STEP_KINDS if k in step)


def _step(row: _Row, last: bool, simplify: bool) -> tuple[dict[str, Any], str | None]:
    step: dict[str, Any] = {"id": f"s{row.adr}"}
    if row.comment:
        step["comment"] = row.comment
    instant = _instant_step(row, last) if simplify else None
    if instant is not None:
        kind, value, why = instant
        step[kind] = value
    else:
        why = None
        if row.ma == 0:
            step["rest"] = True
        else:
            step["charge" if row.letter == "C" else "discharge"] = f"{row.ma} mA"
        step["duration"] = f"{row.sd} s"
        until = [{cond: act.recipe_action()} for cond, act in row.conditions if act.kind != "I"]
        if until:
            step["until"] = until
    step["advance"] = False if row.ctrlz.kind == "I" else row.ctrlz.recipe_action()
    return step, why


# --------------------------------------------------------------------------------------------
# Writing


def _recipe_name(path: Path, name: str | None) -> str:
    if name is not None:
        if not re.match(ID_PATTERN, name):
            raise ValueError(f"recipe name {name!r} must match {ID_PATTERN}")
        return name
    stem = re.sub(r"[^A-Za-z0-9_\-]+", "-", path.stem).strip("-") or "imported"
    if not re.match(r"^[A-Za-z_]", stem):
        stem = f"chadeche-{stem}"
    return stem


def _emit(
    recipe: dict[str, Any],
    header: list[str],
    param_notes: dict[str, str],
    step_notes: list[list[str]],
) -> tuple[str, list[tuple[int, int]]]:
    """Recipe YAML text and, per step, the (first, last) line it spans."""
    out: list[str] = [f"# {yaml_comment(h)}".rstrip() for h in header]

    def put(text: str, note: str | None = None) -> None:
        out.append(f"{text:<24}  # {yaml_comment(note)}" if note else text)

    put(f"recipe: {yaml_scalar(recipe['recipe'])}")
    put(f"description: {yaml_scalar(recipe['description'])}")
    put("parameters:")
    for pname, value in recipe["parameters"].items():
        put(f"  {pname}: {yaml_scalar(value)}", param_notes.get(pname))
    put(f"initial_charge: {recipe['initial_charge']}")
    put(f"cycles: {recipe['cycles']}", param_notes.get("cycles"))
    put("logging:")
    put(f"  period: {yaml_scalar(recipe['logging']['period'])}", param_notes.get("logging.period"))
    put("steps:")
    spans: list[tuple[int, int]] = []
    for step, notes in zip(recipe["steps"], step_notes, strict=True):
        for note in notes:
            put(f"  # {yaml_comment(note)}")
        first = len(out) + 1
        lead = "  - "
        for key, value in step.items():
            if key == "until":
                put(f"    {key}:")
                for item in value:
                    ((cond, act),) = item.items()
                    put(f"      - {yaml_scalar(cond, key=True)}: {yaml_scalar(act)}")
            else:
                put(f"{lead}{key}: {yaml_scalar(value)}")
            lead = "    "
        spans.append((first, len(out)))
    return "\n".join(out) + "\n", spans


def _check_compiles(
    text: str,
    spans: list[tuple[int, int]],
    rows: list[_Row],
    source: str,
) -> None:
    """Load and compile the produced recipe; a refusal is reported at the source row."""
    where = "<imported recipe>"
    try:
        recipe, pos = load_recipe_text(text, where)
        compile_recipe(recipe, pos, where, Target())
    except ConfigErrors as exc:
        mapped: list[ConfigError] = []
        for e in exc.errors:
            line = None
            for (first, last), row in zip(spans, rows, strict=True):
                if e.line is not None and first <= e.line <= last:
                    line = row.line
            mapped.append(
                ConfigError(f"the imported recipe is refused: {e.message}", source, line, 1)
            )
        raise ConfigErrors(mapped) from None


def import_chadeche(
    config_path: str | Path,
    prm_path: str | Path | None = None,
    *,
    name: str | None = None,
    overrides: Mapping[str, str | float | int] | None = None,
    simplify: bool = True,
) -> ImportResult:
    """Translate a Chadèche sequence file (+ optional ``chadecheN.prm``) into a recipe.

    ``overrides`` are command-line options by letter (``{"-m": 1.1, "-i": 1300}``, the
    dash is optional); they win over the parameter file, which wins over the defaults.
    Raises ConfigErrors (every problem, each with file, line and column) for a broken file.
    """
    path = Path(config_path)
    rows, warnings, about = _read_rows(path)

    params = {k: _Param(o.default, o.source) for k, o in OPTIONS.items()}
    calibration: dict[str, _Param] = {}
    if prm_path is not None:
        _read_prm(Path(prm_path), params, calibration, warnings)
    if overrides:
        _apply_overrides(overrides, params, calibration, warnings)

    for r in rows:
        first = next(((c, a) for c, a in r.conditions if a.kind != "I"), None)
        if r.ma and first is not None and first[0] == "true":
            warnings.append(
                f"{path}:{r.line}: TRUE acts at once, so the {r.ma} mA of ADR {r.adr} "
                "flow for one scan at most"
            )

    recipe_params: dict[str, str] = {}
    notes: dict[str, str] = {}
    for letter, opt in OPTIONS.items():
        p = params[letter]
        notes[opt.target] = f"-{letter}: {p.source}"
        if opt.target in ("cycles", "logging.period"):
            continue
        recipe_params[opt.target] = f"{_num(p.value)} {opt.unit}"
    recipe: dict[str, Any] = {
        "recipe": _recipe_name(path, name),
        "description": f"Imported from the Chadèche sequence file {path.name}",
        "parameters": recipe_params,
        "initial_charge": "q_init",
        "cycles": int(params["n"].value),
        "logging": {"period": f"{_num(params['p'].value)} s"},
    }
    steps: list[dict[str, Any]] = []
    step_notes: list[list[str]] = []
    for k, row in enumerate(rows):
        step, why = _step(row, k == len(rows) - 1, simplify)
        steps.append(step)
        note = [f"line {row.line}: " + "  ".join(row.cells)]
        if why:
            note.append(f"  → {_step_kind(step)}: {why}")
        step_notes.append(note)
    recipe["steps"] = steps

    assumed = [
        f"-{o.letter} {_num(o.default)}{(' ' + o.unit) if o.unit else ''}"
        for o in OPTIONS.values()
        if o.assumed and params[o.letter].source == o.source
    ]
    header = [
        "Imported by supervisor.importers.chadeche from a Chadèche sequence file (seed 000",
        "§III.D); edit freely, the source is not read again.",
        f"source: {path} ({about}, {len(rows)} rows)",
        f"parameters: {prm_path if prm_path is not None else 'no .prm file'}"
        + (", with overrides" if overrides else ""),
        "Row ADR → step s<ADR>; TL TH LmAh HmAh TRUE → until (column order, first true acts);",
        "CTRLZ → advance; each source row is repeated above its step.",
    ]
    if assumed:
        header.append(f"Assumed defaults (the seed does not state them): {', '.join(assumed)}.")
    header.append("A sequence file has no safety limits: add `limits:` (voltage, temperature).")
    text, spans = _emit(recipe, header, notes, step_notes)
    _check_compiles(text, spans, rows, str(path))

    cal: dict[str, float] | None = None
    snippet: str | None = None
    if calibration:
        cal = {}
        lines = ["# Chadèche board calibration (seed §III.F); paste under the board's calibration:"]
        for letter, (key, what) in CALIBRATION.items():
            if letter in calibration:
                cal[key] = calibration[letter].value
                source = calibration[letter].source
                lines.append(
                    f"{key + ':':<19} {yaml_float(cal[key]):<8}  # -{letter}: {what} ({source})"
                )
        snippet = "\n".join(lines) + "\n"
    return ImportResult(text, recipe, cal, snippet, warnings)
