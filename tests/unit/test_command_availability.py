"""What a channel's command bar may give now (issue 33, finding 2): ``CommandPath.available``
answers, for every button of the bar (``CHANNEL_BAR``, and force), what ``execute`` would
answer — the same verdict, the same kind and, for a refusal, the same words — without
executing anything.

Proven equal to the command path itself, not to a list of examples: in every state of the
chain's table (the acting states too, caught before the next scan takes them on), in Auto
and Manual, driven and not, with every kind of interlock (a trip whose cause is present,
gone but unacknowledged, acknowledged but not reset; the chain's latched alarm), each
button is asked ahead, then given on a fresh bench in the same situation; the role, the
first check, for every role in a few of them. A last case checks that the situations do
reach every state and both answers of every button.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from commandrig import DISCHARGE, SUPERVISED, recipe, started_bench

from supervisor.app import Bench
from supervisor.chains.states import State
from supervisor.commands import Command, Result, ResultKind, Target, Verb
from supervisor.commands.model import CHANNEL_BAR
from supervisor.tags import Access
from supervisor.testing import run_scans

SHORT = "recipe: q\nsteps:\n  - {id: r, rest: 1 s}\n"
FORCEABLE = "room.temp"  # a thermocouple no safety rule reads: commissioning may force it


ACCESS = {"viewer": Access.READ_ONLY, "operator": Access.OPERATOR, "engineer": Access.ENGINEER}


class ByName:
    """Roles by the actor's name: ``viewer``, ``operator``, ``engineer``."""

    def access_of(self, actor: str) -> Access:
        return ACCESS[actor]

    def refuses(self, command: Command) -> str:
        return f"viewer may not {command.verb.value}" if command.actor == "viewer" else ""


def run(bench: Bench, verb: Verb, **args: Any) -> Result:
    result = bench.commands.execute(Command.channel("ch0", verb, **args))
    assert result.accepted, result
    return result


async def loaded(b: Bench, tmp: Path, text: str = DISCHARGE) -> None:
    run(b, Verb.LOAD, recipe=recipe(tmp, text))


async def running(b: Bench, tmp: Path, text: str = DISCHARGE) -> None:
    run(b, Verb.START, recipe=recipe(tmp, text))
    await run_scans(b.engine, 20)


async def then(b: Bench, verb: Verb, scans: int, **args: Any) -> None:
    run(b, verb, **args)
    await run_scans(b.engine, scans)


async def estop(b: Bench, pressed: bool) -> None:
    assert b.sim is not None
    b.sim.press_estop(pressed)
    await run_scans(b.engine, 10)  # the ADAM polls the sense every 0.2 s


Situation = Callable[[Bench, Path], Awaitable[None]]


async def nothing(b: Bench, tmp: Path) -> None:
    return None


async def idle_loaded(b: Bench, tmp: Path) -> None:
    await loaded(b, tmp)


async def holding(b: Bench, tmp: Path) -> None:
    await running(b, tmp)
    await then(b, Verb.HOLD, 0)


async def held(b: Bench, tmp: Path) -> None:
    await running(b, tmp)
    await then(b, Verb.HOLD, 3)


async def resuming(b: Bench, tmp: Path) -> None:
    await held(b, tmp)
    await then(b, Verb.RESUME, 0)


async def held_in_manual(b: Bench, tmp: Path) -> None:
    await running(b, tmp)
    await then(b, Verb.MODE, 3, value="manual")


async def held_driven_in_manual(b: Bench, tmp: Path) -> None:
    await held_in_manual(b, tmp)
    await then(b, Verb.ENABLE, 3, value=True)


async def stopping(b: Bench, tmp: Path) -> None:
    await running(b, tmp)
    await then(b, Verb.STOP, 0)


async def stopped(b: Bench, tmp: Path) -> None:
    await running(b, tmp)
    await then(b, Verb.STOP, 3)


async def aborting(b: Bench, tmp: Path) -> None:
    await running(b, tmp)
    await then(b, Verb.ABORT, 0)


async def aborted(b: Bench, tmp: Path) -> None:
    await running(b, tmp)
    await then(b, Verb.ABORT, 3)


async def complete(b: Bench, tmp: Path) -> None:
    await running(b, tmp, SHORT)


async def driven_in_manual(b: Bench, tmp: Path) -> None:
    await loaded(b, tmp)
    await then(b, Verb.ENABLE, 3, value=True)


async def in_auto_idle(b: Bench, tmp: Path) -> None:
    await loaded(b, tmp)
    await then(b, Verb.MODE, 3, value="auto")


async def trip_cause_present(b: Bench, tmp: Path) -> None:
    await loaded(b, tmp)
    await estop(b, True)


async def trip_cause_gone(b: Bench, tmp: Path) -> None:
    await trip_cause_present(b, tmp)
    await estop(b, False)


async def trip_acknowledged(b: Bench, tmp: Path) -> None:
    await trip_cause_gone(b, tmp)
    assert b.commands.execute(Command.alarm("estop", Verb.ACKNOWLEDGE)).accepted


