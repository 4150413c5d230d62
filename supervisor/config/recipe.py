"""Validated model of a recipe file (``recipes/*.yaml``): a step chain in YAML.

This layer checks the *shape* (keys, kinds, units of literals); the compiler in
``supervisor.chains`` checks meaning (goto targets, expressions, loops) and turns it
into something executable. Current sign follows BDF: positive charges the cell.

Types are strict, as in the I/O map models: a YAML boolean is not a number nor a
quantity, numbers are finite, and a non-zero number too small for a float (``1e-400 A``,
which Python reads as 0) is refused rather than taken as zero.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)

from supervisor.config.limits import (
    MAX_CYCLES,
    MAX_PROFILE_REPEAT,
    MAX_PROFILE_ROWS,
    MAX_RECIPE_GROUPS,
    MAX_RECIPE_STEPS,
    TooLarge,
)
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.core.units import Dim, Quantity, UnitError, parse_quantity

if TYPE_CHECKING:
    from supervisor.config.yamlpos import Positions

ID_PATTERN = r"^[A-Za-z_][A-Za-z0-9_\-]*$"
# ASCII digits only: ``\d`` would take any Unicode digit (``٠٨:٠٠``) as a time of day.
HHMM = re.compile(r"^([01]?[0-9]|2[0-3]):([0-5][0-9])$")
STEP_KINDS = (
    "rest",
    "charge",
    "discharge",
    "cv",
    "cccv",
    "power",
    "pulse",
    "profile",
    "sleep",
    "sleep_until",
    "goto",
    "end_cycle",
    "end",
)

_NONZERO_MANTISSA = re.compile(r"^\s*[-+]?0*\.?0*[1-9]")


def _quantity_input(v: Any) -> Any:
    """What a quantity may be written as: a text (``"4.2 V"``) or a finite number, never a
    boolean (one message, not one per member of the union)."""
    if isinstance(v, bool):
        raise ValueError("expected a quantity (e.g. '4.2 V', '300 mA'), not a boolean")
    if isinstance(v, float) and not math.isfinite(v):
        raise ValueError("expected a quantity, not an infinite or NaN number")
    return v


Q = Annotated[str | float | int, BeforeValidator(_quantity_input)]
"""A quantity as written: "4.2 V", "300 mA", "0.5 C"."""


def quantity(v: str | float | int, dims: Dim | tuple[Dim, ...] | None = None) -> Quantity:
    """``parse_quantity``, refusing a non-zero literal that underflows to 0 (``1e-400 A``)."""
    q = parse_quantity(v, dims)
    if q.value == 0.0 and isinstance(v, str) and _NONZERO_MANTISSA.match(v):
        raise UnitError(f"{v!r} is too small to be told from zero: write 0 or a larger value")
    return q


PARAMETER_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
"""A step's current given as a parameter's name (``discharge: i_discharge``), not a value."""


def _q(v: Q | None, *dims: Dim) -> Q | None:
    if v is None:
        return None
    try:
        quantity(v, dims)
    except UnitError as exc:
        raise ValueError(str(exc)) from None
    return v


def _q_or_name(v: Q | None, *dims: Dim) -> Q | None:
    """A quantity, or a parameter's name (``voltage: v_charge``) the compiler resolves."""
    if isinstance(v, str) and PARAMETER_NAME.match(v.strip()):
        return v
    return _q(v, *dims)


def _q_nonnegative(v: Q | None, *dims: Dim, what: str = "a duration") -> Q | None:
    q = _q(v, *dims)
    if v is not None and parse_quantity(v).value < 0:
        raise ValueError(f"{v!r}: {what} cannot be negative")
    return q


def _q_positive(v: Q | None, *dims: Dim, what: str) -> Q | None:
    q = _q(v, *dims)
    if v is not None and parse_quantity(v).value <= 0:
        raise ValueError(f"{what} must be greater than zero")
    return q


def _text(x: Any) -> Any:
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, int | float):
        return str(x)
    return x


PROFILE_WINDOWS = (("v_min", "v_max", "V"), ("i_min", "i_max", "A"), ("t_min", "t_max", "degC"))
"""A profile row's windows after its current (seed 002 §2.3), in their CSV column order."""


