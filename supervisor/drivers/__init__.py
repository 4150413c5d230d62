"""Device drivers: one poller per device, each producing a latest-value image."""

from supervisor.drivers.base import PolledDriver

__all__ = ["PolledDriver"]
