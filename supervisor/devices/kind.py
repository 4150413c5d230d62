"""What a device kind registers, and what the composition root hands its factories.

A kind is one folder under ``supervisor/devices/`` (Home Assistant's one package per
integration): its codec, its config model and point catalog, its driver, its simulator and
this registration. ``supervisor.devices.registry`` lists the kinds; configuration checks,
bench wiring, simulation and the screens' mimic iterate it instead of asking "which kind is
this?".
"""

from __future__ import annotations

import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Final, Generic, Protocol, TypeVar

from supervisor.config.models import BenchConfig, ChannelConfig, DeviceConfig
from supervisor.core.clock import Clock
from supervisor.core.driver import Driver
from supervisor.sim.battery import BatteryModel
from supervisor.sim.plant import BenchPlant

C = TypeVar("C", bound=DeviceConfig)


class DeviceRole(StrEnum):
    """What a device is on the bench, for the screens' mimic of the power path."""

    SUPPLY = "supply"
    """A power supply that drives a channel through its DC output (the mimic's supply box)."""
    BMS = "bms"
    """The battery's management system: its link and its cell figures (the BMS box)."""
    IO = "io"
    """Remote I/O: relays, analog inputs, thermocouples (its tags are channels' and alarms')."""
    CYCLER = "cycler"
    """Boards that are channels themselves (their channels are the overview's tiles)."""


LINK: Final = "connected"
"""The pseudo-point of :class:`Shown` for the device's link tag (``<device>.connected``, which
the bench makes for every device); every other ``point`` is one of the kind's points."""


@dataclass(frozen=True)
class Shown:
    """One line of a device's box on the mimic: a point of the device, and how it reads.

    The screen draws the I/O map's tag bound to this device and ``point`` (no tag: no line),
    so no screen knows a device's name or a kind's points."""

    label: str
    point: str
    format: str
    """``link`` (ok / LOST) or a number format the screens know (``n2``: two decimals)."""


class DeviceSimulator(Protocol):
    """A device simulated at the protocol level, built on the same codec as its driver."""

    async def start(self) -> None:
        """Serve it to other processes (protocol servers on loopback), if it can."""
        ...

    async def stop(self) -> None: ...

    def addresses(self) -> list[str]:
        """Where it listens, one line each, for the run banner."""
        ...


@dataclass(frozen=True)
class DriverWiring:
    """What a kind's driver factory gets from the composition root."""

    clock: Clock
    bench: BenchConfig
    simulator: DeviceSimulator | None = None
    """This device's simulator when the driver talks to it in process (dry runs, virtual
    clock tests, a simulated SPI bus); None: the real transport from the config."""

    def owner(self, device: str) -> ChannelConfig | None:
        """The channel this device drives, if any (it may take its limits from it)."""
        return next((c for c in self.bench.channels if c.source.device == device), None)


@dataclass
class SimWiring:
    """What a kind's simulator factory gets: one plant shared by every simulated device."""

    clock: Clock
    bench: BenchConfig
    plant: BenchPlant
    in_process: bool = False
    """The drivers talk to the simulators in this process (dry runs, virtual-clock tests):
    nothing is served on the network, and nothing may sleep on its own (a virtual clock
    only moves when the scan sleeps)."""
    cells: dict[str, BatteryModel] = field(default_factory=dict)
    """Battery models a simulator owns besides the plant (a Chadèche board's cell), by
    ``<device>.<point prefix>``: tests and the dry run look at them."""


@dataclass(frozen=True)
class DeviceKind(Generic[C]):
    """One device kind: its I/O map model and how to build its driver and its simulator."""

    config: type[C]
    build_driver: Callable[[str, C, DriverWiring], Driver]
    build_simulator: Callable[[str, C, SimWiring], DeviceSimulator] | None = None
    in_process_only: bool = False
    """Its simulator cannot be served to another process (a simulated SPI bus): the driver of
    a simulated device of this kind always talks to it in process."""
    role: DeviceRole = DeviceRole.IO
    """What a device of this kind is on the bench (the mimic's box it fills, if any)."""
    shows: tuple[Shown, ...] = ()
    """The lines of its mimic box, in order (its output switch is its channel's, not here)."""

    @property
    def name(self) -> str:
        """The I/O map's ``driver:`` value (the literal of the model's ``driver`` field)."""
        (value,) = typing.get_args(self.config.model_fields["driver"].annotation)
        return str(value)