def profile_window_problem(k: int, low: float | None, high: float | None) -> str | None:
    """What is wrong with window ``k`` of ``PROFILE_WINDOWS`` given as ``low``, ``high``: a
    window written high first holds nothing (found by the mutation corpus)."""
    if low is None or high is None or low < high:
        return None
    lo_name, hi_name, unit = PROFILE_WINDOWS[k]
    return f"{lo_name} {low:g} {unit} is not below {hi_name} {high:g} {unit}"


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


def _list_as_tuple(v: Any) -> Any:
    # YAML has lists, no tuples; strict mode takes a tuple only.
    return tuple(v) if isinstance(v, list) else v


Window = Annotated[tuple[Q | None, Q | None], BeforeValidator(_list_as_tuple)]


class LogSettings(Strict):
    """When to record a result line: every Δt, ΔV or ΔI (and always at a step change)."""

    period: Q | None = None
    delta_v: Q | None = None
    delta_i: Q | None = None

    # Zero or negative would record a line at every scan (or never mean anything).
    @field_validator("period")
    @classmethod
    def _p(cls, v: Q | None) -> Q | None:
        return _q_positive(v, Dim.TIME, what="a logging period")

    @field_validator("delta_v")
    @classmethod
    def _dv(cls, v: Q | None) -> Q | None:
        return _q_positive(v, Dim.VOLTAGE, what="a logging delta")

    @field_validator("delta_i")
    @classmethod
    def _di(cls, v: Q | None) -> Q | None:
        return _q_positive(v, Dim.CURRENT, what="a logging delta")


class Supervision(Strict):
    """S7-GRAPH supervision: exceeding ``max_time`` or meeting ``error`` halts the chain
    with a latched alarm until acknowledged."""

    max_time: Q | None = None
    error: str | None = None

    @field_validator("max_time")
    @classmethod
    def _t(cls, v: Q | None) -> Q | None:
        return _q_positive(v, Dim.TIME, what="a supervision time")


class CvSpec(Strict):
    voltage: Q
    current_limit: Q

    @field_validator("voltage")
    @classmethod
    def _v(cls, v: Q) -> Q | None:
        return _q_or_name(v, Dim.VOLTAGE)

    @field_validator("current_limit")
    @classmethod
    def _i(cls, v: Q) -> Q | None:
        return _q_or_name(v, Dim.CURRENT, Dim.C_RATE)


class CccvSpec(Strict):
    current: Q
    voltage: Q

    @field_validator("voltage")
    @classmethod
    def _v(cls, v: Q) -> Q | None:
        return _q_or_name(v, Dim.VOLTAGE)

    @field_validator("current")
    @classmethod
    def _i(cls, v: Q) -> Q | None:
        return _q_or_name(v, Dim.CURRENT, Dim.C_RATE)


class PulseSpec(Strict):
    """Pulse / DC internal resistance: ``count`` pulses of ``current`` for ``on_time``, then
    rest for ``off_time`` (not ``on``/``off``: YAML reads those words as booleans)."""

    current: Q
    on_time: Q
    off_time: Q
    count: int = Field(1, ge=1, le=100_000)

    @field_validator("current")
    @classmethod
    def _i(cls, v: Q) -> Q | None:
        return _q(v, Dim.CURRENT, Dim.C_RATE)

    @field_validator("on_time")
    @classmethod
    def _on(cls, v: Q) -> Q | None:
        return _q_positive(v, Dim.TIME, what="a pulse's on_time")

    @field_validator("off_time")
    @classmethod
    def _off(cls, v: Q) -> Q | None:
        return _q_nonnegative(v, Dim.TIME, what="a pulse's off_time")


