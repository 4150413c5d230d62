"""EA-PSB 10000 driver: its contract on both transports; in process, on the virtual clock,
its timeouts, the unit's watchdog and the in-process transport; the simulator's SCPI; the
registration and the dry run.

The contract (:class:`TestDriverOnBothTransports`) runs each test on
:class:`InProcessScpiTransport` (no socket, virtual clock: time only moves when a test moves
it) and over SCPI/TCP on loopback (real clock, marked ``integration``): the same assertions
whatever carries the lines (STYLE.md "Contract tests rerunnable on hardware"). What only TCP
has (nothing listening, a socket closed by the device, raw sessions, a restart on the same
port, the watchdog after a silent socket close) stays in tests/integration/test_ea.py.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
from ea_rig import (
    I_MAX_A,
    V_MAX,
    V_MIN,
    EaRig,
    assert_all_bad_comm_failure,
    assert_all_good,
    charge,
    ea_only_io_map,
    open_rig,
    poll_connecting_now,
    reconnect_now,
    value,
)
from rig_transports import IN_PROCESS, clock_for, on_both_transports

from supervisor.app import build_bench
from supervisor.app.dryrun import dry_run, dry_run_config
from supervisor.chains.engine import State
from supervisor.core.clock import RealClock, VirtualClock
from supervisor.core.errors import DeviceIOError, DeviceTimeout, ProtocolError
from supervisor.devices.ea import (
    EaDriver,
    EaSimulator,
    EaTcpSimulator,
    InProcessScpiTransport,
    TcpScpiTransport,
)
from supervisor.devices.ea.protocol import QUES_OCP_BIT, WATCHDOG_ENABLE_HEADER
from supervisor.devices.ea.sim import LINE_LOG_LENGTH
from supervisor.devices.registry import bench_from_data
from supervisor.fieldbus.scpi import MAX_LINE_BYTES
from supervisor.sim.plant import BenchPlant
from supervisor.testing import wait_until

MakeDriver = Callable[..., EaDriver]


@pytest.fixture
async def rig(transport: str, virtual_clock: VirtualClock) -> AsyncIterator[EaRig]:
    """The unit on ``transport`` (in process unless the test runs on both)."""
    async with open_rig(transport, clock_for(transport, virtual_clock)) as r:
        yield r


@pytest.fixture
def plant(rig: EaRig) -> BenchPlant:
    return rig.plant


@pytest.fixture
def sim(rig: EaRig) -> EaSimulator:
    return rig.sim


@pytest.fixture
def make_driver(rig: EaRig) -> MakeDriver:
    return rig.make_driver


@pytest.fixture
async def driver(rig: EaRig) -> EaDriver:
    return await rig.connected_driver()


async def let_time_pass(clock: VirtualClock, dt_s: float) -> None:
    await clock.sleep_until(clock.now() + dt_s)


async def charging_under_watchdog(make_driver: MakeDriver, watchdog_s: float) -> EaDriver:
    """A driver polling every 0.1 s, the unit's watchdog at ``watchdog_s``, charging 2 A."""
    d = make_driver(watchdog_s=watchdog_s, poll_period_s=0.1)
    await charge(d, 2.0)
    return d


# --- construction ----------------------------------------------------------------------------
def test_a_watchdog_shorter_than_three_poll_periods_is_refused(
    virtual_clock: VirtualClock,
) -> None:
    with pytest.raises(ValueError, match="watchdog_s"):
        EaDriver(
            "psu",
            virtual_clock,
            TcpScpiTransport("127.0.0.1", 5025),
            v_min=V_MIN,
            v_max=V_MAX,
            i_charge_max_a=I_MAX_A,
            i_discharge_max_a=I_MAX_A,
            poll_period_s=0.5,
            watchdog_s=1.0,
        )


def test_inconsistent_limits_are_refused(virtual_clock: VirtualClock) -> None:
    with pytest.raises(ValueError, match="v_min"):
        EaDriver(
            "psu",
            virtual_clock,
            TcpScpiTransport("127.0.0.1", 5025),
            v_min=20.0,
            v_max=V_MAX,
            i_charge_max_a=I_MAX_A,
            i_discharge_max_a=I_MAX_A,
        )


