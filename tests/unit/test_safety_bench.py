"""The simulated bench of io_maps/sim.yaml, in process on the virtual clock: what the safety
phase does with the e-stop, recipe limits and read-backs, seen as a user sees it (tags)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from supervisor.app import Bench, build_bench
from supervisor.chains.states import State
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.devices.registry import load_bench, load_bench_text
from supervisor.testing import run_scans

ROOT = Path(__file__).resolve().parents[2]
SIM = ROOT / "io_maps" / "sim.yaml"

CHARGE_WITH_LIMITS = """\
recipe: pack-charge
limits: {voltage: [12 V, 16.8 V]}
steps:
  - {id: charge, charge: 2 A, duration: 1 h}
"""


async def started(bench: Bench) -> Bench:
    await bench.start()
    await run_scans(bench.engine, 20)  # first images in, every device connected
    return bench


@pytest.fixture
async def bench() -> AsyncIterator[Bench]:
    b = await started(build_bench(load_bench(SIM), VirtualClock(), in_process=True))
    yield b
    await b.shutdown()


def v(bench: Bench, name: str) -> Any:
    return bench.db[name].value


def run_recipe(bench: Bench, tmp_path: Path, channel: str, text: str) -> None:
    path = tmp_path / "r.yaml"
    path.write_text(text, encoding="utf-8")
    bench.load_recipe(channel, path, results_dir=tmp_path)
    bench.runners[channel].command("start", actor="test")


# --- finding 1: recipe limits watch the battery, and arm once the contactor is closed -------
async def test_recipe_limits_on_the_ea_channel_do_not_hold_before_the_contactor_closes(
    bench: Bench, tmp_path: Path
) -> None:
    run_recipe(bench, tmp_path, "ch4", CHARGE_WITH_LIMITS)
    await run_scans(bench.engine, 50)
    assert v(bench, "ch4.chain.state") == State.RUNNING.value, v(bench, "ch4.chain.alarm")
    assert v(bench, "ch4.chain.alarm") == ""
    assert v(bench, "ch4.armed") is True
    assert v(bench, "ch4.current") == pytest.approx(2.0, abs=0.05)


async def test_limits_arm_only_once_the_power_path_is_closed_when_measured_at_the_supply(
    tmp_path: Path,
) -> None:
    # The supply's terminals read 0 V until the contactor closes: a channel measured there
    # must not hold on "0 V below 12 V" in its first scans.
    data = yaml.safe_load(SIM.read_text(encoding="utf-8"))
    ch4 = next(c for c in data["channels"] if c["name"] == "ch4")
    del ch4["voltage_tag"]
    ch4["voltage_checks"] = []
    cfg = load_bench_text(yaml.safe_dump(data), "terminals.yaml")
    b = await started(build_bench(cfg, VirtualClock(), in_process=True))
    try:
        assert v(b, "ch4.voltage") == 0.0  # contactor open: nothing on the terminals
        run_recipe(b, tmp_path, "ch4", CHARGE_WITH_LIMITS)
        await run_scans(b.engine, 50)
        assert v(b, "ch4.chain.state") == State.RUNNING.value, v(b, "ch4.chain.alarm")
        assert v(b, "ch4.voltage") > 12.0
    finally:
        await b.shutdown()


# --- finding 4: the e-stop aborts, and cannot be reset while pressed ---------------------------
async def test_the_estop_aborts_the_recipe_and_is_not_reset_while_still_pressed(
    bench: Bench, tmp_path: Path
) -> None:
    run_recipe(bench, tmp_path, "ch4", CHARGE_WITH_LIMITS)
    await run_scans(bench.engine, 30)
    assert bench.sim is not None
    bench.sim.press_estop(True)
    await run_scans(bench.engine, 10)
    assert v(bench, "ch4.chain.state") == State.ABORTED.value  # aborted, not held
    assert "e-stop circuit open" in v(bench, "ch4.fault")
    assert v(bench, "contactor.cmd") is False and not bench.sim.plant.contactor_closed
    bench.db.write("ch4.ack", True)  # acknowledged, but the e-stop is still pressed
    await run_scans(bench.engine, 3)
    assert "e-stop circuit open" in v(bench, "ch4.fault")
    assert v(bench, "ch4.state") == "faulted"
    with pytest.raises(OperatorError, match="cause is still present"):
        bench.safety.guards["ch4"].reset("operator")
    bench.sim.press_estop(False)
    await run_scans(bench.engine, 5)
    bench.safety.guards["ch4"].reset("operator")
    await run_scans(bench.engine, 3)
    assert v(bench, "ch4.fault") == ""
    assert v(bench, "ch4.state") == "idle"
    assert v(bench, "ch4.enable") is False  # never re-energised on its own


async def test_the_estop_trips_every_channel_at_once(bench: Bench) -> None:
    for ch in ("ch0", "ch4"):
        bench.db.write(f"{ch}.manual_current", 0.2)
        bench.db.write(f"{ch}.enable", True)
    await run_scans(bench.engine, 20)
    assert v(bench, "ch0.state") == "charging" and v(bench, "ch4.state") == "charging"
    assert bench.sim is not None
    bench.sim.press_estop(True)
    await run_scans(bench.engine, 5)
    faults = {ch: v(bench, f"{ch}.fault") for ch in ("ch0", "ch1", "ch2", "ch3", "ch4")}
    assert all("e-stop" in f for f in faults.values()), faults
    assert v(bench, "ch0.current_cmd") == 0.0 and v(bench, "ch4.current_cmd") == 0.0
    assert bench.alarms is not None and bench.alarms["estop"].first_out


# --- finding 2: outputs that do not match their read-backs --------------------------------------
async def test_a_supply_switched_off_behind_the_supervisors_back_trips_the_channel(
    bench: Bench,
) -> None:
    # A second supervisor started by mistake connected and switched the supply safe: the
    # first must not go on showing "charging" with 0 A against 2 A commanded.
    bench.db.write("ch4.manual_current", 2.0)
    bench.db.write("ch4.enable", True)
    await run_scans(bench.engine, 30)
    assert v(bench, "ch4.state") == "charging"
    assert bench.sim is not None
    ea = bench.sim.devices["ea"]
    ea.handle_line(b"OUTP OFF\n")  # type: ignore[attr-defined]
    await run_scans(bench.engine, 30)  # 3 s: beyond the 1 s discrepancy time
    fault = v(bench, "ch4.fault")
    assert "supply output off while commanded on" in fault or "against 2.000 A" in fault, fault
    assert v(bench, "ch4.state") == "faulted"
    assert v(bench, "contactor.cmd") is False


async def test_a_contactor_opened_behind_the_supervisors_back_trips_the_channel(
    bench: Bench,
) -> None:
    bench.db.write("ch4.manual_current", 2.0)
    bench.db.write("ch4.enable", True)
    await run_scans(bench.engine, 30)
    assert bench.sim is not None
    adam = bench.sim.devices["adam"]
    adam.write_coils(3 * 16 + 0, [False])  # type: ignore[attr-defined]  # slot 3, relay 0
    await run_scans(bench.engine, 30)
    assert v(bench, "ch4.state") == "faulted", v(bench, "ch4.fault")
    assert v(bench, "ch4.current_cmd") == 0.0


async def test_a_recipe_limit_holds_only_once_the_crossing_lasted_its_delay(
    bench: Bench, tmp_path: Path
) -> None:
    text = (
        "recipe: delayed\nlimits: {voltage: [0.9 V, 1.0 V], delay: 5 s}\n"
        "steps:\n  - {id: charge, charge: 100 mA, duration: 1 h}\n"
    )
    run_recipe(bench, tmp_path, "ch0", text)  # a NiMH cell at about 1.3 V: over 1.0 V
    await run_scans(bench.engine, 30)
    assert v(bench, "ch0.chain.state") == State.RUNNING.value
    await run_scans(bench.engine, 30)
    assert v(bench, "ch0.chain.state") == State.HELD.value
    assert v(bench, "ch0.chain.alarm").startswith("limit: voltage")
