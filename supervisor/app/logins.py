"""The bench's one ``LoginThrottle`` (``supervisor.core.logins``), wired: shared by the
HMI's logins and OPC UA's, on the bench's clock, with its burst alarm.

``security.login_burst`` (MEDIUM, not a trip: guessing passwords is no danger to the
cells, but someone should look) is raised by the scan while the throttle sees a burst of
failed or refused logins, and clears by itself a minute after the tries stop.
"""

from __future__ import annotations

from supervisor.app.bench import Bench
from supervisor.core.logins import LoginThrottle
from supervisor.safety import Alarm, AlarmManager, Severity
from supervisor.tags import TagDB

__all__ = ["BURST_ALARM", "login_throttle"]

BURST_ALARM = "security.login_burst"


class BurstWatch:
    """A scan publisher: the burst alarm follows the throttle (the HTTP and OPC UA threads
    only count; the alarm model is written from the scan, as every other alarm)."""

    name = "logins"

    def __init__(self, throttle: LoginThrottle, alarms: AlarmManager, alarm: Alarm) -> None:
        self.throttle = throttle
        self.alarms = alarms
        self.alarm = alarm

    def on_scan(self, db: TagDB, t: float) -> None:
        burst = self.throttle.burst()
        self.alarms.set(self.alarm, bool(burst), burst)


def login_throttle(bench: Bench) -> LoginThrottle:
    """The bench's throttle: made (with its alarm and the scan publisher that drives it) at
    the first call, the same object after."""
    if bench.logins is None:
        bench.logins = LoginThrottle(bench.clock.now)
        if bench.alarms is not None:
            alarm = bench.alarms.declare(BURST_ALARM, severity=Severity.MEDIUM)
            bench.engine.publishers.append(BurstWatch(bench.logins, bench.alarms, alarm))
    return bench.logins
