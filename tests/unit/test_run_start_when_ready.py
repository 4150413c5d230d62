"""``supervisor run --recipe CH=FILE --start``: the recipes are loaded before anything is
served, and each test starts once the inputs its channel's guard checks read GOOD. Started
at the first scan, the EA channel of the load bench tripped on a busy machine (Held, "BMS
value bms.cell_max is BAD (initial value)"): its BMS had not sent its first frames yet."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field

import pytest

from supervisor.app import service
from supervisor.commands import Command, Result


@dataclass
class FakeGuard:
    missing: list[str]

    def inputs_not_good(self) -> list[str]:
        return list(self.missing)


@dataclass
class FakeCommands:
    done: list[Command] = field(default_factory=list)

    async def execute_async(self, command: Command) -> Result:
        self.done.append(command)
        return Result.ok("started")


@dataclass
class FakeSafety:
    guards: dict[str, FakeGuard]


@dataclass
class FakeBench:
    safety: FakeSafety
    commands: FakeCommands = field(default_factory=FakeCommands)


def started(bench: FakeBench) -> list[str]:
    return [str(c.target.name) for c in bench.commands.done]


async def test_a_test_starts_once_its_channels_inputs_read_good_and_not_before() -> None:
    bms = FakeGuard(["bms.cell_max BAD (initial value)"])
    bench = FakeBench(FakeSafety({"ch0": FakeGuard([]), "ch12": bms}))
    task = asyncio.create_task(service.start_when_ready(bench, ["ch0", "ch12"]))  # type: ignore[arg-type]
    await asyncio.sleep(0.2)
    assert started(bench) == ["ch0"]  # ch12 waits for its BMS
    bms.missing = []  # the first frames came
    await asyncio.wait_for(task, 5.0)
    assert started(bench) == ["ch0", "ch12"]
    assert all(c.verb.value == "start" and c.actor == "command line" for c in bench.commands.done)


async def test_a_channel_whose_inputs_never_read_good_is_not_started_and_says_why(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(service, "START_WAIT_S", 0.2)
    bench = FakeBench(FakeSafety({"ch12": FakeGuard(["bms.cell_max BAD (initial value)"])}))
    with caplog.at_level(logging.ERROR):
        await asyncio.wait_for(service.start_when_ready(bench, ["ch12"]), 5.0)  # type: ignore[arg-type]
    assert started(bench) == []
    assert (
        "--start ch12: start refused: its inputs do not read GOOD 0.2 s after the scan began:"
        " bms.cell_max BAD (initial value)" in caplog.text
    )
