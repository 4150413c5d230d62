"""The battery contactor opens when the supervisor dies: two independent layers (docs/design.md
"Safety"), on virtual time.

- The hardware watchdog relay in series with the contactor coil (simulated in the plant):
  the contactor is closed only while its coil relay is on AND the heartbeat output toggled
  within the watchdog time; the contactor's auxiliary contact (``contactor.closed``) shows
  the contactor itself, not only its coil (``contactor.fb``).
- The ADAM-5000/TCP's own host watchdog: armed at every connect (safe values: every relay
  off), kept alive by the polls; with no request for its timeout the unit switches every
  relay off by itself. A clean stop leaves the relays off and the watchdog armed.

Over Modbus TCP (the served unit's checker on the real clock), and with two real processes
(SIGKILL of ``supervisor run``): tests/integration/test_watchdogs.py.
"""

from __future__ import annotations

import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from adam_rig import AdamRig, open_rig, reconnect_on_every_poll
from rig_transports import IN_PROCESS, clock_for, on_both_transports

from supervisor.app import Bench, build_bench
from supervisor.config.models import BenchConfig
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigErrors
from supervisor.devices.adam import AdamDriver, AdamModule, AdamUnit, InProcessLink
from supervisor.devices.adam.protocol import (
    HOST_WATCHDOG_SAFE_VALUES_REGISTER,
    HOST_WATCHDOG_TIMEOUT_REGISTER,
    host_watchdog_counts,
)
from supervisor.devices.ea import EaSimulator
from supervisor.devices.registry import bench_from_data
from supervisor.fieldbus.modbus import FC_READ_HOLDING_REGISTERS
from supervisor.sim.battery import make_model
from supervisor.sim.plant import BenchPlant

ROOT = Path(__file__).resolve().parents[2]
WATCHDOG_S = 0.5


# --- the hardware watchdog relay, in the plant --------------------------------------------------
def relay_plant(clock: VirtualClock) -> BenchPlant:
    """The seed 002 pack behind a supply set to charge at 2 A, watchdog relay fitted (1.5 s)."""
    battery = make_model("liion-pack", cells_series=4, capacity_ah=10.0, soc=0.5)
    plant = BenchPlant(clock, battery, watchdog_timeout_s=1.5)
    plant.set_supply(remote=True, output_on=True, volt_set_v=16.8, curr_set_a=2.0)
    return plant


def test_without_a_heartbeat_the_coil_relay_alone_does_not_close_the_contactor() -> None:
    plant = relay_plant(VirtualClock())
    plant.set_contactor(True)
    assert plant.contactor_coil_on
    assert not plant.watchdog_relay_closed
    assert not plant.contactor_closed
    assert plant.pack_current_a == 0.0


def test_the_contactor_stays_closed_while_the_heartbeat_toggles() -> None:
    clock = VirtualClock()
    plant = relay_plant(clock)
    plant.set_contactor(True)
    for k in range(20):  # 10 s of a 0.5 s heartbeat
        plant.set_heartbeat(k % 2 == 0)
        clock.advance(0.5)
        assert plant.contactor_closed
    assert plant.pack_current_a == pytest.approx(2.0)
    assert plant.heartbeat_toggles == 20


def test_writing_the_same_heartbeat_state_again_is_not_a_toggle() -> None:
    clock = VirtualClock()
    plant = relay_plant(clock)
    plant.set_contactor(True)
    plant.set_heartbeat(True)
    clock.advance(1.0)
    plant.set_heartbeat(True)  # a stuck output: no edge, no retrigger
    clock.advance(0.6)
    assert not plant.contactor_closed
    assert plant.heartbeat_toggles == 1


def test_the_contact_opens_just_after_the_watchdog_time_and_the_current_stops_then() -> None:
    clock = VirtualClock()
    plant = relay_plant(clock)
    plant.set_contactor(True)
    plant.set_heartbeat(True)
    q0 = plant.battery.charge_ah
    clock.advance(1.5)
    assert plant.contactor_closed  # at exactly the watchdog time it still holds
    clock.advance(10.0)  # nobody looked in between: the opening instant is still exact
    assert not plant.contactor_closed
    assert plant.contactor_coil_on  # the coil relay never moved
    assert plant.pack_current_a == 0.0
    assert plant.battery.charge_ah - q0 == pytest.approx(2.0 * 1.5 / 3600.0, rel=1e-6)


