"""The alarm model (ISA-18.2) and the bench-wide checks that raise alarms: interlocks, tag
alarm limits (HH/H/L/LL with deadband and on-delay), the e-stop, the heartbeat."""

from __future__ import annotations

import itertools

import pytest

from supervisor.config.models import EstopConfig, HeartbeatConfig, InterlockConfig
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.core.quality import Quality, Reason
from supervisor.safety import AlarmManager, AlarmState, Severity
from supervisor.safety.interlocks import Estop, Heartbeat, Interlock, TagAlarms
from supervisor.tags import AlarmLimits, TagDB, TagSpec


@pytest.fixture
def clock() -> VirtualClock:
    return VirtualClock()


@pytest.fixture
def alarms(clock: VirtualClock) -> AlarmManager:
    return AlarmManager(clock)


# --- states ---------------------------------------------------------------------------------
def test_a_plain_alarm_goes_through_the_isa_18_2_states(alarms: AlarmManager) -> None:
    a = alarms.declare("pack.temp.H", severity=Severity.MEDIUM)
    assert a.state is AlarmState.NORMAL
    alarms.set(a, True, "pack.temp 46 degC >= H 45 degC")
    assert a.state is AlarmState.ACTIVE_UNACKED
    alarms.set(a, False)
    assert a.state is AlarmState.RETURNED_UNACKED  # nobody saw it yet
    alarms.acknowledge("pack.temp.H", "alice")
    assert a.state is AlarmState.NORMAL
    alarms.set(a, True, "again")
    alarms.acknowledge("pack.temp.H", "bob")
    assert a.state is AlarmState.ACTIVE_ACKED
    assert a.acked_by == "bob"


def test_a_trip_stays_latched_until_acknowledged_and_reset_and_reset_waits_for_the_cause(
    alarms: AlarmManager, clock: VirtualClock
) -> None:
    a = alarms.declare("ch0.voltage_high", group="ch0", latched=True)
    alarms.set(a, True, "voltage 1.95 V at or above hard limit 1.9 V")
    with pytest.raises(OperatorError, match="cause is still present"):
        alarms.reset("ch0.voltage_high", "alice")
    alarms.set(a, False)
    assert a.state is AlarmState.RETURNED_UNACKED and a.tripped
    alarms.acknowledge("ch0.voltage_high", "alice")
    assert a.state is AlarmState.LATCHED  # acknowledged, still holding its channel
    assert [t.id for t in alarms.trips("ch0")] == ["ch0.voltage_high"]
    alarms.reset("ch0.voltage_high", "alice")
    assert a.state is AlarmState.NORMAL and alarms.trips("ch0") == []


def test_acknowledging_twice_or_resetting_a_plain_alarm_is_refused_with_the_reason(
    alarms: AlarmManager,
) -> None:
    a = alarms.declare("x.H")
    alarms.set(a, True, "high")
    alarms.acknowledge("x.H", "alice")
    with pytest.raises(OperatorError, match="not waiting for an acknowledgement"):
        alarms.acknowledge("x.H", "alice")
    with pytest.raises(OperatorError, match="not a trip"):
        alarms.reset("x.H", "alice")
    with pytest.raises(OperatorError, match="unknown alarm 'nope'"):
        alarms.acknowledge("nope", "alice")


def test_shelving_hides_a_nuisance_alarm_until_it_expires_but_never_a_trip(
    alarms: AlarmManager, clock: VirtualClock
) -> None:
    a = alarms.declare("room.temp.H", severity=Severity.LOW)
    alarms.set(a, True, "warm")
    alarms.shelve("room.temp.H", 600, "alice")
    assert alarms.in_alarm() == []
    clock.advance(601)
    alarms.set(a, True, "warm")  # the next evaluation notices the expiry
    assert [x.id for x in alarms.in_alarm()] == ["room.temp.H"]
    trip = alarms.declare("ch0.source", group="ch0", latched=True)
    with pytest.raises(OperatorError, match="cannot be shelved"):
        alarms.shelve("ch0.source", 600, "alice")
    assert trip.shelved_until is None
    kinds = [e.transition.value for e in alarms.history if e.alarm_id == "room.temp.H"]
    assert kinds == ["activated", "shelved", "unshelved"]


def test_the_first_trip_of_a_channel_is_first_out(alarms: AlarmManager) -> None:
    first = alarms.declare("ch0.contactor_feedback", group="ch0", latched=True)
    second = alarms.declare("ch0.current_feedback", group="ch0", latched=True)
    other = alarms.declare("ch1.source", group="ch1", latched=True)
    alarms.set(first, True, "contactor open")
    alarms.set(second, True, "0 A")
    alarms.set(other, True, "lost")
    assert first.first_out and not second.first_out and other.first_out
    assert [a.id for a in alarms.trips("ch0")] == ["ch0.contactor_feedback", "ch0.current_feedback"]


# --- interlocks ------------------------------------------------------------------------------
def interlock(db: TagDB, alarms: AlarmManager, **cfg: object) -> Interlock:
    return Interlock(
        InterlockConfig.model_validate({"id": "hot", "tag": "pack.t", **cfg}), db, alarms
    )


def db_with(name: str, value: float | bool, dtype: str = "float") -> TagDB:
    db = TagDB()
    db.add(TagSpec(name, dtype=dtype, unit="degC" if dtype == "float" else ""))  # type: ignore[arg-type]
    db.update(db[name], value)
    return db


