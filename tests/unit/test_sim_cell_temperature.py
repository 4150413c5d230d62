"""The simulated cell's temperature reaches the channel (issue 9, "wrong physics in dry
runs"): a simulation-only point of the Chadèche simulator, and the ambient from the I/O map.

A Chadèche board has no temperature sensor (seed 000 §II.B), so the point exists only on
a simulated device (``backend: sim``); on real boards ``check`` refuses it.
"""

from __future__ import annotations

from typing import Any

import pytest

from supervisor.app import build_bench
from supervisor.app.dryrun import DRY_RUN_CELL_TEMPERATURE_TAG, dry_run_config
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigErrors
from supervisor.core.quality import Quality, Reason
from supervisor.devices.chadeche import ChadecheDriver
from supervisor.devices.chadeche.config import SIM_ONLY_MARK
from supervisor.devices.chadeche.protocol import Calibration
from supervisor.devices.chadeche.sim import SimBoard, SimChadecheBus
from supervisor.devices.registry import bench_from_data
from supervisor.sim.battery import NiMHCell
from supervisor.sim.plant import make_plant


def chadeche_bench(backend: str = "sim", **extra: Any) -> dict[str, Any]:
    dev: dict[str, Any] = {
        "driver": "chadeche",
        "backend": backend,
        "poll_period_s": 1.0,
        "stale_after_s": 3.0,
        "boards": [{"address": 0, "sim": {"capacity_ah": 0.8, "soc": 0.5, "temperature_c": 40.0}}],
    }
    return {
        "bench": "t",
        "scan": {"period_s": 1.0},  # hours of virtual time in a fraction of a second
        "devices": {"chadeche": dev},
        "tags": [{"name": "cell0.temp", "device": "chadeche", "point": "b0.temperature"}],
        "channels": [
            {
                "name": "ch0",
                "source": {"device": "chadeche", "board": 0},
                "capacity_ah": 0.8,
                "limits": {"current_a": [-0.4, 0.4], "voltage_v": [0.2, 2.0]},
                "temperature_tag": "cell0.temp",
            }
        ],
        **extra,
    }


# --- the point catalog ------------------------------------------------------------------
def test_a_simulated_board_lists_its_cell_temperature_as_a_simulation_only_point() -> None:
    cfg = bench_from_data(chadeche_bench("sim"))
    info = cfg.devices["chadeche"].points()["b0.temperature"]
    assert (info.direction, info.dtype, info.unit) == ("in", "float", "degC")
    assert SIM_ONLY_MARK in info.description


def test_check_refuses_the_simulated_temperature_point_on_real_boards() -> None:
    with pytest.raises(ConfigErrors) as excinfo:
        bench_from_data(chadeche_bench("spidev"))
    message = str(excinfo.value)
    assert "b0.temperature" in message
    assert "has no point" in message


# --- the driver -------------------------------------------------------------------------
async def test_the_driver_publishes_the_probed_cell_temperature_only_when_given_a_probe() -> None:
    clock = VirtualClock()
    cell = NiMHCell(capacity_ah=2.0, soc=0.5, temperature_c=40.0, ambient_c=25.0)
    bus = SimChadecheBus(clock, {0: SimBoard(cell)})
    plain = ChadecheDriver("c0", clock, bus, {0: Calibration()})
    assert "b0.temperature" not in plain.points()
    driver = ChadecheDriver(
        "c1", clock, bus, {0: Calibration()}, temperature_probe=bus.cell_temperature_c
    )
    assert driver.points()["b0.temperature"].unit == "degC"
    await driver.poll()
    first = driver.image()["b0.temperature"]
    assert first.quality is Quality.GOOD and first.value == pytest.approx(40.0)
    await clock.sleep_until(900.0)  # one thermal time constant at rest
    await driver.poll()
    cooled = driver.image()["b0.temperature"].value
    assert cooled == pytest.approx(cell.temperature_c)
    assert cooled == pytest.approx(25.0 + 15.0 / 2.718281828, abs=0.1)


async def test_a_cell_without_a_thermal_state_reads_as_a_failed_sensor() -> None:
    class Bare:  # a cell model with voltage only (the Cell protocol, nothing more)
        def step(self, current_a: float, dt_s: float) -> None: ...

        def voltage_at(self, current_a: float) -> float:
            return 1.25

        @property
        def terminal_voltage_v(self) -> float:
            return 1.25

    clock = VirtualClock()
    bus = SimChadecheBus(clock, {0: SimBoard(Bare())})
    driver = ChadecheDriver(
        "c", clock, bus, {0: Calibration()}, temperature_probe=bus.cell_temperature_c
    )
    await driver.poll()
    sample = driver.image()["b0.temperature"]
    assert (sample.quality, sample.reason) == (Quality.BAD, Reason.SENSOR_FAILURE)


# --- the benches ------------------------------------------------------------------------
async def test_the_channel_temperature_follows_the_simulated_cell() -> None:
    bench = build_bench(bench_from_data(chadeche_bench("sim")), VirtualClock())
    try:
        await bench.engine.run_for(3.0)
        temp = bench.db["ch0.temperature"]
        assert temp.good
        assert temp.as_float() == pytest.approx(40.0, abs=0.2)
        await bench.engine.run_for(3600.0)
        assert bench.sim is not None
        cell = bench.sim.cells["chadeche.b0"]
        assert bench.db["ch0.temperature"].as_float() == pytest.approx(cell.temperature_c, abs=0.05)
        assert cell.temperature_c < 30.0  # cooling toward the default 25 °C ambient
    finally:
        await bench.shutdown()


async def test_chadeche_cells_cool_toward_the_ambient_of_the_simulation_section() -> None:
    data = chadeche_bench("sim", simulation={"ambient_c": 35.0})
    bench = build_bench(bench_from_data(data), VirtualClock())
    try:
        await bench.engine.run_for(4 * 3600.0)
        assert bench.db["ch0.temperature"].as_float() == pytest.approx(35.0, abs=0.1)
    finally:
        await bench.shutdown()


def test_the_seed_002_pack_cools_toward_the_ambient_of_the_simulation_section() -> None:
    cfg = bench_from_data(chadeche_bench("sim", simulation={"ambient_c": 10.0}))
    clock = VirtualClock()
    plant = make_plant(cfg.simulation, clock)
    plant.battery.step(0.0, 8 * 3600.0)  # 8 thermal time constants of the pack
    assert plant.pack_temperature_c == pytest.approx(10.0, abs=0.1)


async def test_the_nimh_dry_run_bench_maps_the_cell_temperature_on_its_channel() -> None:
    cfg = dry_run_config("nimh-aa", 0.8, 0.5, 1.0)
    (channel,) = cfg.channels
    assert channel.temperature_tag == DRY_RUN_CELL_TEMPERATURE_TAG
    bench = build_bench(cfg, VirtualClock(), in_process=True)
    try:
        await bench.engine.run_for(3.0)
        assert bench.db["ch0.temperature"].good
        assert bench.db["ch0.temperature"].as_float() == pytest.approx(25.0)
    finally:
        await bench.shutdown()
