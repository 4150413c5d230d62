"""A channel guard evaluates a check that reads only tags again only when one of them moved
or while its on-delay runs (docs/adr/0018-scan-performance.md, "Dry run"): the tags, the
alarms (state, message, first-out, times) and the alarm log come out exactly as when every
check is evaluated every scan, whatever the readings, the requests, the operator, the
source's connection and the clock do. And the trips of a channel found from each
channel's cached reach are those a walk over every alarm finds."""

from __future__ import annotations

import contextlib
from typing import Any

from hypothesis import example, given, settings
from hypothesis import strategies as st

from supervisor.channels import Channel, ChannelLimits
from supervisor.config.models import ChannelConfig
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.core.quality import Quality, Reason
from supervisor.safety import AlarmManager, ChannelGuard
from supervisor.safety.alarms import Alarm, Severity
from supervisor.tags import TagDB, TagSpec

DT = 0.5


class Rig:
    def __init__(self, gated: bool) -> None:
        self.clock = VirtualClock()
        self.db = db = TagDB()
        db.add(TagSpec("amb.t", unit="degC"))
        cfg = ChannelConfig.model_validate(
            {
                "name": "ch0",
                "source": {"device": "dev"},
                "capacity_ah": 2.0,
                "limits": {
                    "current_a": [-0.4, 0.4],
                    "voltage_v": [0.8, 1.9],
                    "temperature_c": [0.0, 45.0],
                    "trip_delay_s": 1.0,
                },
                "temperature_tag": "amb.t",
            }
        )
        lim = cfg.limits
        self.ch = Channel(
            "ch0",
            db,
            ChannelLimits(lim.current_a, lim.voltage_v, lim.temperature_c),
            capacity_ah=2.0,
            temperature_tag="amb.t",
        )
        self.alarms = AlarmManager(self.clock)
        self.events: list[Any] = []
        self.alarms.listeners.append(self.events.append)
        self.guard = ChannelGuard(cfg, db, self.alarms)
        self.gated_by_default = self.guard._gated
        self.guard._gated = gated
        db.add(TagSpec("dev.connected", dtype="bool"))  # declared after the guard, as the scan does
        db.update(db["dev.connected"], True)

    def apply(self, o: tuple[Any, ...]) -> None:
        db, kind = self.db, o[0]
        if kind == "scan":
            for _ in range(o[1]):
                now = self.clock.now()
                db.set_scan_time(now)
                self.ch.derive(now, DT)
                self.guard.evaluate(now, DT)
                self.ch.drive(now, DT)
                self.clock.advance(DT)
        elif kind == "reading":
            _, name, value, good = o
            q, r = (Quality.GOOD, Reason.NONE) if good else (Quality.BAD, Reason.COMM_FAILURE)
            db.update(db[name], value, q, r)
        elif kind == "write":
            db.update(db[o[1]], o[2])
        elif kind == "reset":
            with contextlib.suppress(OperatorError):  # a cause still present: refused
                self.guard.reset("op")
        elif kind == "unlatch":
            # What restoring retained alarms does, outside the guard (app/retained.py).
            for a in self.alarms:
                self.alarms.restore(
                    a.id,
                    message=a.message,
                    acked=a.acked,
                    tripped=a.tripped,
                    first_out=a.first_out,
                    acked_by=a.acked_by,
                    activated_t=a.activated_t,
                )

    def state(self) -> Any:
        tags = [(t.name, t.value, t.quality, t.reason, t.version, t.source_t) for t in self.db]
        alarms = [
            (a.id, a.active, a.acked, a.tripped, a.first_out, a.message, a.activated_t)
            for a in self.alarms
        ]
        events = [(e.t, e.alarm_id, e.transition, e.state, e.message) for e in self.events]
        return tags, alarms, events