# --- the driver's contract: the same in process and over SCPI/TCP -----------------------------
@on_both_transports
class TestDriverOnBothTransports:
    """Connect, current, device errors, link failures and the safe state: what the unit
    answers reaches the driver the same way whatever carries the lines."""

    # --- the transport: lines out, lines in --------------------------------------------------
    async def test_a_line_sent_gets_its_reply_line(self, rig: EaRig) -> None:
        link = await rig.scpi_transport().connect("psu", 1.0)
        try:
            await link.send_line(b"OUTP?;SYST:LOCK:OWN?\n", 1.0)
            assert await link.receive_line(1.0) == b"OFF;NONE\n"
        finally:
            await link.close()

    async def test_a_silent_device_times_out_naming_the_line(self, rig: EaRig) -> None:
        link = await rig.scpi_transport().connect("psu", 1.0)
        rig.sim.mute = True
        try:
            await link.send_line(b"*IDN?\n", 0.1)
            with pytest.raises(DeviceTimeout, match=r"psu: no reply to '\*IDN\?' within 0.1 s"):
                await link.receive_line(0.1)
        finally:
            await link.close()

    # --- connect -----------------------------------------------------------------------------
    async def test_connect_identifies_takes_remote_and_arms_the_watchdog_on_its_own_line(
        self, driver: EaDriver, sim: EaSimulator
    ) -> None:
        assert sim.lines[0] == "*IDN?"
        assert sim.lines.index("SYST:LOCK ON") < sim.lines.index(f"{WATCHDOG_ENABLE_HEADER} ON")
        assert "SYST:COMM:MON:TIM 2.000" in sim.lines
        assert sim.lines.index("SYST:COMM:MON:TIM 2.000") < sim.lines.index("SYST:COMM:MON:ACT ON")
        assert sim.remote
        assert sim.watchdog_active
        assert driver.identity is not None and driver.identity.model == "PSB 10060-60"
        assert (driver.nominal_v, driver.nominal_a, driver.nominal_w) == (60.0, 60.0, 1500.0)
        assert_all_good(driver)
        assert value(driver, "remote") is True
        assert value(driver, "error") == ""

    async def test_connect_never_sends_the_seed_syst_timeout(
        self, driver: EaDriver, sim: EaSimulator
    ) -> None:
        await driver.poll()
        assert not any("TIMEOUT" in c.upper() for c in sim.commands)

    async def test_connect_switches_output_off_zeroes_set_values_and_sets_protections(
        self, make_driver: MakeDriver, sim: EaSimulator, plant: BenchPlant
    ) -> None:
        plant.set_supply(remote=True, output_on=True, volt_set_v=16.0, curr_set_a=3.0)
        assert plant.pack_current_a > 2.9
        d = make_driver()
        await d.poll()
        assert d.connected, d.last_error
        s = plant.supply
        assert (s.output_on, s.volt_set_v, s.curr_set_a, s.sink_curr_set_a) == (False, 0, 0, 0)
        assert plant.pack_current_a == 0.0
        assert sim.handle_line(b"VOLT:PROT?\n") == f"{V_MAX * 1.05:.2f} V"
        assert sim.handle_line(b"CURR:PROT?;SINK:CURR:PROT?\n") == "5.25 A;5.25 A"
        assert value(d, "output_on") is False

    async def test_a_wrong_model_is_refused_naming_the_received_idn(
        self, make_driver: MakeDriver, sim: EaSimulator
    ) -> None:
        d = make_driver(expected_model="PSB 10080-120")
        await d.poll()
        assert not d.connected
        assert "PSB 10080-120" in d.last_error
        assert "EA Elektro-Automatik GmbH & Co. KG, PSB 10060-60" in d.last_error
        assert "SYST:LOCK ON" not in sim.commands
        assert_all_bad_comm_failure(d)

    async def test_the_expected_model_is_accepted_whatever_its_spelling(
        self, make_driver: MakeDriver
    ) -> None:
        d = make_driver(expected_model="ea-psb 10060-60")
        await d.poll()
        assert d.connected, d.last_error

    async def test_limits_above_the_nominal_ratings_are_refused_before_taking_remote(
        self, make_driver: MakeDriver, sim: EaSimulator
    ) -> None:
        d = make_driver(v_max=80.0, i_charge_max_a=100.0)
        await d.poll()
        assert not d.connected
        assert "v_max 80 V > nominal 60 V" in d.last_error
        assert "i_charge_max_a 100 A > nominal 60 A" in d.last_error
        assert not sim.remote

    async def test_a_non_ea_device_is_refused(
        self, make_driver: MakeDriver, sim: EaSimulator
    ) -> None:
        sim.identity = sim.identity._replace(manufacturer="ACME Power")
        d = make_driver()
        await d.poll()
        assert not d.connected
        assert "ACME Power" in d.last_error

    # --- current -----------------------------------------------------------------------------
    async def test_a_2_a_charge_sources_2_a_into_the_pack(
        self, driver: EaDriver, sim: EaSimulator, plant: BenchPlant
    ) -> None:
        await charge(driver, 2.0)
        assert plant.pack_current_a == pytest.approx(2.0, abs=0.01)
        assert value(driver, "current") == pytest.approx(2.0, abs=0.01)
        assert value(driver, "output_on") is True
        assert value(driver, "power") > 0
        assert "CURR 2.0000; VOLT 16.8000; SINK:CURR 0" in sim.lines
        assert_all_good(driver)

    async def test_a_discharge_sinks_and_reads_negative_current_and_power(
        self, driver: EaDriver, sim: EaSimulator, plant: BenchPlant
    ) -> None:
        await charge(driver, -3.0)
        assert plant.pack_current_a == pytest.approx(-3.0, abs=0.01)
        assert value(driver, "current") == pytest.approx(-3.0, abs=0.01)
        assert value(driver, "power") < 0
        assert "SINK:CURR 3.0000; VOLT 12.0000; CURR 0" in sim.lines

    async def test_zero_current_stops_both_directions(
        self, driver: EaDriver, plant: BenchPlant
    ) -> None:
        await charge(driver, 2.0)
        driver.write("current_set", 0.0)
        await driver.poll()
        assert plant.pack_current_a == 0.0
        assert value(driver, "current") == pytest.approx(0.0, abs=0.01)

    async def test_a_current_beyond_the_limits_is_clamped_with_a_warning(
        self, driver: EaDriver, plant: BenchPlant, caplog: pytest.LogCaptureFixture
    ) -> None:
        with caplog.at_level(logging.WARNING, logger="supervisor.devices.ea.driver"):
            await charge(driver, 50.0)
        assert plant.supply.curr_set_a == pytest.approx(5.0)
        assert any("clamped" in r.getMessage() and "psu" in r.getMessage() for r in caplog.records)

    # --- device errors and status ------------------------------------------------------------
    async def test_settings_refused_in_local_show_error_201(
        self, driver: EaDriver, sim: EaSimulator, plant: BenchPlant
    ) -> None:
        sim.set_local(True)
        await driver.poll()
        assert value(driver, "remote") is False
        driver.write("current_set", 2.0)
        await driver.poll()
        assert "-201" in value(driver, "error")
        assert "-201" in driver.last_error
        assert plant.supply.curr_set_a == 0.0

    async def test_a_protection_trip_shows_in_ques_before_the_error_read_acknowledges_it(
        self, driver: EaDriver, sim: EaSimulator, plant: BenchPlant
    ) -> None:
        await charge(driver, 2.0)
        sim.handle_line(b"CURR:PROT 1\n")  # someone lowers the OCP under the flowing 2 A
        assert not plant.supply.output_on
        await driver.poll()
        assert value(driver, "ques") == 1 << QUES_OCP_BIT
        assert value(driver, "output_on") is False
        await driver.poll()
        assert value(driver, "ques") == 0

    async def test_device_errors_are_read_from_the_queue(
        self, driver: EaDriver, sim: EaSimulator
    ) -> None:
        sim.handle_line(b"VOLT 99\n")
        await driver.poll()
        assert value(driver, "error") == '-222,"Data out of range"'
        assert sim.error_queue == []

    # --- link failures -----------------------------------------------------------------------
    async def test_a_malformed_reply_marks_inputs_bad_and_the_driver_recovers_after_reconnect(
        self, driver: EaDriver, sim: EaSimulator
    ) -> None:
        sim.corrupt_next_reply("MEAS:ARR?")
        await driver.poll()
        assert not driver.connected
        assert_all_bad_comm_failure(driver)
        assert any("garbage" in line for line in driver.raw_log)
        await reconnect_now(driver)
        assert_all_good(driver)

    async def test_stopping_the_unit_marks_inputs_bad_and_starting_it_makes_them_good(
        self, rig: EaRig, driver: EaDriver, sim: EaSimulator
    ) -> None:
        served = sim.addresses()
        await sim.stop()
        await driver.poll()
        assert_all_bad_comm_failure(driver)
        await poll_connecting_now(driver)  # refused while the unit is stopped (unplugged)
        assert not driver.connected
        assert f"cannot connect to {rig.address}" in driver.last_error
        await sim.start()
        assert sim.addresses() == served  # over TCP: the same port again
        await reconnect_now(driver)
        assert_all_good(driver)

    async def test_a_reconnect_never_re_energises_the_output(
        self, driver: EaDriver, sim: EaSimulator, plant: BenchPlant
    ) -> None:
        await charge(driver, 2.0)
        await sim.drop_clients()
        await driver.poll()
        assert not driver.connected
        driver.write("output", True)  # queued while the link is down: stale at reconnect
        await reconnect_now(driver)
        assert not plant.supply.output_on
        assert plant.pack_current_a == 0.0
        assert value(driver, "output_on") is False

    # --- safe state --------------------------------------------------------------------------
    async def test_safe_state_zeroes_the_current_then_switches_the_output_off(
        self, driver: EaDriver, sim: EaSimulator, plant: BenchPlant
    ) -> None:
        await charge(driver, 2.0)
        await driver.safe_state()
        assert not plant.supply.output_on
        assert (plant.supply.curr_set_a, plant.supply.sink_curr_set_a) == (0.0, 0.0)
        assert sim.lines.index("CURR 0; SINK:CURR 0", -3) < sim.lines.index("OUTP OFF", -3)

    async def test_safe_state_without_a_link_logs_and_does_not_raise(
        self, make_driver: MakeDriver, caplog: pytest.LogCaptureFixture
    ) -> None:
        d = make_driver()
        with caplog.at_level(logging.ERROR, logger="supervisor.devices.base"):
            await d.safe_state()
        assert any("safe state" in r.getMessage() for r in caplog.records)

    async def test_safe_state_says_whether_it_was_confirmed(
        self, driver: EaDriver, make_driver: MakeDriver
    ) -> None:
        await charge(driver, 2.0)
        assert await driver.safe_state() is None
        why = await make_driver().safe_state()  # never connected
        assert why is not None and "not connected" in why

    # --- a clean close ---------------------------------------------------------------------
    async def test_a_clean_close_switches_off_zeroes_the_set_values_then_releases_the_lock(
        self, driver: EaDriver, sim: EaSimulator, plant: BenchPlant
    ) -> None:
        await charge(driver, 2.0)
        await driver.close()
        # Over TCP the last line reaches the unit just after close() returns.
        await wait_until(lambda: not sim.remote, "the remote lock released")
        s = plant.supply
        assert (s.output_on, s.volt_set_v, s.curr_set_a, s.sink_curr_set_a) == (False, 0, 0, 0)
        assert sim.lines[-4:] == [
            "CURR 0; SINK:CURR 0; VOLT 0",
            "OUTP OFF",
            "CURR?; SINK:CURR?; OUTP?",
            "SYST:LOCK OFF",
        ]
        assert sim.handle_line(b"SYST:LOCK:OWN?\n") == "NONE"  # the front panel may take it

    async def test_a_close_that_cannot_confirm_the_output_off_keeps_the_lock(
        self, driver: EaDriver, sim: EaSimulator, caplog: pytest.LogCaptureFixture
    ) -> None:
        await charge(driver, 2.0)
        sim.corrupt_next_reply("CURR?", "#!garbage")
        with caplog.at_level(logging.WARNING, logger="supervisor.devices.ea.driver"):
            await driver.close()
        assert "SYST:LOCK OFF" not in sim.lines
        assert sim.remote  # the unit's watchdog switches it off: watchdog_s after the last line
        assert any("remote lock kept" in r.getMessage() for r in caplog.records)