def test_an_interlock_trips_after_its_on_delay_and_clears_past_its_deadband(
    alarms: AlarmManager, clock: VirtualClock
) -> None:
    db = db_with("pack.t", 49.0)
    il = interlock(
        db, alarms, above=50, delay_s=2, deadband=3, channels=["ch4"], message="pack hot"
    )
    db.update(db["pack.t"], 51.0)
    for _ in range(20):  # over the limit from 0 to 1.9 s
        il.evaluate(clock.now(), 0.1)
        clock.advance(0.1)
    assert not il.alarm.active
    il.evaluate(clock.now(), 0.1)
    clock.advance(0.1)
    assert il.alarm.active and il.alarm.message == "pack hot: pack.t 51 °C (limit > 50)"
    assert il.alarm.affects == ("ch4",)
    assert [a.id for a in alarms.trips("ch4")] == ["interlock.hot"]
    assert alarms.trips("ch0") == []  # not one of its channels
    db.update(db["pack.t"], 48.0)  # below 50 but within the 3 degC deadband
    il.evaluate(clock.now(), 0.1)
    assert il.alarm.active
    db.update(db["pack.t"], 46.5)
    il.evaluate(clock.now(), 0.1)
    assert not il.alarm.active


def test_an_interlock_on_a_value_that_is_not_good_trips_fail_safe(alarms: AlarmManager) -> None:
    db = db_with("pack.t", 20.0)
    il = interlock(db, alarms, above=50)
    db.update(db["pack.t"], 20.0, Quality.BAD, Reason.COMM_FAILURE)
    il.evaluate(0.0, 0.1)
    assert il.alarm.active and "pack.t unknown (bad: comm failure)" in il.alarm.message


def test_a_boolean_interlock_trips_on_its_value_and_can_abort(alarms: AlarmManager) -> None:
    db = db_with("door.open", False, dtype="bool")
    il = Interlock(
        InterlockConfig(id="door", tag="door.open", equals=True, action="abort"), db, alarms
    )
    il.evaluate(0.0, 0.1)
    assert not il.alarm.active
    db.update(db["door.open"], True)
    il.evaluate(0.1, 0.1)
    assert il.alarm.active and il.alarm.action == "abort"


def test_an_interlock_needs_exactly_one_condition() -> None:
    with pytest.raises(ValueError, match="exactly one of above, below or equals"):
        InterlockConfig(id="x", tag="t", above=1, below=0)


# --- tag alarm limits -----------------------------------------------------------------------
def test_hh_h_l_ll_limits_raise_plain_alarms_with_deadband_and_on_delay(
    alarms: AlarmManager, clock: VirtualClock
) -> None:
    db = TagDB()
    db.add(
        TagSpec("pack.t", unit="degC", alarms=AlarmLimits(hh=55, h=45, l=5, deadband=2, delay_s=1))
    )
    t = db["pack.t"]
    db.update(t, 25.0)
    ta = TagAlarms(db, alarms)

    def run(value: float, seconds: float) -> None:
        db.update(t, value)
        for _ in range(round(seconds / 0.1)):
            ta.evaluate(clock.now(), 0.1)
            clock.advance(0.1)

    run(47.0, 0.5)
    assert not alarms["pack.t.H"].active  # on-delay not over
    run(47.0, 0.6)
    assert alarms["pack.t.H"].active and not alarms["pack.t.HH"].active
    assert alarms["pack.t.H"].severity is Severity.MEDIUM and not alarms["pack.t.H"].latched
    run(44.0, 0.1)  # within the 2 degC deadband
    assert alarms["pack.t.H"].active
    run(42.5, 0.1)
    assert not alarms["pack.t.H"].active
    run(3.0, 1.2)
    assert alarms["pack.t.L"].active
    assert "pack.t.LL" not in alarms  # not configured


# --- e-stop and heartbeat --------------------------------------------------------------------
def test_the_estop_opens_the_software_estop_relay_until_it_is_reset(alarms: AlarmManager) -> None:
    db = db_with("estop.ok", True, dtype="bool")
    db.add(TagSpec("estop.relay", dtype="bool", initial=True))
    e = Estop(EstopConfig(tag="estop.ok", relay_tag="estop.relay"), db, alarms)
    e.evaluate(0.0, 0.1)
    assert db["estop.relay"].value is True
    db.update(db["estop.ok"], False)
    e.evaluate(0.1, 0.1)
    assert db["estop.relay"].value is False
    assert alarms["estop"].severity is Severity.CRITICAL and alarms["estop"].action == "abort"
    db.update(db["estop.ok"], True)
    e.evaluate(0.2, 0.1)
    assert db["estop.relay"].value is False  # latched: released e-stop is not enough
    alarms.reset("estop", "alice")
    e.evaluate(0.3, 0.1)
    assert db["estop.relay"].value is True


def test_the_heartbeat_toggles_its_output_every_period() -> None:
    db = TagDB()
    db.add(TagSpec("wd.heartbeat", dtype="bool", initial=False))
    db.update(db["wd.heartbeat"], False)
    hb = Heartbeat(HeartbeatConfig(tag="wd.heartbeat", period_s=0.5), db)
    seen = []
    for k in range(21):  # 2 s at a 0.1 s scan
        hb.evaluate(k * 0.1, 0.1)
        seen.append(db["wd.heartbeat"].value)
    toggles = sum(1 for a, b in itertools.pairwise(seen) if a != b)
    assert toggles == 4
