"""The seed 002 bench over real protocols on loopback: ADAM (Modbus TCP), EA (SCPI/TCP),
BMS (CAN via socketcand), all simulated around one battery, driven by the real drivers."""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import urllib.request
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import yaml
from ea_rig import ea_only_io_map

from supervisor.app import Bench, build_bench
from supervisor.core.clock import RealClock
from supervisor.core.quality import Quality
from supervisor.devices import base
from supervisor.devices.ea.sim import EaTcpSimulator as EaSimulator
from supervisor.devices.registry import load_bench
from supervisor.sim.battery import make_model
from supervisor.sim.plant import BenchPlant
from supervisor.testing import free_tcp_port, wait_until

ROOT = Path(__file__).resolve().parents[2]
# The bench and its three simulators share one event loop with device timeouts of 0.5 s: a
# process kept off the CPU that long loses its devices (Makefile: the "quiet" marker).
pytestmark = [pytest.mark.integration, pytest.mark.quiet]


def seed002_map(tmp_path: Path) -> Path:
    """sim.yaml without the Chadèche stack, on free loopback ports."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["hmi"]["login"] = False  # its HTTP clients do not log in
    del data["devices"]["chadeche"]
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    for name in ("adam", "ea", "bms"):
        data["devices"][name]["port"] = free_tcp_port()
    data["hmi"]["port"] = 0
    data.pop("opcua", None)  # not part of this test (and 4840 may be taken)
    data.pop("modbus_server", None)  # nor Modbus (1502 may be taken)
    path = tmp_path / "seed002.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


@pytest.fixture
async def bench(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[Bench]:
    monkeypatch.setattr(base, "BACKOFF_START_S", 0.2)
    monkeypatch.setattr(base, "BACKOFF_MAX_S", 1.0)
    b = build_bench(load_bench(seed002_map(tmp_path)), RealClock())
    stop = asyncio.Event()
    await b.start()
    task = asyncio.create_task(b.run(stop))
    try:
        db = b.db
        await wait_until(
            lambda: (
                all(db[f"{d}.connected"].value is True for d in ("adam", "ea", "bms"))
                and db["bms.current"].good
                and db["bms.voltage"].good
                and db["pack.voltage"].good
                and db["estop.ok"].value is True
            ),
            "all devices connected",
        )
        yield b
    finally:
        stop.set()
        await task
        await b.shutdown()


def v(b: Bench, name: str) -> float:
    return b.db[name].as_float()


async def test_2_a_charge_on_the_ea_channel_agrees_in_adam_voltage_board_and_bms(
    bench: Bench,
) -> None:
    db = bench.db
    db.write("ch4.manual_current", 2.0)
    db.write("ch4.enable", True)
    assert bench.sim is not None
    await wait_until(
        lambda: (
            abs(v(bench, "pack.current") - 2.0) < 0.1
            and abs(v(bench, "bms.current") - 2.0) < 0.01
            and abs(v(bench, "ch4.current") - 2.0) < 0.01
        ),
        "2 A seen by the LEM sensor, the BMS and the supply",
    )
    assert bench.sim.plant.contactor_closed
    assert db["contactor.fb"].value is True
    # LEM HAL 300-S: ±1 % of 300 A; ADAM 5017 16-bit on ±10 V: about 0.02 A per count.
    assert v(bench, "pack.current") == pytest.approx(v(bench, "bms.current"), abs=0.1)
    # Voltage board (1:10) vs BMS vs the supply's own measurement; the BMS sends its
    # voltages once a second, so wait for a frame sent after the current settled.
    t_settled = bench.clock.now()
    await wait_until(lambda: db["bms.voltage"].source_t > t_settled, "a fresh 0x1B0 frame")
    assert v(bench, "pack.voltage") == pytest.approx(v(bench, "bms.voltage"), abs=0.02)
    assert v(bench, "ch4.voltage") == pytest.approx(v(bench, "bms.voltage"), abs=0.02)
    assert v(bench, "bms.voltage") > bench.sim.plant.battery.ocv_v  # charging lifts the terminal


async def test_pressing_the_estop_trips_the_channel_opens_the_contactor_and_kills_the_supply(
    bench: Bench,
) -> None:
    db = bench.db
    db.write("ch4.manual_current", 2.0)
    db.write("ch4.enable", True)
    await wait_until(lambda: abs(v(bench, "bms.current") - 2.0) < 0.01, "charging")
    assert bench.sim is not None
    bench.sim.press_estop(True)
    await wait_until(lambda: db["ch4.state"].value == "faulted", "channel tripped")
    assert str(db["ch4.fault"].value).startswith("Emergency stop pressed")
    await wait_until(lambda: not bench.sim.plant.contactor_closed, "contactor open")  # type: ignore[union-attr]
    assert bench.sim.plant.pack_current_a == 0.0
    assert db["ch4.current_cmd"].value == 0.0


@pytest.mark.parametrize(
    ("device", "tags"),
    [
        ("adam", ["pack.current", "pack.voltage", "pack.temp", "contactor.fb"]),
        # ch4 measures its voltage on the battery side (voltage board); the supply its own.
        ("ea", ["ea.voltage", "ch4.current"]),
        ("bms", ["bms.voltage", "bms.current", "bms.cell_min"]),
    ],
)
async def test_a_stopped_simulator_turns_its_tags_bad_and_a_restart_brings_them_back(
    bench: Bench, device: str, tags: list[str]
) -> None:
    sim = bench.sim
    assert sim is not None
    server = sim.devices[device]
    db = bench.db
    assert all(db[t].good for t in tags)
    await server.stop()
    await wait_until(lambda: all(db[t].quality is Quality.BAD for t in tags), f"{device} BAD")
    await wait_until(lambda: db[f"{device}.connected"].value is False, f"{device} disconnected")
    await server.start()
    await wait_until(lambda: all(db[t].good for t in tags), f"{device} GOOD again")
    assert db[f"{device}.connected"].value is True


async def test_losing_the_supply_while_charging_trips_the_channel_safe(bench: Bench) -> None:
    db = bench.db
    db.write("ch4.manual_current", 2.0)
    db.write("ch4.enable", True)
    await wait_until(lambda: abs(v(bench, "ch4.current") - 2.0) < 0.01, "charging")
    assert bench.sim is not None
    await bench.sim.devices["ea"].stop()
    await wait_until(lambda: db["ch4.state"].value == "faulted", "channel tripped on comm loss")
    assert db["contactor.cmd"].value is False
    await wait_until(lambda: not bench.sim.plant.contactor_closed, "contactor open")  # type: ignore[union-attr]


def _http(method: str, url: str, body: object) -> None:
    req = urllib.request.Request(
        url,
        data=json.dumps(body).encode(),
        method=method,
        headers={"Content-Type": "application/json"},
    )
    with urllib.request.urlopen(req, timeout=5) as resp:
        resp.read()


async def test_sigkill_of_the_supervisor_lets_the_supply_watchdog_switch_the_output_off(
    tmp_path: Path,
) -> None:
    clock = RealClock()
    plant = BenchPlant(clock, make_model("liion-pack", cells_series=4, capacity_ah=10.0))
    plant.set_contactor(True)  # the contactor is not part of this test
    ea = EaSimulator(plant)
    await ea.start()
    io_map = ea_only_io_map("watchdog", {"port": ea.port, "poll_period_s": 0.1, "watchdog_s": 1.0})
    io_map["hmi"] = {"port": 0}
    path = tmp_path / "watchdog.yaml"
    path.write_text(yaml.safe_dump(io_map), encoding="utf-8")
    proc = subprocess.Popen(  # noqa: ASYNC220 - Popen only starts it; waits go to threads
        [sys.executable, "-m", "supervisor.cli.main", "run", str(path)],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    try:
        assert proc.stdout is not None
        line = await asyncio.to_thread(proc.stdout.readline)
        while "HTTP API listening" not in line:
            assert line, "supervisor exited before listening"
            line = await asyncio.to_thread(proc.stdout.readline)
        m = re.search(r"(http://127\.0\.0\.1:\d+/api)", line)
        assert m
        url = m.group(1)
        await asyncio.to_thread(_http, "PUT", f"{url}/tags/ch0.manual_current", {"value": 2.0})
        await asyncio.to_thread(_http, "PUT", f"{url}/tags/ch0.enable", {"value": True})
        await wait_until(lambda: plant.supply.output_on and plant.pack_current_a > 1.9, "charging")
        proc.send_signal(signal.SIGKILL)
        await asyncio.to_thread(proc.wait, 10)
        await wait_until(lambda: not plant.supply.output_on, "watchdog switched the output off")
        assert plant.pack_current_a == 0.0
        assert ea.watchdog_trips >= 1
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
        await ea.stop()


async def test_a_cccv_step_on_the_ea_channel_sets_the_supply_cv_voltage(
    bench: Bench, tmp_path: Path
) -> None:
    recipe = tmp_path / "cccv.yaml"
    recipe.write_text(
        "recipe: cccv\nsteps:\n  - {id: c, cccv: {current: 2 A, voltage: 16.4 V}, duration: 1 h}\n",
        encoding="utf-8",
    )
    runner = bench.load_recipe("ch4", recipe, results_dir=tmp_path)
    runner.command("start")
    assert bench.sim is not None
    plant = bench.sim.plant
    await wait_until(
        lambda: plant.supply.volt_set_v == pytest.approx(16.4) and plant.pack_current_a > 1.9,
        "CC-CV charge with the supply's voltage set to the CV target",
    )
    assert plant.supply.curr_set_a == pytest.approx(2.0)
    runner.command("stop")


async def test_supervisor_sim_serves_the_devices_for_a_supervisor_started_without_sims(
    tmp_path: Path,
) -> None:
    path = seed002_map(tmp_path)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    log_path = tmp_path / "sim.log"
    log_file = log_path.open("w")
    sim = subprocess.Popen(  # noqa: ASYNC220 - Popen only starts it; waits go to threads
        [sys.executable, "-m", "supervisor.cli.main", "sim", str(path), "--control-port", "0"],
        stdout=subprocess.PIPE,
        stderr=log_file,
        text=True,
        env=env,
    )
    try:
        assert sim.stdout is not None
        lines = []
        while True:
            line = await asyncio.to_thread(sim.stdout.readline)
            assert line, "supervisor sim exited"
            lines.append(line)
            if line.startswith("e-stop button"):
                break
        assert any(line.startswith("ADAM-5000/TCP adam: modbus tcp 127.0.0.1:") for line in lines)
        assert any(line.startswith("EA supply ea: scpi tcp 127.0.0.1:") for line in lines)
        b = build_bench(load_bench(path), RealClock(), simulate=False)
        assert b.sim is None
        stop = asyncio.Event()
        task = asyncio.create_task(b.run(stop))
        try:
            await wait_until(
                lambda: (
                    all(b.db[f"{d}.connected"].value is True for d in ("adam", "ea", "bms"))
                    and b.db["pack.voltage"].good
                    and b.db["bms.voltage"].good
                ),
                "the supervisor reads the simulated devices of another process",
            )
            assert b.db["pack.voltage"].as_float() == pytest.approx(
                b.db["bms.voltage"].as_float(), abs=0.05
            )
        finally:
            stop.set()
            await task
            await b.shutdown()
    finally:
        sim.send_signal(signal.SIGTERM)
        await asyncio.to_thread(sim.wait, 20)
        log_file.close()
        assert sim.returncode == 0
        sim.stdout.close()  # type: ignore[union-attr]
    # A clean stop says nothing alarming (python-can warned of a CAN bus "not properly
    # shut down" at every stop: the socketcand server's).
    assert "not properly shut down" not in log_path.read_text()


async def test_the_ea_channels_result_file_holds_every_measurement_of_the_pack(
    bench: Bench, tmp_path: Path
) -> None:
    """Seed 002 §2.3 "Save Data": voltage, current, temperature, BMS faults, cell voltages
    and cell temperatures; here in BDF's auxiliary columns after its own, with the pack's
    three voltage readings (the voltage board is ``Voltage / V``) and its three currents,
    the cells' lowest and highest voltage, the lowest, highest and average temperature and
    the BMS's fault bits (issue 32, finding 6)."""
    import csv

    recipe = tmp_path / "charge.yaml"
    recipe.write_text(
        "recipe: aux\nlogging: {period: 0.5 s}\nsteps:\n  - {id: c, charge: 5 A, duration: 3 s}\n",
        encoding="utf-8",
    )
    runner = bench.load_recipe("ch4", recipe, results_dir=tmp_path)
    runner.command("start")
    await wait_until(lambda: runner.state.value == "Complete", "the charge complete", 30.0)
    folder = tmp_path / runner.test_id
    with (folder / f"{runner.test_id}.bdf.csv").open(encoding="utf-8", newline="") as f:
        rows = list(csv.DictReader(f))
    aux = [
        "pack.current / A",
        "room.temp / degC",
        "ea.voltage / V",
        "bms.voltage / V",
        "bms.current / A",
        "bms.cell_min / V",
        "bms.cell_max / V",
        "bms.temp_min / degC",
        "bms.temp_max / degC",
        "bms.temp_avg / degC",
        "bms.faults / 1",
        "Fault",
    ]
    assert list(rows[0])[-len(aux) :] == aux
    charging = [r for r in rows if float(r["Current / A"] or 0) > 4.5]
    assert charging, rows
    for r in charging:
        pack_v = float(r["Voltage / V"])
        assert float(r["bms.voltage / V"]) == pytest.approx(pack_v, abs=0.3)
        assert float(r["ea.voltage / V"]) == pytest.approx(pack_v, abs=0.5)
        assert 3.0 < float(r["bms.cell_min / V"]) <= float(r["bms.cell_max / V"]) < 4.2
        assert float(r["bms.cell_max / V"]) == pytest.approx(pack_v / 4, abs=0.1)
        assert float(r["bms.temp_min / degC"]) <= float(r["bms.temp_max / degC"])
        low, high = float(r["bms.temp_min / degC"]), float(r["bms.temp_max / degC"])
        assert low <= float(r["bms.temp_avg / degC"]) <= high
        assert r["bms.faults / 1"] == "0"  # the BMS's fault bits: none
        assert float(r["pack.current / A"]) == pytest.approx(5.0, abs=0.3)
        assert r["Fault"] == ""  # no trip: an empty cell