# --- in process: writes refused before any I/O, a silent device on virtual time ---------------
async def test_a_current_set_that_is_not_a_number_is_refused_at_once(driver: EaDriver) -> None:
    with pytest.raises(ValueError):
        driver.write("current_set", float("nan"))
    with pytest.raises(KeyError):
        driver.write("voltage", 1.0)


async def test_a_silent_device_times_out_and_no_late_reply_is_taken_later(
    make_driver: MakeDriver, sim: EaSimulator, plant: BenchPlant
) -> None:
    d = make_driver(timeout_s=0.2)
    await d.poll()
    sim.mute = True
    await d.poll()
    assert not d.connected
    assert "no reply" in d.last_error
    assert_all_bad_comm_failure(d)
    sim.mute = False
    await reconnect_now(d)
    await d.poll()
    assert_all_good(d)
    assert value(d, "voltage") == pytest.approx(plant.supply_voltage_v, abs=0.01)
    assert value(d, "output_on") is False


async def test_a_stop_that_cancels_a_poll_mid_exchange_still_drives_the_unit_safe() -> None:
    """Issue 13's load case, stopped with SIGTERM: the engine cancelled the EA's task while
    it waited for a reply, the cancellation closed the link, and the stop's safe state
    found no link: "safe state NOT confirmed", the output left to the unit's watchdog.
    (A real clock: on the virtual one the reply's timeout would pass at once.)"""
    async with open_rig(IN_PROCESS, RealClock()) as rig:
        driver = rig.make_driver(timeout_s=1.5)
        await _cancelled_mid_exchange_then_safe(driver, rig.sim, rig.plant)