class ProfileRow(Strict):
    """One row of a load profile (seed 002 §2.3): time, current, per-row V/I/T window."""

    t: float = Field(ge=0, description="seconds from the step start")
    current: float = Field(description="A, + charges")
    v_min: float | None = None
    v_max: float | None = None
    i_min: float | None = None
    i_max: float | None = None
    t_min: float | None = None
    t_max: float | None = None

    @model_validator(mode="after")
    def _windows(self) -> ProfileRow:
        pairs = ((self.v_min, self.v_max), (self.i_min, self.i_max), (self.t_min, self.t_max))
        for k, (low, high) in enumerate(pairs):
            problem = profile_window_problem(k, low, high)
            if problem:
                raise ValueError(problem)
        return self


class ProfileSpec(Strict):
    file: str | None = Field(None, description="CSV relative to the recipe file")
    rows: list[ProfileRow] | None = None
    repeat: int = Field(1, ge=1, json_schema_extra={"maximum": MAX_PROFILE_REPEAT})

    @field_validator("repeat")
    @classmethod
    def _repeat(cls, v: int) -> int:
        if v > MAX_PROFILE_REPEAT:
            # A count of 400 digits is said by its size, not written out in full (and
            # without str(): it refuses more than 4300 digits).
            shown = (
                f"{v:,}" if v < 10**24 else f"more than 10^{int((v.bit_length() - 1) * 0.30103)}"
            )
            raise ValueError(
                f"{shown} is too many; a profile may repeat at most"
                f" {MAX_PROFILE_REPEAT:,} times (README: Input limits)"
            )
        return v

    @field_validator("file")
    @classmethod
    def _file(cls, v: str | None) -> str | None:
        # A NUL cannot be in a path: open() raised ValueError, a traceback (issue 28).
        if v is not None and "\0" in v:
            raise ValueError("a file name cannot hold a NUL character ('\\0')")
        return v

    @model_validator(mode="after")
    def _one(self) -> ProfileSpec:
        if (self.file is None) == (self.rows is None):
            raise ValueError("a profile needs exactly one of 'file' or 'rows'")
        if self.rows is not None:
            ts = [r.t for r in self.rows]
            if not ts or ts != sorted(ts) or len(set(ts)) != len(ts):
                raise ValueError("profile rows need strictly increasing times")
        return self


class Step(Strict):
    id: str = Field(pattern=ID_PATTERN)
    comment: str = ""
    # The step kind: exactly one of these.
    rest: Q | bool | None = None
    charge: Q | None = None
    discharge: Q | None = None
    cv: CvSpec | None = None
    cccv: CccvSpec | None = None
    power: Q | None = None
    pulse: PulseSpec | None = None
    profile: ProfileSpec | None = None
    sleep: Q | None = None
    sleep_until: str | None = None
    goto: str | None = None
    end_cycle: bool | None = None
    end: bool | None = None
    # Common settings.
    duration: Q | None = None
    until: list[dict[str, str]] = []
    advance: str | bool = Field(
        "next", description="what the operator's advance does here (false: refused)"
    )
    interlock: str | None = None
    supervision: Supervision | None = None
    log: LogSettings | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> Step:
        kinds = [k for k in STEP_KINDS if getattr(self, k) is not None]
        if len(kinds) != 1:
            have = ", ".join(kinds) if kinds else "none"
            raise ValueError(
                f"step {self.id!r} needs exactly one kind among {', '.join(STEP_KINDS)}"
                f" (has: {have})"
            )
        return self

    @property
    def kind(self) -> str:
        return next(k for k in STEP_KINDS if getattr(self, k) is not None)

    @field_validator("charge", "discharge")
    @classmethod
    def _current(cls, v: Q | None) -> Q | None:
        if isinstance(v, str) and PARAMETER_NAME.match(v.strip()):
            return v  # a parameter's name: the compiler resolves it (and says if unknown)
        q = _q(v, Dim.CURRENT, Dim.C_RATE)
        if v is not None and parse_quantity(v).value < 0:
            raise ValueError("give a positive magnitude; the step kind says the direction")
        return q

    @field_validator("rest")
    @classmethod
    def _rest(cls, v: Q | bool | None) -> Q | bool | None:
        if isinstance(v, bool):
            if not v:
                raise ValueError("rest: false is not a step; remove the step")
            return v
        return _q_nonnegative(v, Dim.TIME)

    @field_validator("power")
    @classmethod
    def _power(cls, v: Q | None) -> Q | None:
        return _q(v, Dim.POWER)

    @field_validator("sleep", "duration")
    @classmethod
    def _time(cls, v: Q | None) -> Q | None:
        return _q_nonnegative(v, Dim.TIME)

    @field_validator("sleep_until")
    @classmethod
    def _hhmm(cls, v: str | None) -> str | None:
        # fullmatch: ``$`` also matches before a trailing newline ("08:00\n").
        if v is not None and not HHMM.fullmatch(str(v)):
            raise ValueError(f"sleep_until needs a time of day HH:MM, got {v!r}")
        return v

    @field_validator("end_cycle", "end")
    @classmethod
    def _true(cls, v: bool | None) -> bool | None:
        if v is False:
            raise ValueError("write 'true' or remove the key")
        return v

    @field_validator("until", mode="before")
    @classmethod
    def _until_text(cls, v: Any) -> Any:
        # YAML reads `true: end` with a boolean key; conditions and actions are text.
        if isinstance(v, list):
            return [
                {_text(k): _text(a) for k, a in item.items()} if isinstance(item, dict) else item
                for item in v
            ]
        return v

    @field_validator("until")
    @classmethod
    def _until(cls, v: list[dict[str, str]]) -> list[dict[str, str]]:
        for item in v:
            if len(item) != 1:
                raise ValueError("each 'until' entry is one 'condition: action' pair")
        return v


