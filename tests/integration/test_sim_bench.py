"""The default simulated bench end to end: I/O map → drivers → SPI sim → cell → tags."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import pytest
import yaml

from supervisor.app import build_bench
from supervisor.core.clock import VirtualClock
from supervisor.devices.chadeche.sim import SimChadecheBus, SimulatedBoards
from supervisor.devices.registry import load_bench
from supervisor.testing import free_tcp_port

ROOT = Path(__file__).resolve().parents[2]
SIM = ROOT / "io_maps" / "sim.yaml"
pytestmark = pytest.mark.integration


def chadeche_only(tmp: Path) -> Path:
    """sim.yaml's Chadèche stack alone (the network devices need their own servers)."""
    data = yaml.safe_load(SIM.read_text(encoding="utf-8"))
    data["hmi"]["login"] = False  # its HTTP clients do not log in
    data["devices"] = {"chadeche": data["devices"]["chadeche"]}
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "chadeche"]
    data.pop("tags", None)
    data.pop("simulation", None)
    data.pop("safety", None)  # the seed-002 e-stop and its tags are not in this bench
    path = tmp / "chadeche.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def sim_bench():  # type: ignore[no-untyped-def]
    clock = VirtualClock()
    with tempfile.TemporaryDirectory() as tmp:
        bench = build_bench(load_bench(chadeche_only(Path(tmp))), clock)
    return clock, bench


def sim_bus(bench) -> SimChadecheBus:  # type: ignore[no-untyped-def]
    boards = bench.sim.devices["chadeche"]
    assert isinstance(boards, SimulatedBoards)
    return boards.bus


def board(bench, address: int):  # type: ignore[no-untyped-def]
    return sim_bus(bench).boards[address]


async def test_300_ma_charge_raises_the_cell_voltage_and_the_ah_counter_matches_i_times_t() -> None:
    clock, bench = sim_bench()
    ch = bench.channels["ch0"]
    await bench.engine.run_for(10.0)  # settle: first images in, channel idle
    v_before = ch.voltage.as_float()
    bench.db.write("ch0.manual_current", 0.3)
    bench.db.write("ch0.enable", True)
    t_on = clock.now()
    await bench.engine.run_for(3600.0)
    elapsed_s = clock.now() - t_on
    expected_ah = 0.3 * elapsed_s / 3600.0
    assert ch.state.value == "charging"
    assert ch.current.as_float() == pytest.approx(0.3, abs=1e-3)
    assert ch.voltage.as_float() > v_before + 0.02
    assert ch.charge_ah.as_float() == pytest.approx(expected_ah, rel=0.005)
    cell = bench.cells["chadeche.b0"]
    assert ch.charge_ah.as_float() == pytest.approx(cell.charge_ah, rel=0.005)
    await bench.shutdown()


async def test_an_out_of_range_manual_setpoint_is_clamped_before_it_reaches_the_board() -> None:
    _clock, bench = sim_bench()
    # ch2 is limited to 0.2 A in sim.yaml; the command path refuses 1 A, so written past it
    # as a process value: the channel's clamp still holds.
    bench.db.update(bench.db["ch2.manual_current"], 1.0)
    bench.db.write("ch2.enable", True)
    await bench.engine.run_for(2.0)
    assert bench.channels["ch2"].clamped.value is True
    assert board(bench, 2).current_a == pytest.approx(0.2, abs=1e-3)
    await bench.shutdown()


async def test_discharge_sets_the_relay_to_discharge_and_counts_discharged_ah() -> None:
    _clock, bench = sim_bench()
    bench.db.write("ch1.manual_current", -0.2)
    bench.db.write("ch1.enable", True)
    await bench.engine.run_for(600.0)
    b = board(bench, 1)
    assert b.charging is False and b.current_a == pytest.approx(-0.2, abs=1e-3)
    ch = bench.channels["ch1"]
    assert ch.discharged_ah.as_float() == pytest.approx(0.2 * 600 / 3600, rel=0.01)
    assert b.hot_switches == 0
    await bench.shutdown()


async def test_shutdown_puts_every_board_to_zero_current() -> None:
    _clock, bench = sim_bench()
    for n in range(4):
        bench.db.write(f"ch{n}.manual_current", 0.1 if n % 2 else -0.1)
        bench.db.write(f"ch{n}.enable", True)
    await bench.engine.run_for(5.0)
    assert all(board(bench, n).current_a != 0 for n in range(4))
    await bench.shutdown()
    assert [board(bench, n).current_a for n in range(4)] == [0.0, 0.0, 0.0, 0.0]


