"""The file descriptors a bench's configuration may take (issue 27, finding 3): its
listeners' caps, its devices, its files (``supervisor.core.descriptors``)."""

from __future__ import annotations

from typing import Final

from supervisor.config.models import BenchConfig
from supervisor.core.descriptors import PER_DEVICE, DescriptorBudget
from supervisor.hmi.limits import ConnectionLimits

OPCUA_BACKLOG: Final = 100
"""asyncio's default accept queue (asyncua's listener): connections to refuse at once."""


def http_limits(cfg: BenchConfig) -> ConnectionLimits:
    """The HTTP listener's limits from the I/O map's ``hmi:``."""
    h = cfg.hmi
    return ConnectionLimits(
        max_connections=h.max_connections,
        max_websockets=h.max_websockets,
        header_timeout_s=h.header_timeout_s,
        idle_timeout_s=h.idle_timeout_s,
    )


def descriptor_budget(cfg: BenchConfig) -> DescriptorBudget:
    """What ``supervisor run`` of ``cfg`` may hold at most."""
    listeners = {"HTTP": http_limits(cfg).descriptors}
    # The OPC UA server runs in a process of its own (ADR 0029): a flood of its clients
    # takes that process's descriptors, never the devices'.
    apart = {"OPC UA": cfg.opcua.max_connections + OPCUA_BACKLOG} if cfg.opcua.enabled else {}
    return DescriptorBudget(listeners=listeners, devices=PER_DEVICE * len(cfg.devices), apart=apart)