async def _cancelled_mid_exchange_then_safe(
    driver: EaDriver, sim: EaSimulator, plant: BenchPlant
) -> None:
    await charge(driver, 2.0)
    assert plant.supply.output_on
    sim.mute = True  # the reply the poll waits for has not come yet
    poll = asyncio.create_task(driver.poll())
    for _ in range(5):
        await asyncio.sleep(0)
    assert not poll.done()
    poll.cancel()
    with pytest.raises(asyncio.CancelledError):
        await poll
    sim.mute = False
    assert await driver.safe_state() is None
    assert not plant.supply.output_on
    assert (plant.supply.curr_set_a, plant.supply.sink_curr_set_a) == (0.0, 0.0)


async def test_a_driver_that_never_reached_its_unit_does_not_connect_to_it_at_the_stop(
    make_driver: MakeDriver, sim: EaSimulator
) -> None:
    """It cannot have energised anything: the stop says it was not connected, and leaves
    the unit to whoever has it (its front panel)."""
    before = len(sim.lines)
    why = await make_driver().safe_state()
    assert why is not None and "not connected" in why
    assert len(sim.lines) == before


# --- watchdog --------------------------------------------------------------------------------
async def test_the_unit_switches_off_when_the_driver_stops_polling(
    make_driver: MakeDriver, sim: EaSimulator, plant: BenchPlant, virtual_clock: VirtualClock
) -> None:
    await charging_under_watchdog(make_driver, 0.3)
    assert plant.supply.output_on
    # The driver just stops calling poll(): nothing more reaches the unit.
    await let_time_pass(virtual_clock, 0.31)
    sim.check()  # what the unit did meanwhile
    assert not plant.supply.output_on
    assert not sim.remote
    assert sim.watchdog_trips == 1
    assert plant.pack_current_a == 0.0


