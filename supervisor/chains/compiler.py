"""Recipe (validated YAML) → Program (executable): meaning checked before anything starts.

Every error names file:line:column: goto targets that do not exist, unknown actions,
expressions that do not type-check (``voltage >= 300 mA``), unknown parameters, loops
that never let time pass, steps that can never end, and steps the channel's hardware
cannot do (CV on a Chadèche board).
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from supervisor.chains.expr import Expr, ExprError, Signature, compile_condition
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
from supervisor.config.recipe import HHMM, LogSettings, ProfileSpec, Recipe, Step
from supervisor.config.yamlpos import Positions
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.core.units import Dim, Quantity, UnitError, parse_quantity

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

# Step kinds each source can execute (CP is regulated in software from V·I).
CC_ONLY = frozenset(
    {"rest", "charge", "discharge", "power", "pulse", "profile", "sleep", "sleep_until"}
    | {"goto", "end_cycle", "end"}
)
WITH_CV = CC_ONLY | {"cv", "cccv"}


@dataclass
class Target:
    """What the recipe will run on (None fields: unknown, e.g. in ``supervisor check``)."""

    channel: str | None = None
    capabilities: frozenset[str] = WITH_CV
    no_cv_reason: str = "its source drives a constant current only (no voltage regulation)"
    capacity_ah: float | None = None
    current_limits_a: tuple[float, float] | None = None
    tags: Mapping[str, Dim] = field(default_factory=dict)


def compile_recipe(
    recipe: Recipe,
    pos: Positions,
    file: str,
    target: Target | None = None,
    overrides: Mapping[str, str] | None = None,
) -> Program:
    return _Compiler(recipe, pos, file, target or Target(), overrides or {}).run()


class _Compiler:
    def __init__(
        self,
        recipe: Recipe,
        pos: Positions,
        file: str,
        target: Target,
        overrides: Mapping[str, str],
    ) -> None:
        self.r = recipe
        self.pos = pos
        self.file = file
        self.target = target
        self.overrides = overrides
        self.errors: list[ConfigError] = []
        self.ids = {s.id: i for i, s in enumerate(recipe.steps)}

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
        dupes = [s.id for i, s in enumerate(r.steps) if s.id in [t.id for t in r.steps[:i]]]
        for i, s in enumerate(r.steps):
            if s.id in dupes and self.ids[s.id] != i:
                self.err(("steps", i, "id"), f"duplicate step id {s.id!r}")
        group_of: dict[int, list[int]] = {}
        groups = tuple(self._group(gi, g, group_of) for gi, g in enumerate(r.groups))
        steps = tuple(self._step(i, s, tuple(group_of.get(i, ()))) for i, s in enumerate(r.steps))
        self._check_termination(steps, groups)
        init: Quantity | None = None
        if isinstance(r.initial_charge, str) and r.initial_charge in params:
            init = Quantity(*params[r.initial_charge])
            if init.dim is not Dim.CHARGE:
                self.err(("initial_charge",), f"parameter {r.initial_charge!r} is not a charge")
        else:
            init = self.q(r.initial_charge, ("initial_charge",), Dim.CHARGE)
        limits = Limits(
            self._pair(r.limits.voltage, ("limits", "voltage"), Dim.VOLTAGE),
            self._pair(r.limits.current, ("limits", "current"), Dim.CURRENT, Dim.C_RATE),
            self._pair(r.limits.temperature, ("limits", "temperature"), Dim.TEMPERATURE),
        )
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
        )

    def _parameters(self) -> dict[str, tuple[float, Dim]]:
        out: dict[str, tuple[float, Dim]] = {}
        for name, raw in self.r.parameters.items():
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
        try:
            return compile_condition(text, self.sig)
        except ExprError as exc:
            msg = exc.message if text in exc.message else f"{exc.message} (in {text!r})"
            self.err(path, msg, at_key=at_key, offset=exc.offset)
            return None

    def action(self, text: str, path: tuple[str | int, ...]) -> Action | None:
        t = str(text).strip()
        words = t.split(None, 1)
        head = words[0] if words else ""
        rest = words[1] if len(words) > 1 else ""
        if t in ("next", "next_cycle", "end", "hold"):
            return Action(ActionKind(t))
        if HHMM.match(t) or (head == "sleep_until" and HHMM.match(rest)):
            hh, mm = (t if HHMM.match(t) else rest).split(":")
            return Action(ActionKind.SLEEP_UNTIL, hhmm=(int(hh), int(mm)))
        m = re.match(r"^\+(\d{1,3}):([0-5]\d)$", t)
        if m:
            return Action(ActionKind.SLEEP, seconds=int(m[1]) * 3600 + int(m[2]) * 60)
        if head == "sleep":
            s = self._time(rest, path)
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
            amps = self._current(getattr(s, kind), (*path, kind))
            kw["current_a"] = amps if kind == "charge" else -amps
        elif kind == "cv" and s.cv is not None:
            kw["voltage_v"] = parse_quantity(s.cv.voltage).value
            kw["current_a"] = self._current(s.cv.current_limit, (*path, "cv", "current_limit"))
        elif kind == "cccv" and s.cccv is not None:
            kw["voltage_v"] = parse_quantity(s.cccv.voltage).value
            kw["current_a"] = self._current(s.cccv.current, (*path, "cccv", "current"))
        elif kind == "power":
            kw["power_w"] = parse_quantity(s.power).value if s.power is not None else 0.0
        elif kind == "pulse" and s.pulse is not None:
            kw["current_a"] = self._current(s.pulse.current, (*path, "pulse", "current"))
            kw["pulse_on_s"] = parse_quantity(s.pulse.on_time).value
            kw["pulse_off_s"] = parse_quantity(s.pulse.off_time).value
            kw["pulse_count"] = s.pulse.count
        elif kind == "profile" and s.profile is not None:
            kw["profile"] = self._profile(s.profile, (*path, "profile"))
            kw["profile_repeat"] = s.profile.repeat
        elif kind == "sleep":
            kw["sleep_s"] = self._time(s.sleep, (*path, "sleep"))
        elif kind == "sleep_until" and s.sleep_until is not None:
            hh, mm = s.sleep_until.split(":")
            kw["sleep_until"] = (int(hh), int(mm))
        elif kind == "goto" and s.goto is not None:
            a = self.action(f"goto {s.goto}", (*path, "goto"))
            kw["goto"] = a.target if a is not None else None
        self._check_current(kw, s, path)
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

    def _check_current(self, kw: dict[str, object], s: Step, path: tuple[str | int, ...]) -> None:
        lim = self.target.current_limits_a
        amps = kw.get("current_a")
        if lim is None or not isinstance(amps, float):
            return
        lo, hi = lim
        if not lo - 1e-12 <= amps <= hi + 1e-12:
            self.err(
                (*path, s.kind),
                f"step {s.id!r} asks {amps:g} A; channel {self.target.channel} allows"
                f" [{lo:g}, {hi:g}] A",
                at_key=True,
            )

    def _profile(self, p: ProfileSpec, path: tuple[str | int, ...]) -> tuple[ProfilePoint, ...]:
        if p.rows is not None:
            return tuple(
                ProfilePoint(r.t, r.current, r.v_min, r.v_max, r.i_min, r.i_max, r.t_min, r.t_max)
                for r in p.rows
            )
        assert p.file is not None
        csv_path = Path(self.file).parent / p.file
        try:
            return read_profile_csv(csv_path)
        except ConfigError as exc:
            self.err((*path, "file"), exc.location_message())
            return ()

    # --- loops that never let time pass, steps that never end ---------------------------
    def _check_termination(
        self, steps: tuple[CompiledStep, ...], groups: tuple[CompiledGroup, ...]
    ) -> None:
        n = len(steps)
        for s in steps:
            bounded_group = any(
                groups[g].duration_s is not None or groups[g].transitions
                for g in s.groups
                if g < len(groups)
            )
            ends_itself = s.kind in ("pulse", "profile", "sleep", "sleep_until") or s.instant
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
        # A cycle made only of instant steps (goto chains) spins without time passing.
        for start in range(n):
            seen: list[int] = []
            k: int | None = start
            while k is not None and k < n and steps[k].kind == "goto" and k not in seen:
                seen.append(k)
                k = steps[k].goto
            if k is not None and k in seen and k == start:
                path_ids = " → ".join(steps[j].id for j in [*seen, start])
                self.err(
                    ("steps", start, "goto"),
                    f"loop with no exit and no duration: {path_ids}",
                )
                return
