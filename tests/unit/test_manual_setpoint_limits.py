"""A manual setpoint is answered with what will flow (issue 26, finding 4): one beyond the
channel's hard limits (the I/O map's ``limits.current_a``) is refused with the limit named;
one inside them that the safety phase clamps this scan (``chN.limit.charge_a`` /
``discharge_a``: a BMS derating) is accepted with the clamp said, and ``chN.clamped`` shows
it once the channel drives it.

One channel, its guard (with a BMS cell limit) and its chain runner, the command path over
them; scanned on the virtual clock in design order: derive, safety, drive.
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from supervisor.chains.engine import ChainRunner
from supervisor.chains.port import ChannelPort
from supervisor.channels import Channel, ChannelLimits
from supervisor.commands import Command, CommandPath, ResultKind, Verb
from supervisor.config.models import ChannelConfig
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.safety import AlarmManager, ChannelGuard
from supervisor.tags import TagDB, TagSpec

DT = 0.1


@dataclass
class Rig:
    clock: VirtualClock
    db: TagDB
    ch: Channel
    guard: ChannelGuard
    commands: CommandPath

    def scan(self, n: int = 1) -> None:
        for _ in range(n):
            now = self.clock.now()
            self.ch.derive(now, DT)
            self.guard.evaluate(now, DT)
            self.ch.drive(now, DT)
            self.clock.advance(DT)

    def setpoint(self, amps: float) -> tuple[bool, ResultKind, str, int]:
        r = self.commands.execute(Command.write("ch4.manual_current", amps, "operator"))
        return r.accepted, r.kind, r.reason, r.http_status


def rig() -> Rig:
    """ch4 of io_maps/sim.yaml as far as its limits go: ±20 A, a BMS cell limit of 4.2 V
    derating the charge over its last 50 mV."""
    clock = VirtualClock()
    db = TagDB()
    db.add(TagSpec("bms.cell_max", unit="V", initial=4.0))
    db.update(db["bms.cell_max"], 4.0)
    cfg = ChannelConfig.model_validate(
        {
            "name": "ch4",
            "source": {"device": "ea"},
            "capacity_ah": 40.0,
            "limits": {"current_a": [-20, 20], "voltage_v": [12.0, 16.8]},
            "bms": {
                "cell_max_tag": "bms.cell_max",
                "cell_voltage_v": [3.0, 4.2],
                "derate_band_v": 0.05,
            },
        }
    )
    lim = cfg.limits
    ch = Channel("ch4", db, ChannelLimits(lim.current_a, lim.voltage_v), capacity_ah=40.0)
    db.update(ch.voltage, 14.8)
    db.update(ch.current, 0.0)
    alarms = AlarmManager(clock)
    guard = ChannelGuard(cfg, db, alarms)
    runner = ChainRunner(ChannelPort.from_tags(db, "ch4", "auto"), db, clock)
    commands = CommandPath(db, clock, runners={"ch4": runner}, alarms=alarms)
    r = Rig(clock, db, ch, guard, commands)
    r.scan(2)
    return r


def test_a_setpoint_beyond_the_hard_limits_is_refused_with_the_limit_in_the_reason() -> None:
    r = rig()
    assert r.setpoint(500.0) == (
        False,
        ResultKind.OUT_OF_RANGE,
        "ch4: manual setpoint 500 A is beyond the channel's hard limit of 20 A"
        " (range -20 … 20 A); refused",
        409,
    )
    accepted, kind, reason, _ = r.setpoint(-20.5)
    assert (accepted, kind) == (False, ResultKind.OUT_OF_RANGE)
    assert "hard limit of -20 A (range -20 … 20 A)" in reason
    # Nothing staged: the setpoint stays what it was, and nothing flows once enabled.
    assert r.db["ch4.manual_current"].value == 0.0
    assert r.commands.execute(Command.channel("ch4", Verb.ENABLE, "operator", value=True)).accepted
    r.scan(3)
    assert r.ch.current_cmd.value == 0.0 and r.ch.clamped.value is False
    # The refusal is recorded as one, with its kind.
    ev = r.commands.log[-3]
    assert (ev.accepted, ev.kind) == (False, ResultKind.OUT_OF_RANGE)
    assert "manual_current 500 A by operator: refused (out of range)" in ev.text


def test_the_hard_limits_themselves_are_accepted_as_they_are() -> None:
    r = rig()
    accepted, kind, reason, _ = r.setpoint(20.0)
    assert (accepted, kind) == (True, ResultKind.ACCEPTED)
    assert reason == "ch4: manual setpoint 20 A (enable is off: nothing flows yet)"
    assert r.setpoint(-20.0)[0] is True


def test_the_hard_limits_are_the_tags_range_so_a_plain_write_is_refused_too() -> None:
    r = rig()
    assert r.db["ch4.manual_current"].spec.range == (-20.0, 20.0)
    with pytest.raises(OperatorError, match=r"outside its range \[-20.0, 20.0\]"):
        r.db.write("ch4.manual_current", 500.0)


def test_a_setpoint_clamped_by_a_bms_derating_is_accepted_with_the_clamp_said_and_shown() -> None:
    r = rig()
    r.db.update(r.db["bms.cell_max"], 4.175)  # half the derating band left: half the current
    r.scan(1)
    assert r.db["ch4.limit.charge_a"].value == pytest.approx(10.0)
    assert r.commands.execute(Command.channel("ch4", Verb.ENABLE, "operator", value=True)).accepted
    accepted, kind, reason, status = r.setpoint(15.0)
    assert (accepted, kind, status) == (True, ResultKind.ACCEPTED, 200)
    assert reason == (
        "ch4: manual setpoint 15 A, clamped to 10 A by the safety limit ch4.limit.charge_a"
        " = 10 A as it stands (shown in ch4.clamped while it clamps)"
    )
    r.scan(1)
    assert r.ch.current_cmd.value == pytest.approx(10.0)
    assert r.ch.clamped.value is True
    # A discharge is not limited by the charge derating: accepted whole, nothing clamped.
    accepted, _, reason, _ = r.setpoint(-15.0)
    assert accepted and reason == "ch4: manual setpoint -15 A"
    r.scan(1)
    assert r.ch.current_cmd.value == -15.0 and r.ch.clamped.value is False