async def test_polling_keeps_the_watchdog_alive(
    make_driver: MakeDriver, sim: EaSimulator, plant: BenchPlant, virtual_clock: VirtualClock
) -> None:
    d = await charging_under_watchdog(make_driver, 0.6)
    for _ in range(15):  # 1.5 s of polling, well past the 0.6 s timeout
        await d.poll()
        await let_time_pass(virtual_clock, 0.1)
    sim.check()
    assert sim.watchdog_trips == 0
    assert plant.supply.output_on


async def test_a_line_arriving_after_the_watchdog_timeout_finds_the_unit_already_off(
    make_driver: MakeDriver, sim: EaSimulator, plant: BenchPlant, virtual_clock: VirtualClock
) -> None:
    await charging_under_watchdog(make_driver, 0.3)
    await let_time_pass(virtual_clock, 0.5)  # nobody calls check(): the next line sees it first
    assert sim.handle_line(b"OUTP?;SYST:LOCK:OWN?\n") == "OFF;NONE"
    assert sim.watchdog_trips == 1


async def test_the_watchdog_does_not_trip_exactly_at_its_timeout(
    make_driver: MakeDriver, sim: EaSimulator, plant: BenchPlant, virtual_clock: VirtualClock
) -> None:
    await charging_under_watchdog(make_driver, 0.4)
    await let_time_pass(virtual_clock, 0.4)
    sim.check()
    assert (sim.watchdog_trips, plant.supply.output_on) == (0, True)
    await let_time_pass(virtual_clock, 0.001)
    sim.check()
    assert (sim.watchdog_trips, plant.supply.output_on) == (1, False)


