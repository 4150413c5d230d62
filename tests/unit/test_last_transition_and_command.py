"""The channel screen's "last transition" and "last command" (issue 33, finding 5): a refused
Start or a manual setpoint no longer replaces why the chain is where it is. The chain's
transitions (a step entered, a state changed, each with its cause) go to
``chN.chain.last_transition``; every operator command on the channel, accepted or refused,
with its actor, to ``chN.chain.last_command``; ``chN.chain.last_event`` keeps both, as
integrators read it.
"""

from __future__ import annotations

from pathlib import Path

from commandrig import recipe, started_bench

from supervisor.commands import Command, Verb
from supervisor.hmi.layout import CHANNEL_TAGS
from supervisor.testing import run_scans


async def test_a_refused_start_is_the_last_command_and_not_the_last_transition(
    tmp_path: Path,
) -> None:
    bench = await started_bench(tmp_path)
    try:
        cmd = bench.commands
        assert cmd.execute(Command.channel("ch0", Verb.START, recipe=recipe(tmp_path))).accepted
        await run_scans(bench.engine, 20)
        db = bench.db
        transition = db["ch0.chain.last_transition"].value
        assert transition == "starting step 1 d (start)"
        refused = cmd.execute(Command.channel("ch0", Verb.START, "hmi:operator"))
        assert not refused.accepted
        await run_scans(bench.engine, 3)
        assert db["ch0.chain.last_transition"].value == transition
        assert db["ch0.chain.last_command"].value == cmd.log[-1].text
        assert str(db["ch0.chain.last_command"].value).startswith("start by hmi:operator: refused")
        assert db["ch0.chain.last_event"].value == cmd.log[-1].text  # as before, for integrators
        # A manual setpoint while the chain drives: a command, refused; the transition stays.
        cmd.execute(Command.write("ch0.manual_current", 500, "hmi:operator"))
        assert "manual_current 500 A by hmi:operator" in str(db["ch0.chain.last_command"].value)
        assert db["ch0.chain.last_transition"].value == transition
        # The chain's next transition is one; the command stays the last command.
        assert cmd.execute(Command.channel("ch0", Verb.HOLD, "hmi:operator")).accepted
        await run_scans(bench.engine, 3)
        # An acting state's end keeps the cause that began it (not "Holding → Held (done)").
        assert db["ch0.chain.last_transition"].value == (
            "Running → Holding → Held (hold by hmi:operator)"
        )
        assert str(db["ch0.chain.last_command"].value).startswith("hold by hmi:operator: accepted")
    finally:
        await bench.shutdown()


def test_the_screen_s_layout_names_both_tags() -> None:
    assert CHANNEL_TAGS["last_transition"] == "chain.last_transition"
    assert CHANNEL_TAGS["last_command"] == "chain.last_command"