async def test_a_bus_failure_makes_the_channel_inputs_bad_and_trips_a_driving_channel() -> None:
    _clock, bench = sim_bench()
    bench.db.write("ch0.manual_current", 0.3)
    bench.db.write("ch0.enable", True)
    await bench.engine.run_for(5.0)
    sim_bus(bench).fault = OSError("SPI bus error")
    await bench.engine.run_for(2.0)
    ch = bench.channels["ch0"]
    assert ch.voltage.quality.name == "BAD"
    assert ch.state.value == "faulted"
    assert bench.db["chadeche.connected"].value is False
    sim_bus(bench).fault = None
    await bench.engine.run_for(10.0)
    assert ch.voltage.good
    assert ch.current_cmd.value == 0.0  # never re-energised on its own
    assert board(bench, 0).current_a == 0.0
    await bench.shutdown()


def _http(method: str, url: str, body: object | None = None) -> object:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        url, data=data, method=method, headers={"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(req, timeout=5) as resp:
        return json.loads(resp.read())


def test_supervisor_run_serves_the_api_charges_on_request_and_exits_0_on_sigterm(
    tmp_path: Path,
) -> None:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # sim.yaml on free loopback ports, so a bench already running here does not collide.
    data = yaml.safe_load(SIM.read_text(encoding="utf-8"))
    data["hmi"]["login"] = False  # its HTTP clients do not log in
    for dev in ("adam", "ea", "bms"):
        data["devices"][dev]["port"] = free_tcp_port()
    data["opcua"]["port"], data["modbus_server"]["port"] = free_tcp_port(), free_tcp_port()
    # The folders the HTTP loads below come from (it runs in tmp_path: recipes/ is not there).
    data["recipes"] = {"folders": [str(ROOT / "recipes"), str(ROOT / "tests/data/bad_recipes")]}
    io_map = tmp_path / "sim.yaml"
    io_map.write_text(yaml.safe_dump(data), encoding="utf-8")
    ea_port = data["devices"]["ea"]["port"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "supervisor.cli.main", "run", str(io_map), "--http-port", "0"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        url = None
        banner = []
        for line in proc.stdout:
            banner.append(line)
            m = re.search(r"HTTP API listening on (http://127\.0\.0\.1:\d+/api)", line)
            if m:
                url = m.group(1)
            if line.startswith("Ctrl-C"):
                break
        assert f"simulated EA supply ea: scpi tcp 127.0.0.1:{ea_port}\n" in banner
        assert url, "the bench never said where it listens"
        _http("PUT", f"{url}/tags/ch0.manual_current", {"value": 0.3})
        _http("PUT", f"{url}/tags/ch0.enable", {"value": True})
        deadline = time.monotonic() + 20  # an upper bound for a slow machine, not a timing claim
        current = None
        while time.monotonic() < deadline:
            current = _http("GET", f"{url}/tags/ch0.current")
            if isinstance(current, dict) and current["value"] == pytest.approx(0.3, abs=1e-3):
                break
            time.sleep(0.1)
        assert isinstance(current, dict) and current["quality"] == "GOOD"
        assert current["value"] == pytest.approx(0.3, abs=1e-3)
        refused = urllib.request.Request(
            f"{url}/tags/ch0.voltage",
            data=b'{"value": 3}',
            method="PUT",
            headers={"Content-Type": "application/json"},
        )
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(refused, timeout=5)
        assert info.value.code == 403
        info.value.close()
        # A recipe loaded over HTTP and started through the command tag.
        loaded = _http(
            "PUT", f"{url}/channels/ch1/recipe", {"file": str(ROOT / "recipes/nimh-ds2710.yaml")}
        )
        assert isinstance(loaded, dict) and loaded["channel"] == "ch1"
        _http("PUT", f"{url}/tags/ch1.command", {"value": "start"})
        state = None
        while time.monotonic() < deadline:
            state = _http("GET", f"{url}/tags/ch1.chain.state")
            if isinstance(state, dict) and state["value"] == "Running":
                break
            time.sleep(0.1)
        assert isinstance(state, dict) and state["value"] == "Running"
        bad = urllib.request.Request(
            f"{url}/channels/ch2/recipe",
            data=json.dumps(
                {"file": str(ROOT / "tests/data/bad_recipes/unit_mismatch.yaml")}
            ).encode(),
            method="PUT",
            headers={"Content-Type": "application/json"},
        )
        with pytest.raises(urllib.error.HTTPError) as refused_recipe:
            urllib.request.urlopen(bad, timeout=5)
        assert refused_recipe.value.code == 422
        details = json.loads(refused_recipe.value.read())["details"]
        refused_recipe.value.close()
        assert details[0].endswith(
            "unit_mismatch.yaml:7:17: cannot compare a voltage with a current (voltage >= 300 mA)"
        )
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        assert "stopped: all outputs safe" in out
        assert "Traceback" not in err
        assert "not properly shut down" not in err  # python-can, of the socketcand server
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
