"""Recipe (validated YAML) → Program (executable): meaning checked before anything starts.

Every error names file:line:column: goto targets that do not exist, unknown actions,
expressions that do not type-check (``voltage >= 300 mA``), unknown parameters, loops
that never let time pass, steps that can never end, steps the channel's hardware
cannot do (CV on a Chadèche board), and values that do not fit the channel's hard limits
(a one-cell recipe on a pack channel): the recipe's ``limits:`` windows, every voltage
setpoint and every current a step asks for.
"""

from __future__ import annotations

import difflib
import re
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

from supervisor.chains.behaviours import MIN_POWER_VOLTAGE_V
from supervisor.chains.expr import (
    FUNCTIONS,
    KEYWORDS,
    Expr,
    ExprError,
    Signature,
    compile_condition,
)
from supervisor.chains.kinds import kind_names, kind_of
from supervisor.chains.profile_csv import read_profile_csv
from supervisor.chains.program import (
    Action,
    ActionKind,
    CompiledGroup,
    CompiledStep,
    Limits,
    LogRule,
    ProfilePoint,
    Program,
    Transition,
)
from supervisor.chains.zerotime import describe, zero_time_loops
from supervisor.config.limits import MAX_INITIAL_CHARGE_AH
from supervisor.config.recipe import HHMM, PARAMETER_NAME, LogSettings, ProfileSpec, Recipe, Step
from supervisor.config.yamlpos import Positions
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.core.units import Dim, Quantity, UnitError, parse_quantity

_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")
"""C0 and C1 control characters (a newline among them): never in an action."""

# What a step chain can read, besides parameters and bench tags (all in base units).
CHANNEL_VARIABLES: dict[str, Dim] = {
    "voltage": Dim.VOLTAGE,
    "current": Dim.CURRENT,
    "temperature": Dim.TEMPERATURE,
    "power": Dim.POWER,
    "charge": Dim.CHARGE,
    "energy": Dim.ENERGY,
    "step_charge": Dim.CHARGE,
    "step_energy": Dim.ENERGY,
    "step_time": Dim.TIME,
    "cycle_time": Dim.TIME,
    "test_time": Dim.TIME,
    "cycle": Dim.NONE,
    "dv_dt": Dim.VOLTAGE_RATE,
    "delta_peak": Dim.VOLTAGE,
    "peak_voltage": Dim.VOLTAGE,
}

# The names a parameter may not take, by kind: the one table both the refusal and its
# message read. A parameter named ``voltage`` replaced the measurement in every condition
# (issue 28: ``until: voltage <= 1.1 V`` never fired and the dry run drove the cell into
# reversal); one named ``abs`` or ``and`` cannot be read at all.
COUNTERS: frozenset[str] = frozenset(
    {"charge", "energy", "step_charge", "step_energy", "cycle", "step_time", "cycle_time"}
    | {"test_time"}
)
RESERVED_NAMES: dict[str, tuple[str, ...]] = {
    "measurement": tuple(n for n in CHANNEL_VARIABLES if n not in COUNTERS),
    "counter": tuple(n for n in CHANNEL_VARIABLES if n in COUNTERS),
    "function": FUNCTIONS,
    "word": tuple(sorted(KEYWORDS)),  # a word of the expressions
}


def reserved_kind(name: str) -> str | None:
    """``"measurement"``, ``"counter"``, ``"function"``, ``"word"``, or None: free."""
    return next((kind for kind, names in RESERVED_NAMES.items() if name in names), None)


def reserved_names_text() -> str:
    """``measurements: voltage, current, ...; counters: ...; functions: ...; words: ...``."""
    return "; ".join(f"{kind}s: {', '.join(names)}" for kind, names in RESERVED_NAMES.items())


# Step kinds each source can execute (CP is regulated in software from V·I): the kinds
# registry says which need a constant voltage.
CC_ONLY = kind_names(cv=False)
WITH_CV = kind_names()

LIMIT_EPS: Final = 1e-12
"""A value equal to a limit up to float noise is within it."""

SCALE_MISMATCH_RATIO: Final = 1.25
"""A voltage beyond a channel's limit by more than this factor of the limit is not a tuning
slip but another scale (4.2 V on a 12–16.8 V four-cell pack): say so in the refusal."""

OTHER_CELL_HINT: Final = "a recipe for another cell or cell count?"

Window = tuple[float | None, float | None]


