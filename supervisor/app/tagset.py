"""The bench's tags as its wiring declares them, without opening a device.

``supervisor modbus map`` prints the register map of an I/O map on any machine — a PC
beside a bench whose I/O map names an SPI bus or a Modbus host not there: the bench is
wired as ``build_bench`` wires it (the same tags, in the same order, with the same units,
access and choices), but every driver is a stand-in that answers its device's points and
opens nothing. Nothing is started.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from supervisor.app.bench import build_bench
from supervisor.config.models import BenchConfig, DeviceConfig
from supervisor.core.clock import VirtualClock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.devices.kind import DriverWiring
from supervisor.devices.registry import REGISTRY, Registry
from supervisor.tags import TagDB

__all__ = ["declared_tags"]


class _Unopened:
    """A driver that knows its device's points and opens nothing (never polled)."""

    def __init__(self, name: str, dev: DeviceConfig) -> None:
        self.name = name
        self.poll_period_s = float(getattr(dev, "poll_period_s", 1.0))
        self._points = dev.points()

    @property
    def connected(self) -> bool:
        return False

    def points(self) -> Mapping[str, PointInfo]:
        return self._points

    def image(self) -> Mapping[str, Sample]:
        return {}

    def write(self, point: str, value: Value) -> None:
        pass

    async def poll(self) -> None:
        pass

    async def safe_state(self) -> str | None:
        return None

    async def close(self) -> None:
        pass


def _unopened(name: str, dev: Any, wiring: DriverWiring) -> _Unopened:
    return _Unopened(name, dev)


def declared_tags(cfg: BenchConfig, registry: Registry = REGISTRY) -> TagDB:
    """The tag database ``build_bench`` makes for ``cfg`` (nothing opened, nothing run)."""
    unopened = Registry(
        [
            replace(kind, build_driver=_unopened, build_simulator=None)
            for kind in registry.kinds.values()
        ]
    )
    return build_bench(cfg, VirtualClock(), simulate=False, registry=unopened).db
