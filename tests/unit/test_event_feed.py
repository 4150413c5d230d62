"""The bench's one event feed: chain steps, alarm transitions and operator commands reach
every sink in one shape, with the channel, the test and the actor.

A virtual-clock bench with every device in process; the sink only records.
"""

from __future__ import annotations

from pathlib import Path

from commandrig import DISCHARGE, recipe

from supervisor.app import Bench
from supervisor.app.events import EventFeed
from supervisor.commands import Command, Verb
from supervisor.core.records import BenchEvent
from supervisor.testing import run_scans


class Recorder:
    def __init__(self) -> None:
        self.events: list[BenchEvent] = []

    def on_event(self, event: BenchEvent) -> None:
        self.events.append(event)


class Broken:
    def on_event(self, event: BenchEvent) -> None:
        raise RuntimeError("a publisher's bug")


async def test_commands_steps_and_alarms_arrive_in_one_shape_with_test_and_actor(
    bench: Bench, tmp_path: Path
) -> None:
    feed, rec = EventFeed(), Recorder()
    feed.sinks += [Broken(), rec]  # a failing sink does not starve the next one
    feed.attach(bench)

    start = Command.channel("ch0", Verb.START, "alice", recipe=recipe(tmp_path, DISCHARGE))
    assert bench.commands.execute(start).accepted
    await run_scans(bench.engine, 20)
    test_id = bench.runners["ch0"].test_id
    assert bench.sim is not None
    bench.sim.press_estop(True)
    await run_scans(bench.engine, 10)

    kinds = {e.kind for e in rec.events}
    assert {"command", "step", "alarm"} <= kinds, kinds
    command = next(e for e in rec.events if e.kind == "command")
    assert (command.channel, command.actor) == ("ch0", "alice")
    step = next(e for e in rec.events if e.kind == "step")
    assert (step.channel, step.actor, step.test_id) == ("ch0", "recipe", test_id)
    assert step.source, "a step event names its step id"
    alarm = next(e for e in rec.events if e.kind == "alarm")
    assert alarm.severity > 0 and "estop" in alarm.source.lower()
    assert all(e.wall > 1e9 for e in rec.events), "wall time in Unix seconds"