@dataclass
class Target:
    """What the recipe will run on (None fields: unknown, e.g. in ``supervisor check``)."""

    channel: str | None = None
    capabilities: frozenset[str] = WITH_CV
    no_cv_reason: str = "its source drives a constant current only (no voltage regulation)"
    capacity_ah: float | None = None
    current_limits_a: tuple[float, float] | None = None
    voltage_limits_v: tuple[float, float] | None = None
    temperature_limits_c: Window | None = None
    """The channel's hard limits (None: unknown, nothing checked); a None bound: open."""
    tags: Mapping[str, Dim] = field(default_factory=dict)
    scan_period_s: float | None = None
    """The scan period of the bench it runs on (None: unknown, pulse times not checked)."""


def compile_recipe(
    recipe: Recipe,
    pos: Positions,
    file: str,
    target: Target | None = None,
    overrides: Mapping[str, str] | None = None,
    files: FilePolicy | None = None,
) -> Program:
    """``files``: asked about every other file the recipe reads (a load profile's CSV)
    before it is opened (the recipe folders' path policy, ADR 0026); None: any file."""
    return _Compiler(recipe, pos, file, target or Target(), overrides or {}, files).run()


FilePolicy = Callable[[Path], "str | None"]
"""Why a file may not be read (the reason, naming what may), or None when it may."""


