"""The chain's state table, as a specification: every state × every command.

Run on the table and its guards directly (``supervisor.chains.states``), no bench.
"""

from __future__ import annotations

import itertools

import pytest

from supervisor.chains.states import (
    ALWAYS_ALLOWED,
    AUTO_NEXT,
    COMMANDS,
    OPCUA_CODE,
    TABLE,
    Situation,
    State,
    check_load,
    decide,
)
from supervisor.core.errors import OperatorError

S = State
READY = Situation(has_program=True)  # every guard satisfied
TROUBLED = Situation(has_program=True, channel_fault="voltage input BAD", alarm="limit: x")

# from state    command    → next state (every other pair, but ack, is refused)
TRANSITIONS = [
    (S.IDLE, "start", S.RUNNING),
    (S.RUNNING, "hold", S.HOLDING),
    (S.RUNNING, "advance", S.RUNNING),
    (S.RUNNING, "stop", S.STOPPING),
    (S.RUNNING, "abort", S.ABORTING),
    (S.HOLDING, "stop", S.STOPPING),
    (S.HOLDING, "abort", S.ABORTING),
    (S.HELD, "resume", S.RESUMING),
    (S.HELD, "stop", S.STOPPING),
    (S.HELD, "abort", S.ABORTING),
    (S.RESUMING, "hold", S.HOLDING),
    (S.RESUMING, "stop", S.STOPPING),
    (S.RESUMING, "abort", S.ABORTING),
    (S.STOPPING, "abort", S.ABORTING),
    (S.STOPPED, "reset", S.IDLE),
    (S.ABORTED, "reset", S.IDLE),
    (S.COMPLETE, "reset", S.IDLE),
]
# What a refusal lists as allowed, per state (the table's order).
ALLOWED = {
    S.IDLE: "start",
    S.RUNNING: "hold, advance, stop, abort",
    S.HOLDING: "stop, abort",
    S.HELD: "resume, stop, abort",
    S.RESUMING: "hold, stop, abort",
    S.STOPPING: "abort",
    S.STOPPED: "reset",
    S.ABORTING: "none",
    S.ABORTED: "reset",
    S.COMPLETE: "reset",
}
ACCEPTED = {(s, c) for s, c, _ in TRANSITIONS}
REFUSED = [
    (s, c)
    for s, c in itertools.product(State, COMMANDS)
    if (s, c) not in ACCEPTED and c not in ALWAYS_ALLOWED
]


def _ids(cases: list[tuple[State, str, State]]) -> list[str]:
    return [f"{s.value} --{c}--> {n.value}" for s, c, n in cases]


@pytest.mark.parametrize(("state", "command", "next_state"), TRANSITIONS, ids=_ids(TRANSITIONS))
def test_a_command_the_table_allows_leads_to_its_next_state(
    state: State, command: str, next_state: State
) -> None:
    assert decide("ch0", state, command, READY) is next_state


@pytest.mark.parametrize(
    ("state", "command"), REFUSED, ids=[f"{s.value} refuses {c}" for s, c in REFUSED]
)
def test_any_other_command_is_refused_with_what_is_allowed(state: State, command: str) -> None:
    with pytest.raises(OperatorError) as info:
        decide("ch0", state, command, READY)
    assert str(info.value) == (
        f"ch0: {command} is not allowed while {state.value} (allowed: {ALLOWED[state]})"
    )


def test_every_state_and_command_pair_is_specified() -> None:
    pairs = {(s, c) for s, c in itertools.product(State, COMMANDS)}
    acks = {(s, c) for s, c in pairs if c in ALWAYS_ALLOWED}
    assert ACCEPTED | set(REFUSED) | acks == pairs
    assert len(TRANSITIONS) + len(REFUSED) + len(acks) == len(State) * len(COMMANDS)


def test_the_table_the_hmi_draws_is_the_specification() -> None:
    spec: dict[State, dict[str, State]] = {s: {} for s in State}
    for s, c, nxt in TRANSITIONS:
        spec[s][c] = nxt
    assert spec == TABLE


@pytest.mark.parametrize("state", list(State), ids=str)
@pytest.mark.parametrize("situation", [READY, TROUBLED], ids=["ready", "fault and alarm"])
def test_ack_is_accepted_in_every_state_and_changes_no_state(
    state: State, situation: Situation
) -> None:
    assert decide("ch0", state, "ack", situation) is state


