"""The device kinds this supervisor knows, and the bench model they make together.

Adding a kind is one folder under ``supervisor/devices/`` and one line in ``KINDS`` (see
docs/adr/0006-device-kinds.md). Everything that depends on the kind — the I/O map schema,
``supervisor check``, bench wiring, simulation — iterates this registry.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

from supervisor.config import bench as bench_file
from supervisor.config.models import BenchConfig, DeviceConfig, bench_model
from supervisor.core.errors import ConfigError
from supervisor.devices import adam, bms, chadeche, ea
from supervisor.devices.kind import DeviceKind

KINDS: Final[Mapping[str, DeviceKind[Any]]] = MappingProxyType(
    {k.name: k for k in (chadeche.KIND, adam.KIND, ea.KIND, bms.KIND)}
)
"""Registered kinds by their I/O map ``driver:`` value, in the order messages list them."""

BENCH_MODEL: Final[type[BenchConfig]] = bench_model([k.config for k in KINDS.values()])
"""The I/O map model: ``BenchConfig`` whose ``devices`` are the registered kinds."""


def kind_of(device: DeviceConfig) -> DeviceKind[Any]:
    """The registration of a configured device; a kind not registered names the known ones."""
    kind = KINDS.get(device.driver)
    if kind is None:
        raise ConfigError(
            f"device driver {device.driver!r} is not a registered device kind"
            f" (known: {', '.join(KINDS)})"
        )
    return kind


def load_bench(path: str | Path) -> BenchConfig:
    """Load and fully check an I/O map (every problem in one ConfigErrors)."""
    return bench_file.load_bench(path, BENCH_MODEL)


def load_bench_text(text: str, file: str) -> BenchConfig:
    """The same checks on text not yet written (e.g. an I/O map about to be edited)."""
    return bench_file.load_bench_text(text, file, BENCH_MODEL)


def bench_from_data(data: object, file: str = "<generated>") -> BenchConfig:
    """A bench built in code (dry runs, benchmarks), checked like a file."""
    return bench_file.check_data(data, file, BENCH_MODEL)
