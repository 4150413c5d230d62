"""Foundation shared by every layer: quality model, clocks, errors, driver protocol."""

from typing import TYPE_CHECKING, Any

from supervisor.core.errors import (
    ConfigError,
    DeviceIOError,
    DeviceTimeout,
    OperatorError,
    ProtocolError,
    SupervisorError,
)
from supervisor.core.quality import Quality, Reason

if TYPE_CHECKING:
    from supervisor.core.clock import Clock, RealClock, VirtualClock

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


def __getattr__(name: str) -> Any:
    # The clocks import asyncio: imported when asked for, not with every ``supervisor.core.*``
    # module (``supervisor check`` runs no loop; issue 30).
    if name in ("Clock", "RealClock", "VirtualClock"):
        from supervisor.core import clock

        return getattr(clock, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