async def running_tripped(b: Bench, tmp: Path) -> None:
    await running(b, tmp)
    await estop(b, True)


async def chain_alarm(b: Bench, tmp: Path) -> None:
    await running(b, tmp, SUPERVISED)
    await run_scans(b.engine, 100)  # past the step's max_time: the chain latches its alarm


SITUATIONS: dict[str, Situation] = {
    f.__name__: f
    for f in (
        nothing,
        idle_loaded,
        running,
        holding,
        held,
        resuming,
        held_in_manual,
        held_driven_in_manual,
        stopping,
        stopped,
        aborting,
        aborted,
        complete,
        driven_in_manual,
        in_auto_idle,
        trip_cause_present,
        trip_cause_gone,
        trip_acknowledged,
        running_tripped,
        chain_alarm,
    )
}
ACTORS = ("viewer", "operator", "engineer")
ROLE_SITUATIONS = ("nothing", "running", "trip_cause_present", "stopped")
BUTTONS = (*(key for key, _, _ in CHANNEL_BAR), "force")


def given(key: str, actor: str, tmp: Path) -> Command:
    """The command the button ``key`` gives, with the arguments an operator fills in."""
    if key == "force":
        return Command.force(FORCEABLE, "21.5", actor)
    _, verb, args = next(b for b in CHANNEL_BAR if b[0] == key)
    full = dict(args)
    if verb is Verb.LOAD:
        full["recipe"] = recipe(tmp, DISCHARGE, "other.yaml")
    elif verb is Verb.MANUAL_CURRENT:
        full["value"] = 0.1
    return Command(Target.channel("ch0"), verb, full, actor)


def verdict(r: Result) -> tuple[bool, ResultKind, str]:
    return (r.accepted, r.kind, "" if r.accepted else r.reason)


async def situation_at(tmp: Path, name: str) -> Bench:
    bench = await started_bench(tmp)
    bench.commands.roles = ByName()
    await SITUATIONS[name](bench, tmp)
    return bench


@pytest.mark.parametrize("name", list(SITUATIONS))
async def test_each_button_is_answered_ahead_as_the_command_path_answers_it(
    tmp_path: Path, name: str
) -> None:
    # The role is the first check, whatever the state: the other roles in a few states.
    actors = ACTORS if name in ROLE_SITUATIONS else ("operator",)
    for actor in actors:
        for key in BUTTONS:
            folder = tmp_path / f"{actor}-{key}"
            folder.mkdir()
            bench = await situation_at(folder, name)
            try:
                ahead = bench.commands.available("ch0", actor)
                assert set(ahead) == set(BUTTONS)
                command = given(key, actor, folder)
                checked = bench.commands.check(command)
                done = bench.commands.execute(command)
                assert verdict(checked) == verdict(done), (name, actor, key)
                # The bar's button (no tag to force yet: its refusal names none).
                button = verdict(ahead[key])
                if key == "force":
                    button = (*button[:2], button[2].replace("force:", f"force {FORCEABLE}:"))
                assert button == verdict(done), (name, actor, key)
            finally:
                await bench.shutdown()


async def test_the_situations_cover_every_state_and_both_answers_of_every_button(
    tmp_path: Path,
) -> None:
    states: set[State] = set()
    answers: dict[str, set[bool]] = {key: set() for key in BUTTONS}
    for name in SITUATIONS:
        for actor in ("operator", "engineer"):
            folder = tmp_path / f"{name}-{actor}"
            folder.mkdir()
            bench = await situation_at(folder, name)
            try:
                states.add(bench.runners["ch0"].state)
                for key, r in bench.commands.available("ch0", actor).items():
                    answers[key].add(r.accepted)
            finally:
                await bench.shutdown()
    assert states == set(State)
    # Switching to manual is never refused to an operator (a running chain is held first).
    always = {"mode_manual"}
    assert {k for k, a in answers.items() if a != {True, False}} == always, answers


async def test_the_answer_ahead_changes_nothing_and_records_nothing(tmp_path: Path) -> None:
    bench = await situation_at(tmp_path, "running")
    try:
        before = (len(bench.commands.log), bench.runners["ch0"].state, bench.db.version)
        for actor in ACTORS:
            bench.commands.available("ch0", actor)
        assert (len(bench.commands.log), bench.runners["ch0"].state, bench.db.version) == before
    finally:
        await bench.shutdown()


async def test_running_start_and_resume_are_refused_ahead_with_the_state_table_s_words(
    tmp_path: Path,
) -> None:
    bench = await situation_at(tmp_path, "running")
    try:
        ahead = bench.commands.available("ch0", "operator")
        assert not ahead["start"].accepted and not ahead["resume"].accepted
        assert ahead["start"].reason == (
            "ch0: start is not allowed while Running (allowed: hold, advance, stop, abort)"
        )
        assert [k for k, r in ahead.items() if r.accepted] == [
            "hold",
            "advance",
            "stop",
            "abort",
            "acknowledge",
            "mode_auto",
            "mode_manual",
        ]
    finally:
        await bench.shutdown()
