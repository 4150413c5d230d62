"""Auto and Manual at the chain's seam: the guards of ``states.decide`` and ``check_load``,
and what the port does when a test starts and when it is reset (no bench)."""

from __future__ import annotations

import pytest

from supervisor.chains.engine import ChainRunner
from supervisor.chains.port import ChannelPort
from supervisor.chains.states import Situation, State, check_load, decide
from supervisor.channels import Channel, ChannelLimits, Mode
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.tags import TagDB

S = State
DRIVEN = Situation(has_program=True, in_manual=True, manual_enabled=True)
IN_MANUAL = Situation(has_program=True, in_manual=True)


def test_start_is_refused_while_the_operator_drives_the_channel_in_manual() -> None:
    with pytest.raises(
        OperatorError,
        match=r"^ch0: cannot start while the channel is driven in manual \(enable on\): "
        r"turn enable off first$",
    ):
        decide("ch0", S.IDLE, "start", DRIVEN)
    assert decide("ch0", S.IDLE, "start", IN_MANUAL) is S.RUNNING  # enable off: start takes it


def test_resume_is_refused_while_the_channel_is_in_manual() -> None:
    with pytest.raises(
        OperatorError, match=r"^ch0: the channel is in manual: switch it to auto before resuming$"
    ):
        decide("ch0", S.HELD, "resume", IN_MANUAL)


@pytest.mark.parametrize("command", ["hold", "stop", "abort"])
def test_manual_never_blocks_a_command_towards_safe(command: str) -> None:
    assert decide("ch0", S.RUNNING, command, DRIVEN) in (S.HOLDING, S.STOPPING, S.ABORTING)


def test_a_recipe_is_not_loaded_from_under_an_operator_driving_the_channel() -> None:
    with pytest.raises(
        OperatorError,
        match=r"^ch0: cannot load a recipe while the channel is driven in manual",
    ):
        check_load("ch0", S.IDLE, manual_driven=True)
    check_load("ch0", S.IDLE, manual_driven=False)


@pytest.fixture
def runner() -> ChainRunner:
    db = TagDB()
    Channel("ch0", db, ChannelLimits((-0.4, 0.4), (0.8, 1.9)), capacity_ah=2.0)
    port = ChannelPort.from_tags(db, "ch0", Mode.AUTO.value, Mode.MANUAL.value)
    return ChainRunner(port, db, VirtualClock())


def test_releasing_the_channel_gives_it_to_the_operator_in_manual_disabled_at_0_a(
    runner: ChainRunner,
) -> None:
    port, db = runner.port, runner.db
    port.take_control()
    db.update(port.manual_current, 0.3)
    port.request(-0.2, 0.0, True)
    port.release_control()
    assert (port.mode.value, port.enable.value, port.manual_current.value) == ("manual", False, 0.0)
    assert (port.auto_current.value, port.auto_active.value) == (0.0, False)
    assert not port.manual_driven


def test_a_command_tag_goes_to_the_handler_when_the_bench_gives_one(runner: ChainRunner) -> None:
    seen: list[str] = []
    runner.command_handler = seen.append
    runner.db.write("ch0.command", "start")
    runner.run(0.0, 0.1)
    assert seen == ["start"]
    assert runner.state is S.IDLE  # the handler decides; the runner did not act alone
    assert runner.db["ch0.command"].value == ""
