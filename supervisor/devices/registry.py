"""The device kinds this supervisor knows, and the bench model they make together.

Adding a kind is one folder under ``supervisor/devices/`` and one entry in ``REGISTRY``
(docs/adr/0006-device-kinds.md). Everything that depends on the kind — the I/O map model
and its JSON Schema, ``supervisor check``, bench wiring, simulation — asks the registry.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

from supervisor.config import bench as bench_file
from supervisor.config.models import BenchConfig, DeviceConfig, bench_model
from supervisor.core.errors import ConfigError
from supervisor.devices import adam, bms, chadeche, ea
from supervisor.devices.kind import DeviceKind


class Registry:
    """A set of device kinds: the I/O map model they accept and the lookup by ``driver:``."""

    def __init__(self, kinds: Iterable[DeviceKind[Any]]) -> None:
        by_name: dict[str, DeviceKind[Any]] = {}
        for kind in kinds:
            if kind.name in by_name:
                raise ValueError(f"device kind {kind.name!r} is registered twice")
            by_name[kind.name] = kind
        self.kinds: Mapping[str, DeviceKind[Any]] = MappingProxyType(by_name)
        """Kinds by their I/O map ``driver:`` value, in the order messages list them."""
        self.bench_model: type[BenchConfig] = bench_model([k.config for k in by_name.values()])
        """The I/O map model: ``BenchConfig`` whose ``devices`` are these kinds."""

    def kind_of(self, device: DeviceConfig) -> DeviceKind[Any]:
        """The registration of a configured device; an unknown kind names the known ones."""
        kind = self.kinds.get(device.driver)
        if kind is None:
            raise ConfigError(
                f"device driver {device.driver!r} is not a registered device kind"
                f" (known: {', '.join(self.kinds)})"
            )
        return kind

    def load_bench(self, path: str | Path) -> BenchConfig:
        """Load and fully check an I/O map (every problem in one ConfigErrors)."""
        return bench_file.load_bench(path, self.bench_model)

    def load_bench_text(self, text: str, file: str) -> BenchConfig:
        """The same checks on text not yet written (e.g. an I/O map about to be edited)."""
        return bench_file.load_bench_text(text, file, self.bench_model)

    def bench_from_data(self, data: object, file: str = "<generated>") -> BenchConfig:
        """A bench built in code (dry runs, benchmarks), checked like a file."""
        return bench_file.check_data(data, file, self.bench_model)


REGISTRY: Final = Registry([chadeche.KIND, adam.KIND, ea.KIND, bms.KIND])
"""The kinds this supervisor ships with."""

KINDS: Final = REGISTRY.kinds
BENCH_MODEL: Final = REGISTRY.bench_model
kind_of = REGISTRY.kind_of
load_bench = REGISTRY.load_bench
load_bench_text = REGISTRY.load_bench_text
bench_from_data = REGISTRY.bench_from_data
