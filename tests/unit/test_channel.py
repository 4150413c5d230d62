"""Channel logic: integration, clamping, Manual mode (trips: test_channel_guard.py)."""

from __future__ import annotations

import pytest

from supervisor.channels import Channel, ChannelLimits
from supervisor.core.quality import Quality, Reason
from supervisor.tags import TagDB, TagSpec


def make(v: float = 1.3, i: float = 0.0) -> tuple[TagDB, Channel]:
    db = TagDB()
    ch = Channel("ch0", db, ChannelLimits((-0.4, 0.4), (0.8, 1.9)), capacity_ah=2.0)
    db.update(ch.voltage, v)
    db.update(ch.current, i)
    return db, ch


def scan(ch: Channel, n: int, dt: float = 0.1) -> None:
    for _ in range(n):
        ch.run(0.0, dt)


def test_manual_setpoint_reaches_the_command_only_when_enabled() -> None:
    db, ch = make()
    db.write("ch0.manual_current", 0.3)
    scan(ch, 1)
    assert ch.current_cmd.value == 0.0
    db.write("ch0.enable", True)
    scan(ch, 1)
    assert ch.current_cmd.value == 0.3
    assert ch.state.value == "charging"


def test_an_out_of_range_setpoint_is_clamped_to_the_hard_limit_and_reported() -> None:
    db, ch = make()
    db.write("ch0.enable", True)
    # Past the command path (which refuses it, and TagDB.write too: the tag's range is the
    # hard limits), the channel's clamp still holds: written as a process value.
    db.update(ch.manual_current, 5.0)
    scan(ch, 1)
    assert ch.current_cmd.value == 0.4
    assert ch.clamped.value is True
    db.update(ch.manual_current, -5.0)
    scan(ch, 1)
    assert ch.current_cmd.value == -0.4
    db.write("ch0.manual_current", 0.1)
    scan(ch, 1)
    assert ch.clamped.value is False


def test_charge_counter_integrates_the_current_that_flowed_during_each_scan() -> None:
    _db, ch = make(i=0.3)
    scan(ch, 36_001, dt=0.1)  # the first scan has no previous current
    assert ch.charge_ah.value == pytest.approx(0.3, rel=1e-9)
    assert ch.charged_ah.value == pytest.approx(0.3, rel=1e-9)
    assert ch.discharged_ah.value == 0.0
    assert ch.energy_wh.value == pytest.approx(0.3 * 1.3, rel=1e-9)


def test_discharge_counts_negative_net_charge_and_positive_discharged_ah() -> None:
    _db, ch = make(i=-0.2)
    scan(ch, 18_001, dt=0.1)
    assert ch.charge_ah.value == pytest.approx(-0.1)
    assert ch.discharged_ah.value == pytest.approx(0.1)
    assert ch.discharged_wh.value == pytest.approx(0.13)


def test_a_bad_current_is_not_integrated_and_power_becomes_bad() -> None:
    db, ch = make(i=0.3)
    db.update(ch.current, 0.3, Quality.BAD, Reason.COMM_FAILURE)
    scan(ch, 10)
    assert ch.charge_ah.value == 0.0
    assert ch.power.quality is Quality.BAD


def test_auto_mode_follows_the_step_chain_request_not_the_manual_setpoint() -> None:
    db, ch = make()
    db.write("ch0.manual_current", 0.3)
    db.write("ch0.enable", True)
    db.write("ch0.mode", "auto")
    db.update(ch.auto_current, -0.1)
    scan(ch, 1)
    assert ch.current_cmd.value == 0.0  # no chain running
    db.update(ch.auto_active, True)
    scan(ch, 1)
    assert ch.current_cmd.value == -0.1


def test_a_value_of_the_wrong_type_from_the_process_is_stored_as_bad() -> None:
    db, ch = make()
    db.update(ch.voltage, "garbage")
    assert ch.voltage.value is None and ch.voltage.quality is Quality.BAD


def test_a_channel_without_a_temperature_sensor_says_not_fitted_not_waiting() -> None:
    # A Chadèche board measures no temperature: BAD for every reader (a guard with limits
    # would trip), but "not fitted" — the screens show n/a in grey, OPC UA Bad_OutOfService.
    _db, ch = make()
    scan(ch, 3)
    assert (ch.temperature.quality, ch.temperature.reason) == (Quality.BAD, Reason.NOT_FITTED)


def test_a_channel_with_a_temperature_tag_takes_its_value() -> None:
    db = TagDB()
    src = db.add(TagSpec("pack.temp", unit="degC"))
    limits = ChannelLimits((-1.0, 1.0), (0.8, 1.9))
    ch = Channel("ch0", db, limits, capacity_ah=2.0, temperature_tag="pack.temp")
    db.update(src, 24.5)
    scan(ch, 1)
    assert (ch.temperature.value, ch.temperature.quality) == (24.5, Quality.GOOD)
