"""The tags of a channel's step chain (``chN.chain.*`` and ``chN.command``): what it shows
to screens, OPC UA, the historian and the result files."""

from __future__ import annotations

from supervisor.chains.states import COMMANDS, OPCUA_CODE, State
from supervisor.tags import Access, TagDB, TagSpec
from supervisor.tags.spec import HistorySettings

CLOCK_HISTORY = HistorySettings(min_interval_s=1.0)
"""The chain's clocks and what follows from them (step and test time, progress, ETA) change
every scan, linearly: the historian and InfluxDB store them at most once a second (the
latest value at its own time). At a 10 ms scan they were half of every scan's changes (64
of 130 in issue 13's load case), 64 points a second of straight lines; screens and OPC UA
still see every scan's value."""

CHAIN_FIELDS = (
    "state",
    "state_code",
    "recipe",
    "test_id",
    "step",
    "step_index",
    "cycle",
    "step_time",
    "test_time",
    "alarm",
    "interlock",
    "last_event",
    "last_transition",
    "last_command",
    "progress",
    "eta_s",
    "internal_resistance",
    "charge_ah",
)


def _last_event_split(n: str) -> tuple[TagSpec, ...]:
    """The last event split by what it is (issue 33, finding 5; ADR 0039): a refused command
    must not hide why the chain went where it is."""
    return (
        TagSpec(
            f"{n}.chain.last_transition",
            dtype="str",
            initial="",
            description="The chain's last step or state transition, with its cause",
        ),
        TagSpec(
            f"{n}.chain.last_command",
            dtype="str",
            initial="",
            description="The last operator command on the channel, accepted or refused, by whom",
        ),
    )


def add_chain_tags(db: TagDB, n: str) -> None:
    """Add channel ``n``'s chain tags to ``db``, each at its initial value."""
    db.add(
        TagSpec(
            f"{n}.command",
            dtype="str",
            access=Access.OPERATOR,
            initial="",
            choices=("", *COMMANDS),
            description="start/hold/resume/advance/stop/abort/reset/ack",
        )
    )
    for spec in (
        TagSpec(f"{n}.chain.state", dtype="str", initial=State.IDLE.value),
        TagSpec(f"{n}.chain.state_code", dtype="int", initial=OPCUA_CODE[State.IDLE]),
        TagSpec(f"{n}.chain.recipe", dtype="str", initial=""),
        TagSpec(f"{n}.chain.test_id", dtype="str", initial=""),
        TagSpec(
            f"{n}.chain.cell_id",
            dtype="str",
            initial="",
            description="The cell (or sample) of the test (its metadata; '' when not given)",
        ),
        TagSpec(f"{n}.chain.step", dtype="str", initial=""),
        TagSpec(f"{n}.chain.step_index", dtype="int", initial=0),
        TagSpec(f"{n}.chain.cycle", dtype="int", initial=0),
        TagSpec(f"{n}.chain.step_time", unit="s", initial=0.0, history=CLOCK_HISTORY),
        TagSpec(f"{n}.chain.test_time", unit="s", initial=0.0, history=CLOCK_HISTORY),
        TagSpec(f"{n}.chain.alarm", dtype="str", initial=""),
        TagSpec(f"{n}.chain.interlock", dtype="str", initial=""),
        TagSpec(f"{n}.chain.last_event", dtype="str", initial=""),
        *_last_event_split(n),
        TagSpec(f"{n}.chain.progress", unit="1", initial=0.0, history=CLOCK_HISTORY),
        TagSpec(f"{n}.chain.eta_s", unit="s", initial=None, history=CLOCK_HISTORY),
        TagSpec(f"{n}.chain.internal_resistance", unit="ohm", initial=None),
        # The test's charge (docs/integrator.md "Tags"): what the ``charge`` condition tests.
        TagSpec(
            f"{n}.chain.charge_ah",
            unit="Ah",
            initial=None,
            description=(
                "The test's charge: the recipe's initial_charge plus the net charge"
                " since the start (what a step's `charge` condition tests); none before"
                " a recipe is loaded, the final figure kept after the end"
            ),
            history=CLOCK_HISTORY,
        ),
    ):
        db.add(spec)
    for t in db:
        if t.name.startswith(f"{n}.chain.") or t.name == f"{n}.command":
            db.update(t, t.spec.initial)
