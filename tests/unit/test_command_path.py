"""The one command path, as a specification: every verb accepted in the right state, refused
with its reason otherwise, and every command recorded with its actor.

A virtual-clock bench (four Chadèche channels, the ADAM with the e-stop sense), every device
in process; commands run between scans, as the HTTP API gives them.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from commandrig import CV_ON_CHADECHE, DISCHARGE, SUPERVISED, recipe

from supervisor.app import Bench
from supervisor.chains.states import State
from supervisor.commands import Command, CommandEvent, Result, ResultKind, Target, Verb
from supervisor.commands.roles import EveryoneOperates
from supervisor.tags import Access, TagSpec
from supervisor.testing import run_scans

V = Verb
ACCEPTED, BAD, FORBIDDEN, NOT_FOUND, REFUSED = (
    ResultKind.ACCEPTED,
    ResultKind.BAD_ARGUMENT,
    ResultKind.FORBIDDEN,
    ResultKind.NOT_FOUND,
    ResultKind.REFUSED,
)


def run(bench: Bench, channel: str, verb: Verb, actor: str = "operator", **args: object) -> Result:
    return bench.commands.execute(Command.channel(channel, verb, actor, **args))


def write(bench: Bench, tag: str, value: object, actor: str = "operator") -> Result:
    return bench.commands.execute(Command.write(tag, value, actor))


def value(bench: Bench, tag: str) -> object:
    return bench.db[tag].value


def manual_state(bench: Bench, ch: str = "ch0") -> tuple[object, object, object]:
    return (
        value(bench, f"{ch}.mode"),
        value(bench, f"{ch}.enable"),
        value(bench, f"{ch}.manual_current"),
    )


async def running(bench: Bench, tmp_path: Path, text: str = DISCHARGE) -> None:
    """ch0 running ``text`` (a 200 mA discharge by default), settled."""
    assert run(bench, "ch0", V.START, recipe=recipe(tmp_path, text)).accepted
    await run_scans(bench.engine, 20)


async def press_estop(bench: Bench, pressed: bool = True) -> None:
    assert bench.sim is not None
    bench.sim.press_estop(pressed)
    await run_scans(bench.engine, 10)  # the ADAM polls the sense every 0.2 s


def refused(result: Result, kind: ResultKind, reason: str) -> bool:
    """Refused with this kind, and the reason says (at least) ``reason``."""
    assert not result.accepted, result
    assert result.kind is kind, result
    assert reason in result.reason, result.reason
    return True


# --- loading a recipe ----------------------------------------------------------------------
async def test_load_is_accepted_with_the_test_id_and_leaves_mode_and_enable_alone(
    bench: Bench, tmp_path: Path
) -> None:
    write(bench, "ch0.manual_current", 0.1)
    before = manual_state(bench)
    res = run(bench, "ch0", V.LOAD, recipe=recipe(tmp_path))
    assert res.accepted and res.kind is ACCEPTED
    assert res.data["test_id"] == bench.runners["ch0"].test_id
    assert res.data["channel"] == "ch0" and res.data["recipe"] == "d"
    await run_scans(bench.engine, 3)
    assert manual_state(bench) == before == ("manual", False, 0.1)


async def test_load_is_refused_while_the_channel_is_driven_in_manual(
    bench: Bench, tmp_path: Path
) -> None:
    assert write(bench, "ch0.enable", True).accepted
    res = run(bench, "ch0", V.LOAD, recipe=recipe(tmp_path))
    assert refused(
        res,
        REFUSED,
        "ch0: cannot load a recipe while the channel is driven in manual (enable on):"
        " turn enable off first",
    )
    assert bench.runners["ch0"].program is None
    assert value(bench, "ch0.enable") is True  # nothing taken from the operator


async def test_load_is_refused_while_a_test_is_under_way(bench: Bench, tmp_path: Path) -> None:
    await running(bench, tmp_path)
    res = run(bench, "ch0", V.LOAD, recipe=recipe(tmp_path))
    assert refused(
        res,
        REFUSED,
        "ch0: cannot load a recipe while Running: a test is under way: stop or abort it first",
    )


async def test_load_names_a_missing_file_and_every_error_of_a_refused_recipe(
    bench: Bench, tmp_path: Path
) -> None:
    missing = str(tmp_path / "nope.yaml")
    assert refused(
        run(bench, "ch0", V.LOAD, recipe=missing), NOT_FOUND, f"{missing}: no such recipe"
    )
    res = run(bench, "ch0", V.LOAD, recipe=recipe(tmp_path, CV_ON_CHADECHE))
    assert refused(res, ResultKind.INVALID_RECIPE, "ch0: recipe refused: ")
    assert res.details and res.details[0].startswith(str(tmp_path / "r.yaml") + ":")
    assert res.http_status == 422


# --- start and the chain's commands ----------------------------------------------------------
async def test_start_hands_the_channel_to_its_chain(bench: Bench, tmp_path: Path) -> None:
    res = run(bench, "ch0", V.START, recipe=recipe(tmp_path))
    assert res.accepted
    assert "started: the step chain drives the channel (mode manual → auto)" in res.reason
    assert bench.runners["ch0"].state is State.RUNNING
    assert manual_state(bench)[:2] == ("auto", False)
    await run_scans(bench.engine, 20)
    assert bench.channels["ch0"].current_cmd.value == pytest.approx(-0.2)


async def test_start_is_refused_without_a_recipe_and_while_driven_in_manual(
    bench: Bench, tmp_path: Path
) -> None:
    assert refused(run(bench, "ch0", V.START), REFUSED, "ch0: no recipe loaded")
    assert run(bench, "ch1", V.LOAD, recipe=recipe(tmp_path)).accepted
    assert write(bench, "ch1.enable", True).accepted
    assert refused(
        run(bench, "ch1", V.START),
        REFUSED,
        "ch1: cannot start while the channel is driven in manual (enable on):"
        " turn enable off first",
    )
    assert bench.runners["ch1"].state is State.IDLE


async def test_start_is_refused_by_a_trip_naming_it_and_does_not_load_either(
    bench: Bench, tmp_path: Path
) -> None:
    await press_estop(bench)
    res = run(bench, "ch0", V.START, recipe=recipe(tmp_path))
    assert refused(
        res,
        REFUSED,
        "ch0: start refused: tripped by estop (Emergency stop pressed (e-stop circuit open)):"
        " its cause is still present",
    )
    assert bench.runners["ch0"].program is None
    await press_estop(bench, False)
    assert refused(run(bench, "ch0", V.START, recipe=recipe(tmp_path)), REFUSED, "acknowledge it")


# Each step: command, whether accepted, the state after it or the reason of the refusal.
SEQUENCE = [
    (
        V.RESUME,
        False,
        "ch0: resume is not allowed while Running (allowed: hold, advance, stop, abort)",
    ),
    (V.HOLD, True, "Holding"),
    (V.ADVANCE, False, "ch0: advance is not allowed while Held (allowed: resume, stop, abort)"),
    (V.RESUME, True, "Resuming"),
    (V.ADVANCE, True, "Running"),
    (
        V.RESET,
        False,
        "ch0: reset is not allowed while Running (allowed: hold, advance, stop, abort)",
    ),
    (V.STOP, True, "Stopping"),
    (V.ABORT, False, "ch0: abort is not allowed while Stopped (allowed: reset)"),
    (V.RESET, True, "Idle"),
]


async def test_each_chain_command_is_accepted_in_its_state_and_refused_with_the_table_otherwise(
    bench: Bench, tmp_path: Path
) -> None:
    await running(bench, tmp_path)
    for verb, ok, then in SEQUENCE:
        res = run(bench, "ch0", verb)
        assert res.accepted is ok, (verb, res)
        if ok:
            assert res.data["state"] == then
            assert bench.runners["ch0"].state.value == then
        else:
            assert res.kind is REFUSED and res.reason == then
        await run_scans(bench.engine, 2)
    assert value(bench, "ch0.chain.step") == ""  # reset: back to before the test


async def test_abort_from_every_active_state_and_reset_gives_the_channel_back_in_manual_at_0_a(
    bench: Bench, tmp_path: Path
) -> None:
    await running(bench, tmp_path)
    assert manual_state(bench)[0] == "auto"
    assert run(bench, "ch0", V.ABORT).accepted
    await run_scans(bench.engine, 2)
    assert bench.runners["ch0"].state is State.ABORTED
    res = run(bench, "ch0", V.RESET)
    assert res.accepted and "the channel is in manual, enable off, 0 A" in res.reason
    assert manual_state(bench) == ("manual", False, 0.0)
    await run_scans(bench.engine, 2)
    assert bench.channels["ch0"].current_cmd.value == 0.0


async def test_resume_is_refused_in_manual_until_the_channel_is_handed_back(
    bench: Bench, tmp_path: Path
) -> None:
    await running(bench, tmp_path)
    assert run(bench, "ch0", V.MODE, value="manual").accepted
    await run_scans(bench.engine, 2)
    assert refused(
        run(bench, "ch0", V.RESUME),
        REFUSED,
        "ch0: the channel is in manual: switch it to auto before resuming",
    )
    res = run(bench, "ch0", V.MODE, value="auto")
    assert res.accepted and "(Held: resume to continue the test)" in res.reason
    assert run(bench, "ch0", V.RESUME).accepted
    await run_scans(bench.engine, 5)
    assert bench.runners["ch0"].state is State.RUNNING
    assert bench.channels["ch0"].current_cmd.value == pytest.approx(-0.2)


async def test_resume_and_start_are_refused_until_the_chains_alarm_is_acknowledged(
    bench: Bench, tmp_path: Path
) -> None:
    await running(bench, tmp_path, SUPERVISED)
    await run_scans(bench.engine, 100)
    runner = bench.runners["ch0"]
    assert runner.state is State.HELD
    assert refused(run(bench, "ch0", V.RESUME), REFUSED, "ch0: acknowledge the alarm first")
    res = run(bench, "ch0", V.ACKNOWLEDGE)
    assert res.accepted and "chain alarm acknowledged (supervision: step c exceeded" in res.reason
    assert run(bench, "ch0", V.RESUME).accepted


# --- Auto and Manual: explicit, bumpless --------------------------------------------------------
async def test_a_manual_setpoint_or_enable_in_auto_is_refused_saying_to_switch_first(
    bench: Bench, tmp_path: Path
) -> None:
    await running(bench, tmp_path)
    for res in (
        run(bench, "ch0", V.MANUAL_CURRENT, value=0.3),
        run(bench, "ch0", V.ENABLE, value=True),
    ):
        assert refused(res, REFUSED, "channel ch0 is in auto (step chain): switch to manual first")
    assert value(bench, "ch0.manual_current") == 0.0 and value(bench, "ch0.enable") is False


async def test_switching_to_manual_mid_recipe_holds_the_chain_and_starts_from_0_a_disabled(
    bench: Bench, tmp_path: Path
) -> None:
    write(bench, "ch0.manual_current", 0.3)  # staged earlier, in Manual
    await running(bench, tmp_path)
    res = run(bench, "ch0", V.MODE, value="manual")
    assert (
        res.reason == "ch0: mode manual: chain held (was Running), manual setpoint 0 A, enable off"
    )
    assert manual_state(bench) == ("manual", False, 0.0)
    await run_scans(bench.engine, 3)
    assert bench.runners["ch0"].state is State.HELD
    assert bench.channels["ch0"].current_cmd.value == 0.0  # never the staged +0.3 A


async def test_switching_to_manual_can_keep_the_present_setpoint_without_a_bump(
    bench: Bench, tmp_path: Path
) -> None:
    await running(bench, tmp_path)
    res = run(bench, "ch0", V.MODE, value="manual", keep_setpoint=True)
    assert res.accepted and "manual setpoint -0.2 A (kept), enable on" in res.reason
    seen = []
    for _ in range(5):
        await run_scans(bench.engine)
        seen.append(bench.channels["ch0"].current_cmd.value)
    assert seen == [pytest.approx(-0.2)] * 5  # every scan: the same setpoint
    assert bench.runners["ch0"].state is State.HELD


async def test_back_to_auto_is_refused_while_the_operator_drives_the_channel(
    bench: Bench, tmp_path: Path
) -> None:
    await running(bench, tmp_path)
    run(bench, "ch0", V.MODE, value="manual", keep_setpoint=True)
    assert refused(
        run(bench, "ch0", V.MODE, value="auto"),
        REFUSED,
        "ch0: cannot switch to auto while the channel is driven in manual (enable on, -0.2 A):"
        " turn enable off first",
    )
    assert run(bench, "ch0", V.ENABLE, value=False).accepted
    assert run(bench, "ch0", V.MODE, value="auto").accepted


async def test_manual_setpoint_and_enable_are_accepted_in_manual(bench: Bench) -> None:
    res = run(bench, "ch0", V.MANUAL_CURRENT, value=0.3)
    assert res.reason == "ch0: manual setpoint 0.3 A (enable is off: nothing flows yet)"
    assert run(bench, "ch0", V.ENABLE, value=True).reason == "ch0: enable on at 0.3 A"
    await run_scans(bench.engine, 3)
    assert bench.channels["ch0"].current_cmd.value == pytest.approx(0.3)
    assert run(bench, "ch0", V.ENABLE, value=False).reason == "ch0: enable off"
    assert run(bench, "ch0", V.MODE, value="manual").reason == "ch0: already in manual"


async def test_enable_is_refused_while_tripped_and_accepted_once_acknowledged_and_reset(
    bench: Bench,
) -> None:
    await press_estop(bench)
    assert refused(run(bench, "ch0", V.ENABLE, value=True), REFUSED, "tripped by estop")
    assert run(bench, "ch0", V.ENABLE, value=False).accepted  # towards safe: always
    await press_estop(bench, False)
    res = run(bench, "ch0", V.ACKNOWLEDGE)
    assert res.accepted and res.reason == "ch0: reset: estop"
    assert run(bench, "ch0", V.ENABLE, value=True).accepted


@pytest.mark.parametrize(
    ("verb", "args", "reason"),
    [
        (V.MODE, {"value": "semi"}, "ch0: mode is auto or manual, not 'semi'"),
        (V.MODE, {}, "value must be a text, not None"),
        (V.MODE, {"value": "manual", "keep_setpoint": 2}, "keep_setpoint must be true or false"),
        (V.MANUAL_CURRENT, {"value": "0.3"}, "value must be a number (A), not '0.3'"),
        (V.MANUAL_CURRENT, {"value": True}, "value must be a number (A), not True"),
        (V.MANUAL_CURRENT, {"value": float("nan")}, "value must be a number (A)"),
        (V.ENABLE, {"value": 3}, "value must be true or false, not 3"),
        (V.HOLD, {"now": True}, "hold: unknown argument now (expected: none)"),
        (V.LOAD, {"recipe": 3}, "recipe must be a text, not 3"),
        (V.LOAD, {"recipe": "x.yaml", "parameters": [1]}, "parameters must be a mapping"),
    ],
)
async def test_a_wrong_argument_is_a_bad_argument_naming_it(
    bench: Bench, verb: Verb, args: dict[str, object], reason: str
) -> None:
    assert refused(run(bench, "ch0", verb, **args), BAD, reason)


async def test_an_unknown_channel_or_a_verb_a_channel_has_not_is_not_found(bench: Bench) -> None:
    assert refused(
        run(bench, "ch9", V.HOLD), NOT_FOUND, "unknown channel 'ch9' (channels: ch0, ch1, ch2, ch3)"
    )
    assert refused(run(bench, "ch0", V.SHELVE), NOT_FOUND, "a channel has no command shelve")


# --- alarms --------------------------------------------------------------------------------
def alarm(bench: Bench, alarm_id: str, verb: Verb, **args: object) -> Result:
    return bench.commands.execute(Command.alarm(alarm_id, verb, "alice", **args))


async def test_acknowledge_while_the_estop_is_pressed_is_refused_with_the_reason(
    bench: Bench,
) -> None:
    await press_estop(bench)
    res = run(bench, "ch0", V.ACKNOWLEDGE)
    assert refused(
        res,
        REFUSED,
        "ch0: cannot reset estop: the cause is still present (Emergency stop pressed (e-stop"
        " circuit open)); acknowledged: reset once the cause is gone",
    )
    assert bench.alarms is not None and bench.alarms["estop"].acked_by == "operator"


async def test_an_alarm_is_acknowledged_reset_shelved_and_unshelved_by_its_id(
    bench: Bench,
) -> None:
    await press_estop(bench)
    assert refused(
        alarm(bench, "estop", V.RESET), REFUSED, "cannot reset estop: the cause is still present"
    )
    assert (
        alarm(bench, "estop", V.ACKNOWLEDGE).reason
        == "alarm estop acknowledge: now active, acknowledged"
    )
    assert refused(
        alarm(bench, "estop", V.ACKNOWLEDGE), REFUSED, "not waiting for an acknowledgement"
    )
    assert refused(alarm(bench, "estop", V.SHELVE, duration_s=60), REFUSED, "is a trip")
    await press_estop(bench, False)
    assert alarm(bench, "estop", V.RESET).reason == "alarm estop reset: now normal"
    # A plain alarm (room.temp above its H limit) can be shelved for a while.
    assert alarm(bench, "room.temp.H", V.SHELVE, duration_s=600).accepted
    assert refused(
        alarm(bench, "room.temp.H", V.SHELVE, duration_s="1 h"),
        BAD,
        "duration_s must be a number (s)",
    )
    assert alarm(bench, "room.temp.H", V.UNSHELVE).accepted
    assert refused(
        alarm(bench, "room.temp.H", V.UNSHELVE), REFUSED, "alarm room.temp.H is not shelved"
    )
    assert refused(alarm(bench, "nope", V.ACKNOWLEDGE), NOT_FOUND, "unknown alarm 'nope'")
    assert refused(alarm(bench, "estop", V.HOLD), NOT_FOUND, "an alarm has no command hold")
    assert bench.alarms is not None
    assert ("estop", "alice") in [(e.alarm_id, e.actor) for e in bench.alarms.history if e.actor]


async def test_an_unacknowledged_channel_alarm_refuses_start_naming_it(
    bench: Bench, tmp_path: Path
) -> None:
    assert bench.alarms is not None
    a = bench.alarms["ch0.voltage_high"]
    bench.alarms.set(a, True, "voltage 2.000 V at or above hard limit 1.9 V while charging")
    bench.alarms.set(a, False)
    bench.alarms.reset("ch0.voltage_high", "test")  # the trip released ...
    bench.alarms.set(a, True, "again")  # ... and a new one unacknowledged
    assert refused(run(bench, "ch0", V.START, recipe=recipe(tmp_path)), REFUSED, "ch0.voltage_high")


# --- tags ------------------------------------------------------------------------------------
async def test_a_write_of_a_channels_command_tags_is_that_command(
    bench: Bench, tmp_path: Path
) -> None:
    assert (
        write(bench, "ch0.mode", "auto").reason
        == "ch0: mode auto: the step chain drives the channel"
    )
    assert refused(write(bench, "ch0.manual_current", 0.2), REFUSED, "switch to manual first")
    assert write(bench, "ch0.mode", "manual").accepted
    res = write(bench, "ch0.manual_current", 0.2)
    assert res.accepted and res.tag == "ch0.manual_current"
    assert refused(
        write(bench, "ch0.command", "resume"), REFUSED, "resume is not allowed while Idle"
    )
    assert refused(write(bench, "ch0.command", "jump"), BAD, "ch0.command: unknown command 'jump'")
    assert refused(write(bench, "ch0.ack", False), BAD, "write true to ch0.ack to acknowledge")
    assert write(bench, "ch0.ack", True).reason == "ch0: nothing to acknowledge"
    assert bench.commands.log[-1].command == "acknowledge"


async def test_a_generic_write_checks_existence_access_type_and_range(bench: Bench) -> None:
    db = bench.db
    db.add(
        TagSpec("lab.setpoint", unit="degC", access=Access.OPERATOR, initial=20.0, range=(0, 40))
    )
    db.add(TagSpec("lab.calibration", access=Access.ENGINEER, initial=1.0))
    assert write(bench, "lab.setpoint", 25).reason == "lab.setpoint := 25.0"
    assert refused(write(bench, "nope.tag", 1), NOT_FOUND, "unknown tag 'nope.tag'")
    assert refused(write(bench, "ch0.voltage", 1.0), FORBIDDEN, "ch0.voltage is read-only")
    assert refused(write(bench, "lab.calibration", 2.0), FORBIDDEN, "needs engineer access")
    assert refused(write(bench, "lab.setpoint", "warm"), BAD, "expected a number")
    assert refused(write(bench, "lab.setpoint", 99), BAD, "outside its range [0, 40]")
    assert db["lab.setpoint"].value == 25.0


class NobodyStops(EveryoneOperates):
    """A role policy: stop is for supervisors only."""

    def refuses(self, command: Command) -> str:
        return "stop needs the supervisor role" if command.verb is Verb.STOP else ""


async def test_the_role_hook_refuses_a_command_as_forbidden(bench: Bench, tmp_path: Path) -> None:
    bench.commands.roles = NobodyStops()
    await running(bench, tmp_path)
    assert refused(run(bench, "ch0", V.STOP), FORBIDDEN, "stop needs the supervisor role")
    assert bench.runners["ch0"].state is State.RUNNING
    assert refused(write(bench, "ch0.command", "stop"), FORBIDDEN, "supervisor role")


# --- the record ----------------------------------------------------------------------------------
async def test_every_command_accepted_or_refused_is_recorded_with_its_actor(
    bench: Bench, tmp_path: Path
) -> None:
    seen: list[CommandEvent] = []
    bench.commands.listeners.append(seen.append)
    run(bench, "ch0", V.START, actor="alice", recipe=recipe(tmp_path))
    run(bench, "ch0", V.ENABLE, actor="bob", value=True)
    bench.commands.execute(Command(Target.bench(), V.WRITE, {"tag": "nope", "value": 1}, "carol"))
    log = list(bench.commands.log)
    assert seen == log
    assert [(e.actor, e.target, e.command, e.accepted, e.kind) for e in log] == [
        ("alice", "ch0", f"start {tmp_path / 'r.yaml'}", True, ACCEPTED),
        ("bob", "ch0", "enable on", False, REFUSED),
        ("carol", "bench", "write nope := 1", False, NOT_FOUND),
    ]
    assert log[1].text == (
        "enable on by bob: refused: channel ch0 is in auto (step chain): switch to manual first"
    )
    assert log[1].channel == "ch0" and log[2].channel == ""


async def test_the_commands_of_a_running_test_are_in_its_timeline_with_their_actor(
    bench: Bench, tmp_path: Path
) -> None:
    await running(bench, tmp_path)
    run(bench, "ch0", V.ENABLE, actor="bob", value=True)
    run(bench, "ch0", V.HOLD, actor="alice")
    await run_scans(bench.engine, 2)
    run(bench, "ch0", V.STOP, actor="alice")
    await run_scans(bench.engine, 2)
    runner = bench.runners["ch0"]
    folder = Path(bench.cfg.state_dir) / "results" / runner.test_id
    timeline = json.loads((folder / "summary.json").read_text(encoding="utf-8"))["timeline"]
    commands = [e["text"] for e in timeline if e["kind"] == "command"]
    assert commands[0].startswith(f"start {tmp_path / 'r.yaml'} by operator: accepted: ")
    assert commands[1:] == [
        "enable on by bob: refused: channel ch0 is in auto (step chain): switch to manual first",
        "hold by alice: accepted: ch0: hold: Running → Holding",
        "stop by alice: accepted: ch0: stop: Held → Stopping",
    ]
    assert timeline[0]["test_time_s"] == 0.0 and timeline[0]["kind"] == "state"  # from start


async def test_a_command_written_to_the_chain_tag_takes_the_path_and_its_refusal_is_an_event(
    bench: Bench,
) -> None:
    bench.db.write("ch0.command", "resume")  # an older client writes the tag
    await run_scans(bench.engine, 1)
    last = bench.commands.log[-1]
    assert (last.actor, last.command, last.accepted) == (
        "operator via ch0.command",
        "resume",
        False,
    )
    assert last.reason == "ch0: resume is not allowed while Idle (allowed: start)"
    event = bench.runners["ch0"].events[-1]
    assert event.text == f"resume by operator via ch0.command: refused: {last.reason}"
    assert value(bench, "ch0.chain.last_event") == event.text
    assert value(bench, "ch0.command") == ""