ops = st.one_of(
    st.tuples(st.just("scan"), st.integers(1, 4)),
    st.tuples(
        st.just("reading"),
        st.sampled_from(["ch0.voltage", "ch0.current", "amb.t"]),
        st.sampled_from([0.5, 1.2, 1.95, 2.5, -0.1, 0.1, 30.0, 50.0]),
        st.booleans(),
    ),
    st.tuples(st.just("write"), st.just("ch0.mode"), st.sampled_from(["manual", "auto"])),
    st.tuples(st.just("write"), st.sampled_from(["ch0.enable", "ch0.auto_active"]), st.booleans()),
    st.tuples(
        st.just("write"),
        st.sampled_from(["ch0.manual_current", "ch0.auto_current"]),
        st.sampled_from([0.0, 0.2, -0.2]),
    ),
    st.tuples(st.just("write"), st.just("ch0.ack"), st.just(True)),
    st.tuples(st.just("write"), st.just("ch0.logic_error"), st.sampled_from(["", "boom"])),
    st.tuples(st.just("write"), st.just("dev.connected"), st.booleans()),
    st.tuples(st.just("reset")),
    st.tuples(st.just("unlatch")),
)


CHARGING = [
    ("write", "ch0.manual_current", 0.2),
    ("write", "ch0.enable", True),
]


@settings(max_examples=150, deadline=None)
@given(st.lists(ops, max_size=40))
# A limit crossed while charging, held through the on-delay (nothing else moves).
@example([*CHARGING, ("scan", 1), ("reading", "ch0.voltage", 1.95, True), ("scan", 4)])
# A trip whose alarm is cleared behind the guard's back, its cause still present.
@example(
    [*CHARGING, ("scan", 1), ("reading", "ch0.voltage", 1.2, False), ("scan", 2), ("unlatch",)]
)
# The source lost while charging, then a trip drops the enable in the middle of a scan.
@example(
    [
        *CHARGING,
        ("scan", 1),
        ("write", "dev.connected", False),
        ("write", "ch0.logic_error", "boom"),
        ("scan", 3),
    ]
)
def test_gated_checks_give_what_evaluating_every_check_every_scan_gives(
    program: list[tuple[Any, ...]],
) -> None:
    gated, every = Rig(gated=True), Rig(gated=False)
    for o in [("scan", 1), *program, ("scan", 2)]:
        gated.apply(o)
        every.apply(o)
        assert gated.state() == every.state(), o


def test_guards_are_gated_unless_told_otherwise() -> None:
    assert Rig(gated=False).gated_by_default is True


def walked_trips(alarms: AlarmManager, channel: str) -> list[Alarm]:
    """``AlarmManager.trips`` as it was: a walk over every alarm."""
    out = [
        a
        for a in alarms
        if a.tripped
        and (a.group == channel or (a.group == "" and (a.affects is None or channel in a.affects)))
    ]
    out.sort(key=lambda a: (not a.first_out, a.activated_t or 0.0))
    return out


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.tuples(
                st.just("declare"),
                st.sampled_from(["", "ch0", "ch1"]),
                st.sampled_from([None, ("ch0",), ("ch1",), ("ch0", "ch1")]),
            ),
            st.tuples(st.just("trip"), st.integers(0, 20), st.booleans()),
            st.tuples(st.just("advance"), st.floats(0.0, 3.0)),
        ),
        max_size=40,
    )
)
def test_trips_from_the_cached_reach_are_those_of_a_walk_over_every_alarm(
    ops: list[tuple[Any, ...]],
) -> None:
    clock = VirtualClock()
    alarms = AlarmManager(clock)
    declared: list[Alarm] = []
    for o in ops:
        if o[0] == "declare":
            declared.append(
                alarms.declare(
                    f"a{len(declared)}",
                    group=o[1],
                    severity=Severity.HIGH,
                    latched=True,
                    affects=o[2] if o[1] == "" else None,
                )
            )
        elif o[0] == "trip" and declared:
            alarms.set(declared[o[1] % len(declared)], o[2], "why")
        elif o[0] == "advance":
            clock.advance(o[1])
        for ch in ("ch0", "ch1", "ch2"):
            assert alarms.trips(ch) == walked_trips(alarms, ch)
