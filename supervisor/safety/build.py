"""The safety phase of a bench, from its I/O map."""

from __future__ import annotations

from supervisor.config.models import BenchConfig
from supervisor.safety.alarms import AlarmManager
from supervisor.safety.guard import ChannelGuard
from supervisor.safety.interlocks import Estop, Heartbeat, Interlock, TagAlarms
from supervisor.safety.phase import SafetyCheck, SafetyPhase
from supervisor.safety.stall import ScanStall
from supervisor.tags import TagDB


def build_safety(cfg: BenchConfig, db: TagDB, alarms: AlarmManager) -> SafetyPhase:
    """Checks in the order they must run: bench-wide trips first (so a channel's first-out
    is the e-stop when the e-stop came first), then tag alarms (when a tag has limits),
    then each channel's guard, the scan's own stalls, then the heartbeat (it stops when
    anything before it crashes the scan)."""
    checks: list[SafetyCheck] = []
    s = cfg.safety
    estop = Estop(s.estop, db, alarms) if s.estop is not None else None
    if estop is not None:
        checks.append(estop)
    checks += [Interlock(i, db, alarms) for i in s.interlocks]
    tag_alarms = TagAlarms(db, alarms)
    if tag_alarms.levels:
        checks.append(tag_alarms)  # without limits to watch it would have nothing to do
    guards = [ChannelGuard(c, db, alarms) for c in cfg.channels]
    checks += guards
    checks.append(ScanStall(db, alarms))
    if s.heartbeat is not None:
        checks.append(Heartbeat(s.heartbeat, db))
    phase = SafetyPhase(checks)
    phase.guards = {g.name: g for g in guards}
    phase.estop = estop  # the software e-stop's commands press the same button
    return phase
