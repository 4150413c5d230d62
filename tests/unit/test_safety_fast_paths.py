"""The safety phase's fast paths answer what its plain paths do (issue 13, the dry run's
fourth pass; docs/adr/0018-scan-performance.md):

- the scan-stall check, which does not tell an inactive, unshelved alarm that it is still
  inactive, gives the alarm, its log and its listeners' events that telling it every scan
  gives, whatever the lateness, the shelving, the acknowledgements and the clock do;
- a channel guard that skips every check at once while none of their tags moved and no
  alarm was written, finds its trips again only when an alarm was written, computes its
  admission again only when its tags moved and stamps the tags it writes when they hold
  their value gives the tags (values, qualities, reasons, versions, source and server
  times), the alarms and the alarm log that evaluating every check and updating every tag
  every scan gives, whatever the readings, the requests, the operator, other checks,
  restored or shelved alarms, forced or rewritten outputs and the clock do;
- every write to an alarm counts in its manager's ``writes``, which the guard relies on;
- the phase has no tag-alarm check when no tag has limits (it would do nothing).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from supervisor.app.dryrun import dry_run_config
from supervisor.channels import Channel, ChannelLimits
from supervisor.config.models import ChannelConfig, InterlockConfig
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.core.quality import Quality, Reason
from supervisor.safety import AlarmManager, ChannelGuard
from supervisor.safety.alarms import Alarm
from supervisor.safety.build import build_safety
from supervisor.safety.interlocks import Interlock, TagAlarms
from supervisor.safety.stall import STALL_TAG, STALLS_TAG, ScanStall
from supervisor.tags import AlarmLimits, Tag, TagDB, TagSpec


# --- the scan-stall check ----------------------------------------------------------------------
class PlainScanStall(ScanStall):
    """``ScanStall.evaluate`` as it was: the alarm told the lateness every scan."""

    def evaluate(self, now: float, dt: float) -> None:
        late = self._late or self.db.get(STALL_TAG)
        if late is None:
            return
        self._late = late
        v = late.value
        late_s = (v if type(v) is float else late.as_float()) if v is not None else 0.0
        if late_s > 0.0:
            stalls = self.db.get(STALLS_TAG)
            count = stalls.value if stalls is not None else "?"
            why = (
                f"scan started {late_s:.2f} s late: its event loop was held between two scans"
                f" (stall {count} since start; see the log)"
            )
        else:
            why = ""
        self.alarms.set(self.alarm, late_s > 0.0, why)


class StallRig:
    def __init__(self, check: type[ScanStall]) -> None:
        self.clock = VirtualClock()
        self.db = TagDB()
        self.alarms = AlarmManager(self.clock)
        self.events: list[Any] = []
        self.alarms.listeners.append(self.events.append)
        self.check = check(self.db, self.alarms)
        self.late: Tag | None = None

    def apply(self, o: tuple[Any, ...]) -> None:
        kind, db = o[0], self.db
        if kind == "scan":
            now = self.clock.now()
            db.set_scan_time(now)
            self.check.evaluate(now, 1.0)
            self.clock.advance(o[1])
        elif kind == "declare":
            # The scan engine declares its tags after the safety phase is built.
            if self.late is None:
                self.late = db.add(TagSpec(STALL_TAG, unit="s"))
                db.add(TagSpec(STALLS_TAG, dtype="int"))
        elif kind == "late" and self.late is not None:
            db.update(self.late, o[1])
            db.update(db[STALLS_TAG], o[2])
        elif kind in ("acknowledge", "shelve", "unshelve"):
            try:
                if kind == "shelve":
                    self.alarms.shelve("scan.stall", o[1], "op")
                else:
                    getattr(self.alarms, kind)("scan.stall", "op")
            except OperatorError:
                pass  # refused the same way on both rigs

    def state(self) -> Any:
        a = self.alarms["scan.stall"]
        alarm = (a.active, a.acked, a.message, a.activated_t, a.shelved_until, a.acked_by)
        events = [(e.t, e.transition, e.state, e.message, e.actor) for e in self.events]
        return alarm, events


stall_ops = st.one_of(
    st.tuples(st.just("scan"), st.sampled_from([0.5, 1.0, 30.0])),
    st.tuples(st.just("declare")),
    st.tuples(
        st.just("late"),
        st.sampled_from([0.0, 0.0, 2.5, 6.8, -0.0, math.nan, None, 3]),
        st.integers(0, 5),
    ),
    st.tuples(st.just("acknowledge")),
    st.tuples(st.just("shelve"), st.sampled_from([1.0, 5.0, 60.0])),
    st.tuples(st.just("unshelve")),
)


@settings(max_examples=200, deadline=None)
@given(st.lists(stall_ops, max_size=40))
def test_the_stall_check_gives_what_telling_the_alarm_every_scan_gives(
    program: list[tuple[Any, ...]],
) -> None:
    fast, plain = StallRig(ScanStall), StallRig(PlainScanStall)
    for o in [("scan", 1.0), *program, ("scan", 1.0), ("scan", 100.0), ("scan", 1.0)]:
        fast.apply(o)
        plain.apply(o)
        assert fast.state() == plain.state(), o


def test_a_late_scan_then_one_on_time_raise_and_clear_the_stall_alarm() -> None:
    rig = StallRig(ScanStall)
    rig.apply(("declare",))
    rig.apply(("late", 6.8, 1))
    rig.apply(("scan", 1.0))
    assert rig.alarms["scan.stall"].active
    rig.apply(("late", 0.0, 1))
    rig.apply(("scan", 1.0))
    assert not rig.alarms["scan.stall"].active
    assert [e[1].value for e in rig.state()[1]] == ["activated", "cleared"]


# --- the channel guard -------------------------------------------------------------------------
DT = 0.5

GATED = {
    # Every check a function of its tags (as the dry run's channel): the whole pass over
    # the checks is skipped while nothing moved.
    "limits": {
        "current_a": [-0.4, 0.4],
        "voltage_v": [0.8, 1.9],
        "temperature_c": [0.0, 45.0],
        "trip_delay_s": 1.0,
    },
    "temperature_tag": "amb.t",
}
EVERY_KIND = {
    # Checks evaluated every scan too (read-backs, permissive, a second voltage, BMS): the
    # trips, the admission (derated by the BMS) and the stamps still take their fast paths.
    **GATED,
    "contactor_tag": "k.cmd",
    "contactor_feedback_tag": "k.closed",
    "feedback": {"delay_s": 1.0, "current_tolerance_a": 0.05},
    "permissives": ["door.closed"],
    "voltage_checks": [{"tag": "v2", "tolerance_v": 0.1, "delay_s": 1.0}],
    "bms": {
        "cell_max_tag": "bms.cell_max",
        "cell_min_tag": "bms.cell_min",
        "temperature_tag": "bms.t",
        "cell_voltage_v": [0.9, 1.85],
        "derate_band_v": 0.1,
        "temperature_max_c": 50.0,
    },
}
CONFIGS = {"gated": GATED, "every kind": EVERY_KIND}
OUTPUTS = ["ch0.armed", "ch0.fault", "ch0.fault_action", "ch0.first_out"]
OUTPUTS += ["ch0.limit.charge_a", "ch0.limit.discharge_a"]


class GuardRig:
    """One channel, a bench-wide interlock that aborts and its guard, scanned in design
    order (derive, safety, drive), with what people, other checks and restored state do
    to them between scans."""

    def __init__(self, fast: bool, config: str) -> None:
        self.clock = VirtualClock()
        self.db = db = TagDB()
        db.add(TagSpec("amb.t", unit="degC"))
        db.add(TagSpec("v2", unit="V"))
        db.add(TagSpec("il.x", unit="bar"))
        for name in ("bms.cell_max", "bms.cell_min"):
            db.add(TagSpec(name, unit="V"))
        db.add(TagSpec("bms.t", unit="degC"))
        for name in ("door.closed", "k.cmd", "k.closed"):
            db.add(TagSpec(name, dtype="bool"))
        cfg = ChannelConfig.model_validate(
            {"name": "ch0", "source": {"device": "dev"}, "capacity_ah": 2.0, **CONFIGS[config]}
        )
        lim = cfg.limits
        self.ch = Channel(
            "ch0",
            db,
            ChannelLimits(lim.current_a, lim.voltage_v, lim.temperature_c),
            capacity_ah=2.0,
            temperature_tag="amb.t",
            contactor_tag=cfg.contactor_tag,
            has_output_switch=config == "every kind",
            has_output_feedback=config == "every kind",
        )
        self.alarms = AlarmManager(self.clock)
        self.events: list[Any] = []
        self.alarms.listeners.append(self.events.append)
        self.interlock = Interlock(
            InterlockConfig(id="pressure", tag="il.x", above=5.0, action="abort"),
            db,
            self.alarms,
        )
        self.guard = ChannelGuard(cfg, db, self.alarms)
        self.guard._gated = fast
        db.add(TagSpec("dev.connected", dtype="bool"))  # declared after the guard, as the scan does
        for name, value in [("dev.connected", True), ("door.closed", True), ("il.x", 1.0)]:
            db.update(db[name], value)
        self.later: Alarm | None = None

    def apply(self, o: tuple[Any, ...]) -> None:
        db, kind, alarms = self.db, o[0], self.alarms
        if kind == "scan":
            for _ in range(o[1]):
                now = self.clock.now()
                db.set_scan_time(now)
                self.ch.derive(now, DT)
                self.interlock.evaluate(now, DT)
                self.guard.evaluate(now, DT)
                self.ch.drive(now, DT)
                self.clock.advance(DT)
        elif kind == "reading" and o[1] in db:  # the supply's output only with "every kind"
            _, name, value, good = o
            q, r = (Quality.GOOD, Reason.NONE) if good else (Quality.BAD, Reason.COMM_FAILURE)
            db.update(db[name], value, q, r)
        elif kind == "write":
            db.update(db[o[1]], o[2])
        elif kind == "reset":
            with contextlib.suppress(OperatorError):  # a cause still present: refused
                self.guard.reset("op")
        elif kind == "restored":
            # What restoring retained alarms does, outside the checks (app/retained.py).
            a = list(alarms)[o[1] % len(list(alarms))]
            alarms.restore(
                a.id,
                message="restored",
                acked=o[2],
                tripped=o[2],
                first_out=o[2],
                activated_t=self.clock.now() - 3.0,
            )
        elif kind == "shelved":
            with contextlib.suppress(OperatorError):  # a trip cannot be shelved
                alarms.shelve(list(alarms)[o[1] % len(list(alarms))].id, o[2], "op")
        elif kind == "quality":
            db.set_quality(db[o[1]], *o[2])
        elif kind == "force":
            db.force(o[1], o[2])
        elif kind == "unforce":
            db.unforce(o[1])
        elif kind == "fail_safe":
            self.guard.fail_safe("guard failed")
        elif kind == "meddler" and len(self.alarms.listeners) == 1:
            # A listener that clears another alarm whenever one changes: even a write made
            # during the guard's own evaluation is seen.
            victim = list(alarms)[o[1] % len(list(alarms))]

            def meddle(ev: Any) -> None:
                if ev.alarm_id != victim.id:
                    alarms.set(victim, False)

            alarms.listeners.append(meddle)
        elif kind == "later_alarm":
            # A bench-wide trip declared after the first scans, raised by some other check.
            if self.later is None:
                self.later = alarms.declare("later", latched=True, action=o[1])
            alarms.set(self.later, o[2], "later trip")

    def state(self) -> Any:
        tags = [
            (t.name, t.value, t.quality, t.reason, t.version, t.source_t, t.server_t, t.forced)
            for t in self.db
        ]
        alarms = [
            (
                a.id,
                a.active,
                a.acked,
                a.tripped,
                a.first_out,
                a.message,
                a.activated_t,
                a.shelved_until,
                a.acked_by,
            )
            for a in self.alarms
        ]
        events = [(e.t, e.alarm_id, e.transition, e.state, e.message, e.actor) for e in self.events]
        return tags, alarms, events


def reading(names: list[str], values: list[Any]) -> st.SearchStrategy[tuple[Any, ...]]:
    return st.tuples(
        st.just("reading"), st.sampled_from(names), st.sampled_from(values), st.booleans()
    )


guard_ops = st.one_of(
    st.tuples(st.just("scan"), st.integers(1, 4)),
    st.tuples(st.just("scan"), st.integers(1, 4)),
    reading(
        ["ch0.voltage", "ch0.current", "amb.t", "v2", "bms.cell_max", "bms.cell_min"],
        [0.5, 1.2, 1.8, 1.95, 2.5, -0.1, 0.1, 0.3, 30.0, 50.0, math.inf],
    ),
    reading(["bms.t", "il.x"], [1.0, 6.0, 55.0]),
    reading(["k.closed", "ch0.output_fb", "door.closed"], [True, False]),
    st.tuples(st.just("write"), st.just("ch0.mode"), st.sampled_from(["manual", "auto"])),
    st.tuples(st.just("write"), st.sampled_from(["ch0.enable", "ch0.auto_active"]), st.booleans()),
    st.tuples(
        st.just("write"),
        st.sampled_from(["ch0.manual_current", "ch0.auto_current"]),
        st.sampled_from([0.0, 0.2, -0.2]),
    ),
    st.tuples(st.just("write"), st.just("ch0.ack"), st.just(True)),
    # The command as the source was last given it (before the channel drives it again).
    st.tuples(st.just("write"), st.just("ch0.current_cmd"), st.sampled_from([0.0, 0.3])),
    st.tuples(st.just("write"), st.just("ch0.logic_error"), st.sampled_from(["", "boom"])),
    st.tuples(st.just("write"), st.just("dev.connected"), st.booleans()),
    # Someone else writes what the guard publishes.
    st.tuples(st.just("write"), st.sampled_from(OUTPUTS[1:4]), st.sampled_from(["", "x", "hold"])),
    st.tuples(st.just("write"), st.sampled_from(OUTPUTS[4:]), st.sampled_from([0.0, 0.4, 0.1])),
    st.tuples(st.just("write"), st.just("ch0.armed"), st.booleans()),
    st.tuples(
        st.just("quality"),
        st.sampled_from(OUTPUTS),
        st.sampled_from(
            [
                (Quality.UNCERTAIN, Reason.NONE),
                (Quality.BAD, Reason.NONE),
                (Quality.GOOD, Reason.STALE),
            ]
        ),
    ),
    st.tuples(st.just("reset")),
    st.tuples(st.just("restored"), st.integers(0, 30), st.booleans()),
    st.tuples(st.just("shelved"), st.integers(0, 30), st.sampled_from([0.4, 2.0])),
    st.tuples(st.just("force"), st.sampled_from(OUTPUTS[4:]), st.sampled_from([0.0, 0.3])),
    st.tuples(st.just("force"), st.sampled_from(OUTPUTS[1:4]), st.sampled_from(["", "forced"])),
    st.tuples(st.just("unforce"), st.sampled_from(OUTPUTS)),
    st.tuples(st.just("fail_safe")),
    st.tuples(st.just("meddler"), st.integers(0, 30)),
    st.tuples(st.just("later_alarm"), st.sampled_from(["hold", "abort"]), st.booleans()),
)

CHARGING = [("write", "ch0.manual_current", 0.2), ("write", "ch0.enable", True)]


@pytest.mark.parametrize("config", CONFIGS)
@settings(max_examples=150, deadline=None)
@given(st.lists(guard_ops, max_size=40))
# A limit crossed while charging, held through the on-delay, then nothing moves for a while.
@example([*CHARGING, ("scan", 1), ("reading", "ch0.voltage", 1.95, True), ("scan", 4), ("scan", 4)])
# Only the request moves: the chain's mode left while a trip holds (its cause goes with
# it); a command given to the source while the voltage input is lost.
@example(
    [
        ("write", "ch0.mode", "auto"),
        ("write", "ch0.auto_active", True),
        ("write", "ch0.auto_current", 0.2),
        ("scan", 5),
        ("write", "ch0.mode", "manual"),
        ("scan", 2),
    ]
)
@example([("scan", 3), ("write", "ch0.current_cmd", 0.3), ("scan", 1)])
# The source lost while charging, then a trip drops the enable in the middle of a scan.
@example(
    [
        *CHARGING,
        ("reading", "ch0.voltage", 1.2, True),
        ("reading", "ch0.current", 0.2, True),
        ("reading", "amb.t", 25.0, True),
        ("scan", 1),
        ("write", "dev.connected", False),
        ("write", "ch0.logic_error", "boom"),
        ("scan", 3),
    ]
)
# A trip cleared by restored state behind the guard's back, its cause still present.
@example(
    [
        *CHARGING,
        ("scan", 1),
        ("reading", "ch0.voltage", 1.2, False),
        ("scan", 4),
        ("restored", 1, True),
    ]
)
# A trip shelved behind the guard's back while nothing moves (the shelving expires).
@example([("scan", 2), ("write", "ch0.logic_error", "boom"), ("scan", 2), ("shelved", 0, 0.4)])
# Someone else writes the fault and a limit while nothing moves; then they are forced.
@example(
    [
        ("scan", 2),
        ("write", "ch0.fault", "x"),
        ("write", "ch0.limit.charge_a", 0.1),
        ("scan", 1),
        ("force", "ch0.limit.discharge_a", 0.0),
        ("scan", 1),
        ("unforce", "ch0.limit.discharge_a"),
    ]
)
# A bench-wide trip declared late; an operator's reset between scans; the guard fails.
@example(
    [
        ("scan", 2),
        ("later_alarm", "abort", True),
        ("scan", 1),
        ("later_alarm", "abort", False),
        ("reset",),
        ("scan", 1),
        ("fail_safe",),
    ]
)
# A listener clears the current input's trip (its cause still present) while the voltage
# trip is raised, in the guard's own evaluation; then nothing moves (the chain's request
# stays, the command stays 0).
@example(
    [
        ("meddler", 3),
        ("reading", "ch0.voltage", 1.2, True),
        ("write", "ch0.mode", "auto"),
        ("write", "ch0.auto_active", True),
        ("write", "ch0.auto_current", 0.2),
        ("scan", 2),
        ("reading", "ch0.voltage", 1.95, True),
        ("scan", 4),
    ]
)
def test_the_guard_s_fast_paths_give_what_evaluating_and_updating_everything_gives(
    config: str, program: list[tuple[Any, ...]]
) -> None:
    fast, plain = GuardRig(True, config), GuardRig(False, config)
    for o in [("scan", 1), *program, ("scan", 2), ("scan", 3)]:
        fast.apply(o)
        plain.apply(o)
        assert fast.state() == plain.state(), o


def counted(monkeypatch: pytest.MonkeyPatch, obj: object, name: str) -> list[int]:
    calls = [0]
    real = getattr(obj, name)

    def counting(*args: Any, **kw: Any) -> Any:
        calls[0] += 1
        return real(*args, **kw)

    monkeypatch.setattr(obj, name, counting)
    return calls


def test_a_guard_whose_tags_and_alarms_do_not_move_evaluates_no_check_and_finds_no_trip(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rig = GuardRig(True, "gated")
    readings = [("ch0.voltage", 1.2), ("ch0.current", 0.2), ("amb.t", 25.0)]
    for o in [*[("reading", n, x, True) for n, x in readings], *CHARGING, ("scan", 3)]:
        rig.apply(o)
    assert rig.db["ch0.fault"].value == "" and rig.db["ch0.current_cmd"].value == 0.2
    passes = counted(monkeypatch, rig.guard, "_evaluate_checks")
    trips = counted(monkeypatch, rig.alarms, "trips")
    admissions = counted(monkeypatch, rig.guard, "_admission")
    writes = rig.alarms.writes
    changed_t = {n: rig.db[n].source_t for n in OUTPUTS}
    rig.apply(("scan", 10))
    assert passes == trips == admissions == [0]
    assert rig.alarms.writes == writes
    # Outputs that held their values keep the time they last changed (ADR 0037).
    assert {n: rig.db[n].source_t for n in OUTPUTS} == changed_t
    rig.apply(("reading", "ch0.voltage", 1.21, True))
    rig.apply(("scan", 1))
    assert passes == admissions == [1] and trips == [0]  # the voltage moved, no alarm did
    rig.apply(("reading", "ch0.voltage", 1.95, True))
    rig.apply(("scan", 3))  # through the on-delay: a trip
    assert rig.db["ch0.first_out"].value == "ch0.voltage_high"
    assert trips[0] >= 1


def test_every_check_is_skipped_at_once_only_when_each_declares_its_tags() -> None:
    rig = GuardRig(True, "gated")
    assert rig.guard._gate_tags is None  # the source's status tag is not declared yet
    rig.apply(("scan", 1))
    assert rig.guard._gate_tags is not None  # found by the first scan: its check declares it
    # Read-backs, permissives, a second voltage, the BMS: evaluated every scan.
    assert GuardRig(True, "every kind").guard._gate_tags is None


# --- the alarms' writes --------------------------------------------------------------------
def _alarm_state(alarms: AlarmManager) -> list[tuple[Any, ...]]:
    return [dataclasses.astuple(a) for a in alarms]


@pytest.mark.parametrize(
    "change",
    [
        "declare",
        "activate",
        "clear",
        "new message",
        "acknowledge",
        "reset",
        "shelve",
        "unshelve",
        "shelving expires",
        "restore",
    ],
)
def test_every_change_the_manager_makes_to_an_alarm_counts_in_its_writes(change: str) -> None:
    """The guard's way to know that no alarm changed (issue 29, item 4: it was an
    ``Alarm.__setattr__`` that counted every attribute written)."""
    clock = VirtualClock()
    alarms = AlarmManager(clock)
    trip, plain = alarms.declare("trip", latched=True), alarms.declare("plain")
    do: dict[str, Callable[[], object]] = {
        "declare": lambda: alarms.declare("more"),
        "activate": lambda: alarms.set(trip, True, "high"),
        "clear": lambda: alarms.set(trip, False),
        "new message": lambda: alarms.set(trip, True, "higher"),
        "acknowledge": lambda: alarms.acknowledge("trip", "op"),
        "reset": lambda: alarms.reset("trip", "op"),
        "shelve": lambda: alarms.shelve("plain", 10.0, "op"),
        "unshelve": lambda: alarms.unshelve("plain", "op"),
        "shelving expires": lambda: (clock.advance(20.0), alarms.set(plain, False)),
        "restore": lambda: alarms.restore("trip", message="m", acked=False, tripped=True,
                                          first_out=True),
    }  # fmt: skip
    before_steps = {
        "clear": ["activate"],
        "new message": ["activate"],
        "acknowledge": ["activate"],
        "reset": ["activate", "clear", "acknowledge"],
        "unshelve": ["shelve"],
        "shelving expires": ["shelve"],
    }
    for step in before_steps.get(change, []):
        do[step]()
    state, writes = _alarm_state(alarms), alarms.writes
    do[change]()
    assert _alarm_state(alarms) != state or change == "declare"
    assert alarms.writes > writes


def test_a_call_that_changes_no_alarm_is_not_counted() -> None:
    alarms = AlarmManager(VirtualClock())
    a = alarms.declare("a")
    writes = alarms.writes
    alarms.set(a, False)
    alarms.set(a, False, "low")  # a message only matters to an active alarm
    assert alarms.writes == writes


def test_an_alarm_is_a_plain_record() -> None:
    """Writing an alarm's attribute runs no code (issue 29, item 4): the manager counts
    what it changes, and nothing else changes an alarm (``test_state_writes.py``)."""
    assert Alarm.__setattr__ is object.__setattr__
    alarms = AlarmManager(VirtualClock())
    a = alarms.declare("a")
    writes = alarms.writes
    a.message = "by hand"
    assert alarms.writes == writes


def test_an_alarm_held_active_with_the_same_message_is_not_written_every_scan() -> None:
    alarms = AlarmManager(VirtualClock())
    a = alarms.declare("a")
    alarms.set(a, True, "high")
    before = alarms.writes
    alarms.set(a, True, "high")
    assert alarms.writes == before
    alarms.set(a, True, "higher")
    assert alarms.writes == before + 1 and a.message == "higher"


# --- the safety phase --------------------------------------------------------------------------
def test_tag_alarm_limits_are_a_check_of_the_phase_only_when_a_tag_has_some() -> None:
    cfg = dry_run_config("nimh-aa", 2.0, 0.0, 1.0).model_copy(update={"channels": []})
    db = TagDB()
    db.add(TagSpec("a.t", unit="degC"))
    phase = build_safety(cfg, db, AlarmManager(VirtualClock()))
    assert [type(c) for c in phase.checks] == [ScanStall]
    db.add(TagSpec("b.t", unit="degC", alarms=AlarmLimits(h=40.0)))
    phase = build_safety(cfg, db, AlarmManager(VirtualClock()))
    assert [type(c) for c in phase.checks] == [TagAlarms, ScanStall]