def test_heartbeats_coming_back_close_the_contactor_again_while_its_coil_is_on() -> None:
    """A plain watchdog relay does not latch: a supervisor that starts again must open the
    coil relay itself before it toggles (it does: outputs start off)."""
    clock = VirtualClock()
    plant = relay_plant(clock)
    plant.set_contactor(True)
    plant.set_heartbeat(True)
    clock.advance(2.0)
    assert not plant.contactor_closed
    plant.set_heartbeat(False)
    assert plant.contactor_closed


def test_without_a_watchdog_relay_the_contactor_follows_its_coil() -> None:
    battery = make_model("liion-pack", cells_series=4, capacity_ah=10.0, soc=0.5)
    plant = BenchPlant(VirtualClock(), battery)
    assert plant.watchdog_relay_closed
    plant.set_contactor(True)
    assert plant.contactor_closed
    plant.set_contactor(False)
    assert not plant.contactor_closed


# --- the I/O map's simulation section ------------------------------------------------------------
def sim_yaml() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load(
        (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    )
    return data


def seed002(data: dict[str, Any], period_s: float = 0.1) -> BenchConfig:
    """``data``'s seed-002 devices and the EA channel (no Chadèche stack)."""
    data["devices"] = {k: data["devices"][k] for k in ("adam", "ea", "bms")}
    data["tags"] = [t for t in data["tags"] if t["device"] in ("adam", "ea", "bms")]
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "ea"]
    data["scan"] = {"period_s": period_s}
    return bench_from_data(data)


def test_sim_yaml_wires_the_contactor_feedback_and_the_heartbeat() -> None:
    cfg = seed002(sim_yaml())
    sim = cfg.simulation
    assert sim is not None and sim.contactor_feedback is not None
    assert (sim.contactor_feedback.device, sim.contactor_feedback.point) == ("adam", "slot0.ai3")
    tags = {t.name: t for t in cfg.tags}
    assert (tags["contactor.closed"].point, tags["contactor.closed"].threshold) == (
        "slot0.ai3",
        2.5,
    )
    assert tags["watchdog.heartbeat"].point == "slot3.do5"


@pytest.mark.parametrize(
    ("entry", "words"),
    [
        ({"watchdog_relay": {"device": "adam", "point": "slot0.ai4"}}, "must be a relay output"),
        ({"contactor_feedback": {"device": "adam", "point": "slot3.do4"}}, "an analog input"),
        ({"watchdog_relay": {"device": "adam", "point": "slot3.do0"}}, "its own output"),
        ({"watchdog_relay": {"device": "adam", "point": "slot3.do9"}}, "has no point"),
        ({"watchdog_relay": {"device": "adam", "point": "slot3.do5", "timeout_s": 0}}, "greater"),
    ],
)
def test_the_simulation_section_refuses_a_miswired_watchdog_relay_or_feedback(
    entry: dict[str, Any], words: str
) -> None:
    data = sim_yaml()
    data["simulation"].update(entry)
    with pytest.raises(ConfigErrors, match=words):
        seed002(data)


# --- the relay in a bench: the test toggles the heartbeat itself ------------------------------
@pytest.fixture
async def relay_bench(virtual_clock: VirtualClock) -> AsyncIterator[Bench]:
    """sim.yaml's ADAM alone in process, the watchdog relay fitted (1.5 s) and the ADAM host
    watchdog off (this relay alone). No channel: the test drives ``contactor.cmd`` itself."""
    data = sim_yaml()
    wd = {"device": "adam", "point": "slot3.do5", "timeout_s": 1.5}
    data["simulation"]["watchdog_relay"] = wd
    data["devices"] = {"adam": data["devices"]["adam"]}
    data["devices"]["adam"].pop("host_watchdog_s")
    data["tags"] = [t for t in data["tags"] if t["device"] == "adam"]
    data["channels"] = []
    data["safety"].pop("heartbeat")  # the test toggles it, so it can stop it
    bench = build_bench(bench_from_data(data), virtual_clock, in_process=True)
    await bench.start()
    bench.db.update(bench.db["contactor.cmd"], True)  # the coil relay on
    try:
        yield bench
    finally:
        await bench.shutdown()


async def run_with_heartbeat(bench: Bench, duration_s: float, period_s: float = 0.5) -> None:
    """Scan for ``duration_s``, flipping ``watchdog.heartbeat`` every ``period_s``."""
    heartbeat = bench.db["watchdog.heartbeat"]
    for _ in range(round(duration_s / period_s)):
        bench.db.update(heartbeat, not heartbeat.value)
        await bench.engine.run_for(period_s)