# --- the in-process transport --------------------------------------------------------------
async def test_in_process_a_muted_unit_times_out_after_exactly_the_timeout_of_virtual_time(
    sim: EaSimulator, virtual_clock: VirtualClock
) -> None:
    link = await InProcessScpiTransport(sim, virtual_clock).connect("psu", 1.0)
    sim.mute = True
    t0 = virtual_clock.now()
    await link.send_line(b"*IDN?\n", 0.25)
    assert virtual_clock.now() == t0  # sending never waits
    with pytest.raises(DeviceTimeout, match=r"psu: no reply to '\*IDN\?' within 0.25 s"):
        await link.receive_line(0.25)
    assert virtual_clock.now() == t0 + 0.25
    assert sim.commands == ["*IDN?"]  # executed, only the reply was withheld
    await link.close()


async def test_in_process_a_reply_is_read_without_time_passing(
    sim: EaSimulator, virtual_clock: VirtualClock
) -> None:
    link = await InProcessScpiTransport(sim, virtual_clock).connect("psu", 1.0)
    await link.send_line(b"OUTP?;SYST:LOCK:OWN?\n", 1.0)
    assert await link.receive_line(1.0) == b"OFF;NONE\n"
    assert virtual_clock.now() == 0.0
    await link.close()


async def test_in_process_an_unplugged_simulator_refuses_to_connect(
    sim: EaSimulator, virtual_clock: VirtualClock
) -> None:
    transport = InProcessScpiTransport(sim, virtual_clock)
    await sim.stop()
    assert not sim.reachable
    with pytest.raises(DeviceIOError, match="psu: cannot connect to in-process simulator ea"):
        await transport.connect("psu", 1.0)
    await sim.start()
    link = await transport.connect("psu", 1.0)
    await link.close()


async def test_in_process_unplugging_closes_open_connections(
    sim: EaSimulator, virtual_clock: VirtualClock
) -> None:
    link = await InProcessScpiTransport(sim, virtual_clock).connect("psu", 1.0)
    await sim.stop()
    with pytest.raises(DeviceIOError, match="connection closed by the simulator"):
        await link.send_line(b"OUTP?\n", 1.0)
    assert sim.commands == []


