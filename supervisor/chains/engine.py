"""The step-chain engine: one chain per channel, ISA-88 states, S7-GRAPH guards.

The chain reads tags and requests setpoints through its ``ChannelPort`` (``chN.auto_current``,
``chN.auto_active``); it never calls a driver nor sees the channel object. The channel's own
protection runs after it in the same scan and always wins (a chain can never override an
interlock).

``ChainRunner`` orchestrates its collaborators, each with one job:

- ``states``: the state table and the command guards (``decide``);
- ``behaviours``: what each step asks for and when it is done by itself (chosen at load);
- ``conditions``: the values conditions read (dV/dt window, peak since the step start);
- ``sampling``: when a result sample is due and what it holds;
- ``progress``: progress and ETA.

It emits ``ChainEvent``s to its listeners, ``Record``s to its recorders, and snapshots to
its samplers (``supervisor.core.records``); result files and the Chadèche display line are
publishers of those (``supervisor.publish``).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable

from supervisor.chains.behaviours import StepBehaviour
from supervisor.chains.chaintags import CHAIN_FIELDS, add_chain_tags
from supervisor.chains.conditions import ConditionValues, Values
from supervisor.chains.kinds import behaviours_for
from supervisor.chains.port import ChannelPort
from supervisor.chains.program import Action, ActionKind, CompiledStep, Program
from supervisor.chains.progress import Progress
from supervisor.chains.rules import StepRules
from supervisor.chains.run import ChainSnapshot, RunState, check_snapshot
from supervisor.chains.sampling import LogRules, build_record
from supervisor.chains.states import (
    ACTIVE,
    AUTO_NEXT,
    COMMANDS,
    ENERGISED,
    FINAL,
    LOADABLE,
    OPCUA_CODE,
    TABLE,
    Situation,
    State,
    check_load,
    decide,
)
from supervisor.config.limits import MAX_TRANSITIONS_PER_SCAN
from supervisor.core.clock import Clock
from supervisor.core.driver import Value
from supervisor.core.errors import OperatorError
from supervisor.core.quality import Quality, Reason
from supervisor.core.records import ChainEvent, Record, Sampler
from supervisor.tags import Tag, TagDB

__all__ = [
    "COMMANDS",
    "OPCUA_CODE",
    "TABLE",
    "ChainEvent",
    "ChainRunner",
    "ChainSnapshot",
    "Record",
    "State",
    "seconds_until",
]

log = logging.getLogger(__name__)

EVENTS_KEPT = 200
TRANSITION_KINDS = ("step", "state")
"""The events that are the chain's own transitions (``chN.chain.last_transition``): a step
entered, a cycle ended, a state changed, each with its cause; not a command, a message or
an alarm."""
_GOOD = Quality.GOOD
_NONE = Reason.NONE
_RUNNING = State.RUNNING


class ChainRunner:
    """Executes a Program on one channel. Runs as a scan logic phase before the channel."""

    _fast = True
    _acting: tuple[State, State, str] | None = None
    """The last entry into an acting state: from, to, cause (``_note_acting``)."""
    """The running scan computes only the condition values the program reads and asks a
    behaviour only what it answers differently from a rest step, and a steady scan (see
    ``run``) takes its short way (docs/adr/0018, "Dry run"); False only in the tests that
    check it against asking everything every scan."""

    def __init__(self, port: ChannelPort, db: TagDB, clock: Clock) -> None:
        self.port = port
        self.db = db
        self.clock = clock
        self.name = port.name
        self.program: Program | None = None
        self.state = State.IDLE
        self.listeners: list[Callable[[ChainEvent], None]] = []
        self.recorders: list[Callable[[Record], None]] = []
        self.samplers: list[Sampler] = []
        # The latest events, for a look from a debugger or a test; every event also goes
        # to the listeners (results, retained state, publishers). 200: full after minutes,
        # not after half an hour (issue 13's memory growth).
        self.events: deque[ChainEvent] = deque(maxlen=EVENTS_KEPT)
        # Set by the composition root: a command written to ``chN.command`` (by an older
        # client) goes through the bench's one command path, which checks and records it.
        self.command_handler: Callable[[str], None] | None = None
        self.progress = Progress()
        self._r = RunState()
        self.hold_reason = ""
        """Why the chain last went Holding: an until's ``hold``, a fault, a supervision
        rule, an operator. A hold with no alarm and no fault (``voltage >= 0 V: hold``) had
        no other words, and a dry run ended with "end: Held: " (issue 28)."""
        # Whether the loaded test (``_r.test_id``) has been started: a later start (after
        # a reset) is a new test with a new id, never the old one reopened (issue 26).
        self._test_started = False
        # Set by the composition root: a new test id for this channel, unique among its
        # result folders. The default serves a chain without result files (unit tests).
        self.new_test_id: Callable[[], str] = self._default_test_id
        self._alarm_latched = False
        self._pending_advance = False
        # The steps started in the scan at ``_scan_t`` (bounded: MAX_TRANSITIONS_PER_SCAN).
        self._scan_t: float | None = None
        self._started: list[int] = []
        # Set at load: one behaviour per step, the condition values, the logging rules.
        self._behaviours: tuple[StepBehaviour, ...] = ()
        self._instant: tuple[bool, ...] = ()
        self._setpoints: tuple[float | None, ...] = ()
        self._conditions: ConditionValues | None = None
        self._log_rules: LogRules | None = None
        # The running steps' rules (limits, supervision, interlock, untils, ends), set at
        # load: one description for the plain and the steady scan.
        self._rules: StepRules | None = None
        # Per step, from when a record may be due (``LogRules.may_be_due_s``), set at load.
        self._may_be_due_s: tuple[float, ...] = ()
        n = port.name
        add_chain_tags(db, n)
        self._cmd = db[f"{n}.command"]
        self._tags: dict[str, Tag] = {f: db[f"{n}.chain.{f}"] for f in CHAIN_FIELDS}
        tags = self._tags
        self._publish_tags = (
            tags["step"],
            tags["step_index"],
            tags["cycle"],
            tags["step_time"],
            tags["test_time"],
        )
        self._interlock_tag = tags["interlock"]
        self._progress_tags = (tags["progress"], tags["eta_s"])
        self._charge_tag = tags["charge_ah"]
        # Whether ``chN.chain.charge_ah`` follows the counter: from a start (or a restored
        # test) until the scan after the test ends, which writes the final figure.
        self._charge_live = False

    @property
    def estimated_duration_s(self) -> float | None:
        return self.progress.estimated_duration_s

    @estimated_duration_s.setter
    def estimated_duration_s(self, value: float | None) -> None:
        self.progress.estimated_duration_s = value

    # --- loading and commands ----------------------------------------------------------
    def load(self, program: Program, test_id: str | None = None) -> None:
        """Load a recipe; mode and enable are left as they are (refused while the operator
        drives the channel in Manual)."""
        check_load(self.name, self.state, self.port.manual_driven)
        self._install(program)
        self._r = RunState(test_id=test_id or self.new_test_id())
        self._test_started = False
        self._set("recipe", program.name)
        self._set("test_id", self._r.test_id)
        self._charge_live = False
        self._set("charge_ah", program.initial_charge_ah)
        self._set_state(State.IDLE, f"recipe {program.name} loaded")

    def _install(self, program: Program) -> None:
        self.program = program
        # Each step's behaviour is chosen once, here: the scan never looks at a kind name.
        behaviours = self._behaviours = behaviours_for(program.steps)
        self._instant = tuple(step.instant for step in program.steps)
        # A behaviour whose setpoint is a constant: asked once, here (``_outputs``).
        self._setpoints = tuple(
            None if b.setpoint_varies else b.setpoint(0.0, None) for b in behaviours
        )
        rules = self._rules = StepRules(program)
        # The readings the running scan looks at besides the conditions' names: the
        # limits' and each behaviour's own (derived from its class, all of them when it
        # says nothing).
        readings = {"voltage", *rules.readings}
        for b in behaviours:
            readings |= b.readings
        self._conditions = ConditionValues(self.port, self.db, program, readings)
        self._log_rules = log_rules = LogRules(program)
        self._may_be_due_s = log_rules.may_be_due_s

    # --- retained state (docs/design.md "Safety": a restart brings the test back Held) ---
    def snapshot(self) -> ChainSnapshot | None:
        """The test as a restart needs it (None when no recipe is loaded). Cheap: plain
        values copied in the scan; writing them is someone else's job, off the scan."""
        program = self.program
        if program is None:
            return None
        now = self.clock.now()
        r = self._r
        conditions = self._conditions
        return r.freeze(
            state=self.state.value,
            recipe=program.name,
            step_id=program.steps[r.step].id if r.step_count else "",
            alarm=str(self._get("alarm") or "") if self._alarm_latched else "",
            peak_v=conditions.peak_v if conditions is not None else None,
            now=now,
            wall=self.clock.to_wall(now),
            to_wall=None if r.sleep_until_t is None else self.clock.to_wall(r.sleep_until_t),
        )

    def restore(self, snapshot: ChainSnapshot, program: Program) -> float:
        """Bring back a test saved by ``snapshot`` (by this or another process), with
        ``program`` compiled from the same recipe: Held at the same step, with its step
        time, cycle, counter baselines and latched alarm, ``resume`` available; nothing is
        energised until someone resumes (seed 001: the context is saved so that an
        interrupted test resumes later). Returns the time the test was away (s).

        Only a test under way (Running, Holding, Held, Resuming) is restored; the caller
        keeps the channel Idle for any other. ValueError when the snapshot does not fit
        ``program``.
        """
        check_load(self.name, self.state)
        check_snapshot(self.name, snapshot, program)
        self._install(program)
        now = self.clock.now()
        self._r, away_s = RunState.thaw(snapshot, now, self.clock.to_wall(now))
        self._test_started = True  # the same test goes on: a later start is a new one
        r = self._r
        assert self._conditions is not None
        self._conditions.restart()
        self._conditions.peak_v = snapshot.peak_v
        port = self.port
        v, i = port.voltage, port.current
        self._behaviours[r.step].enter(
            v.as_float() if v.good else None, i.as_float() if i.good else None
        )
        self._pending_advance = False
        self._alarm_latched = bool(snapshot.alarm)
        self._set("alarm", snapshot.alarm)
        self._set("interlock", "")
        self._set("recipe", program.name)
        self._set("test_id", r.test_id)
        self._set("step_time", snapshot.step_time_s)
        self._set("test_time", now - r.t_test0)
        self.state = State.HELD
        self._set("state", State.HELD.value)
        self._set("state_code", OPCUA_CODE[State.HELD])
        self._charge_live = True
        self._publish(now)
        self._emit(
            "state",
            f"supervisor restarted after {away_s:.1f} s; test held"
            f" (was {snapshot.state} in step {snapshot.step_id or r.step + 1})",
        )
        return away_s

    def situation(self) -> Situation:
        """What the command guards look at (see ``states.decide``)."""
        return Situation(
            has_program=self.program is not None,
            channel_fault=self.port.fault_text(),
            alarm=str(self._get("alarm")) if self._alarm_latched else None,
            in_manual=not self.port.in_auto,
            manual_enabled=self.port.enable.value is True,
        )

    def command(self, cmd: str, actor: str = "operator") -> None:
        nxt = decide(self.name, self.state, cmd, self.situation())
        if cmd == "ack":
            if self._alarm_latched:
                self._emit("alarm", f"acknowledged by {actor}: {self._get('alarm')}")
                self._alarm_latched = False
                # S7-GRAPH: an acknowledged step-time error does not fire again for the
                # same activation of the step.
                self._r.max_time_acked = self._r.step_count
                self._set("alarm", "")
            return
        if cmd == "start":
            self._start(actor)
            return
        if cmd == "advance":
            self._pending_advance = True  # acted on by the next running scan
            return
        if cmd == "reset":
            if self.program is not None:
                # The ended test keeps its id (its files are closed); the next start makes
                # a new one (``_start``).
                self._r = RunState(test_id=self._r.test_id)
            # The test is over: the channel goes back to the operator, Manual, disabled, at
            # 0 A (an explicit, recorded part of the reset, never left in Auto).
            self.port.release_control()
            self._set_state(nxt, f"reset by {actor}; channel in manual, enable off, 0 A")
            return
        self._set_state(nxt, f"{cmd} by {actor}")

    def record_command(self, text: str) -> None:
        """An operator command concerning this channel, accepted or refused (from the
        command path, which has logged it): into this chain's events, and into the test's
        timeline while a test is under way."""
        under_way = self.state not in LOADABLE
        self._set("last_command", text)
        self._emit("command" if under_way else "message", text, quiet=True, echo=True)

    def _start(self, actor: str) -> None:
        assert self.program is not None
        now = self.clock.now()
        r = self._r
        if self._test_started:
            # Start after a reset: a new test, with a new id and its own result files;
            # the previous one stays as it ended (issue 26: a second run was recorded
            # nowhere, its rows dropped by the first test's closed files).
            r.test_id = self.new_test_id()
            self._set("test_id", r.test_id)
        self._test_started = True
        r.t_test0 = r.t_cycle0 = now
        r.q0_ah = self.port.charge_ah.as_float()
        self._charge_live = True
        self._set("charge_ah", self.program.initial_charge_ah)
        r.test0 = self.port.counters()
        r.cycle = 1
        # Start hands the channel to its chain: Auto mode, the manual enable dropped.
        self.port.take_control()
        r.cycle0 = self.port.counters()
        self._set_state(State.RUNNING, f"start by {actor}")
        self._enter(0, "start", now)

    # --- the scan phase ------------------------------------------------------------------
    def run(self, now: float, dt: float) -> None:
        """One scan: the command, the running step's checks, the outputs, the tags.

        A steady scan — running, nothing commanded, no fault and no latched alarm, in
        Auto, no sleep or advance pending, in a step that takes time — takes a short way
        (issue 13: nearly every scan of a test is one): the step's rules (``StepRules``,
        the plain scan's too) without the checks a steady scan cannot need, then the
        outputs and tags as ``_outputs`` and ``_publish`` write them, in one
        ``TagDB.update_many`` (``_steady_outputs``: an unchanged tag left as it is, as its
        update would, ADR 0037). Whatever
        happens in the step (an alarm, a transition, a record) ends the scan the plain
        way. ``tests/unit/test_chain_steady_scan.py`` and
        ``tests/unit/test_step_kinds_equivalence.py`` check it, tag by tag, against the
        plain scan (``_fast`` False).
        """
        port, r = self.port, self._r
        index = r.step
        if not (
            self._fast
            and self.state is _RUNNING
            and not self._cmd.value
            and not port.fault.value
            and port.mode.value == port.auto_mode
            and not self._alarm_latched
            and not self._pending_advance
            and r.sleep_until_t is None
            and r.step_count
            and not self._instant[index]
        ):
            self._scan(now, dt)
            return
        program, conditions = self.program, self._conditions
        assert program is not None and conditions is not None
        step = program.steps[index]
        try:
            # ``_running`` of a steady scan: the voltage observed and the values read in
            # one call, then the step's rules (the checks a steady scan cannot need left
            # out; here, not in a method of its own: a call fewer every scan).
            values = conditions.observed_values(now, r)
            steady = self._step_rules(now, r, step, self._behaviours[index], values)
        except Exception as exc:  # as in ``_scan``: an exception in logic is an alarm
            log.exception("%s: chain failed", self.name)
            self._alarm(f"internal error: {exc}")
            self._set_state(State.ABORTING, "internal error")
            steady = False
        if not steady:
            self._outputs()
            self._publish(now)
            return
        self._steady_outputs(now, r, program, step)

    def _scan(self, now: float, dt: float) -> None:
        """``run``'s plain way: every case."""
        cmd = self._cmd.value
        if cmd:
            self.db.update(self._cmd, "")
            if self.command_handler is not None:
                self.command_handler(str(cmd))  # checked, answered and recorded there
            else:
                try:
                    self.command(str(cmd))
                except OperatorError as exc:
                    log.warning("%s", exc)
                    self._emit("message", str(exc))
        port = self.port
        if port.fault.value and port.trip_aborts and self.state in ACTIVE:
            # docs/design.md "Safety": the e-stop aborts the test (a hold would leave it resumable).
            self._set_state(State.ABORTING, f"channel trip: {self.port.fault_text()}")
        state = self.state
        if state in AUTO_NEXT:
            self._set_state(AUTO_NEXT[state], "done")
            if self.state is State.RUNNING:
                r = self._r
                if r.held_since is not None:
                    # Step time excludes the time spent held (the step resumes where it
                    # was); a sleep until a time of day keeps its wall-clock target.
                    r.t_step0 += now - r.held_since
                    for g in r.group_t0:
                        r.group_t0[g] += now - r.held_since
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
        port, r, program, conditions = self.port, self._r, self.program, self._conditions
        assert program is not None and conditions is not None
        if port.fault.value:
            self._set_state(State.HOLDING, f"channel fault: {port.fault_text()}")
            return
        if port.mode.value != port.auto_mode:  # not port.in_auto
            self._set_state(State.HOLDING, "channel switched to manual")
            return
        voltage = port.voltage
        if voltage.quality is _GOOD:
            conditions.observe(now, voltage.number)
        index = r.step
        step = program.steps[index]
        behaviour = self._behaviours[index]
        if self._instant[index]:  # step.instant
            self._carry_on(step, now)  # held in a goto chain, resumed (ADR 0011)
            return
        if r.sleep_until_t is not None:
            if now < r.sleep_until_t:
                self._record(now, step)
                return
            nxt = r.sleep_then if r.sleep_then is not None else r.step + 1
            r.sleep_until_t = r.sleep_then = None
            self._goto(nxt, "woke up", now)
            return
        # Only the values this chain reads (its conditions, limits and behaviours).
        fast = self._fast
        values = conditions.values_read(now, r) if fast else conditions.values(now, r)
        self._step_rules(now, r, step, behaviour, values)

    def _step_rules(
        self,
        now: float,
        r: RunState,
        step: CompiledStep,
        behaviour: StepBehaviour,
        values: Values,
    ) -> bool:
        """The running step's rules (``StepRules``) for this scan, acted on in their order:
        True when the step simply goes on, False when something happened (an alarm, a
        transition, a record)."""
        rules = self._rules
        assert rules is not None
        fast = self._fast
        st = values["step_time"]
        assert isinstance(st, float)
        # A limit held past its on-delay, a supervision: hold, latched alarm.
        why = rules.hold(now, r, step, behaviour, st, values, self.port.armed.value is True, fast)
        if why:
            self._alarm(why)
            self._set_state(State.HOLDING, why)
            return False
        # The interlock's text: an update only when it would change the tag (an unchanged
        # one is left as it is, ADR 0037; no call most scans).
        text = "" if step.interlock is None else rules.interlock(step, values)
        tag = self._interlock_tag
        if text != tag.value or tag.quality is not _GOOD or tag.reason is not _NONE:
            self.db.update(tag, text)
        if self._pending_advance:
            self._pending_advance = False
            if step.advance is None:
                self._emit("message", f"advance refused in step {step.id}")
            else:
                self._act(step.advance, "operator advance", now)
                return False
        hit, resistance = rules.next(now, r, step, behaviour, st, values, fast)
        if resistance is not None:
            self._set("internal_resistance", resistance)
            self._emit("message", f"DC internal resistance {resistance * 1000:.1f} mohm")
        if hit is not None:
            self._act(hit[0], hit[1], now)
            return False
        # ``_record(now, step)`` once a record may be due (it does nothing when none is).
        # A record calls out to the recorders, which may act on the chain: the plain
        # outputs and tags follow it.
        if self.recorders and now - r.last_rec_t >= self._may_be_due_s[step.index]:
            return not self._record(now, step)
        return True

    def setpoint(self) -> float:
        """Current the running step asks for now (A, + charges)."""
        if self.state is not State.RUNNING or self.program is None:
            return 0.0
        r = self._r
        if r.sleep_until_t is not None:
            return 0.0
        v = self.port.voltage
        return self._behaviours[r.step].setpoint(
            self.clock.now() - r.t_step0, v.as_float() if v.quality is _GOOD else None
        )

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
            assert self.program is not None
            r.sleep_until_t = self._wake_time(action, now)
            r.sleep_then = r.step + 1
            self._record(now, self.program.steps[r.step], "step change")
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
        if self._close_cycle(cause, now):
            self._enter(0, f"cycle {self._r.cycle} starts", now, record_prev=False)

    def _close_cycle(self, cause: str, now: float) -> bool:
        """End the cycle: True when another one starts (its first step is for the caller to
        enter), False when the test is complete."""
        r = self._r
        assert self.program is not None
        self._record(now, self.program.steps[r.step], "step change")
        self._emit("step", f"end of cycle {r.cycle} ({cause})")
        if r.cycle >= self.program.cycles:
            self._complete(f"{cause}; cycle {r.cycle} of {self.program.cycles} done", now)
            return False
        r.cycle += 1
        r.t_cycle0 = now
        r.cycle0 = self.port.counters()
        return True

    def _complete(self, cause: str, now: float) -> None:
        r = self._r
        if self.program is not None:
            step = self.program.steps[r.step]
            r.end_reason = f"complete after step {step.id} of cycle {r.cycle}: {cause}"
            self._record(now, step, "end")
        else:
            r.end_reason = f"complete: {cause}"
        self._set_state(State.COMPLETE, cause)

    def _enter(self, index: int, cause: str, now: float, record_prev: bool = True) -> None:
        """Activate a step; instant steps (goto, end of cycle, end, sleep_until) act at once,
        so one scan may start several steps: at most ``MAX_TRANSITIONS_PER_SCAN``, past
        which the chain is held with a supervision alarm (a loop that lets no time pass,
        ADR 0011) rather than spinning in the scan."""
        program, conditions = self.program, self._conditions
        assert program is not None and conditions is not None
        r, port = self._r, self.port
        if now != self._scan_t:
            self._scan_t, self._started = now, []
        while True:
            step = program.steps[index]
            if len(self._started) >= MAX_TRANSITIONS_PER_SCAN:
                self._too_many_transitions(step, now)
                return
            self._started.append(index)
            prev = program.steps[r.step] if r.step_count else None
            if prev is not None and record_prev:
                self._record(now, prev, "step change")
            record_prev = True
            behaviour = self._behaviours[index]
            for g in step.groups:
                if prev is None or g not in prev.groups:
                    r.group_t0[g] = now
            r.step = index
            r.step_count += 1
            r.t_step0 = now
            r.step_q0 = port.charge_ah.as_float()
            r.step_e0 = port.energy_wh.as_float()
            conditions.restart()
            v, i = port.voltage, port.current
            behaviour.enter(v.as_float() if v.good else None, i.as_float() if i.good else None)
            label = f"{step.id}" + (f" ({step.comment})" if step.comment else "")
            self._emit("step", f"starting step {index + 1} {label} ({cause})")
            entry = behaviour.entry
            if entry is not None:
                if entry.kind is ActionKind.GOTO and entry.target is not None:
                    index, cause = entry.target, f"goto {program.steps[entry.target].id}"
                    continue
                if entry.kind is ActionKind.NEXT_CYCLE:
                    # On to the next cycle in this loop (not by recursion): the steps it
                    # starts count against the same per-scan bound.
                    if not self._close_cycle("end of cycle step", now):
                        return
                    index, cause, record_prev = 0, f"cycle {r.cycle} starts", False
                    continue
                if entry.kind is ActionKind.END:
                    self._complete("end step", now)
                    return
                if entry.kind is ActionKind.SLEEP_UNTIL and entry.hhmm is not None:
                    r.sleep_until_t = now + seconds_until(self.clock.to_wall(now), *entry.hhmm)
                    r.sleep_then = index + 1
            self._record(now, step, "step change")
            return

    def _too_many_transitions(self, step: CompiledStep, now: float) -> None:
        """``MAX_TRANSITIONS_PER_SCAN`` steps started in this scan and ``step`` would be
        the next: hold the chain (in the instant step it is in; ``resume`` carries on from
        there, with a new scan's allowance) with a latched supervision alarm naming the
        loop, like a step-time supervision (ADR 0004)."""
        assert self.program is not None
        steps = self.program.steps
        started = self._started
        # The loop: from the last time the next step was started to now.
        last = max((k for k, j in enumerate(started) if j == step.index), default=None)
        loop = [steps[j].id for j in started[last:]] + [step.id] if last is not None else []
        where = f" (loop {' → '.join(loop)})" if loop else ""
        why = (
            f"supervision: {len(started)} steps started in one scan without time passing"
            f"{where}; held before step {step.id!r} (at most {MAX_TRANSITIONS_PER_SCAN}"
            " per scan)"
        )
        self._alarm(why)
        self._set_state(State.HOLDING, why)

    def _carry_on(self, step: CompiledStep, now: float) -> None:
        """The chain was held in an instant step (too many steps in one scan) and resumed:
        that step acts now, as it would have in the scan it started."""
        entry = self._behaviours[step.index].entry
        assert self.program is not None and entry is not None
        if entry.kind is ActionKind.GOTO and entry.target is not None:
            self._enter(entry.target, f"goto {self.program.steps[entry.target].id}", now)
        elif entry.kind is ActionKind.NEXT_CYCLE:
            self._next_cycle("end of cycle step", now)
        elif entry.kind is ActionKind.END:
            self._complete("end step", now)

    # --- outputs, records, tags -----------------------------------------------------------------
    def _outputs(self) -> None:
        running = self.state in ENERGISED and not self._alarm_latched
        amps = cv = 0.0
        if running and self.program is not None and self._r.sleep_until_t is None:
            # ``self.setpoint()`` (Running, a program, no sleep pending), with a constant
            # setpoint taken as it is: asking for it again gives the same.
            index = self._r.step
            if not self._interlock_tag.value:
                amps_now = self._setpoints[index] if self._fast else None
                amps = self.setpoint() if amps_now is None else amps_now
            cv = self._behaviours[index].cv_target_v
        self.port.request(amps, cv, running)

    _held_writes: tuple[CompiledStep | None, int, bool, bool, tuple[Tag, ...], list[Value | None]]
    _held_writes = (None, 0, False, False, (), [])
    """The steady scan's writes for a step, its cycle, whether its progress is shown and
    whether the test's charge is live: (step, cycle, shown, live, tags, values), the values
    that these fix set once for them, the others set each scan (``_steady_outputs``)."""

    def _step_writes(
        self, step: CompiledStep, cycle: int, shown: bool, live: bool
    ) -> tuple[CompiledStep, int, bool, bool, tuple[Tag, ...], list[Value | None]]:
        """The tags ``_steady_outputs`` writes, in its order, and their values, those that
        ``step`` and ``cycle`` fix set (active, the CV target, the step, its number, the
        cycle; the others are set each scan): the request, those five, the clocks, the
        progress and time left if ``shown``, the test's charge if ``live``."""
        port = self.port
        t_step, t_index, t_cycle, t_step_time, t_test_time = self._publish_tags
        tags: tuple[Tag, ...] = (
            port.auto_current,
            port.auto_active,
            port.auto_voltage,
            t_step,
            t_index,
            t_cycle,
            t_step_time,
            t_test_time,
        )
        values: list[Value | None] = [
            0.0,
            True,
            self._behaviours[step.index].cv_target_v,
            step.id,
            step.index + 1,
            cycle,
            0.0,
            0.0,
        ]
        if shown:
            tags += self._progress_tags
            values += (0.0, None)
        if live:
            tags += (self._charge_tag,)
            values.append(0.0)
        return step, cycle, shown, live, tags, values

    def _steady_outputs(
        self, now: float, r: RunState, program: Program, step: CompiledStep
    ) -> None:
        """``_outputs`` then ``_publish`` of a steady scan of ``step`` (see ``run``): the
        same writes in the same order, what a steady scan cannot change left out, in one
        ``TagDB.update_each`` (each value computed before the first is written: none reads
        a tag written here; ``tests/unit/test_chain_steady_scan.py``)."""
        index = step.index
        behaviour = self._behaviours[index]
        port = self.port
        # ``_outputs`` of a running step: its setpoint unless its interlock holds it back.
        amps = 0.0
        if not self._interlock_tag.value:
            amps_now = self._setpoints[index]
            amps = self.setpoint() if amps_now is None else amps_now
        # ``self.progress.shown`` of an active test, inline (the same expressions, with
        # ``min(1.0, x)`` and ``max(0.0, x)`` as conditional ones: the same answers, NaN
        # included): the fraction done and the time left (None: unknown), if shown.
        elapsed_s = now - r.t_test0
        est, current_a = self.progress.estimated_duration_s, behaviour.progress_current_a
        fraction: float | None = None  # None: no progress shown
        left_s: float | None = None  # None: no time left known
        if est:
            fraction, left_s = elapsed_s / est, est - elapsed_s
        elif current_a is not None and program.capacity_ah:
            moved = abs(port.charge_ah.number - r.step_q0)
            fraction, amps_a = moved / program.capacity_ah, abs(current_a)
            if amps_a > 0:
                left_s = (program.capacity_ah - moved) * 3600.0 / amps_a
        shown, live = fraction is not None, self._charge_live
        # What ``port.request(amps, cv, True)`` writes (Running, no alarm latched: active)
        # and what ``_publish`` of a running step writes, in their order: the request, the
        # step, its number and the cycle (the same but after an event, which leaves the
        # steady way), the clocks, the progress, the test's charge. The values the step
        # and its cycle fix are set once for them (``_step_writes``).
        held = self._held_writes
        if held[0] is not step or held[1] != r.cycle or held[2] is not shown or held[3] is not live:
            held = self._held_writes = self._step_writes(step, r.cycle, shown, live)
        values = held[5]
        values[0] = amps
        values[6] = now - r.t_step0
        values[7] = elapsed_s
        if fraction is not None:
            values[8] = fraction if fraction < 1.0 else 1.0
            values[9] = None if left_s is None else left_s if left_s > 0.0 else 0.0
        if live:
            # ``_publish``'s test charge (``ConditionValues.charge_ah``), inline.
            values[-1] = program.initial_charge_ah + port.charge_ah.number - r.q0_ah
        self.db.update_each(held[4], values)
        if self.samplers:
            self._sample(now, step)

    def _record(self, now: float, step: CompiledStep, reason: str = "") -> bool:
        """A record to the recorders when ``reason`` is given or a logging rule says one is
        due; whether one went out."""
        if not self.recorders or self.program is None:
            return False
        assert self._log_rules is not None
        r, port = self._r, self.port
        vt, it = port.voltage, port.current
        # ``Tag.number``: ``as_float()`` without a call (every running scan asks whether a
        # record is due).
        v = vt.number if vt.quality is _GOOD else None
        i = it.number if it.quality is _GOOD else None
        if not reason:
            reason = self._log_rules.reason(step.index, now, r, v, i)
            if not reason:
                return False
        elif reason == "end" and r.last_rec_t == now:
            # The end of the last cycle wrote its record at this very instant: the file
            # ends with it, not with a copy of it (issue 26, 6c: the last row twice).
            return False
        r.last_rec_t, r.last_rec_v, r.last_rec_i = now, v, i
        rec = self._build(now, step, reason)
        for rec_fn in self.recorders:
            try:
                rec_fn(rec)
            except Exception:
                log.exception("%s: result recorder failed", self.name)
        return True

    def _build(self, now: float, step: CompiledStep, reason: str) -> Record:
        assert self._conditions is not None
        return build_record(
            self.port,
            self.clock,
            now,
            self._r,
            step,
            self._behaviours[step.index].step_type,
            self._conditions.charge_ah(self._r),
            self.setpoint(),
            reason,
        )

    def sample(self, now: float | None = None) -> Record | None:
        """The active step's sample at ``now`` (default: the clock's now) for displays;
        None when no step is active."""
        if self.program is None or not self._r.step_count:
            return None
        now = self.clock.now() if now is None else now
        return self._build(now, self.program.steps[self._r.step], "sample")

    def _publish(self, now: float) -> None:
        r, program = self._r, self.program
        state = self.state
        active = state in ACTIVE
        step = program.steps[r.step] if (program and r.step_count) else None
        # Every scan: the tags straight, not by field name (issue 13: the chains' share).
        update = self.db.update
        t_step, t_index, t_cycle, t_step_time, t_test_time = self._publish_tags
        update(t_step, step.id if step else "")
        update(t_index, (step.index + 1) if step else 0)
        update(t_cycle, r.cycle if r.step_count else 0)
        if active and state is State.RUNNING:
            update(t_step_time, now - r.t_step0)
            update(t_test_time, now - r.t_test0)
        shown = self.progress.shown(
            active,
            state is State.COMPLETE,
            now - r.t_test0,
            self._behaviours[r.step].progress_current_a if step is not None else None,
            self.port.charge_ah.as_float() - r.step_q0,
            program.capacity_ah if program is not None else None,
        )
        if shown is not None:
            t_progress, t_eta = self._progress_tags
            update(t_progress, shown[0])
            update(t_eta, shown[1])
        if self._charge_live and self._conditions is not None:
            # The test's charge as the ``charge`` condition and the display line compute
            # it (one definition: ``ConditionValues.charge_ah``), until the scan after the
            # end, whose figure stays until the next load or start.
            update(self._charge_tag, self._conditions.charge_ah(r))
            if state in LOADABLE:
                self._charge_live = False
        if active and step is not None and self.samplers:
            self._sample(now, step)

    def _sample(self, now: float, step: CompiledStep) -> None:
        """The samplers due at ``now`` get the active step's sample, built once."""
        rec: Record | None = None
        for sampler in self.samplers:
            if sampler.due(now):
                if rec is None:  # built once, for every sampler due in this scan
                    rec = self._build(now, step, "sample")
                try:
                    sampler.on_sample(rec)
                except Exception:
                    log.exception("%s: sampler failed", self.name)

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
        if state is State.HOLDING and old not in (State.HOLDING, State.HELD):
            self.hold_reason = cause
        r = self._r
        if state in (State.STOPPING, State.ABORTING) and old in ACTIVE:
            self._end_record()
        if state in (State.STOPPING, State.ABORTING) and (
            not r.end_reason or (state is State.ABORTING and old is State.STOPPING)
        ):
            # The cause of the end, with its actor or the trip behind it (not the "done"
            # of the acting state that follows).
            why = cause
            alarm = str(self._get("alarm") or "") if self._alarm_latched else ""
            if alarm and alarm not in why:
                why += f" ({alarm})"
            r.end_reason = f"{'stopped' if state is State.STOPPING else 'aborted'}: {why}"
        elif state in FINAL and not r.end_reason:
            r.end_reason = cause
        self._emit("state", f"{old.value} → {state.value} ({cause})")
        self._note_acting(old, state, cause)

    def _note_acting(self, old: State, state: State, cause: str) -> None:
        """The last transition as the screen shows it: an acting state's end ("done" in the
        next scan) with the cause that began it — "Running → Holding → Held (hold by
        hmi:operator)", not "Holding → Held (done)"."""
        acting = self._acting
        if cause == "done" and acting is not None and acting[1] is old:
            self._set(
                "last_transition", f"{acting[0].value} → {old.value} → {state.value} ({acting[2]})"
            )
        self._acting = (old, state, cause) if state in AUTO_NEXT else None

    def _end_record(self) -> None:
        """Sampling rules: a record at the end, so the result files end where the test
        did (a stop or an abort, as a completion does)."""
        if self.program is None or not self._r.step_count:
            return
        try:
            self._record(self.clock.now(), self.program.steps[self._r.step], "end")
        except Exception:  # the end is reached anyway
            log.exception("%s: end record failed", self.name)

    def _emit(self, kind: str, text: str, quiet: bool = False, echo: bool = False) -> None:
        now = self.clock.now()
        r = self._r
        step_id = ""
        if self.program is not None and r.step_count:
            step_id = self.program.steps[r.step].id
        ev = ChainEvent(
            now, self.clock.to_wall(now), self.name, kind, text, r.step, step_id, r.cycle, echo
        )
        self.events.append(ev)
        self._set("last_event", text)
        if kind in TRANSITION_KINDS:
            self._set("last_transition", text)
        if not quiet:
            log.info("%s: %s", self.name, text)
        # A copy: a listener may replace listeners (a start after a reset attaches the
        # new test's result files), and every listener of now hears this event once.
        for fn in tuple(self.listeners):
            try:
                fn(ev)
            except Exception:
                log.exception("%s: event listener failed", self.name)

    def _set(self, field_: str, value: object) -> None:
        self.db.update(self._tags[field_], value)  # type: ignore[arg-type]

    def _get(self, field_: str) -> object:
        return self._tags[field_].value

    def _default_test_id(self) -> str:
        """``<UTC date>-<UTC time>-<channel>`` at the clock's wall time."""
        wall = self.clock.to_wall(self.clock.now())
        return time.strftime("%Y%m%d-%H%M%S", time.gmtime(wall)) + f"-{self.name}"

    @property
    def end_reason(self) -> str:
        return self._r.end_reason

    @property
    def test_id(self) -> str:
        return self._r.test_id


def seconds_until(wall_now: float, hh: int, mm: int) -> float:
    """Seconds from ``wall_now`` to the next local HH:MM (Chadèche's sleep action)."""
    lt = time.localtime(wall_now)
    target = time.mktime((lt.tm_year, lt.tm_mon, lt.tm_mday, hh, mm, 0, 0, 0, -1))
    if target <= wall_now:
        lt2 = time.localtime(wall_now + 86400)
        target = time.mktime((lt2.tm_year, lt2.tm_mon, lt2.tm_mday, hh, mm, 0, 0, 0, -1))
    return target - wall_now
