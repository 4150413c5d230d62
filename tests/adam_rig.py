"""The seed 002 ADAM-5000/TCP on a test bench: a simulated unit, a link to it, the driver.

One rig for both transports (:mod:`rig_transports`): ``in-process`` links the driver to the
unit with :class:`InProcessLink` (virtual clock), ``tcp`` serves the same unit with
:class:`AdamSimulator` on a loopback port the OS picks and links with
:class:`PymodbusTcpLink` (real clock). The driver tests in tests/unit/test_adam_driver.py
(both transports, or in process) and tests/integration/test_adam.py (TCP only) build it here.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Any, Final, Protocol

import pytest
from rig_transports import IN_PROCESS, TCP

import supervisor.devices.base as base
from supervisor.core.clock import Clock
from supervisor.core.quality import Quality, Reason
from supervisor.devices.adam.driver import AdamDriver, AdamModule
from supervisor.devices.adam.sim import AdamSimulator
from supervisor.devices.adam.transport import InProcessLink, PymodbusTcpLink
from supervisor.devices.adam.unit import AdamUnit
from supervisor.testing.ports import LOOPBACK

TIMEOUT_S: Final = 0.5
"""The link's answer timeout (both links)."""

# Seed 002 layout: 5017 (slot 0), two 5018 (slots 1, 2; slot 2 in two's complement), 5060.
MODULES: Final = {0: "5017", 1: "5018", 2: "5018", 3: "5060"}
FORMATS: Final = {2: "twos"}

Inputs = dict[tuple[int, int], float | None]
RelayCalls = dict[tuple[int, int], list[bool]]


class Pluggable(Protocol):
    """What a test unplugs and plugs in again: the unit itself in process, its server on TCP."""

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    def addresses(self) -> list[str]: ...


def make_unit(
    bench_inputs: Inputs, calls: RelayCalls, clock: Clock | None = None, **unit: Any
) -> AdamUnit:
    """The seed 002 unit; its inputs read ``bench_inputs``, its relays record into ``calls``;
    with a ``clock`` it has a host watchdog (``unit``: more :class:`AdamUnit` settings)."""

    def source(key: tuple[int, int]) -> Callable[[], float | None]:
        return lambda: bench_inputs.get(key)

    def sink(key: tuple[int, int]) -> Callable[[bool], None]:
        return lambda state: calls.setdefault(key, []).append(state)

    analog = {
        (slot, ch): source((slot, ch))
        for slot, kind in MODULES.items()
        if kind != "5060"
        for ch in range(8 if kind == "5017" else 7)
    }
    relays = {(3, ch): sink((3, ch)) for ch in range(6)}
    return AdamUnit(MODULES, analog, relays, raw_format=FORMATS, clock=clock, **unit)


def seed002_inputs() -> Inputs:
    """0 V on the 5017, 20 °C on every thermocouple."""
    inputs: Inputs = {(0, ch): 0.0 for ch in range(8)}
    inputs.update({(slot, ch): 20.0 for slot in (1, 2) for ch in range(7)})
    return inputs


def driver_modules() -> dict[int, AdamModule]:
    return {s: AdamModule(k, FORMATS.get(s, "offset")) for s, k in MODULES.items()}


def inputs_all(driver: AdamDriver, quality: Quality, reason: Reason) -> bool:
    return all(s.quality == quality and s.reason == reason for s in driver.image().values())


def reconnect_on_every_poll(monkeypatch: pytest.MonkeyPatch) -> None:
    """No backoff: tests that drive time by calling poll() reconnect on the next poll (the
    backoff itself is specified on the virtual clock, tests/unit/test_adam_driver.py)."""
    monkeypatch.setattr(base, "BACKOFF_START_S", 0.0)
    monkeypatch.setattr(base, "BACKOFF_MAX_S", 0.0)


@dataclass
class AdamRig:
    transport: str
    clock: Clock
    unit: AdamUnit
    server: Pluggable
    """``stop()`` unplugs the unit, ``start()`` plugs it in again (relay states kept)."""
    link: InProcessLink | PymodbusTcpLink
    driver: AdamDriver
    address: str
    """Where the driver connects, as its messages name it (written out here, not read from
    the link, so that a test comparing messages with it checks the link's wording)."""
    inputs: Inputs = field(default_factory=dict)
    relay_calls: RelayCalls = field(default_factory=dict)

    @property
    def sim(self) -> AdamSimulator:
        """The Modbus TCP server around the unit (``tcp`` rig only)."""
        if not isinstance(self.server, AdamSimulator):
            raise TypeError(f"the {self.transport} rig serves nothing on TCP")
        return self.server


@asynccontextmanager
async def open_rig(
    transport: str, clock: Clock, unit: dict[str, Any] | None = None, **driver: Any
) -> AsyncIterator[AdamRig]:
    """The seed 002 unit plugged in (on ``clock``: its host watchdog runs on it; ``unit``:
    more :class:`AdamUnit` settings), a link to it over ``transport``, its driver (not
    polled yet; ``driver``: more :class:`AdamDriver` settings); on exit the driver is closed
    and the unit unplugged."""
    inputs = seed002_inputs()
    calls: RelayCalls = {}
    unit_ = make_unit(inputs, calls, clock, **(unit or {}))
    server: Pluggable
    link: InProcessLink | PymodbusTcpLink
    if transport == IN_PROCESS:
        server = unit_
        await unit_.start()
        link = InProcessLink("adam1", clock, unit_, timeout_s=TIMEOUT_S)
        address = "in-process simulator adam"
    elif transport == TCP:
        sim = AdamSimulator(unit_, host=LOOPBACK, port=0)
        server = sim
        await sim.start()
        link = PymodbusTcpLink("adam1", sim.host, sim.port, timeout_s=TIMEOUT_S)
        address = f"{LOOPBACK}:{sim.port}"
    else:
        raise ValueError(f"unknown transport {transport!r}")
    adam = AdamDriver("adam1", clock, link, driver_modules(), **driver)
    try:
        yield AdamRig(transport, clock, unit_, server, link, adam, address, inputs, calls)
    finally:
        await adam.close()
        await server.stop()