class Group(Strict):
    """Steps sharing a time limit or conditions (limits across several steps)."""

    id: str = Field(pattern=ID_PATTERN)
    steps: list[str] = Field(min_length=1)
    duration: Q | None = None
    until: list[dict[str, str]] = []

    @field_validator("duration")
    @classmethod
    def _time(cls, v: Q | None) -> Q | None:
        return _q_nonnegative(v, Dim.TIME)

    _until_text = field_validator("until", mode="before")(Step._until_text.__func__)  # type: ignore[attr-defined]
    # One pair per entry, as for a step (`until: [{}]` was a traceback in the compiler).
    _until = field_validator("until")(Step._until.__func__)  # type: ignore[attr-defined]


class Limits(Strict):
    """Recipe-level limits (a crossing holds the chain with an alarm)."""

    voltage: Window | None = None
    current: Window | None = None
    temperature: Window | None = None
    delay: Q | None = Field(None, description="a crossing must last this long to hold (trip delay)")

    @field_validator("delay")
    @classmethod
    def _delay(cls, v: Q | None) -> Any:
        return _q_nonnegative(v, Dim.TIME, what="a trip delay")

    @field_validator("voltage")
    @classmethod
    def _v(cls, v: tuple[Q | None, Q | None] | None) -> Any:
        return v and tuple(_q(x, Dim.VOLTAGE) for x in v)

    @field_validator("current")
    @classmethod
    def _i(cls, v: tuple[Q | None, Q | None] | None) -> Any:
        return v and tuple(_q(x, Dim.CURRENT, Dim.C_RATE) for x in v)

    @field_validator("temperature")
    @classmethod
    def _t(cls, v: tuple[Q | None, Q | None] | None) -> Any:
        return v and tuple(_q(x, Dim.TEMPERATURE) for x in v)


