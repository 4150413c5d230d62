"""The ``scan.stall`` supervision alarm: the scan started late because its event loop was
held (issue 9: a recipe parsed on the loop stopped every scan for 6.8 s, and nothing said
so). The scan engine counts stalls and publishes ``scan.stall_s`` (how late this scan
started, 0 when on time); this check turns it into an alarm of the one alarm model
(ISA-18.2, ADR 0009). A plain alarm of the whole bench, not a trip: by the time the scan
can see a stall it is over, and the channels' own guards have already acted on whatever it
made stale. It clears with the next scan on time and stays annunciated (returned,
unacknowledged) until someone acknowledges it.
"""

from __future__ import annotations

from supervisor.safety.alarms import AlarmManager, AlarmText, Severity
from supervisor.tags import Tag, TagDB

STALL_TAG = "scan.stall_s"
"""Published by the scan engine (``scan/engine.py``) at the start of every scan."""
STALLS_TAG = "scan.stalls"


class ScanStall:
    name = "scan stall"

    def __init__(self, db: TagDB, alarms: AlarmManager) -> None:
        self.db = db
        self.alarms = alarms
        self.alarm = alarms.declare("scan.stall", severity=Severity.HIGH)
        # The engine declares its tags after the safety phase is built: found at first use.
        self._late: Tag | None = None

    def evaluate(self, now: float, dt: float) -> None:
        late = self._late
        if late is None:
            late = self._late = self.db.get(STALL_TAG)
            if late is None:
                return  # no scan engine on this database (a test of the checks alone)
        v = late.value
        late_s = (v if type(v) is float else late.as_float()) if v is not None else 0.0
        alarm = self.alarm
        if late_s > 0.0:
            stalls = self.db.get(STALLS_TAG)
            count = stalls.value if stalls is not None else "?"
            why = AlarmText(
                f"scan started {late_s:.2f} s late: its event loop was held between two scans"
                f" (stall {count} since start; see the log)",
                "scan.stall",
                {"late_s": late_s, "count": count},
            )
            self.alarms.set(alarm, True, why)
        elif alarm.active or alarm.shelved_until is not None:
            # An inactive alarm's message is not read (AlarmManager.set keeps the last
            # active one): nothing to format on the scans that start on time.
            self.alarms.set(alarm, False)
        # Else on time, the alarm inactive and not shelved: ``set(alarm, False)`` would
        # change nothing (no shelving to expire, no edge, no message to keep), so it is not
        # called on the scans that start on time (all but a few; issue 13).

    def fail_safe(self, why: str) -> None:
        self.alarms.set(self.alarm, True, why)
