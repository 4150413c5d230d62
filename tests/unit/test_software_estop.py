"""The bench-wide software e-stop (seed 002 §1.5; issue 32, finding 7), as a specification of
its command's rules: who may press it, what a press does to every channel (the hardware
button's ``estop`` trip: recipes aborted, outputs safe), a second press, and its reset
(acknowledged first, never while the hardware button is pressed, nothing energised again).

A virtual-clock bench (commandrig: four Chadèche channels, the ADAM with the e-stop sense),
every device in process; commands run between scans, as every client gives them.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from commandrig import DISCHARGE, recipe

from supervisor.app import Bench
from supervisor.chains.states import State
from supervisor.commands import Command, Result, ResultKind, Verb
from supervisor.config.models import EstopConfig
from supervisor.core.clock import VirtualClock
from supervisor.safety import AlarmManager, AlarmState, Transition
from supervisor.safety.interlocks import Estop
from supervisor.tags import Access, TagDB, TagSpec
from supervisor.testing import run_scans

CHANNELS = ("ch0", "ch1", "ch2", "ch3")


class ViewerBob:
    """The role hook of a bench with users: ``bob`` is a viewer, everyone else operates."""

    def access_of(self, actor: str) -> Access:
        return Access.READ_ONLY if actor == "bob" else Access.OPERATOR

    def refuses(self, command: Command) -> str:
        return ""  # the e-stop's own check refuses bob (no hook may let a viewer through)


def estop(bench: Bench, actor: str = "alice") -> Result:
    return bench.commands.execute(Command.estop(actor))


def estop_reset(bench: Bench, actor: str = "alice") -> Result:
    return bench.commands.execute(Command.estop_reset(actor))


def acknowledge_estop(bench: Bench, actor: str = "alice") -> Result:
    return bench.commands.execute(Command.alarm("estop", Verb.ACKNOWLEDGE, actor))


async def busy(bench: Bench, tmp_path: Path) -> None:
    """ch0 runs a discharge recipe, ch1 charges 0.1 A by hand: two channels doing something."""
    start = Command.channel("ch0", Verb.START, "alice", recipe=recipe(tmp_path, DISCHARGE))
    assert bench.commands.execute(start).accepted
    for tag, value in (("ch1.manual_current", 0.1), ("ch1.enable", True)):
        assert bench.commands.execute(Command.write(tag, value, "alice")).accepted
    await run_scans(bench.engine, 10)
    assert bench.runners["ch0"].state is State.RUNNING
    assert bench.db["ch1.current_cmd"].value == pytest.approx(0.1)


def safe(bench: Bench, ch: str) -> bool:
    """What a trip makes of a channel: no current asked, its power stage off, faulted."""
    db = bench.db
    return (
        db[f"{ch}.current_cmd"].value == 0.0
        and db[f"{ch}.enable"].value is False
        and db[f"{ch}.state"].value == "faulted"
    )


def activations(bench: Bench) -> int:
    return sum(
        1
        for e in bench.alarms.history
        if e.alarm_id == "estop" and e.transition is Transition.ACTIVATED
    )


async def test_a_press_trips_every_channel_like_the_button_and_aborts_their_recipes(
    bench: Bench, tmp_path: Path
) -> None:
    await busy(bench, tmp_path)
    res = estop(bench)
    assert res.accepted and res.kind is ResultKind.ACCEPTED
    assert res.reason.startswith("software e-stop pressed by alice: every channel tripped")
    alarm = bench.alarms["estop"]
    # The trip is there at once (no scan needed), the hardware button's own alarm.
    assert alarm.state is AlarmState.ACTIVE_UNACKED and alarm.tripped
    assert alarm.message == "Software e-stop pressed by alice"
    await run_scans(bench.engine, 5)
    assert all(safe(bench, ch) for ch in CHANNELS)
    assert all("Software e-stop pressed by alice" in str(bench.db[f"{ch}.fault"].value)
               for ch in CHANNELS)  # fmt: skip
    assert bench.runners["ch0"].state is State.ABORTED  # the e-stop aborts, not holds
    # The hardware sense is untouched: it is the software button that holds the bench.
    assert bench.db["estop.ok"].value is True
    # Recorded with its actor: the command log and every channel's timeline.
    (ev,) = [e for e in bench.commands.log if e.command == "estop"]
    assert (ev.actor, ev.accepted, ev.target) == ("alice", True, "bench")
    for ch in CHANNELS:
        assert any("estop by alice: accepted" in e.text for e in bench.runners[ch].events), ch


async def test_a_second_press_is_accepted_and_names_the_first(bench: Bench) -> None:
    assert estop(bench, "alice").accepted
    await run_scans(bench.engine, 3)
    assert acknowledge_estop(bench, "alice").accepted
    again = estop(bench, "carol")
    assert again.accepted  # an e-stop button is never refused
    assert again.reason.startswith("software e-stop already pressed by alice")
    assert activations(bench) == 1  # one trip, not two
    # The acknowledgement of the first press stands: the reset needs no second one.
    assert bench.alarms["estop"].state is AlarmState.ACTIVE_ACKED
    assert [e.actor for e in bench.commands.log if e.command == "estop"] == ["alice", "carol"]


async def test_a_viewer_may_not_press_it_nor_reset_it(bench: Bench) -> None:
    bench.commands.roles = ViewerBob()
    res = estop(bench, "bob")
    assert (res.accepted, res.kind) == (False, ResultKind.FORBIDDEN)
    assert res.reason == "bob may not press the e-stop: needs operator access"
    await run_scans(bench.engine, 3)
    assert bench.alarms["estop"].state is AlarmState.NORMAL
    assert bench.db["ch0.state"].value != "faulted"
    assert estop(bench, "alice").accepted
    assert acknowledge_estop(bench, "alice").accepted
    res = estop_reset(bench, "bob")
    assert (res.accepted, res.kind) == (False, ResultKind.FORBIDDEN)
    assert bench.alarms["estop"].tripped
    (refusal,) = [e for e in bench.commands.log if e.actor == "bob" and e.command == "estop"]
    assert refusal.kind is ResultKind.FORBIDDEN  # the refusal is recorded too


async def test_reset_before_acknowledge_is_refused_with_the_reason(bench: Bench) -> None:
    assert estop(bench).accepted
    await run_scans(bench.engine, 3)
    res = estop_reset(bench)
    assert (res.accepted, res.kind) == (False, ResultKind.REFUSED)
    assert res.reason == (
        "e-stop reset refused: acknowledge the e-stop first (alarm estop is unacknowledged:"
        " Software e-stop pressed by alice)"
    )
    await run_scans(bench.engine, 3)
    assert bench.alarms["estop"].state is AlarmState.ACTIVE_UNACKED
    assert all(safe(bench, ch) for ch in CHANNELS)


async def test_acknowledged_then_reset_releases_it_and_energises_nothing(
    bench: Bench, tmp_path: Path
) -> None:
    await busy(bench, tmp_path)
    assert estop(bench).accepted
    await run_scans(bench.engine, 3)
    assert acknowledge_estop(bench, "carol").accepted
    res = estop_reset(bench, "carol")
    assert res.accepted, res.reason
    assert res.reason.startswith("e-stop reset by carol: the software e-stop is released")
    assert bench.alarms["estop"].state is AlarmState.NORMAL
    transitions = [(e.transition, e.actor) for e in bench.alarms.history if e.alarm_id == "estop"]
    assert transitions == [
        (Transition.ACTIVATED, ""),
        (Transition.ACKNOWLEDGED, "carol"),
        (Transition.CLEARED, ""),
        (Transition.RESET, "carol"),
    ]
    await run_scans(bench.engine, 10)
    # Released, the bench does not start again by itself: manual enable stays off, the
    # aborted recipe stays aborted.
    assert bench.db["ch1.enable"].value is False and bench.db["ch1.current_cmd"].value == 0.0
    assert bench.runners["ch0"].state is State.ABORTED
    again = estop_reset(bench)
    assert (again.accepted, again.reason) == (
        False,
        "e-stop reset refused: the e-stop is not pressed: nothing to reset",
    )


async def test_reset_is_refused_while_the_hardware_button_is_still_pressed(bench: Bench) -> None:
    assert bench.sim is not None
    assert estop(bench).accepted
    bench.sim.press_estop(True)
    await run_scans(bench.engine, 10)  # the ADAM polls the sense
    assert bench.alarms["estop"].message == (
        "Emergency stop pressed (e-stop circuit open), and the software e-stop by alice"
    )
    assert acknowledge_estop(bench).accepted
    res = estop_reset(bench)
    assert (res.accepted, res.kind) == (False, ResultKind.REFUSED)
    assert res.reason == (
        "e-stop reset refused: the hardware e-stop is still pressed (e-stop circuit open):"
        " release the button first"
    )
    assert bench.alarms["estop"].tripped
    bench.sim.press_estop(False)
    await run_scans(bench.engine, 10)
    assert bench.alarms["estop"].message == "Software e-stop pressed by alice"
    assert estop_reset(bench).accepted
    assert bench.alarms["estop"].state is AlarmState.NORMAL


async def test_it_takes_no_arguments(bench: Bench) -> None:
    res = bench.commands.execute(Command(Command.estop().target, Verb.ESTOP, {"force": True}))
    assert (res.accepted, res.kind) == (False, ResultKind.BAD_ARGUMENT)
    assert bench.alarms["estop"].state is AlarmState.NORMAL


def test_a_bench_without_an_estop_says_so() -> None:
    from supervisor.commands import CommandPath

    path = CommandPath(TagDB(), VirtualClock())
    res = path.execute(Command.estop("alice"))
    assert (res.accepted, res.kind) == (False, ResultKind.NOT_FOUND)
    assert "this bench has no e-stop (safety.estop in its I/O map)" in res.reason


def test_a_press_opens_the_software_estop_relay_at_once_until_the_reset() -> None:
    clock = VirtualClock()
    alarms = AlarmManager(clock)
    db = TagDB()
    db.add(TagSpec("estop.ok", dtype="bool", initial=True))
    db.add(TagSpec("estop.relay", dtype="bool", initial=True))
    e = Estop(EstopConfig(tag="estop.ok", relay_tag="estop.relay"), db, alarms)
    db.update(db["estop.ok"], True)
    e.evaluate(clock.now(), 0.1)
    assert db["estop.relay"].value is True
    e.press("alice")
    assert db["estop.relay"].value is False  # before any scan
    e.evaluate(clock.now(), 0.1)
    assert db["estop.relay"].value is False
    alarms.acknowledge("estop", "alice")
    e.release("alice")
    e.evaluate(clock.now(), 0.1)
    assert db["estop.relay"].value is True


async def test_the_hardware_button_too_energises_nothing_once_reset(
    bench: Bench, tmp_path: Path
) -> None:
    """The same rule for the button the software e-stop stands beside: a channel driven by
    hand before the press has its enable dropped by the trip, and stays at 0 A once reset
    (before, its enable stayed on and the current came back with the reset)."""
    assert bench.sim is not None
    await busy(bench, tmp_path)
    bench.sim.press_estop(True)
    await run_scans(bench.engine, 10)
    assert safe(bench, "ch1")
    bench.sim.press_estop(False)
    await run_scans(bench.engine, 10)
    assert bench.commands.execute(Command.alarm("estop", Verb.RESET, "alice")).accepted
    await run_scans(bench.engine, 10)
    assert bench.db["ch1.enable"].value is False and bench.db["ch1.current_cmd"].value == 0.0