async def test_in_a_bench_the_contactor_closes_only_while_the_heartbeat_toggles(
    relay_bench: Bench,
) -> None:
    assert relay_bench.sim is not None
    plant = relay_bench.sim.plant
    db = relay_bench.db
    await relay_bench.engine.run_for(1.0)  # no heartbeat yet
    assert db["contactor.fb"].value is True  # the coil relay is on...
    assert not plant.contactor_closed  # ...but the watchdog relay's contact is open
    assert db["contactor.closed"].value is False  # and the auxiliary contact says so
    await run_with_heartbeat(relay_bench, 3.0)
    assert plant.contactor_closed
    assert db["contactor.closed"].value is True


async def test_in_a_bench_a_heartbeat_that_stops_opens_the_contactor_its_coil_still_on(
    relay_bench: Bench,
) -> None:
    assert relay_bench.sim is not None
    plant = relay_bench.sim.plant
    db = relay_bench.db
    await run_with_heartbeat(relay_bench, 3.0)
    assert plant.contactor_closed
    await relay_bench.engine.run_for(0.9)  # the heartbeat stopped 1.4 s ago: still closed
    assert plant.contactor_closed
    await relay_bench.engine.run_for(0.3)  # past 1.5 s since the last toggle
    assert not plant.contactor_closed
    assert db["contactor.closed"].value is False
    assert db["contactor.fb"].value is True  # the coil relay alone would have lied


# --- the ADAM host watchdog ---------------------------------------------------------------------
@pytest.fixture
async def guarded(
    transport: str, virtual_clock: VirtualClock, monkeypatch: pytest.MonkeyPatch
) -> AsyncIterator[AdamRig]:
    """The seed 002 ADAM with the host watchdog at 0.5 s, connected, contactor relay on."""
    reconnect_on_every_poll(monkeypatch)
    clock = clock_for(transport, virtual_clock)
    async with open_rig(transport, clock, poll_period_s=0.1, host_watchdog_s=WATCHDOG_S) as rig:
        await rig.driver.poll()
        assert rig.driver.connected, rig.driver.last_error
        rig.driver.write("slot3.do0", True)
        await rig.driver.flush()
        assert rig.unit.relay_state(3, 0)
        yield rig


async def let_time_pass(clock: VirtualClock, dt_s: float) -> None:
    await clock.sleep_until(clock.now() + dt_s)


@on_both_transports
async def test_connect_arms_the_host_watchdog_with_every_relay_off_as_safe_value(
    guarded: AdamRig,
) -> None:
    assert guarded.unit.host_watchdog_s == pytest.approx(WATCHDOG_S)
    assert guarded.unit.read_registers(
        FC_READ_HOLDING_REGISTERS, HOST_WATCHDOG_SAFE_VALUES_REGISTER + 3, 1
    ) == [0]
    assert any(
        f"@{HOST_WATCHDOG_TIMEOUT_REGISTER}={host_watchdog_counts(WATCHDOG_S)}" in line
        for line in guarded.driver.raw_log
    )


async def test_the_unit_switches_every_relay_off_when_the_driver_stops_talking(
    guarded: AdamRig, virtual_clock: VirtualClock
) -> None:
    await let_time_pass(virtual_clock, WATCHDOG_S)
    guarded.unit.check()
    assert guarded.unit.relay_state(3, 0)  # at exactly its timeout it still holds
    await let_time_pass(virtual_clock, 0.001)
    guarded.unit.check()  # what the unit did meanwhile
    assert not guarded.unit.relay_state(3, 0)
    assert guarded.relay_calls[(3, 0)][-1] is False  # the contactor coil let go
    assert guarded.unit.host_watchdog_trips == 1


async def test_polling_keeps_the_host_watchdog_alive(
    guarded: AdamRig, virtual_clock: VirtualClock
) -> None:
    for _ in range(30):  # 3 s of polls every 0.1 s, well past the 0.5 s timeout
        await let_time_pass(virtual_clock, 0.1)
        await guarded.driver.poll()
    guarded.unit.check()
    assert guarded.unit.host_watchdog_trips == 0
    assert guarded.unit.relay_state(3, 0)


async def test_a_request_after_the_timeout_finds_the_relays_already_off(
    guarded: AdamRig, virtual_clock: VirtualClock
) -> None:
    await let_time_pass(virtual_clock, 1.0)  # nobody calls check(): the next request sees it
    await guarded.driver.poll()
    assert guarded.unit.host_watchdog_trips == 1
    assert guarded.driver.image()["slot3.do0_fb"].value is False
    await let_time_pass(virtual_clock, 0.1)
    await guarded.driver.poll()  # talking again: the timer runs again, nothing more trips
    assert guarded.unit.host_watchdog_trips == 1


