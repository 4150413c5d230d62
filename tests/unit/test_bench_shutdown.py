"""A truthful shutdown (finding 5): ``Bench.shutdown`` says which devices could not confirm
their safe state, and why; a clean stop leaves the EA supply off with its remote lock
released and the ADAM relays off with its host watchdog still armed.

The command line's exit code and wording: tests/integration/test_run_shutdown.py.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from supervisor.app import Bench, build_bench
from supervisor.core.clock import VirtualClock
from supervisor.devices.adam import AdamUnit
from supervisor.devices.ea import EaSimulator
from supervisor.devices.registry import bench_from_data
from supervisor.testing import RecordingDriver

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
async def charging(virtual_clock: VirtualClock) -> AsyncIterator[Bench]:
    """sim.yaml's seed-002 devices and the EA channel in process, charging at 2 A."""
    data: dict[str, Any] = yaml.safe_load(
        (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    )
    data["devices"] = {k: data["devices"][k] for k in ("adam", "ea", "bms")}
    data["tags"] = [t for t in data["tags"] if t["device"] in ("adam", "ea", "bms")]
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    bench = build_bench(bench_from_data(data), virtual_clock, in_process=True)
    await bench.start()
    bench.db.write("ch4.manual_current", 2.0)
    bench.db.write("ch4.enable", True)
    await bench.engine.run_for(1.0)
    assert bench.sim is not None and bench.sim.plant.contactor_closed
    yield bench


def units(bench: Bench) -> tuple[AdamUnit, EaSimulator]:
    assert bench.sim is not None
    adam, ea = bench.sim.devices["adam"], bench.sim.devices["ea"]
    assert isinstance(adam, AdamUnit) and isinstance(ea, EaSimulator)
    return adam, ea


async def test_a_clean_stop_confirms_every_device_and_leaves_everything_off(
    charging: Bench,
) -> None:
    adam, ea = units(charging)
    assert charging.sim is not None
    plant = charging.sim.plant
    assert await charging.shutdown() == {}
    assert not plant.contactor_closed and not plant.supply.output_on
    assert (plant.supply.curr_set_a, plant.supply.sink_curr_set_a) == (0.0, 0.0)
    assert not ea.remote  # the front panel is free again
    assert ea.lines[-1] == "SYST:LOCK OFF"
    assert all(not adam.relay_state(3, ch) for ch in range(6))
    assert adam.host_watchdog_s == 2.0  # the ADAM driver disarmed nothing


async def test_an_unreachable_supply_is_reported_not_confirmed_and_the_others_still_go_safe(
    charging: Bench,
) -> None:
    adam, ea = units(charging)
    await ea.stop()  # unplugged from the network: the driver cannot reach it any more
    unconfirmed = await charging.shutdown()
    assert list(unconfirmed) == ["ea"]
    assert "not connected" in unconfirmed["ea"]
    assert "watchdog switches the output off" in unconfirmed["ea"]
    assert all(not adam.relay_state(3, ch) for ch in range(6))  # went on past the failure


async def test_a_device_whose_safe_state_fails_is_named_with_its_reason(
    virtual_clock: VirtualClock,
) -> None:
    data = {
        "bench": "two",
        "devices": {
            "adam": {
                "driver": "adam5000tcp",
                "host": "127.0.0.1",
                "sim": True,
                "modules": {3: {"kind": "5060"}},
            }
        },
    }
    bench = build_bench(bench_from_data(data), virtual_clock, in_process=True)
    await bench.start()
    await bench.engine.run_for(0.5)
    adam = bench.sim.devices["adam"] if bench.sim is not None else None
    assert isinstance(adam, AdamUnit)
    adam.stick_relay(3, 2, True)  # a welded relay: writes acknowledged, read back on
    unconfirmed = await bench.shutdown()
    assert list(unconfirmed) == ["adam"]
    assert "not verified off" in unconfirmed["adam"]
    assert "slot3.do2" in unconfirmed["adam"]


async def test_a_driver_without_outputs_to_fail_confirms_its_safe_state(
    virtual_clock: VirtualClock,
) -> None:
    driver = RecordingDriver("dev", virtual_clock, {"ai0": 1.0}, ["ao0"])
    assert await driver.safe_state() is None
    assert driver.safe_calls == 1
