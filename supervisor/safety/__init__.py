"""Safety: the scan phase that runs after derived values and before the step chains.

Every trip and alarm of the bench is evaluated here, every scan, in order: the e-stop, the
I/O map's interlocks, tag alarm limits, each channel's guard, the scan's own stalls
(``scan.stall``), the watchdog heartbeat.
Running before the chains and publishing what the outputs may do, no recipe can override
it. One alarm model (``alarms.AlarmManager``, ISA-18.2) holds every alarm's state.
"""

from supervisor.safety.alarms import (
    Alarm,
    AlarmEvent,
    AlarmManager,
    AlarmState,
    Severity,
    Transition,
)
from supervisor.safety.build import build_safety
from supervisor.safety.guard import ChannelGuard
from supervisor.safety.interlocks import Estop, SoftwarePress
from supervisor.safety.phase import SafetyCheck, SafetyPhase

__all__ = [
    "Alarm",
    "AlarmEvent",
    "AlarmManager",
    "AlarmState",
    "ChannelGuard",
    "Estop",
    "SafetyCheck",
    "SafetyPhase",
    "Severity",
    "SoftwarePress",
    "Transition",
    "build_safety",
]