async def test_in_process_dropped_clients_fail_their_next_exchange_like_a_closed_socket(
    sim: EaSimulator, virtual_clock: VirtualClock
) -> None:
    transport = InProcessScpiTransport(sim, virtual_clock)
    link = await transport.connect("psu", 1.0)
    await link.send_line(b"OUTP?\n", 1.0)
    await sim.drop_clients()
    # A reply already received can still be read, as from a socket's buffer...
    assert await link.receive_line(1.0) == b"OFF\n"
    # ...then the connection is gone: no waiting for a reply that cannot come.
    with pytest.raises(DeviceIOError, match="connection closed by the device while waiting"):
        await link.receive_line(1.0)
    assert virtual_clock.now() == 0.0
    with pytest.raises(DeviceIOError, match="connection closed by the simulator"):
        await link.send_line(b"OUTP?\n", 1.0)
    assert sim.reachable  # only the connections were dropped: reconnecting works
    again = await transport.connect("psu", 1.0)
    await again.send_line(b"OUTP?\n", 1.0)
    assert await again.receive_line(1.0) == b"OFF\n"
    await again.close()


async def test_in_process_a_reply_line_too_long_is_a_protocol_error_with_the_bytes(
    sim: EaSimulator, virtual_clock: VirtualClock
) -> None:
    link = await InProcessScpiTransport(sim, virtual_clock).connect("psu", 1.0)
    sim.corrupt_next_reply("*IDN?", "X" * MAX_LINE_BYTES)
    await link.send_line(b"*IDN?\n", 1.0)
    with pytest.raises(ProtocolError, match="at most 4096 bytes") as info:
        await link.receive_line(1.0)
    assert info.value.raw.startswith(b"XXXX")
    await link.close()


# --- simulator behaviour ---------------------------------------------------------------------
def test_sim_refuses_settings_in_local_out_of_range_and_unknown_commands(
    sim: EaSimulator, plant: BenchPlant
) -> None:
    assert sim.handle_line(b"VOLT 12\n") is None
    assert sim.handle_line(b"OUTP ON\n") is None
    assert sim.handle_line(b"SYST:ERR?\n") == '-201,"Invalid while in local"'
    assert sim.handle_line(b"SYST:ERR?;SYST:ERR?\n") == '-201,"Invalid while in local";0,"No error"'
    sim.handle_line(b"SYST:LOCK ON\n")
    sim.handle_line(b"VOLT 61 V; FOO:BAR 1; VOLT 12.00 V; SINK:CURR 2.5 A\n")
    assert sim.handle_line(b"SYST:ERR?;SYST:ERR?\n") == (
        '-222,"Data out of range";-100,"Command error"'
    )
    assert sim.handle_line(b"VOLT?;SINK:CURR?\n") == "12.00 V;2.50 A"
    assert plant.supply.volt_set_v == 12.0
    assert not plant.supply.output_on


def test_sim_protection_trip_latches_ques_until_the_error_queue_is_read(
    sim: EaSimulator, plant: BenchPlant
) -> None:
    sim.handle_line(b"SYST:LOCK ON;VOLT 16.8;CURR 2;OUTP ON\n")
    assert plant.supply.output_on
    sim.handle_line(b"VOLT:PROT 15\n")  # the pack sits above 15 V while charging
    assert not plant.supply.output_on
    assert sim.handle_line(b"STAT:QUES:COND?\n") == "1"
    assert sim.handle_line(b"SYST:ERR?\n") == '0,"No error"'
    assert sim.handle_line(b"STAT:QUES:COND?\n") == "0"


def test_sim_protection_tripped_between_lines_is_enforced_by_check(
    sim: EaSimulator, plant: BenchPlant
) -> None:
    sim.handle_line(b"SYST:LOCK ON;VOLT 16.8;CURR 2;OUTP ON;CURR:PROT 5\n")
    assert plant.supply.output_on
    plant.set_supply(curr_set_a=6.0)  # over the OCP without a command line
    sim.check()
    assert not plant.supply.output_on
    assert sim.ques == 1 << QUES_OCP_BIT
    assert sim.protection_trips == 1