class _Compiler:
    def __init__(
        self,
        recipe: Recipe,
        pos: Positions,
        file: str,
        target: Target,
        overrides: Mapping[str, str],
        files: FilePolicy | None = None,
    ) -> None:
        self.r = recipe
        self.files = files
        self.pos = pos
        self.file = file
        self.target = target
        self.overrides = overrides
        self.errors: list[ConfigError] = []
        self.ids = {s.id: i for i, s in enumerate(recipe.steps)}
        # The parameters something reads (a condition, a setpoint, initial_charge): one
        # declared and read by nothing is warned of (issue 26, finding 6: capacity-test's
        # i_discharge was given on the command line and changed nothing).
        self.used: set[str] = set()
        # Where a bare action word names a step too ("end" with a step 'end'): the word is
        # the action, which its author may not have meant (warned, not refused).
        self.shadowed: list[tuple[tuple[str | int, ...], str]] = []
        # Each distinct condition text compiled once against this recipe's signature (the
        # same for every step): an anchored condition used as the `until` of N steps is
        # tokenised once, not N times (issue 28: 100 uses of a 100 kB condition took a
        # minute). An error is kept too and reported at every use site, each its own place.
        self._conditions: dict[str, Expr | ExprError] = {}

    # --- errors --------------------------------------------------------------------
    def err(
        self, path: tuple[str | int, ...], msg: str, at_key: bool = False, offset: int = 0
    ) -> None:
        m = (self.pos.key(path) if at_key else None) or self.pos.value(path)
        m = m or self.pos.nearest(path)
        self.errors.append(ConfigError(msg, self.file, m.line, m.col + offset))

    def q(self, v: object, path: tuple[str | int, ...], *dims: Dim) -> Quantity | None:
        if v is None:
            return None
        try:
            return parse_quantity(v if isinstance(v, str | int | float) else str(v), dims or None)
        except UnitError as exc:
            self.err(path, str(exc))
            return None

    # --- whole recipe ----------------------------------------------------------------
    def run(self) -> Program:
        r = self.r
        cap = self.target.capacity_ah
        cq = self.q(r.capacity, ("capacity",), Dim.CHARGE)
        if cq is not None:
            cap = cq.value  # the recipe's rated capacity wins over the channel's
        self.capacity_ah = cap
        params = self._parameters()
        names = dict(CHANNEL_VARIABLES)
        names.update(self.target.tags)
        names.update({k: d for k, (_, d) in params.items()})
        self.sig = Signature(names=names, capacity_ah=cap)
        self.params = params
        # Counted once (was a scan of the steps before each: seconds for 10 000 steps).
        dupes = {k for k, n in Counter(s.id for s in r.steps).items() if n > 1}
        for i, s in enumerate(r.steps):
            if s.id in dupes and self.ids[s.id] != i:
                self.err(("steps", i, "id"), f"duplicate step id {s.id!r}")
        group_of: dict[int, list[int]] = {}
        groups = tuple(self._group(gi, g, group_of) for gi, g in enumerate(r.groups))
        steps = tuple(self._step(i, s, tuple(group_of.get(i, ()))) for i, s in enumerate(r.steps))
        self._check_termination(steps, groups)
        init: Quantity | None = None
        if isinstance(r.initial_charge, str) and r.initial_charge in params:
            self.used.add(r.initial_charge)
            init = Quantity(*params[r.initial_charge])
            if init.dim is not Dim.CHARGE:
                self.err(("initial_charge",), f"parameter {r.initial_charge!r} is not a charge")
        else:
            init = self.q(r.initial_charge, ("initial_charge",), Dim.CHARGE)
        if init is not None and abs(init.value) > MAX_INITIAL_CHARGE_AH:  # README: Input limits
            self.err(
                ("initial_charge",),
                f"initial_charge {init.value:g} Ah is too large; a recipe may start from at"
                f" most {MAX_INITIAL_CHARGE_AH:,g} Ah either way (README: Input limits)",
            )
        limits = Limits(
            self._pair(r.limits.voltage, ("limits", "voltage"), Dim.VOLTAGE),
            self._pair(r.limits.current, ("limits", "current"), Dim.CURRENT, Dim.C_RATE),
            self._pair(r.limits.temperature, ("limits", "temperature"), Dim.TEMPERATURE),
            self._time(r.limits.delay, ("limits", "delay")) or 0.0,
        )
        self._check_windows(limits)
        warnings = self._warnings(r)
        if self.errors:
            self.errors.sort(key=lambda e: (e.line or 0, e.col or 0))
            raise ConfigErrors(self.errors)
        return Program(
            name=r.recipe,
            file=self.file,
            steps=steps,
            groups=groups,
            cycles=r.cycles,
            limits=limits,
            parameters={k: v for k, (v, _) in params.items()},
            capacity_ah=cap,
            initial_charge_ah=init.value if init is not None else 0.0,
            log=self._log(r.logging, ("logging",)) or LogRule(period_s=120.0),
            description=r.description,
            warnings=tuple(warnings),
        )

    def _check_parameter_name(self, name: str) -> None:
        """A parameter may not take the name of a measurement, a counter, a function, a
        word of the expressions or a bench tag: it would hide it (or never be read)."""
        kind = reserved_kind(name)
        if kind is None and name in self.target.tags:
            kind = "bench tag"
        if kind is None:
            return
        why = (
            f"an expression could not read it (it would read the {kind})"
            if kind in ("function", "word")
            else f"the conditions would read it instead of the {kind} {name!r}"
        )
        self.err(
            ("parameters", name),
            f"parameter {name!r} takes the name of a {kind}: {why}; rename it"
            f" (e.g. '{name}_set'). Reserved names: {reserved_names_text()}",
            at_key=True,
        )

    def _parameters(self) -> dict[str, tuple[float, Dim]]:
        out: dict[str, tuple[float, Dim]] = {}
        for name, raw in self.r.parameters.items():
            self._check_parameter_name(name)
            q = self.q(raw, ("parameters", name))
            if q is not None:
                out[name] = self._resolve_c(q, ("parameters", name))
        for name, raw in self.overrides.items():
            if name not in out:
                close = difflib.get_close_matches(name, list(out), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                known = ", ".join(sorted(out)) or "none"
                self.errors.append(
                    ConfigError(
                        f"unknown parameter {name!r}{hint}; this recipe has: {known}",
                        "<command line>",
                    )
                )
                continue
            try:
                q = parse_quantity(raw)
            except UnitError as exc:
                self.errors.append(ConfigError(f"parameter {name}: {exc}", "<command line>"))
                continue
            v, d = self._resolve_c(q, ("parameters", name))
            if d is not out[name][1] and not (d is Dim.NONE and out[name][1] is Dim.NONE):
                self.errors.append(
                    ConfigError(
                        f"parameter {name}={raw!r} is a {d}; the recipe declares a {out[name][1]}",
                        "<command line>",
                    )
                )
                continue
            out[name] = (v, d)
        return out

    def _resolve_c(self, q: Quantity, path: tuple[str | int, ...]) -> tuple[float, Dim]:
        if q.dim is Dim.C_RATE:
            if self.capacity_ah is None:
                self.err(path, f"{q}: a C-rate needs the rated capacity (capacity: in the recipe)")
                return 0.0, Dim.CURRENT
            return q.value * self.capacity_ah, Dim.CURRENT
        return q.value, q.dim

    def _current(self, v: object, path: tuple[str | int, ...]) -> float:
        if isinstance(v, str) and v.strip() in self.params:
            # A parameter's name: its value as given (a C-rate already made a current).
            name = v.strip()
            self.used.add(name)
            amps, dim = self.params[name]
            if dim is not Dim.CURRENT:
                self.err(path, f"parameter {name!r} is a {dim}, not a current")
                return 0.0
            return amps
        if isinstance(v, str) and PARAMETER_NAME.match(v.strip()):
            close = difflib.get_close_matches(v.strip(), list(self.params), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            known = ", ".join(sorted(self.params)) or "none"
            self.err(path, f"unknown parameter {v.strip()!r}{hint}; this recipe has: {known}")
            return 0.0
        q = self.q(v, path, Dim.CURRENT, Dim.C_RATE)
        if q is None:
            return 0.0
        amps, _ = self._resolve_c(q, path)
        return amps

    def _time(self, v: object, path: tuple[str | int, ...]) -> float | None:
        q = self.q(v, path, Dim.TIME)
        return None if q is None else q.value

    def _pair(
        self, v: tuple[object, object] | None, path: tuple[str | int, ...], *dims: Dim
    ) -> tuple[float | None, float | None]:
        if v is None:
            return (None, None)
        out: list[float | None] = []
        for k, x in enumerate(v):
            q = self.q(x, (*path, k), *dims)
            out.append(None if q is None else self._resolve_c(q, (*path, k))[0])
        if out[0] is not None and out[1] is not None and out[0] >= out[1]:
            self.err(path, "limits must be [low, high] with low < high")
        return (out[0], out[1])

    def _log(self, ls: LogSettings | None, path: tuple[str | int, ...]) -> LogRule | None:
        if ls is None:
            return None
        dv = self.q(ls.delta_v, (*path, "delta_v"), Dim.VOLTAGE)
        di = self.q(ls.delta_i, (*path, "delta_i"), Dim.CURRENT)
        return LogRule(
            period_s=self._time(ls.period, (*path, "period")),
            delta_v=dv.value if dv else None,
            delta_i=di.value if di else None,
        )

    # --- expressions and actions -------------------------------------------------------
    def cond(self, text: str, path: tuple[str | int, ...], at_key: bool = False) -> Expr | None:
        compiled = self._conditions.get(text)
        if compiled is None:
            try:
                compiled = compile_condition(text, self.sig)
            except ExprError as exc:
                compiled = exc
            self._conditions[text] = compiled
        if isinstance(compiled, Expr):
            self.used.update(compiled.names & self.params.keys())
            return compiled
        msg = compiled.message if text in compiled.message else f"{compiled.message} (in {text!r})"
        self.err(path, msg, at_key=at_key, offset=compiled.offset)
        return None

    def _warnings(self, r: Recipe) -> list[ConfigError]:
        """What ``check`` says without refusing: parameters nothing reads, and bare action
        words that also name a step."""
        # A warning, not a refusal: a recipe imported from a Chadèche sequence declares the
        # seed's command-line values (-m -M -c -C) whether its rows read them or not.
        warnings: list[ConfigError] = []
        for name in r.parameters:
            if name not in self.used:
                m = self.pos.key(("parameters", name)) or self.pos.nearest(("parameters", name))
                warnings.append(
                    ConfigError(
                        f"parameter {name!r} is declared but nothing reads it (a condition,"
                        f" a setpoint such as 'discharge: {name}', or initial_charge): giving"
                        " it changes nothing; use it or remove it",
                        self.file,
                        m.line,
                        m.col,
                    )
                )
        for path, word in self.shadowed:
            m = self.pos.value(path) or self.pos.nearest(path)
            warnings.append(
                ConfigError(
                    f"{word!r} is the action {word}, not the step {word!r}: write"
                    f" 'goto {word}' to go to the step",
                    self.file,
                    m.line,
                    m.col,
                )
            )
        return warnings

    def action(self, text: str, path: tuple[str | int, ...]) -> Action | None:
        control = _CONTROL.search(str(text))
        if control is not None:
            # Stripped, "sleep_until 08:00\n" was read as 08:00; an action is one line
            # (the journal and the log show it).
            self.err(
                path,
                f"action {text!r} has the control character {control[0]!r}: one line of text only",
            )
            return None
        t = str(text).strip()
        words = t.split(None, 1)
        head = words[0] if words else ""
        rest = words[1] if len(words) > 1 else ""
        if t in ("next", "next_cycle", "end", "hold"):
            if t in self.ids:
                self.shadowed.append((path, t))
            return Action(ActionKind(t))
        if HHMM.match(t) or (head == "sleep_until" and HHMM.match(rest)):
            hh, mm = (t if HHMM.match(t) else rest).split(":")
            return Action(ActionKind.SLEEP_UNTIL, hhmm=(int(hh), int(mm)))
        m = re.match(r"^\+([0-9]{1,3}):([0-5][0-9])$", t)  # ASCII: \d takes any Unicode digit
        if m:
            return Action(ActionKind.SLEEP, seconds=int(m[1]) * 3600 + int(m[2]) * 60)
        if head == "sleep":
            s = self._time(rest, path)
            if s is not None and s < 0:
                self.err(path, f"action {t!r}: a sleep cannot be negative (write sleep 10 s)")
                return None
            return None if s is None else Action(ActionKind.SLEEP, seconds=s)
        target = rest if head == "goto" else t
        if target in self.ids:
            return Action(ActionKind.GOTO, target=self.ids[target], target_id=target)
        close = difflib.get_close_matches(target, list(self.ids), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        if head == "goto" or re.match(r"^[A-Za-z_][\w\-]*$", t):
            self.err(path, f"goto to a missing step {target!r}{hint}")
        else:
            self.err(
                path,
                f"unknown action {t!r}: expected next, next_cycle, end, hold, a step id,"
                " goto <step>, HH:MM, +HH:MM or sleep <duration>",
            )
        return None

    def transitions(
        self, until: Sequence[dict[str, str]], path: tuple[str | int, ...]
    ) -> tuple[Transition, ...]:
        out = []
        for k, item in enumerate(until):
            ((text, act),) = item.items()
            c = self.cond(str(text), (*path, k, str(text)), at_key=True)
            a = self.action(str(act), (*path, k, str(text)))
            if c is not None and a is not None:
                out.append(Transition(k + 1, str(text), c, a))
        return tuple(out)

    # --- steps and groups ---------------------------------------------------------------
    def _group(self, gi: int, g: object, group_of: dict[int, list[int]]) -> CompiledGroup:
        from supervisor.config.recipe import Group

        assert isinstance(g, Group)
        path: tuple[str | int, ...] = ("groups", gi)
        members = set()
        for k, sid in enumerate(g.steps):
            if sid not in self.ids:
                self.err((*path, "steps", k), f"group {g.id!r} names a missing step {sid!r}")
                continue
            members.add(self.ids[sid])
            group_of.setdefault(self.ids[sid], []).append(gi)
        return CompiledGroup(
            gi,
            g.id,
            frozenset(members),
            self._time(g.duration, (*path, "duration")),
            self.transitions(g.until, (*path, "until")),
        )

    def _step(self, i: int, s: Step, groups: tuple[int, ...]) -> CompiledStep:
        path: tuple[str | int, ...] = ("steps", i)
        kind = s.kind
        kw: dict[str, object] = {}
        if kind not in self.target.capabilities:
            where = f" on channel {self.target.channel}" if self.target.channel else ""
            self.err(
                (*path, kind),
                f"step {s.id!r} ({kind}) cannot run{where}: {self.target.no_cv_reason}",
                at_key=True,
            )
        duration = self._time(s.duration, (*path, "duration"))
        if kind == "rest":
            if not isinstance(s.rest, bool):
                rd = self._time(s.rest, (*path, "rest"))
                if duration is not None and rd is not None and rd != duration:
                    self.err((*path, "duration"), "rest gives a duration already; keep one")
                duration = duration if duration is not None else rd
        elif kind in ("charge", "discharge"):
            raw = getattr(s, kind)
            amps = self._current(raw, (*path, kind))
            kw["current_a"] = amps if kind == "charge" else -amps
            # At the step's key, as this refusal always pointed (the value follows it).
            self._check_amps(s, kw["current_a"], raw, (*path, kind), at_key=True)
        elif kind == "cv" and s.cv is not None:
            at = (*path, "cv")
            kw["voltage_v"] = self._setpoint_volts(s, s.cv.voltage, (*at, "voltage"))
            kw["current_a"] = self._current(s.cv.current_limit, (*at, "current_limit"))
            self._check_amps(s, kw["current_a"], s.cv.current_limit, (*at, "current_limit"))
        elif kind == "cccv" and s.cccv is not None:
            at = (*path, "cccv")
            kw["voltage_v"] = self._setpoint_volts(s, s.cccv.voltage, (*at, "voltage"))
            kw["current_a"] = self._current(s.cccv.current, (*at, "current"))
            self._check_amps(s, kw["current_a"], s.cccv.current, (*at, "current"))
        elif kind == "power":
            power_w = parse_quantity(s.power).value if s.power is not None else 0.0
            self._check_power(s, power_w, (*path, "power"))
            kw["power_w"] = power_w
        elif kind == "pulse" and s.pulse is not None:
            at = (*path, "pulse", "current")
            kw["current_a"] = self._current(s.pulse.current, at)
            self._check_amps(s, kw["current_a"], s.pulse.current, at)
            on_s = parse_quantity(s.pulse.on_time).value
            off_s = parse_quantity(s.pulse.off_time).value
            self._check_pulse_times(s, on_s, off_s, (*path, "pulse"))
            kw["pulse_on_s"] = on_s
            kw["pulse_off_s"] = off_s
            kw["pulse_count"] = s.pulse.count
        elif kind == "profile" and s.profile is not None:
            points = self._profile(s.profile, (*path, "profile"))
            self._check_profile(s, points, (*path, "profile"))
            kw["profile"] = points
            kw["profile_repeat"] = s.profile.repeat
        elif kind == "sleep":
            kw["sleep_s"] = self._time(s.sleep, (*path, "sleep"))
        elif kind == "sleep_until" and s.sleep_until is not None:
            hh, mm = s.sleep_until.split(":")
            kw["sleep_until"] = (int(hh), int(mm))
        elif kind == "goto" and s.goto is not None:
            a = self.action(f"goto {s.goto}", (*path, "goto"))
            kw["goto"] = a.target if a is not None else None
        advance: Action | None = None
        if s.advance is True:
            advance = Action(ActionKind.NEXT)
        elif s.advance is not False:
            advance = self.action(str(s.advance), (*path, "advance"))
        interlock = None
        if s.interlock is not None:
            interlock = self.cond(s.interlock, (*path, "interlock"))
        max_time = error = None
        if s.supervision is not None:
            max_time = self._time(s.supervision.max_time, (*path, "supervision", "max_time"))
            if s.supervision.error is not None:
                error = self.cond(s.supervision.error, (*path, "supervision", "error"))
        return CompiledStep(
            index=i,
            id=s.id,
            kind=kind,
            comment=s.comment,
            duration_s=duration,
            transitions=self.transitions(s.until, (*path, "until")),
            advance=advance,
            interlock=interlock,
            max_time_s=max_time,
            error=error,
            log=self._log(s.log, (*path, "log")) or LogRule(),
            groups=groups,
            **kw,  # type: ignore[arg-type]
        )

    # --- what the channel's hard limits allow -------------------------------------------
    def _where(self) -> str:
        return f"channel {self.target.channel}" if self.target.channel else "the channel"

    def _check_amps(
        self,
        s: Step,
        amps: object,
        written: object,
        path: tuple[str | int, ...],
        at_key: bool = False,
        what: str = "",
    ) -> None:
        """A current the step asks for (+ charges), within the channel's current limits."""
        lim = self.target.current_limits_a
        if lim is None or not isinstance(amps, int | float):
            return
        lo, hi = lim
        if lo - LIMIT_EPS <= amps <= hi + LIMIT_EPS:
            return
        rate = ""
        if isinstance(written, str) and _is_c_rate(written) and self.capacity_ah is not None:
            rate = f" ({written.strip()} of {self.capacity_ah:g} Ah)"
        self.err(
            path,
            f"step {s.id!r}{what} asks {amps:g} A{rate}; {self._where()} allows [{lo:g}, {hi:g}] A",
            at_key=at_key,
        )

    def _setpoint_volts(
        self, s: Step, written: str | float | int, path: tuple[str | int, ...]
    ) -> float:
        """A CV target, within the channel's voltage limits (not checked where the step
        cannot run at all: the capability refusal says enough); a parameter's name is its
        value."""
        name = written.strip() if isinstance(written, str) else ""
        if PARAMETER_NAME.match(name):
            if name not in self.params:
                known = ", ".join(sorted(self.params)) or "none"
                self.err(path, f"unknown parameter {name!r}; this recipe has: {known}")
                return 0.0
            self.used.add(name)
            volts, dim = self.params[name]
            if dim is not Dim.VOLTAGE:
                self.err(path, f"parameter {name!r} is a {dim}, not a voltage")
                return 0.0
        else:
            volts = parse_quantity(written).value
        lim = self.target.voltage_limits_v
        if lim is not None and s.kind in self.target.capabilities:
            lo, hi = lim
            if not lo - LIMIT_EPS <= volts <= hi + LIMIT_EPS:
                self.err(
                    path,
                    f"step {s.id!r} asks {volts:g} V; {self._where()} allows"
                    f" [{lo:g}, {hi:g}] V{_scale_hint((volts,), lim)}",
                )
        return volts

    def _check_power(self, s: Step, power_w: float, path: tuple[str | int, ...]) -> None:
        """I = P / V (``ConstantPower``). First, can the power be reached at all: the most
        the channel gives in that direction is its current limit at its high voltage limit
        (the cell's voltage stays below it), so a 1000 W step on a 0.4 A board is refused
        whatever its low voltage limit. Then, above the low voltage limit the current is at
        most P / V_low; no simple bound when that limit reaches zero volts."""
        vlim, ilim = self.target.voltage_limits_v, self.target.current_limits_a
        if vlim is None or ilim is None:
            return
        lo, hi = ilim
        v_high = vlim[1]
        if power_w != 0 and v_high > 0:
            limit_a = hi if power_w > 0 else lo
            reach_w = limit_a * v_high
            if abs(power_w) > abs(reach_w) * (1 + LIMIT_EPS) + LIMIT_EPS:
                self.err(
                    path,
                    f"step {s.id!r} asks {power_w:g} W; {self._where()} reaches at most"
                    f" {abs(reach_w):.3g} W {'charging' if power_w > 0 else 'discharging'}"
                    f" ({limit_a:g} A at its {v_high:g} V high limit)",
                )
                return
        if vlim[0] <= MIN_POWER_VOLTAGE_V:
            return
        amps = power_w / vlim[0]
        if not lo - LIMIT_EPS <= amps <= hi + LIMIT_EPS:
            self.err(
                path,
                f"step {s.id!r} asks {power_w:g} W: up to {amps:.3g} A at the"
                f" {vlim[0]:g} V low limit; {self._where()} allows [{lo:g}, {hi:g}] A",
            )

    def _check_pulse_times(
        self, s: Step, on_s: float, off_s: float, path: tuple[str | int, ...]
    ) -> None:
        """Refused, not warned: the scan sets the current once per period, so a pulse (or
        the rest between two) shorter than a scan would last a whole scan or not happen,
        and the internal resistance would be measured on another pulse than the one
        written. An off_time of 0 (pulses back to back) asks for no rest: allowed."""
        scan = self.target.scan_period_s
        if scan is None:
            return
        where = f"channel {self.target.channel}'s" if self.target.channel else "the"
        for name, seconds in (("on_time", on_s), ("off_time", off_s)):
            if name == "off_time" and seconds == 0:
                continue
            if seconds < scan - LIMIT_EPS:
                self.err(
                    (*path, name),
                    f"step {s.id!r} pulse {name} {seconds:g} s is shorter than {where} scan"
                    f" period ({scan:g} s): the current changes once per scan; make it at"
                    f" least {scan:g} s",
                )

    def _check_profile(
        self, s: Step, points: tuple[ProfilePoint, ...], path: tuple[str | int, ...]
    ) -> None:
        """Each row's current and voltage window within the channel's limits. A CSV row has
        no position in the recipe: the refusal points at ``file:`` and names the row."""
        assert s.profile is not None
        inline = s.profile.rows is not None
        vlim = self.target.voltage_limits_v
        for k, p in enumerate(points):
            row = f" profile row {k + 1}" if inline else f" profile {s.profile.file} row {k + 1}"
            at: tuple[str | int, ...] = (*path, "rows", k) if inline else (*path, "file")
            self._check_amps(s, p.current_a, None, (*at, "current") if inline else at, what=row)
            if vlim is None:
                continue
            lo, hi = vlim
            for name, volts in (("v_min", p.v_min), ("v_max", p.v_max)):
                if volts is None or lo - LIMIT_EPS <= volts <= hi + LIMIT_EPS:
                    continue
                self.err(
                    (*at, name) if inline else at,
                    f"step {s.id!r}{row}: {name} {volts:g} V is outside {self._where()}'s"
                    f" voltage limits [{lo:g}, {hi:g}] V{_scale_hint((volts,), vlim)}",
                )

    def _check_windows(self, limits: Limits) -> None:
        """The recipe's ``limits:`` inside the channel's hard limits: a recipe that would
        let the cell go where the channel trips was written for something else."""
        t = self.target
        for name, window, hard, field_, unit in (
            ("voltage", limits.voltage_v, t.voltage_limits_v, "voltage_v", "V"),
            ("current", limits.current_a, t.current_limits_a, "current_a", "A"),
            ("temperature", limits.temperature_c, t.temperature_limits_c, "temperature_c", "degC"),
        ):
            if hard is None:
                continue
            outside = [k for k, b in enumerate(window) if b is not None and not _within(b, hard)]
            if not outside:
                continue
            apart = _apart(window, hard)
            hint = ""
            if name == "voltage":
                hint = _scale_hint([b for b in window if b is not None], hard)
            self.err(
                ("limits", name, outside[0]),
                f"recipe limits {name} {_fmt_window(window)} {unit}"
                f" {'lie outside' if apart else 'reach beyond'} {self._where()}'s hard limits"
                f" {field_} {_fmt_window(hard)} {unit}{hint}",
            )

    def _profile(self, p: ProfileSpec, path: tuple[str | int, ...]) -> tuple[ProfilePoint, ...]:
        if p.rows is not None:
            return tuple(
                ProfilePoint(r.t, r.current, r.v_min, r.v_max, r.i_min, r.i_max, r.t_min, r.t_max)
                for r in p.rows
            )
        assert p.file is not None
        csv_path = Path(self.file).parent / p.file
        refused = self.files(csv_path) if self.files is not None else None
        if refused is not None:  # never opened: not a byte of it in the message
            self.err((*path, "file"), refused)
            return ()
        try:
            return read_profile_csv(csv_path)
        except ConfigError as exc:
            self.err((*path, "file"), exc.location_message())
            return ()

    # --- loops that never let time pass, steps that never end ---------------------------
    def _check_termination(
        self, steps: tuple[CompiledStep, ...], groups: tuple[CompiledGroup, ...]
    ) -> None:
        for s in steps:
            bounded_group = any(
                groups[g].duration_s is not None or groups[g].transitions
                for g in s.groups
                if g < len(groups)
            )
            ends_itself = kind_of(s.kind).ends_by_itself
            if (
                not ends_itself
                and s.duration_s is None
                and not s.transitions
                and s.advance is None
                and not bounded_group
            ):
                self.err(
                    ("steps", s.index, s.kind),
                    f"step {s.id!r} never ends: give it a duration or an until condition",
                    at_key=True,
                )
        self._check_zero_time_loops(steps, groups)

    def _check_zero_time_loops(
        self, steps: tuple[CompiledStep, ...], groups: tuple[CompiledGroup, ...]
    ) -> None:
        """A cycle of steps that can all end in the scan they start lets no time pass
        (``rest: 0 s`` and a goto back, ``until: [true: <itself>]``, a group of 0 s, a
        body of such steps repeated by ``cycles``): refused, naming its steps, at the
        first one (ADR 0011; ``chains/zerotime.py`` says what ends a step at once)."""
        keys = [
            "rest" if s.kind == "rest" and s.duration is None and s.rest is not True else "duration"
            for s in self.r.steps
        ]
        parameters = {k: v for k, (v, _) in self.params.items()}
        for loop in zero_time_loops(steps, groups, self.r.cycles, parameters, keys):
            path, details = describe(loop, steps)
            first = loop.reasons[0]
            if all(k < len(steps) and steps[k].kind == "goto" for k in loop.nodes):
                # Only gotos: the message this refusal always had.
                self.err(first.path, f"loop with no exit and no duration: {path}")
                continue
            self.err(
                first.path,
                f"loop that lets no time pass: {path}; each of its steps can end in the"
                f" scan it starts ({details}); give one of them a duration above 0 s or a"
                " condition that takes time",
                at_key=first.at_key,
            )


def _is_c_rate(text: str) -> bool:
    try:
        return parse_quantity(text).dim is Dim.C_RATE
    except UnitError:
        return False


def _within(value: float, window: Window) -> bool:
    lo, hi = window
    return (lo is None or value >= lo - LIMIT_EPS) and (hi is None or value <= hi + LIMIT_EPS)


def _apart(a: Window, b: Window) -> bool:
    """No value lies in both windows (None: open on that side)."""
    return (a[1] is not None and b[0] is not None and a[1] < b[0] - LIMIT_EPS) or (
        a[0] is not None and b[1] is not None and a[0] > b[1] + LIMIT_EPS
    )


def _scale_hint(volts: Sequence[float], window: Window) -> str:
    """The hint for voltages beyond the window by more than ``SCALE_MISMATCH_RATIO``."""
    lo, hi = window
    r = SCALE_MISMATCH_RATIO
    for v in volts:
        if (lo is not None and lo > 0 and v * r < lo) or (hi is not None and hi > 0 and v > hi * r):
            return f" ({OTHER_CELL_HINT})"
    return ""


def _fmt_window(window: Window) -> str:
    return "[" + ", ".join("null" if b is None else f"{b:g}" for b in window) + "]"