class Recipe(Strict):
    recipe: str = Field(pattern=ID_PATTERN, description="Recipe name")
    description: str = ""
    chemistry: str | None = None
    capacity: Q | None = Field(None, description="rated capacity, for C-rates and progress")
    parameters: dict[str, Q] = {}
    initial_charge: Q | None = Field(None, description="charge the Ah counter starts from")
    limits: Limits = Limits()
    # The bound is checked before the model (check_sizes: a message naming the limit) and
    # again by _cycles for data validated directly; the schema keeps it for editors.
    cycles: int = Field(1, ge=1, json_schema_extra={"maximum": MAX_CYCLES})
    logging: LogSettings = LogSettings(period="120 s")
    groups: list[Group] = []
    steps: list[Step] = Field(min_length=1)

    @field_validator("cycles")
    @classmethod
    def _cycles(cls, v: int) -> int:
        if v > MAX_CYCLES:
            raise ValueError(
                f"{v:,} is too many cycles; a recipe may run at most {MAX_CYCLES:,}"
                " (README: Input limits)"
            )
        return v

    @field_validator("capacity")
    @classmethod
    def _cap(cls, v: Q | None) -> Q | None:
        # C-rates resolve against it: a negative capacity made a 0.5 C charge a discharge.
        return _q_positive(v, Dim.CHARGE, what="a rated capacity")

    @field_validator("parameters")
    @classmethod
    def _params(cls, v: dict[str, Q]) -> dict[str, Q]:
        for name, val in v.items():
            # fullmatch: ``$`` also matches before a trailing newline, and a name with
            # one splits the log lines that show it.
            if not PARAMETER_NAME.fullmatch(name):
                raise ValueError(f"parameter name {name!r} must be an identifier")
            try:
                quantity(val)
            except UnitError as exc:
                raise ValueError(f"parameter {name}: {exc}") from None
        return v


def load_recipe(path: str | Path) -> tuple[Recipe, Positions]:
    """Load a recipe file; shape errors as ConfigErrors with file:line:col."""
    from supervisor.config.yamlpos import load_yaml

    try:
        data, pos = load_yaml(path)
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    return recipe_of(data, pos, str(path)), pos


def recipe_of(data: object, pos: Positions, file: str) -> Recipe:
    """The recipe of a YAML document already parsed (``load_yaml``'s data and positions):
    what :func:`load_recipe` checks, without reading and parsing the file again (``supervisor
    check`` parses a file once to tell a recipe from an I/O map)."""
    from supervisor.config.yamlpos import validate

    check_sizes(data, pos, file)
    return validate(Recipe, data, pos, file)


def load_recipe_text(text: str, file: str = "<recipe>") -> tuple[Recipe, Positions]:
    from supervisor.config.yamlpos import load_yaml_text, validate

    try:
        data, pos = load_yaml_text(text, file)
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    check_sizes(data, pos, file)
    return validate(Recipe, data, pos, file), pos


def check_sizes(data: object, pos: Positions, file: str) -> None:
    """Cycles, steps, groups and each profile's inline rows within their limits (README:
    Input limits), counted once YAML aliases are expanded and before the model validates
    them all: refused at the first one over the limit."""
    if not isinstance(data, dict):
        return  # the model says what it expected
    cycles = data.get("cycles")
    if isinstance(cycles, int) and not isinstance(cycles, bool) and cycles > MAX_CYCLES:
        mark = pos.value(("cycles",)) or pos.nearest(("cycles",))
        message = (
            f"cycles: {cycles:,} is too many; a recipe may run at most {MAX_CYCLES:,} cycles"
            " (README: Input limits)"
        )
        raise ConfigErrors([TooLarge(message, file, mark.line, mark.col)])
    for key, limit in (("steps", MAX_RECIPE_STEPS), ("groups", MAX_RECIPE_GROUPS)):
        items = data.get(key)
        if isinstance(items, list) and len(items) > limit:
            raise _too_many(pos, file, (key, limit), f"{key}: {len(items):,}", "a recipe", limit)
    steps = data.get("steps")
    for i, step in enumerate(steps if isinstance(steps, list) else ()):
        profile = step.get("profile") if isinstance(step, dict) else None
        rows = profile.get("rows") if isinstance(profile, dict) else None
        if isinstance(rows, list) and len(rows) > MAX_PROFILE_ROWS:
            where = ("steps", i, "profile", "rows", MAX_PROFILE_ROWS)
            what = f"profile rows: {len(rows):,}"
            raise _too_many(pos, file, where, what, "a profile", MAX_PROFILE_ROWS)


def _too_many(
    pos: Positions, file: str, where: tuple[str | int, ...], what: str, of: str, limit: int
) -> ConfigErrors:
    mark = pos.value(where) or pos.nearest(where)
    message = f"too many {what}; {of} may have at most {limit:,} (README: Input limits)"
    return ConfigErrors([TooLarge(message, file, mark.line, mark.col)])