def test_sim_in_process_serves_nothing_and_keeps_its_name(plant: BenchPlant) -> None:
    sim = EaSimulator(plant, name="psu1")
    assert sim.name == "psu1"
    assert sim.addresses() == []


# --- registration ------------------------------------------------------------------------------
def _ea_bench() -> Any:
    return bench_from_data(ea_only_io_map("ea_only", {"sim": True}))


def test_an_in_process_bench_drives_the_ea_simulator_without_a_socket() -> None:
    bench = build_bench(_ea_bench(), VirtualClock(), in_process=True)
    assert bench.sim is not None
    sim = bench.sim.devices["ea"]
    assert type(sim) is EaSimulator
    driver = bench.drivers["ea"]
    assert isinstance(driver, EaDriver)
    assert isinstance(driver.transport, InProcessScpiTransport)
    assert driver.transport.unit is sim


def test_a_served_bench_drives_the_ea_over_tcp_to_host_and_port() -> None:
    bench = build_bench(_ea_bench(), RealClock())
    assert bench.sim is not None
    assert isinstance(bench.sim.devices["ea"], EaTcpSimulator)
    driver = bench.drivers["ea"]
    assert isinstance(driver, EaDriver)
    assert isinstance(driver.transport, TcpScpiTransport)
    assert driver.transport.address == "127.0.0.1:5025"


# --- the dry run -------------------------------------------------------------------------------
def test_the_li_ion_dry_run_bench_is_an_ea_supply_on_a_unit_rated_for_the_channel() -> None:
    cfg = dry_run_config("liion-pack", 10.0, 0.5, 1.0)
    dev = cfg.devices["supply"]
    assert dev.driver == "ea-psb"
    assert dev.simulated
    bench = build_bench(cfg, VirtualClock(), in_process=True)
    driver = bench.drivers["supply"]
    assert isinstance(driver, EaDriver)
    assert isinstance(driver.transport, InProcessScpiTransport)
    assert (driver.i_charge_max_a, driver.i_discharge_max_a) == (100.0, 100.0)


async def test_a_cccv_dry_run_goes_through_the_ea_driver_and_simulator(tmp_path: Path) -> None:
    recipe = tmp_path / "cccv.yaml"
    recipe.write_text(
        "recipe: short-cccv\nchemistry: liion\ncapacity: 2 Ah\nsteps:\n"
        "  - id: charge\n    cccv: {current: 1 A, voltage: 3.9 V}\n    duration: 30 min\n"
        "  - {id: discharge, discharge: 1 A, duration: 20 min}\n",
        encoding="utf-8",
    )
    res = await dry_run(recipe, soc=0.5)
    assert res.state is State.COMPLETE, res.end_reason
    (cycle,) = res.summary["cycles"]
    # 1 A for 20 min out; in: 1 A until the CV phase at 3.9 V tapers it, within 30 min.
    assert cycle["discharge_capacity_ah"] == pytest.approx(1 / 3, rel=0.01)
    assert 0.05 < cycle["charge_capacity_ah"] < 0.45


# --- the simulator's own memory ----------------------------------------------------------------
def test_the_simulator_keeps_a_bounded_log_of_the_lines_it_received(sim: EaSimulator) -> None:
    # A simulated bench runs for days: one line per poll must not grow memory without end
    # (issue 13: about 7 MiB per hour before).
    for i in range(3 * LINE_LOG_LENGTH):
        sim.handle_line(f"VOLT {i % 50}.0000".encode())
    assert len(sim.lines) <= LINE_LOG_LENGTH
    assert len(sim.commands) <= LINE_LOG_LENGTH
    assert sim.lines[-1] == f"VOLT {(3 * LINE_LOG_LENGTH - 1) % 50}.0000"  # the newest kept
