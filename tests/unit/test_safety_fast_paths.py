"""The safety phase's fast paths answer what its plain paths do (issue 13, the dry run's
fourth pass; docs/adr/0018-scan-performance.md): the scan-stall check that does not tell
an inactive, unshelved alarm that it is still inactive gives the alarm, its log and its
listeners' events the plain check (``AlarmManager.set`` every scan) gives, whatever the
lateness, the shelving, the acknowledgements and the clock do."""

from __future__ import annotations

import math
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.safety import AlarmManager
from supervisor.safety.stall import STALL_TAG, STALLS_TAG, ScanStall
from supervisor.tags import Tag, TagDB, TagSpec


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
