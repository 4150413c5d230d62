"""Foundation shared by every layer: quality model, clocks, errors, driver protocol."""

from supervisor.core.clock import Clock, RealClock, VirtualClock
from supervisor.core.errors import (
    ConfigError,
    DeviceIOError,
    DeviceTimeout,
    OperatorError,
    ProtocolError,
    SupervisorError,
)
from supervisor.core.quality import Quality, Reason

__all__ = [
    "Clock",
    "ConfigError",
    "DeviceIOError",
    "DeviceTimeout",
    "OperatorError",
    "ProtocolError",
    "Quality",
    "RealClock",
    "Reason",
    "SupervisorError",
    "VirtualClock",
]
