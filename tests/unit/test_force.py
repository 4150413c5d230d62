"""Forcing tags through the one command path, as a specification: engineers only, recorded
with the actor, the value read as the tag's type and checked against its range, and never
a tag the e-stop or a channel's guard reads (a force must never defeat the e-stop).

The commandrig bench (four Chadèche channels, the ADAM with the e-stop sense on
``estop.ok``), virtual clock, every device in process.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from commandrig import started_bench

from supervisor.app import Bench
from supervisor.commands import Command, Result, ResultKind, Verb
from supervisor.core.quality import Quality, Reason
from supervisor.tags import Access
from supervisor.testing import run_scans


class EngineerRoles:
    """ "engineer" has engineer access; everyone else operates (the default hook)."""

    def access_of(self, actor: str) -> Access:
        return Access.ENGINEER if actor == "engineer" else Access.OPERATOR

    def refuses(self, command: Command) -> str:
        return ""


@pytest.fixture
async def bench(tmp_path: Path) -> AsyncIterator[Bench]:
    b = await started_bench(tmp_path)
    b.commands.roles = EngineerRoles()
    try:
        yield b
    finally:
        await b.shutdown()


def force(bench: Bench, tag: str, value: object, actor: str = "engineer") -> Result:
    return bench.commands.execute(Command.force(tag, value, actor))


def unforce(bench: Bench, tag: str, actor: str = "engineer") -> Result:
    return bench.commands.execute(Command.unforce(tag, actor))


async def test_an_engineer_forces_a_tag_and_the_process_no_longer_moves_it(bench: Bench) -> None:
    r = force(bench, "room.temp", "31.5")  # a text, read as the tag's type
    assert r.accepted, r.reason
    assert r.reason == "room.temp forced := 31.5 (until unforced)"
    tag = bench.db["room.temp"]
    await run_scans(bench.engine, 5)  # the ADAM keeps reading 25 degC
    assert (tag.value, tag.quality, tag.reason, tag.forced) == (
        31.5,
        Quality.GOOD,
        Reason.FORCED,
        True,
    )
    ev = bench.commands.log[-1]
    assert (ev.actor, ev.command, ev.accepted) == ("engineer", "force room.temp := '31.5'", True)


async def test_unforce_hands_the_tag_back_to_the_process(bench: Bench) -> None:
    assert force(bench, "room.temp", 31.5).accepted
    r = unforce(bench, "room.temp")
    assert r.accepted and "unforced" in r.reason
    tag = bench.db["room.temp"]
    assert not tag.forced
    await run_scans(bench.engine, 5)
    assert tag.reason is not Reason.FORCED and tag.value != 31.5
    assert unforce(bench, "room.temp").reason == "room.temp was not forced"
    assert bench.commands.log[-1].command == "unforce room.temp"


async def test_an_operator_may_not_force_or_unforce(bench: Bench) -> None:
    for r in (force(bench, "room.temp", 1.0, "operator"), unforce(bench, "room.temp", "operator")):
        assert not r.accepted and r.kind is ResultKind.FORBIDDEN
        assert "needs engineer access" in r.reason
    assert not bench.db["room.temp"].forced
    assert bench.commands.log[-1].actor == "operator"


async def test_the_estop_sense_can_never_be_forced(bench: Bench) -> None:
    assert bench.sim is not None
    bench.sim.press_estop(True)
    await run_scans(bench.engine, 10)
    r = force(bench, "estop.ok", True)
    assert not r.accepted and r.kind is ResultKind.REFUSED
    assert r.reason == (
        "estop.ok cannot be forced: the e-stop reads it (circuit closed = true)"
        " (a force never overrides the safety phase)"
    )
    await run_scans(bench.engine, 5)
    assert bench.alarms is not None and bench.alarms["estop"].tripped  # still tripped


@pytest.mark.parametrize(
    ("tag", "why"),
    [
        ("ch0.voltage", "channel ch0's guard reads it against the hard voltage limits"),
        ("ch0.current", "channel ch0's guard reads it"),
        ("ch1.enable", "channel ch1's guard: dropped by a trip"),
        ("ch2.limit.charge_a", "channel ch2's guard: the charge current the guard allows"),
        ("ch0.fault", "channel ch0's guard: the channel's first-out trip"),
    ],
)
async def test_what_a_channel_guard_reads_or_drives_can_never_be_forced(
    bench: Bench, tag: str, why: str
) -> None:
    r = force(bench, tag, 0 if tag != "ch0.fault" else "")
    assert not r.accepted and r.kind is ResultKind.REFUSED
    assert r.reason.startswith(f"{tag} cannot be forced: {why}")
    assert not bench.db[tag].forced


async def test_a_channel_command_tag_is_commanded_not_forced(bench: Bench) -> None:
    r = force(bench, "ch0.mode", "auto")
    assert not r.accepted and r.kind is ResultKind.REFUSED
    assert "a command tag of ch0 (give the command)" in r.reason


async def test_a_forced_value_is_checked_like_a_write(bench: Bench) -> None:
    r = force(bench, "room.temp", "warm")
    assert r.kind is ResultKind.BAD_ARGUMENT
    assert r.reason == "room.temp: expected a number, got 'warm'"
    assert force(bench, "nope.tag", 1.0).kind is ResultKind.NOT_FOUND
    assert force(bench, "room.temp", float("nan")).kind is ResultKind.BAD_ARGUMENT
    r = bench.commands.execute(Command(Command.force("room.temp", 1).target, Verb.FORCE, {}))
    assert r.kind is ResultKind.BAD_ARGUMENT
