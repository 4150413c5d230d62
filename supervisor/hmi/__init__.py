"""HTTP API over the tag database (the base the SCADA screens build on)."""

from supervisor.hmi.server import HttpApi

__all__ = ["HttpApi"]
