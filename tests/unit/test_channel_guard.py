"""A channel's protection (safety phase): trips latched until acknowledged and reset, nothing
ever driven towards a crossed limit, outputs checked against their read-backs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pytest

from supervisor.channels import Channel, ChannelLimits
from supervisor.config.models import ChannelConfig
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.core.quality import Quality, Reason
from supervisor.safety import AlarmManager, AlarmState, ChannelGuard
from supervisor.tags import TagDB, TagSpec

DT = 0.1


@dataclass
class Rig:
    """One channel with its guard, scanned in design order: derive, safety, drive."""

    clock: VirtualClock
    db: TagDB
    ch: Channel
    guard: ChannelGuard
    alarms: AlarmManager

    def scan(self, n: int = 1) -> None:
        for _ in range(n):
            now = self.clock.now()
            self.ch.derive(now, DT)
            self.guard.evaluate(now, DT)
            self.ch.drive(now, DT)
            self.clock.advance(DT)

    def set(self, name: str, value: Any, quality: Quality = Quality.GOOD) -> None:
        reason = Reason.NONE if quality is Quality.GOOD else Reason.COMM_FAILURE
        self.db.update(self.db[name], value, quality, reason)

    def value(self, name: str) -> Any:
        return self.db[name].value


def make(
    v: float = 1.3,
    i: float = 0.0,
    extra_tags: tuple[TagSpec, ...] = (),
    output: bool = False,
    **cfg: Any,
) -> Rig:
    clock = VirtualClock()
    db = TagDB()
    for spec in extra_tags:
        db.add(spec)
        db.update(db[spec.name], spec.initial)
    config = ChannelConfig.model_validate(
        {
            "name": "ch0",
            "source": {"device": "dev"},
            "capacity_ah": 2.0,
            "limits": {"current_a": [-0.4, 0.4], "voltage_v": [0.8, 1.9]},
            **cfg,
        }
    )
    lim = config.limits
    ch = Channel(
        "ch0",
        db,
        ChannelLimits(lim.current_a, lim.voltage_v, lim.temperature_c),
        capacity_ah=2.0,
        temperature_tag=config.temperature_tag,
        contactor_tag=config.contactor_tag,
        has_output_switch=output,
        has_output_feedback=output,
    )
    db.update(ch.voltage, v)
    db.update(ch.current, i)
    alarms = AlarmManager(clock)
    return Rig(clock, db, ch, ChannelGuard(config, db, alarms), alarms)


def bool_tag(name: str, initial: bool = True) -> TagSpec:
    return TagSpec(name, dtype="bool", initial=initial)


def float_tag(name: str, initial: float, unit: str = "V") -> TagSpec:
    return TagSpec(name, unit=unit, initial=initial)


# --- hard limits (moved from test_channel.py, assertions kept) -----------------------------
def test_charging_at_the_voltage_hard_limit_trips_latched_and_needs_ack_and_enable() -> None:
    r = make(v=1.95)
    db, ch = r.db, r.ch
    db.write("ch0.enable", True)
    db.write("ch0.manual_current", 0.3)
    r.scan(1)
    assert ch.current_cmd.value == 0.0
    assert "1.950 V at or above hard limit 1.9 V" in str(ch.fault.value)
    assert ch.enable.value is False
    db.update(ch.voltage, 1.4)
    r.scan(3)
    assert ch.fault.value  # latched: the condition clearing is not enough
    db.write("ch0.ack", True)
    r.scan(1)
    assert ch.fault.value == ""
    assert ch.current_cmd.value == 0.0  # not re-energised on its own
    db.write("ch0.enable", True)
    r.scan(1)
    assert ch.current_cmd.value == 0.3


def test_discharging_below_the_low_voltage_limit_trips() -> None:
    r = make(v=0.79)
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", -0.2)
    r.scan(1)
    assert r.ch.current_cmd.value == 0.0 and r.ch.state.value == "faulted"


def test_losing_the_voltage_input_while_driving_trips_the_channel() -> None:
    r = make()
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.3)
    r.scan(1)
    r.set("ch0.voltage", 1.3, Quality.BAD)
    r.scan(1)
    assert r.ch.current_cmd.value == 0.0
    assert "comm failure" in str(r.ch.fault.value)


def test_an_exception_in_channel_logic_makes_the_channel_safe_not_the_scan_crash(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    r = make()
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.3)
    r.scan(1)

    def broken(request: float) -> float:
        raise RuntimeError("corrupted request")

    monkeypatch.setattr(r.ch, "_clamp", broken)
    r.scan(1)
    assert r.ch.current_cmd.value == 0.0  # safe at once, in the failing scan
    r.scan(1)
    assert "internal error" in str(r.ch.fault.value)  # and latched by the next safety phase


# --- admission: nothing flows towards a crossed limit ---------------------------------------
def test_no_current_ever_flows_towards_a_crossed_limit_even_in_the_scan_it_is_asked() -> None:
    r = make(v=1.95)
    r.scan(1)
    assert r.value("ch0.limit.charge_a") == 0.0
    assert r.value("ch0.limit.discharge_a") == 0.4  # away from the limit stays allowed
    r.db.write("ch0.mode", "auto")
    r.db.update(r.ch.auto_active, True)
    r.db.update(r.ch.auto_current, 0.3)  # a chain asks for a charge, after the safety phase
    r.ch.drive(r.clock.now(), DT)
    assert r.ch.current_cmd.value == 0.0
    r.scan(1)  # the next safety phase latches the attempt
    assert "at or above hard limit" in str(r.ch.fault.value)


def test_a_trip_delay_ignores_a_crossing_shorter_than_the_delay() -> None:
    r = make(
        v=1.95, limits={"current_a": [-0.4, 0.4], "voltage_v": [0.8, 1.9], "trip_delay_s": 1.0}
    )
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.3)
    r.scan(5)  # 0.5 s over the limit (charge blocked meanwhile)
    assert r.ch.fault.value == ""
    assert r.ch.current_cmd.value == 0.0
    r.scan(6)
    assert "at or above hard limit" in str(r.ch.fault.value)


# --- reset is refused while the cause is present -------------------------------------------
def test_a_reset_is_refused_while_the_permissive_is_still_false() -> None:
    r = make(extra_tags=(bool_tag("door.closed"),), permissives=["door.closed"])
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.2)
    r.scan(1)
    r.set("door.closed", False)
    r.scan(1)
    assert "Permissive lost: door.closed" in str(r.ch.fault.value)
    with pytest.raises(OperatorError, match="cause is still present"):
        r.guard.reset("operator")
    r.db.write("ch0.ack", True)  # the tag way: acknowledged, not reset
    r.scan(1)
    assert r.ch.fault.value
    alarm = r.alarms["ch0.permissive.door.closed"]
    assert alarm.acked and alarm.state is AlarmState.ACTIVE_ACKED
    r.set("door.closed", True)
    r.scan(1)
    assert r.guard.reset("operator") == ["ch0.permissive.door.closed"]
    r.scan(1)
    assert r.ch.fault.value == "" and r.ch.state.value == "idle"


# --- outputs against their read-backs (S7 discrepancy) ---------------------------------------
def test_a_contactor_that_does_not_follow_its_coil_trips_after_the_discrepancy_time() -> None:
    r = make(
        extra_tags=(bool_tag("k.cmd", False), bool_tag("k.closed", False)),
        contactor_tag="k.cmd",
        contactor_feedback_tag="k.closed",
        feedback={"delay_s": 0.5},
    )
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.2)
    r.scan(1)
    assert r.value("k.cmd") is True  # coil energised; the auxiliary contact never closes
    assert r.value("ch0.armed") is False
    r.scan(4)
    assert r.ch.fault.value == ""
    r.scan(2)
    assert "Contactor open while commanded closed" in str(r.ch.fault.value)
    assert r.value("k.cmd") is False and r.ch.current_cmd.value == 0.0


def test_a_supply_output_that_reads_off_while_commanded_on_trips() -> None:
    r = make(output=True, feedback={"delay_s": 0.3})
    r.db.update(r.db["ch0.output_fb"], False)
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.2)
    r.scan(5)
    assert "supply output off while commanded on" in str(r.ch.fault.value)


def test_a_current_that_does_not_follow_its_setpoint_trips_once_settled() -> None:
    # Finding: a second instance switched the supply off; 0 A against 5 A, no fault.
    r = make(feedback={"delay_s": 1.0, "current_tolerance_a": 0.05})
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.3)
    r.scan(1)
    r.scan(5)  # 0 A measured: not yet settled
    assert r.ch.fault.value == ""
    r.scan(7)
    assert "current 0.000 A against 0.300 A commanded" in str(r.ch.fault.value)


def test_less_current_than_set_is_normal_while_the_source_holds_its_voltage() -> None:
    r = make(v=1.895, feedback={"delay_s": 0.5, "current_tolerance_a": 0.05})  # at 1.9 V CV
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.3)
    r.db.update(r.ch.current, 0.1)  # tapering, as a CV stage does
    r.scan(20)
    assert r.ch.fault.value == ""


# --- a second measurement of the same voltage --------------------------------------------------
def test_a_broken_sense_wire_is_noticed_when_two_voltages_disagree() -> None:
    r = make(
        extra_tags=(float_tag("bms.voltage", 1.3),),
        voltage_checks=[{"tag": "bms.voltage", "tolerance_v": 0.05, "delay_s": 1.0}],
    )
    r.scan(3)
    assert r.ch.fault.value == ""
    r.set("ch0.voltage", 0.0)  # the sense wire broke
    r.scan(12)
    assert "disagree by 1.300 V" in str(r.ch.fault.value)


# --- BMS limits clamp before they trip ------------------------------------------------------------
def test_a_bms_cell_near_its_limit_derates_the_charge_current_then_trips_beyond_it() -> None:
    r = make(
        extra_tags=(float_tag("bms.cell_max", 4.10),),
        bms={"cell_max_tag": "bms.cell_max", "cell_voltage_v": [3.0, 4.2], "derate_band_v": 0.05},
    )
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.4)
    r.scan(1)
    assert r.ch.current_cmd.value == pytest.approx(0.4)
    r.set("bms.cell_max", 4.175)  # half the band left
    r.scan(1)
    assert r.ch.current_cmd.value == pytest.approx(0.2)
    assert r.ch.clamped.value is True
    r.set("bms.cell_max", 4.21)
    r.scan(11)
    assert "BMS cell voltage 4.210 V above 4.2 V" in str(r.ch.fault.value)


# --- first-out and the alarm log ------------------------------------------------------------------
def test_the_first_trip_is_first_out_and_every_transition_is_logged_with_its_actor() -> None:
    r = make(v=1.95, extra_tags=(bool_tag("door.closed"),), permissives=["door.closed"])
    r.db.write("ch0.enable", True)
    r.db.write("ch0.manual_current", 0.3)
    r.scan(1)
    r.set("door.closed", False)
    r.db.write("ch0.enable", True)
    r.scan(1)
    assert r.value("ch0.first_out") == "ch0.voltage_high"
    r.set("ch0.voltage", 1.4)
    r.set("door.closed", True)
    r.scan(1)
    r.guard.reset("alice")
    log = [(e.alarm_id, e.transition.value, e.actor) for e in r.alarms.history]
    assert ("ch0.voltage_high", "activated", "") in log
    assert ("ch0.voltage_high", "acknowledged", "alice") in log
    assert ("ch0.voltage_high", "reset", "alice") in log


# --- what a start waits for ----------------------------------------------------------------
def test_a_channel_whose_bms_has_not_sent_yet_lists_it_among_its_inputs_not_good() -> None:
    r = make(
        extra_tags=(TagSpec("bms.cell_max", unit="V"), TagSpec("dev.connected", dtype="bool")),
        bms={"cell_max_tag": "bms.cell_max", "cell_voltage_v": [3.0, 4.2]},
    )
    r.db.update(r.db["bms.cell_max"], None, Quality.BAD, Reason.INITIAL)  # no frame yet
    assert r.guard.inputs_not_good() == [
        "bms.cell_max BAD (initial value)",
        "dev.connected not true",
    ]
    r.set("dev.connected", True)
    r.set("bms.cell_max", 4.0)
    assert r.guard.inputs_not_good() == []
    r.set("ch0.voltage", None, Quality.BAD)
    assert r.guard.inputs_not_good() == ["ch0.voltage BAD (comm failure)"]