def test_an_unknown_command_is_refused_with_the_list_of_commands() -> None:
    with pytest.raises(OperatorError) as info:
        decide("ch0", S.RUNNING, "jump", READY)
    assert str(info.value) == (
        "ch0: unknown command 'jump' (start, hold, resume, advance, stop, abort, reset, ack)"
    )


# --- guards ---------------------------------------------------------------------------
def test_start_needs_a_loaded_recipe() -> None:
    with pytest.raises(OperatorError, match=r"^ch0: no recipe loaded$"):
        decide("ch0", S.IDLE, "start", Situation(has_program=False))


def test_start_needs_no_channel_fault() -> None:
    with pytest.raises(OperatorError, match=r"^ch0: channel fault must be acknowledged first$"):
        decide("ch0", S.IDLE, "start", Situation(has_program=True, channel_fault="tripped"))


def test_start_is_checked_against_the_table_before_its_guards() -> None:
    with pytest.raises(OperatorError, match="start is not allowed while Running"):
        decide("ch0", S.RUNNING, "start", Situation(has_program=False))


def test_resume_needs_the_latched_alarm_acknowledged_and_names_it() -> None:
    with pytest.raises(
        OperatorError, match=r"^ch0: acknowledge the alarm first \(limit: voltage above\)$"
    ):
        decide("ch0", S.HELD, "resume", Situation(True, alarm="limit: voltage above"))


def test_resume_needs_no_channel_fault() -> None:
    with pytest.raises(OperatorError, match=r"^ch0: channel fault must be acknowledged first$"):
        decide("ch0", S.HELD, "resume", Situation(True, channel_fault="tripped"))


def test_resume_names_the_alarm_before_the_channel_fault() -> None:
    with pytest.raises(OperatorError, match="acknowledge the alarm first"):
        decide("ch0", S.HELD, "resume", TROUBLED)


UNGUARDED = [t for t in TRANSITIONS if t[1] not in ("start", "resume")]


@pytest.mark.parametrize(("state", "command", "next_state"), UNGUARDED, ids=_ids(UNGUARDED))
def test_a_fault_or_an_alarm_never_blocks_the_other_commands(
    state: State, command: str, next_state: State
) -> None:
    assert decide("ch0", state, command, TROUBLED) is next_state


# --- acting states, codes, loading -------------------------------------------------------
def test_each_acting_state_finishes_into_its_wait_state() -> None:
    assert AUTO_NEXT == {
        S.HOLDING: S.HELD,
        S.RESUMING: S.RUNNING,
        S.STOPPING: S.STOPPED,
        S.ABORTING: S.ABORTED,
    }


def test_state_codes_are_the_opc_ua_state_enumeration() -> None:
    # OPC UA TMC StateEnumeration: Running is Execute, Resuming is Unholding.
    assert {s.value: OPCUA_CODE[s] for s in State} == {
        "Stopped": 0,
        "Idle": 2,
        "Running": 4,
        "Complete": 6,
        "Aborting": 7,
        "Aborted": 8,
        "Stopping": 9,
        "Holding": 14,
        "Held": 15,
        "Resuming": 16,
    }


LOADABLE = [S.IDLE, S.COMPLETE, S.STOPPED, S.ABORTED]


@pytest.mark.parametrize("state", LOADABLE, ids=str)
def test_a_recipe_loads_when_no_test_is_under_way(state: State) -> None:
    check_load("ch0", state)


# What ends the test under way in each state, as the refusal says it (a channel that came
# back Held after a restart is refused a load at start-up: the message says what to do).
WAY_OUT = {
    S.RUNNING: "stop or abort it first",
    S.HOLDING: "stop or abort it first",
    S.HELD: "resume it, or stop or abort it first",
    S.RESUMING: "stop or abort it first",
    S.STOPPING: "wait for it to stop",
    S.ABORTING: "wait for it to abort",
}


@pytest.mark.parametrize("state", [s for s in State if s not in LOADABLE], ids=str)
def test_a_recipe_is_refused_while_a_test_is_under_way_saying_how_to_end_it(
    state: State,
) -> None:
    text = f"ch0: cannot load a recipe while {state.value}: a test is under way: {WAY_OUT[state]}"
    with pytest.raises(OperatorError) as err:
        check_load("ch0", state)
    assert str(err.value) == text