async def test_a_clean_stop_leaves_the_relays_off_and_the_host_watchdog_armed(
    guarded: AdamRig, virtual_clock: VirtualClock
) -> None:
    assert await guarded.driver.safe_state() is None
    await guarded.driver.close()
    assert not guarded.unit.relay_state(3, 0)
    assert guarded.unit.host_watchdog_s == pytest.approx(WATCHDOG_S)  # nothing disarmed
    await let_time_pass(virtual_clock, 1.0)
    guarded.unit.check()
    assert all(not guarded.unit.relay_state(3, ch) for ch in range(6))


async def test_a_unit_that_refuses_the_watchdog_registers_is_not_connected(
    virtual_clock: VirtualClock, caplog: pytest.LogCaptureFixture
) -> None:
    unit = AdamUnit({0: "5017", 3: "5060"})  # no clock: this unit has no such registers
    await unit.start()
    link = InProcessLink("adam", virtual_clock, unit)
    modules = {0: AdamModule("5017"), 3: AdamModule("5060")}
    driver = AdamDriver("adam", virtual_clock, link, modules, host_watchdog_s=1.0)
    await driver.poll()
    assert not driver.connected
    assert "host watchdog not armed" in driver.last_error
    assert "UNVERIFIED" in driver.last_error


async def test_a_unit_that_wants_host_ok_writes_is_kept_alive_only_by_them(
    virtual_clock: VirtualClock,
) -> None:
    for refresh, trips in ((False, 1), (True, 0)):
        async with open_rig(
            IN_PROCESS,
            virtual_clock,
            unit={"watchdog_needs_refresh": True},
            poll_period_s=0.1,
            host_watchdog_s=WATCHDOG_S,
            host_watchdog_refresh=refresh,
        ) as rig:
            await rig.driver.poll()
            for _ in range(10):
                await let_time_pass(virtual_clock, 0.1)
                await rig.driver.poll()
            rig.unit.check()
            assert rig.unit.host_watchdog_trips == trips, f"refresh={refresh}"


@pytest.mark.parametrize(
    ("host_watchdog_s", "words"),
    [
        (0.25, "not a multiple of 0.1 s"),
        (0.1, "at least 3 x the fastest poll period (0.2 s)"),
        (7000.0, "outside 0.1..6553.5 s"),
    ],
)
def test_an_io_map_refuses_a_host_watchdog_the_unit_cannot_hold_or_the_polls_cannot_feed(
    host_watchdog_s: float, words: str
) -> None:
    data = sim_yaml()
    for module in data["devices"]["adam"]["modules"].values():
        module.pop("poll_period_s", None)  # every slot at the device's 0.2 s
    data["devices"]["adam"]["host_watchdog_s"] = host_watchdog_s
    with pytest.raises(ConfigErrors, match=re.escape(words)):
        seed002(data)


def test_the_driver_refuses_a_host_watchdog_its_polls_cannot_feed() -> None:
    link = InProcessLink("adam", VirtualClock(), AdamUnit({3: "5060"}))
    with pytest.raises(ValueError, match="at least 3 x"):
        AdamDriver("adam", VirtualClock(), link, {3: AdamModule("5060")}, host_watchdog_s=0.3)


# --- finding 3 on virtual time: the supervisor dies while charging --------------------------------
async def test_when_the_supervisor_stops_talking_the_contactor_opens_and_the_supply_goes_off(
    virtual_clock: VirtualClock,
) -> None:
    """sim.yaml as shipped (ADAM host watchdog 2 s, EA watchdog 2 s): after the last request
    nothing reaches the devices (a SIGKILL); each unit acts on its own."""
    bench = build_bench(seed002(sim_yaml(), 0.01), virtual_clock, in_process=True)
    await bench.start()
    bench.db.write("ch4.manual_current", 2.0)
    bench.db.write("ch4.enable", True)
    await bench.engine.run_for(1.0)
    sim = bench.sim
    assert sim is not None
    plant = sim.plant
    assert plant.contactor_closed and plant.supply.output_on
    adam, ea = sim.devices["adam"], sim.devices["ea"]
    assert isinstance(adam, AdamUnit) and isinstance(ea, EaSimulator)
    # The scan is gone: no poll, no write, no safe state. Time goes on for the units only.
    await let_time_pass(virtual_clock, 2.1)
    adam.check()
    ea.check()
    assert not plant.contactor_closed
    assert not plant.supply.output_on
    assert plant.pack_current_a == 0.0
    assert adam.host_watchdog_trips == 1
    await bench.shutdown()
