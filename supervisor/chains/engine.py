"""The step-chain engine: one chain per channel, ISA-88 states, S7-GRAPH guards.

The chain reads tags and requests setpoints (``chN.auto_current``, ``chN.auto_active``);
it never calls a driver. The channel's own protection runs after it in the same scan and
always wins (a chain can never override an interlock).

State model (OPC UA ``StateEnumeration`` numbers in ``chN.chain.state_code``)::

    Idle --start--> Running --hold--> Holding --> Held --resume--> Resuming --> Running
    Running --stop--> Stopping --> Stopped --reset--> Idle
    any active --abort--> Aborting --> Aborted --reset--> Idle
    Running --(last step / end)--> Complete --reset--> Idle
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum

from supervisor.chains.compiler import CHANNEL_VARIABLES
from supervisor.chains.program import Action, ActionKind, CompiledStep, Program
from supervisor.channels import Channel, Mode
from supervisor.core.clock import Clock
from supervisor.core.errors import OperatorError
from supervisor.tags import Access, TagDB, TagSpec

log = logging.getLogger(__name__)


class State(StrEnum):
    IDLE = "Idle"
    RUNNING = "Running"
    HOLDING = "Holding"
    HELD = "Held"
    RESUMING = "Resuming"
    STOPPING = "Stopping"
    STOPPED = "Stopped"
    ABORTING = "Aborting"
    ABORTED = "Aborted"
    COMPLETE = "Complete"


# OPC UA Part 10 / PackML StateEnumeration numbering (documented in the README).
OPCUA_CODE = {
    State.STOPPED: 0,
    State.IDLE: 2,
    State.RUNNING: 4,
    State.COMPLETE: 6,
    State.ABORTING: 7,
    State.ABORTED: 8,
    State.STOPPING: 9,
    State.HOLDING: 14,
    State.HELD: 15,
    State.RESUMING: 16,
}

COMMANDS = ("start", "hold", "resume", "advance", "stop", "abort", "reset", "ack")

# {state: {command: next state}} — the HMI can draw its diagram from this table.
TABLE: dict[State, dict[str, State]] = {
    State.IDLE: {"start": State.RUNNING},
    State.RUNNING: {
        "hold": State.HOLDING,
        "advance": State.RUNNING,
        "stop": State.STOPPING,
        "abort": State.ABORTING,
    },
    State.HOLDING: {"stop": State.STOPPING, "abort": State.ABORTING},
    State.HELD: {"resume": State.RESUMING, "stop": State.STOPPING, "abort": State.ABORTING},
    State.RESUMING: {"hold": State.HOLDING, "stop": State.STOPPING, "abort": State.ABORTING},
    State.STOPPING: {"abort": State.ABORTING},
    State.STOPPED: {"reset": State.IDLE},
    State.ABORTING: {},
    State.ABORTED: {"reset": State.IDLE},
    State.COMPLETE: {"reset": State.IDLE},
}
# Acting states finish in one scan.
AUTO_NEXT = {
    State.HOLDING: State.HELD,
    State.RESUMING: State.RUNNING,
    State.STOPPING: State.STOPPED,
    State.ABORTING: State.ABORTED,
}
ENERGISED = (State.RUNNING,)
COUNTERS = ("charged_ah", "discharged_ah", "charged_wh", "discharged_wh")
MAX_INSTANT_STEPS = 1000  # guard: a chain of goto steps in one scan
DV_DT_WINDOW_S = 60.0
DV_DT_MIN_SPAN_S = 10.0


@dataclass(frozen=True, slots=True)
class ChainEvent:
    t: float  # Clock.now()
    wall: float
    channel: str
    kind: str  # "state" | "step" | "alarm" | "message"
    text: str
    step_index: int = -1
    step_id: str = ""
    cycle: int = 0


@dataclass(frozen=True, slots=True)
class Record:
    """One result sample (BDF columns), emitted when a logging rule says so."""

    t: float
    wall: float
    test_time_s: float
    step_time_s: float
    cycle_time_s: float
    cycle: int
    step_count: int  # increments at every step start, never resets (BDF)
    step_index: int
    step_id: str
    step_type: str
    voltage_v: float | None
    current_a: float | None
    power_w: float | None
    temperature_c: float | None
    charge_ah: float  # counter incl. the initial charge
    charged_ah: float
    discharged_ah: float
    charged_wh: float
    discharged_wh: float
    cycle_charged_ah: float
    cycle_discharged_ah: float
    cycle_charged_wh: float
    cycle_discharged_wh: float
    setpoint_a: float
    step_remaining_s: float | None
    reason: str  # "period" | "delta_v" | "delta_i" | "step change" | "end"


@dataclass
class _Run:
    """Everything that matters to resume a test (persisted by the safety layer later)."""

    test_id: str = ""
    step: int = 0
    cycle: int = 1
    step_count: int = 0
    t_test0: float = 0.0
    t_cycle0: float = 0.0
    t_step0: float = 0.0
    held_since: float | None = None
    q0_ah: float = 0.0  # channel counters at test start
    step_q0: float = 0.0
    step_e0: float = 0.0
    test0: dict[str, float] = field(default_factory=dict)  # counters at test start
    cycle0: dict[str, float] = field(default_factory=dict)  # counters at cycle start
    peak_v: float | None = None
    sleep_until_t: float | None = None
    sleep_then: int | None = None  # step index after a sleep action
    group_t0: dict[int, float] = field(default_factory=dict)
    last_rec_t: float = -math.inf
    last_rec_v: float | None = None
    last_rec_i: float | None = None
    end_reason: str = ""
    max_time_acked: int = -1
    pulse_on: bool | None = None
    rest_vi: tuple[float, float] | None = None
    on_vi: tuple[float, float] | None = None
    pulse_start: tuple[float, float] | None = (
        None  # step activation whose step-time supervision was acknowledged
    )


class ChainRunner:
    """Executes a Program on one channel. Runs as a scan logic phase before the channel."""

    def __init__(self, channel: Channel, db: TagDB, clock: Clock) -> None:
        self.ch = channel
        self.db = db
        self.clock = clock
        self.name = channel.name
        self.program: Program | None = None
        self.state = State.IDLE
        self.listeners: list[Callable[[ChainEvent], None]] = []
        self.recorders: list[Callable[[Record], None]] = []
        self.events: deque[ChainEvent] = deque(maxlen=1000)
        self.estimated_duration_s: float | None = None
        self.display_period_s = 60.0
        self.dba = 0  # board address shown in the Chadèche display line
        self._r = _Run()
        self._alarm_latched = False
        self._dv: deque[tuple[float, float]] = deque()
        self._pending_advance = False
        self._last_display_t = -math.inf
        self._tag_names: list[str] = []
        n = channel.name

        def add(spec: TagSpec) -> TagSpec:
            db.add(spec)
            return spec

        add(
            TagSpec(
                f"{n}.command",
                dtype="str",
                access=Access.OPERATOR,
                initial="",
                choices=("", *COMMANDS),
                description="start/hold/resume/advance/stop/abort/reset/ack",
            )
        )
        for spec in (
            TagSpec(f"{n}.chain.state", dtype="str", initial=State.IDLE.value),
            TagSpec(f"{n}.chain.state_code", dtype="int", initial=OPCUA_CODE[State.IDLE]),
            TagSpec(f"{n}.chain.recipe", dtype="str", initial=""),
            TagSpec(f"{n}.chain.test_id", dtype="str", initial=""),
            TagSpec(f"{n}.chain.step", dtype="str", initial=""),
            TagSpec(f"{n}.chain.step_index", dtype="int", initial=0),
            TagSpec(f"{n}.chain.cycle", dtype="int", initial=0),
            TagSpec(f"{n}.chain.step_time", unit="s", initial=0.0),
            TagSpec(f"{n}.chain.test_time", unit="s", initial=0.0),
            TagSpec(f"{n}.chain.alarm", dtype="str", initial=""),
            TagSpec(f"{n}.chain.interlock", dtype="str", initial=""),
            TagSpec(f"{n}.chain.last_event", dtype="str", initial=""),
            TagSpec(f"{n}.chain.progress", unit="1", initial=0.0),
            TagSpec(f"{n}.chain.eta_s", unit="s", initial=None),
            TagSpec(f"{n}.chain.internal_resistance", unit="ohm", initial=None),
        ):
            add(spec)
        for t in db:
            if t.name.startswith(f"{n}.chain.") or t.name == f"{n}.command":
                db.update(t, t.spec.initial)
        self._cmd = db[f"{n}.command"]

    # --- loading and commands ----------------------------------------------------------
    def load(self, program: Program, test_id: str | None = None) -> None:
        if self.state not in (State.IDLE, State.COMPLETE, State.STOPPED, State.ABORTED):
            raise OperatorError(f"{self.name}: cannot load a recipe while {self.state.value}")
        self.program = program
        used: set[str] = set()
        exprs = [t.condition for st in program.steps for t in st.transitions]
        exprs += [t.condition for g in program.groups for t in g.transitions]
        exprs += [e for st in program.steps for e in (st.interlock, st.error) if e is not None]
        for e in exprs:
            used |= e.names
        self._tag_names = sorted(used - set(CHANNEL_VARIABLES) - set(program.parameters))
        self._r = _Run(test_id=test_id or time.strftime("%Y%m%d-%H%M%S") + f"-{self.name}")
        self._set("recipe", program.name)
        self._set("test_id", self._r.test_id)
        self._set_state(State.IDLE, f"recipe {program.name} loaded")

    def command(self, cmd: str, actor: str = "operator") -> None:
        if cmd not in COMMANDS:
            raise OperatorError(f"{self.name}: unknown command {cmd!r} ({', '.join(COMMANDS)})")
        if cmd == "ack":
            if self._alarm_latched:
                self._emit("alarm", f"acknowledged by {actor}: {self._get('alarm')}")
                self._alarm_latched = False
                # S7-GRAPH: an acknowledged step-time error does not fire again for the
                # same activation of the step.
                self._r.max_time_acked = self._r.step_count
                self._set("alarm", "")
            return
        allowed = TABLE[self.state]
        if cmd not in allowed:
            ok = ", ".join(allowed) or "none"
            raise OperatorError(
                f"{self.name}: {cmd} is not allowed while {self.state.value} (allowed: {ok})"
            )
        if cmd == "start":
            if self.program is None:
                raise OperatorError(f"{self.name}: no recipe loaded")
            if self.ch.fault.value:
                raise OperatorError(f"{self.name}: channel fault must be acknowledged first")
            self._start(actor)
            return
        if cmd == "resume":
            if self._alarm_latched:
                raise OperatorError(
                    f"{self.name}: acknowledge the alarm first ({self._get('alarm')})"
                )
            if self.ch.fault.value:
                raise OperatorError(f"{self.name}: channel fault must be acknowledged first")
        if cmd == "advance":
            self._pending_advance = True
            return
        if cmd == "reset" and self.program is not None:
            self._r = _Run(test_id=self._r.test_id)
        self._set_state(allowed[cmd], f"{cmd} by {actor}")

    def _start(self, actor: str) -> None:
        assert self.program is not None
        now = self.clock.now()
        r = self._r
        r.t_test0 = r.t_cycle0 = now
        r.q0_ah = self.ch.charge_ah.as_float()
        r.test0 = self._counters()
        r.cycle = 1
        self.db.update(self.ch.mode, Mode.AUTO.value)
        self.db.update(self.ch.enable, False)
        self._reset_cycle_counters()
        self._set_state(State.RUNNING, f"start by {actor}")
        self._enter(0, "start", now)

    # --- the scan phase ------------------------------------------------------------------
    def run(self, now: float, dt: float) -> None:
        cmd = self._cmd.value
        if cmd:
            self.db.update(self._cmd, "")
            try:
                self.command(str(cmd))
            except OperatorError as exc:
                log.warning("%s", exc)
                self._emit("message", str(exc))
        state = self.state
        if state in AUTO_NEXT:
            self._set_state(AUTO_NEXT[state], "done")
            if self.state is State.RUNNING:
                r = self._r
                if r.held_since is not None:
                    # Step time excludes the time spent held (the step resumes where it was).
                    r.t_step0 += now - r.held_since
                    for g in r.group_t0:
                        r.group_t0[g] += now - r.held_since
                    if r.sleep_until_t is not None:
                        pass  # a sleep until a time of day keeps its wall-clock target
                    r.held_since = None
        if self.state is State.RUNNING:
            try:
                self._running(now)
            except Exception as exc:  # an exception in logic is an alarm, not a crash
                log.exception("%s: chain failed", self.name)
                self._alarm(f"internal error: {exc}")
                self._set_state(State.ABORTING, "internal error")
        self._outputs()
        self._publish(now)

    def _running(self, now: float) -> None:
        ch, r = self.ch, self._r
        assert self.program is not None
        if ch.fault.value:
            self._set_state(State.HOLDING, f"channel fault: {ch.fault.value}")
            return
        if ch.mode.value != Mode.AUTO.value:
            self._set_state(State.HOLDING, "channel switched to manual")
            return
        v = ch.voltage.as_float() if ch.voltage.good else None
        if v is not None:
            self._dv.append((now, v))
            while self._dv and now - self._dv[0][0] > DV_DT_WINDOW_S:
                self._dv.popleft()
            r.peak_v = v if r.peak_v is None else max(r.peak_v, v)
        step = self.program.steps[r.step]
        if r.sleep_until_t is not None:
            if now < r.sleep_until_t:
                self._record(now, step)
                return
            nxt = r.sleep_then if r.sleep_then is not None else r.step + 1
            r.sleep_until_t = r.sleep_then = None
            self._goto(nxt, "woke up", now)
            return
        values = self._values(now, step)
        # Recipe limits: hold with a latched alarm.
        why = self._limit_violation(values, step, now)
        if why:
            self._alarm(why)
            self._set_state(State.HOLDING, why)
            return
        # S7-GRAPH supervision: latched error, chain halts until acknowledged.
        if (
            step.max_time_s is not None
            and r.max_time_acked != r.step_count
            and values["step_time"] > step.max_time_s  # type: ignore[operator]
        ):
            why = f"supervision: step {step.id} exceeded {step.max_time_s:g} s"
            self._alarm(why)
            self._set_state(State.HOLDING, why)
            return
        if step.error is not None and step.error.evaluate(values) is True:
            why = f"supervision: {step.error.text}"
            self._alarm(why)
            self._set_state(State.HOLDING, why)
            return
        # Interlock: outputs safe while false; clears itself; transitions still evaluated.
        if step.interlock is not None:
            ok = step.interlock.evaluate(values)
            self._set("interlock", "" if ok is True else f"interlock: {step.interlock.text}")
        else:
            self._set("interlock", "")
        if self._pending_advance:
            self._pending_advance = False
            if step.advance is None:
                self._emit("message", f"advance refused in step {step.id}")
            else:
                self._act(step.advance, "operator advance", now)
                return
        # Transitions in order: step's, then its groups'; the first true one wins.
        for tr in step.transitions:
            if tr.condition.evaluate(values) is True:
                self._act(tr.action, f"until #{tr.index}: {tr.text}", now)
                return
        for g in step.groups:
            grp = self.program.groups[g]
            for tr in grp.transitions:
                if tr.condition.evaluate(values) is True:
                    self._act(tr.action, f"group {grp.id} until #{tr.index}: {tr.text}", now)
                    return
        st = values["step_time"]
        assert isinstance(st, float)
        if step.kind == "pulse":
            self._pulse_resistance(step, st, values)
        done = self._kind_done(step, st)
        if done:
            self._act(Action(ActionKind.NEXT), done, now)
            return
        if step.duration_s is not None and st >= step.duration_s - 1e-9:
            self._act(Action(ActionKind.NEXT), "duration elapsed", now)
            return
        for g in step.groups:
            grp = self.program.groups[g]
            t0 = r.group_t0.get(g)
            if grp.duration_s is not None and t0 is not None and now - t0 >= grp.duration_s:
                # A group's time limit leaves the group: on to the step after its last one.
                self._goto(max(grp.steps) + 1, f"group {grp.id} duration elapsed", now)
                return
        self._record(now, step)

    # --- step behaviour ----------------------------------------------------------------------
    def _pulse_resistance(
        self, step: CompiledStep, st: float, values: dict[str, float | bool | None]
    ) -> None:
        """DC internal resistance: R = ΔV/ΔI between the last sample at rest before a pulse
        and the last sample under current at its end (the usual DCIR definition)."""
        period = step.pulse_on_s + step.pulse_off_s
        if period <= 0:
            return
        v, i = values["voltage"], values["current"]
        if not isinstance(v, float) or not isinstance(i, float):
            return
        on = (st % period) < step.pulse_on_s and st < period * step.pulse_count
        r = self._r
        if on and r.pulse_on is False and r.rest_vi is not None:
            r.pulse_start = r.rest_vi
        if not on and r.pulse_on is True and r.pulse_start is not None and r.on_vi is not None:
            dv = r.on_vi[0] - r.pulse_start[0]
            di = r.on_vi[1] - r.pulse_start[1]
            if abs(di) > 1e-6:
                res = dv / di
                self._set("internal_resistance", res)
                self._emit("message", f"DC internal resistance {res * 1000:.1f} mohm")
        if on:
            r.on_vi = (v, i)
        else:
            r.rest_vi = (v, i)
        r.pulse_on = on

    def _kind_done(self, step: CompiledStep, st: float) -> str:
        if step.kind == "pulse":
            period = step.pulse_on_s + step.pulse_off_s
            if period > 0 and st >= period * step.pulse_count - 1e-9:
                return "pulses done"
        elif step.kind == "profile" and step.profile:
            if st >= step.profile[-1].t_s * step.profile_repeat - 1e-9:
                return "profile done"
        elif step.kind == "sleep" and step.sleep_s is not None and st >= step.sleep_s - 1e-9:
            return "sleep done"
        return ""

    def setpoint(self) -> float:
        """Current the running step asks for now (A, + charges)."""
        if self.state is not State.RUNNING or self.program is None:
            return 0.0
        r = self._r
        if r.sleep_until_t is not None:
            return 0.0
        step = self.program.steps[r.step]
        st = self.clock.now() - r.t_step0
        if step.kind in ("charge", "discharge", "cv", "cccv"):
            return step.current_a
        if step.kind == "pulse":
            period = step.pulse_on_s + step.pulse_off_s
            return step.current_a if period > 0 and (st % period) < step.pulse_on_s else 0.0
        if step.kind == "power" and step.power_w is not None:
            v = self.ch.voltage.as_float()
            return step.power_w / v if self.ch.voltage.good and v > 0.05 else 0.0
        if step.kind == "profile" and step.profile:
            row = self._profile_row(step, st)
            return row.current_a if row is not None else 0.0
        return 0.0

    def _profile_row(self, step: CompiledStep, st: float):  # type: ignore[no-untyped-def]
        total = step.profile[-1].t_s
        t = st % total if total > 0 else 0.0
        row = None
        for p in step.profile:
            if p.t_s <= t + 1e-9:
                row = p
            else:
                break
        return row

    def _values(self, now: float, step: CompiledStep) -> dict[str, float | bool | None]:
        ch, r = self.ch, self._r

        def g(tag) -> float | None:  # type: ignore[no-untyped-def]
            return tag.as_float() if tag.good else None

        q = ch.charge_ah.as_float()
        v = g(ch.voltage)
        dv_dt = None
        if len(self._dv) >= 2 and self._dv[-1][0] - self._dv[0][0] >= DV_DT_MIN_SPAN_S:
            (t0, v0), (t1, v1) = self._dv[0], self._dv[-1]
            dv_dt = (v1 - v0) / (t1 - t0)
        values: dict[str, float | bool | None] = {
            "voltage": v,
            "current": g(ch.current),
            "temperature": g(ch.temperature),
            "power": g(ch.power),
            "charge": self._charge(),
            "energy": ch.energy_wh.as_float(),
            "step_charge": q - r.step_q0,
            "step_energy": ch.energy_wh.as_float() - r.step_e0,
            "step_time": now - r.t_step0,
            "cycle_time": now - r.t_cycle0,
            "test_time": now - r.t_test0,
            "cycle": float(r.cycle),
            "dv_dt": dv_dt,
            "delta_peak": (r.peak_v - v) if (r.peak_v is not None and v is not None) else None,
            "peak_voltage": r.peak_v,
        }
        assert self.program is not None
        values.update(self.program.parameters)
        # Bench tags by full name (only those the program reads are looked up).
        for name in self._tag_names:
            tag = self.db.get(name)
            tv = tag.value if tag is not None and tag.good else None
            values[name] = (
                tv if isinstance(tv, bool | float) else float(tv) if isinstance(tv, int) else None
            )
        return values

    def _charge(self) -> float:
        assert self.program is not None
        return self.program.initial_charge_ah + self.ch.charge_ah.as_float() - self._r.q0_ah

    def _limit_violation(
        self, values: dict[str, float | bool | None], step: CompiledStep, now: float
    ) -> str:
        assert self.program is not None
        lim = self.program.limits
        checks = [
            ("voltage", lim.voltage_v, "V"),
            ("current", lim.current_a, "A"),
            ("temperature", lim.temperature_c, "degC"),
        ]
        if step.kind == "profile" and step.profile:
            row = self._profile_row(step, now - self._r.t_step0)
            if row is not None:
                checks += [
                    ("voltage", (row.v_min, row.v_max), "V"),
                    ("current", (row.i_min, row.i_max), "A"),
                    ("temperature", (row.t_min, row.t_max), "degC"),
                ]
        for name, (lo, hi), unit in checks:
            x = values.get(name)
            if not isinstance(x, float):
                continue
            if lo is not None and x < lo:
                return f"limit: {name} {x:.4g} {unit} below {lo:g} {unit} in step {step.id}"
            if hi is not None and x > hi:
                return f"limit: {name} {x:.4g} {unit} above {hi:g} {unit} in step {step.id}"
        return ""

    # --- transitions --------------------------------------------------------------------------
    def _act(self, action: Action, cause: str, now: float) -> None:
        r = self._r
        k = action.kind
        if k is ActionKind.NEXT:
            self._goto(r.step + 1, cause, now)
        elif k is ActionKind.GOTO:
            assert action.target is not None
            self._goto(action.target, cause, now)
        elif k is ActionKind.NEXT_CYCLE:
            self._next_cycle(cause, now)
        elif k is ActionKind.END:
            self._complete(cause, now)
        elif k is ActionKind.HOLD:
            self._set_state(State.HOLDING, cause)
        elif k in (ActionKind.SLEEP, ActionKind.SLEEP_UNTIL):
            r.sleep_until_t = self._wake_time(action, now)
            r.sleep_then = r.step + 1
            self._record(now, self.program.steps[r.step], "step change")  # type: ignore[union-attr]
            self._emit("step", f"{action} ({cause})")

    def _wake_time(self, action: Action, now: float) -> float:
        if action.kind is ActionKind.SLEEP:
            return now + (action.seconds or 0.0)
        assert action.hhmm is not None
        return now + seconds_until(self.clock.to_wall(now), *action.hhmm)

    def _goto(self, index: int, cause: str, now: float) -> None:
        assert self.program is not None
        if index >= len(self.program.steps):
            self._next_cycle(f"{cause}; end of steps", now)
            return
        self._enter(index, cause, now)

    def _next_cycle(self, cause: str, now: float) -> None:
        r = self._r
        assert self.program is not None
        self._record(now, self.program.steps[r.step], "step change")
        self._emit("step", f"end of cycle {r.cycle} ({cause})")
        if r.cycle >= self.program.cycles:
            self._complete(f"{cause}; cycle {r.cycle} of {self.program.cycles} done", now)
            return
        r.cycle += 1
        r.t_cycle0 = now
        self._reset_cycle_counters()
        self._enter(0, f"cycle {r.cycle} starts", now, record_prev=False)

    def _complete(self, cause: str, now: float) -> None:
        r = self._r
        r.end_reason = cause
        if self.program is not None:
            self._record(now, self.program.steps[r.step], "end")
        self._set_state(State.COMPLETE, cause)

    def _enter(self, index: int, cause: str, now: float, record_prev: bool = True) -> None:
        """Activate a step; instant steps (goto, end of cycle, end, sleep_until) act at once."""
        assert self.program is not None
        r = self._r
        for _ in range(MAX_INSTANT_STEPS):
            prev = self.program.steps[r.step] if r.step_count else None
            if prev is not None and record_prev:
                self._record(now, prev, "step change")
            record_prev = True
            step = self.program.steps[index]
            for g in step.groups:
                if prev is None or g not in prev.groups:
                    r.group_t0[g] = now
            r.step = index
            r.step_count += 1
            r.t_step0 = now
            r.step_q0 = self.ch.charge_ah.as_float()
            r.step_e0 = self.ch.energy_wh.as_float()
            r.peak_v = None
            self._dv.clear()
            # DCIR reference: the last reading before the step's first pulse.
            ch = self.ch
            r.pulse_on, r.on_vi, r.pulse_start = False, None, None
            r.rest_vi = (
                (ch.voltage.as_float(), ch.current.as_float())
                if ch.voltage.good and ch.current.good
                else None
            )
            label = f"{step.id}" + (f" ({step.comment})" if step.comment else "")
            self._emit("step", f"starting step {index + 1} {label} ({cause})")
            if step.kind == "goto" and step.goto is not None:
                index, cause = step.goto, f"goto {self.program.steps[step.goto].id}"
                continue
            if step.kind == "end_cycle":
                self._next_cycle("end of cycle step", now)
                return
            if step.kind == "end":
                self._complete("end step", now)
                return
            if step.kind == "sleep_until" and step.sleep_until is not None:
                r.sleep_until_t = now + seconds_until(self.clock.to_wall(now), *step.sleep_until)
                r.sleep_then = index + 1
            self._record(now, step, "step change")
            return
        self._alarm("goto loop without a step that takes time")
        self._set_state(State.ABORTING, "goto loop")

    # --- outputs, records, tags -----------------------------------------------------------------
    def _outputs(self) -> None:
        running = self.state in ENERGISED and not self._alarm_latched
        interlocked = bool(self._get("interlock"))
        amps = self.setpoint() if running and not interlocked else 0.0
        self.db.update(self.ch.auto_current, amps)
        self.db.update(self.ch.auto_active, running)
        cv = 0.0
        if running and self.program is not None and self._r.sleep_until_t is None:
            step = self.program.steps[self._r.step]
            if step.kind in ("cv", "cccv") and step.voltage_v is not None:
                cv = step.voltage_v
        self.db.update(self.ch.auto_voltage, cv)

    def _record(self, now: float, step: CompiledStep, reason: str = "") -> None:
        if not self.recorders or self.program is None:
            return
        r, ch = self._r, self.ch
        v = ch.voltage.as_float() if ch.voltage.good else None
        i = ch.current.as_float() if ch.current.good else None
        if not reason:
            rule = step.log
            period = rule.period_s if rule.period_s is not None else self.program.log.period_s
            dv = rule.delta_v if rule.delta_v is not None else self.program.log.delta_v
            di = rule.delta_i if rule.delta_i is not None else self.program.log.delta_i
            if period is not None and now - r.last_rec_t >= period - 1e-9:
                reason = "period"
            elif _moved(v, r.last_rec_v, dv):
                reason = "delta_v"
            elif _moved(i, r.last_rec_i, di):
                reason = "delta_i"
            else:
                return
        r.last_rec_t, r.last_rec_v, r.last_rec_i = now, v, i
        st = now - r.t_step0
        rec = Record(
            t=now,
            wall=self.clock.to_wall(now),
            test_time_s=now - r.t_test0,
            step_time_s=st,
            cycle_time_s=now - r.t_cycle0,
            cycle=r.cycle,
            step_count=r.step_count,
            step_index=step.index,
            step_id=step.id,
            step_type=step.step_type,
            voltage_v=v,
            current_a=i,
            power_w=ch.power.as_float() if ch.power.good else None,
            temperature_c=ch.temperature.as_float() if ch.temperature.good else None,
            charge_ah=self._charge(),
            charged_ah=self._since("charged_ah", r.test0),
            discharged_ah=self._since("discharged_ah", r.test0),
            charged_wh=self._since("charged_wh", r.test0),
            discharged_wh=self._since("discharged_wh", r.test0),
            cycle_charged_ah=self._since("charged_ah", r.cycle0),
            cycle_discharged_ah=self._since("discharged_ah", r.cycle0),
            cycle_charged_wh=self._since("charged_wh", r.cycle0),
            cycle_discharged_wh=self._since("discharged_wh", r.cycle0),
            setpoint_a=self.setpoint(),
            step_remaining_s=(step.duration_s - st) if step.duration_s is not None else None,
            reason=reason,
        )
        for rec_fn in self.recorders:
            try:
                rec_fn(rec)
            except Exception:
                log.exception("%s: result recorder failed", self.name)

    def _counters(self) -> dict[str, float]:
        return {name: getattr(self.ch, name).as_float() for name in COUNTERS}

    def _since(self, name: str, base: dict[str, float]) -> float:
        """A channel counter relative to the test start or the cycle start (BDF scopes)."""
        return float(getattr(self.ch, name).as_float() - base.get(name, 0.0))

    def _reset_cycle_counters(self) -> None:
        self._r.cycle0 = self._counters()

    def _publish(self, now: float) -> None:
        r = self._r
        running = self.state in (State.RUNNING, State.HOLDING, State.HELD, State.RESUMING)
        step = self.program.steps[r.step] if (self.program and r.step_count) else None
        self._set("step", step.id if step else "")
        self._set("step_index", (step.index + 1) if step else 0)
        self._set("cycle", r.cycle if r.step_count else 0)
        if running and self.state is State.RUNNING:
            self._set("step_time", now - r.t_step0)
            self._set("test_time", now - r.t_test0)
        est = self.estimated_duration_s
        if running and est:
            elapsed = now - r.t_test0
            self._set("progress", min(1.0, elapsed / est))
            self._set("eta_s", max(0.0, est - elapsed))
        elif (
            running
            and step is not None
            and step.kind in ("charge", "discharge")
            and self.program is not None
            and self.program.capacity_ah
        ):
            # Against the rated capacity (seed 001's progress bar): charge moved in this
            # step over the capacity; ETA at the step's current.
            cap = self.program.capacity_ah
            moved = abs(self.ch.charge_ah.as_float() - r.step_q0)
            self._set("progress", min(1.0, moved / cap))
            amps = abs(step.current_a)
            self._set("eta_s", max(0.0, (cap - moved) * 3600.0 / amps) if amps > 0 else None)
        elif self.state is State.COMPLETE:
            self._set("progress", 1.0)
            self._set("eta_s", 0.0)
        if running and now - self._last_display_t >= self.display_period_s and step is not None:
            self._last_display_t = now
            log.info("%s: %s", self.name, self.display_line(now))

    def display_line(self, now: float) -> str:
        """Seed 000 §III.E.1 display: ``C/01/07 dba=0 mA= 50 CET= … V=1.373 mAh=1302.0, date``."""
        r = self._r
        assert self.program is not None
        step = self.program.steps[r.step]
        amps = self.ch.current_cmd.as_float()
        cd = "C" if amps >= 0 else "D"
        st = now - r.t_step0
        sta = max(0.0, step.duration_s - st) if step.duration_s is not None else 0.0
        wall = time.strftime("%a %b %d %H:%M:%S %Y", time.localtime(self.clock.to_wall(now)))
        return (
            f"{cd}/{r.cycle:02d}/{step.index + 1:02d} dba={self.dba} mA={abs(amps) * 1000:3.0f}"
            f" CET= {now - r.t_cycle0:.0f} SET= {st:.0f} TET= {now - r.t_test0:.0f}"
            f" STA= {sta:.0f} V={self.ch.voltage.as_float():.3f} mAh={self._charge() * 1000:.1f},"
            f" {wall}"
        )

    def _alarm(self, text: str) -> None:
        self._alarm_latched = True
        self._set("alarm", text)
        log.error("%s: %s", self.name, text)
        self._emit("alarm", text)

    def _set_state(self, state: State, cause: str) -> None:
        if state is self.state and not cause.startswith("recipe "):
            return
        old = self.state
        self.state = state
        self._set("state", state.value)
        self._set("state_code", OPCUA_CODE[state])
        if state in (State.HOLDING, State.HELD) and self._r.held_since is None:
            self._r.held_since = self.clock.now()
        if state in (State.STOPPED, State.ABORTED, State.COMPLETE) and not self._r.end_reason:
            self._r.end_reason = cause
        self._emit("state", f"{old.value} → {state.value} ({cause})")

    def _emit(self, kind: str, text: str) -> None:
        now = self.clock.now()
        r = self._r
        step_id = ""
        if self.program is not None and r.step_count:
            step_id = self.program.steps[r.step].id
        ev = ChainEvent(
            now, self.clock.to_wall(now), self.name, kind, text, r.step, step_id, r.cycle
        )
        self.events.append(ev)
        self._set("last_event", text)
        log.info("%s: %s", self.name, text)
        for fn in self.listeners:
            try:
                fn(ev)
            except Exception:
                log.exception("%s: event listener failed", self.name)

    def _set(self, field_: str, value: object) -> None:
        self.db.update(self.db[f"{self.name}.chain.{field_}"], value)  # type: ignore[arg-type]

    def _get(self, field_: str) -> object:
        return self.db[f"{self.name}.chain.{field_}"].value

    @property
    def end_reason(self) -> str:
        return self._r.end_reason

    @property
    def test_id(self) -> str:
        return self._r.test_id


def _moved(x: float | None, last: float | None, delta: float | None) -> bool:
    """A logging rule's ΔV / ΔI: has the value moved by ``delta`` since the last record?"""
    return delta is not None and x is not None and last is not None and abs(x - last) >= delta


def seconds_until(wall_now: float, hh: int, mm: int) -> float:
    """Seconds from ``wall_now`` to the next local HH:MM (Chadèche's sleep action)."""
    lt = time.localtime(wall_now)
    target = time.mktime((lt.tm_year, lt.tm_mon, lt.tm_mday, hh, mm, 0, 0, 0, -1))
    if target <= wall_now:
        lt2 = time.localtime(wall_now + 86400)
        target = time.mktime((lt2.tm_year, lt2.tm_mon, lt2.tm_mday, hh, mm, 0, 0, 0, -1))
    return target - wall_now
