"""Adding a device kind is one new package plus one registry entry (ADR 0006).

The toy kind below stands for such a package (a supply of another make): a config model
with its point catalog, a driver, a registration. Nothing else in the supervisor changes,
yet the I/O map accepts it, ``check`` judges it, the bench wires and scans it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar, Literal

import pytest

from supervisor.app import build_bench
from supervisor.config.models import DeviceConfig, SourcePoints, SourceSpec
from supervisor.core.clock import Clock, VirtualClock
from supervisor.core.driver import Driver, PointInfo, Sample, Value
from supervisor.core.errors import ConfigErrors
from supervisor.devices.base import PolledDriver
from supervisor.devices.kind import DeviceKind, DriverWiring
from supervisor.devices.registry import REGISTRY, Registry
from supervisor.testing import run_scans

TOY_POINTS = {
    "voltage": PointInfo("voltage", "in", "float", "V"),
    "current": PointInfo("current", "in", "float", "A"),
    "current_set": PointInfo("current_set", "out", "float", "A"),
}


class ToySupplyDevice(DeviceConfig):
    driver: Literal["toy-supply"]
    source_noun: ClassVar[str | None] = "a toy supply"

    def points(self) -> Mapping[str, PointInfo]:
        return TOY_POINTS

    def channel_source(self) -> SourceSpec:
        return SourceSpec(
            noun="a toy supply",
            title="toy supply",
            max_current_a=2.0,
            points=lambda board: SourcePoints("voltage", "current", "current_set"),
        )


class ToySupplyDriver(PolledDriver):
    """An ideal current source into a 3.7 V cell with 10 mΩ of resistance."""

    def __init__(self, name: str, clock: Clock) -> None:
        self.current_a = 0.0
        super().__init__(name, clock, 0.1)

    def points(self) -> Mapping[str, PointInfo]:
        return TOY_POINTS

    async def _connect(self) -> None:
        return None

    async def _read(self) -> dict[str, Sample]:
        t = self.clock.now()
        return {
            "voltage": Sample(3.7 + 0.01 * self.current_a, t=t),
            "current": Sample(self.current_a, t=t),
        }

    async def _write(self, point: str, value: Value) -> None:
        assert isinstance(value, float)
        self.current_a = value

    async def _safe(self) -> None:
        self.current_a = 0.0


def _toy_driver(name: str, dev: ToySupplyDevice, wiring: DriverWiring) -> Driver:
    return ToySupplyDriver(name, wiring.clock)


TOY_KIND = DeviceKind(ToySupplyDevice, _toy_driver)
WITH_TOY = Registry([*REGISTRY.kinds.values(), TOY_KIND])

TOY_BENCH = """\
bench: toy
devices:
  psu: {driver: toy-supply}
channels:
  - name: ch0
    source: {device: psu}
    capacity_ah: 2.0
    limits: {current_a: [-1.0, 1.0], voltage_v: [3.0, 4.2]}
"""


def test_a_registered_kind_is_accepted_by_the_io_map_model_and_its_schema() -> None:
    cfg = WITH_TOY.load_bench_text(TOY_BENCH, "toy.yaml")
    assert isinstance(cfg.devices["psu"], ToySupplyDevice)
    assert "ToySupplyDevice" in str(WITH_TOY.bench_model.model_json_schema())


def test_an_unregistered_kind_is_refused_naming_the_known_kinds() -> None:
    with pytest.raises(ConfigErrors) as info:
        REGISTRY.load_bench_text(TOY_BENCH, "toy.yaml")
    first = info.value.errors[0]
    assert (first.line, first.col) == (3, 17)
    assert "unknown value 'toy-supply'" in first.message
    assert all(f"'{name}'" in first.message for name in REGISTRY.kinds)


def test_the_bench_checks_use_what_the_kind_says_of_itself() -> None:
    over = TOY_BENCH.replace("current_a: [-1.0, 1.0]", "current_a: [-3.0, 3.0]")
    with pytest.raises(ConfigErrors) as info:
        WITH_TOY.load_bench_text(over, "toy.yaml")
    assert [e.message for e in info.value.errors] == [
        "a toy supply drives at most 2.0 A; limits [-3.0, 3.0] A exceed it"
    ]


def test_a_device_that_cannot_drive_a_channel_is_refused_naming_every_kind_that_can() -> None:
    text = TOY_BENCH.replace(
        "devices:\n", "devices:\n  pack_bms: {driver: bms-can, interface: virtual}\n"
    ).replace("source: {device: psu}", "source: {device: pack_bms}")
    with pytest.raises(ConfigErrors) as info:
        WITH_TOY.load_bench_text(text, "toy.yaml")
    assert any(
        "cannot drive a channel; use a Chadèche board or an EA supply or a toy supply" in e.message
        for e in info.value.errors
    )


async def test_a_registered_kind_is_wired_and_scanned_like_the_shipped_ones() -> None:
    cfg = WITH_TOY.load_bench_text(TOY_BENCH, "toy.yaml")
    bench = build_bench(cfg, VirtualClock(), registry=WITH_TOY)
    bench.db.write("ch0.manual_current", 0.5)
    bench.db.write("ch0.enable", True)
    await run_scans(bench.engine, 10)
    assert bench.db["ch0.current"].value == pytest.approx(0.5)
    assert bench.db["ch0.voltage"].value == pytest.approx(3.705)
    assert bench.db["ch0.state"].value == "charging"
    await bench.shutdown()
    assert bench.db["ch0.current_cmd"].value == 0.0


def test_a_kind_is_registered_once() -> None:
    with pytest.raises(ValueError, match="registered twice"):
        Registry([*REGISTRY.kinds.values(), REGISTRY.kinds["chadeche"]])
