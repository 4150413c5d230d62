"""The chain's ISA-88 state model: states, their OPC UA codes, the command table, guards.

Everything here is data or a pure function of it, so the HMI can draw the diagram from
``TABLE`` and the tests can check every state × command without running a chain.

State model (OPC UA ``StateEnumeration`` numbers in ``chN.chain.state_code``)::

    Idle --start--> Running --hold--> Holding --> Held --resume--> Resuming --> Running
    Running --stop--> Stopping --> Stopped --reset--> Idle
    any active --abort--> Aborting --> Aborted --reset--> Idle
    Running --(last step / end)--> Complete --reset--> Idle

``ack`` is accepted in every state (it acknowledges a latched alarm, ISA-18.2) and does
not change the state; ``advance`` is accepted while Running and stays Running (the
operator's CTRL-Z of seed 000, acted on by the next scan).

Auto and Manual (docs/design.md "Recipes"): a mode change is an explicit command, never a side
effect. A channel the operator drives in Manual (enable on) is not taken from them by a
``start`` or a load: they turn enable off first. A test held in Manual resumes only once
the channel is handed back to its chain (mode auto).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from supervisor.core.errors import OperatorError


class State(StrEnum):
    IDLE = "Idle"
    RUNNING = "Running"
    HOLDING = "Holding"
    HELD = "Held"
    RESUMING = "Resuming"
    STOPPING = "Stopping"
    STOPPED = "Stopped"
    ABORTING = "Aborting"
    ABORTED = "Aborted"
    COMPLETE = "Complete"


# OPC UA Part 10 / PackML StateEnumeration numbering (docs/integrator.md "Tags";
# reference/semantics.md: "pick the OPC UA one"). Running is Execute, Resuming Unholding.
OPCUA_CODE = {
    State.STOPPED: 0,
    State.IDLE: 2,
    State.RUNNING: 4,
    State.COMPLETE: 6,
    State.ABORTING: 7,
    State.ABORTED: 8,
    State.STOPPING: 9,
    State.HOLDING: 14,
    State.HELD: 15,
    State.RESUMING: 16,
}

COMMANDS = ("start", "hold", "resume", "advance", "stop", "abort", "reset", "ack")
ALWAYS_ALLOWED = ("ack",)  # not in the table: it changes no state

# {state: {command: next state}} — the HMI can draw its diagram from this table.
TABLE: dict[State, dict[str, State]] = {
    State.IDLE: {"start": State.RUNNING},
    State.RUNNING: {
        "hold": State.HOLDING,
        "advance": State.RUNNING,
        "stop": State.STOPPING,
        "abort": State.ABORTING,
    },
    State.HOLDING: {"stop": State.STOPPING, "abort": State.ABORTING},
    State.HELD: {"resume": State.RESUMING, "stop": State.STOPPING, "abort": State.ABORTING},
    State.RESUMING: {"hold": State.HOLDING, "stop": State.STOPPING, "abort": State.ABORTING},
    State.STOPPING: {"abort": State.ABORTING},
    State.STOPPED: {"reset": State.IDLE},
    State.ABORTING: {},
    State.ABORTED: {"reset": State.IDLE},
    State.COMPLETE: {"reset": State.IDLE},
}
# Acting states (ISA-88 "…ing") finish in one scan.
AUTO_NEXT = {
    State.HOLDING: State.HELD,
    State.RESUMING: State.RUNNING,
    State.STOPPING: State.STOPPED,
    State.ABORTING: State.ABORTED,
}
ENERGISED = (State.RUNNING,)  # the only state in which the chain asks for current
ACTIVE = (State.RUNNING, State.HOLDING, State.HELD, State.RESUMING)  # a test is under way
FINAL = (State.COMPLETE, State.STOPPED, State.ABORTED)
LOADABLE = (State.IDLE, *FINAL)
MANUAL_DRIVEN = "the channel is driven in manual (enable on): turn enable off first"
# What ends the test under way, for a refused load: a test held after a restart comes back
# Held, and the operator who asked for another recipe at start-up needs the way out.
_WAY_OUT = {
    State.HELD: "resume it, or stop or abort it first",
    State.STOPPING: "wait for it to stop",
    State.ABORTING: "wait for it to abort",
}


@dataclass(frozen=True, slots=True)
class Situation:
    """What the command guards look at besides the state."""

    has_program: bool = False
    channel_fault: str = ""  # the channel's latched trip ("" when none)
    alarm: str | None = None  # the chain's latched alarm text (None when none)
    in_manual: bool = False  # the channel is in Manual mode (operator setpoints)
    manual_enabled: bool = False  # ... and the operator's enable is on


def decide(channel: str, state: State, command: str, situation: Situation) -> State:
    """The state ``command`` leads to from ``state``, or an ``OperatorError`` saying why
    not (and, for a command the table refuses, what is allowed)."""
    if command not in COMMANDS:
        raise OperatorError(f"{channel}: unknown command {command!r} ({', '.join(COMMANDS)})")
    if command in ALWAYS_ALLOWED:
        return state
    allowed = TABLE[state]
    if command not in allowed:
        ok = ", ".join(allowed) or "none"
        raise OperatorError(
            f"{channel}: {command} is not allowed while {state.value} (allowed: {ok})"
        )
    if command == "start":
        if not situation.has_program:
            raise OperatorError(f"{channel}: no recipe loaded")
        _no_fault(channel, situation)
        if situation.in_manual and situation.manual_enabled:
            raise OperatorError(f"{channel}: cannot start while {MANUAL_DRIVEN}")
    elif command == "resume":
        # ISA-18.2 / S7-GRAPH: a latched alarm is acknowledged before running again.
        if situation.alarm is not None:
            raise OperatorError(f"{channel}: acknowledge the alarm first ({situation.alarm})")
        _no_fault(channel, situation)
        if situation.in_manual:
            raise OperatorError(
                f"{channel}: the channel is in manual: switch it to auto before resuming"
            )
    return allowed[command]


def check_load(channel: str, state: State, manual_driven: bool = False) -> None:
    """A recipe is loaded only when no test is under way, and never from under an
    operator driving the channel in Manual (loading does not touch mode or enable)."""
    if state not in LOADABLE:
        raise OperatorError(
            f"{channel}: cannot load a recipe while {state.value}: a test is under way: "
            + _WAY_OUT.get(state, "stop or abort it first")
        )
    if manual_driven:
        raise OperatorError(f"{channel}: cannot load a recipe while {MANUAL_DRIVEN}")


def _no_fault(channel: str, situation: Situation) -> None:
    if situation.channel_fault:
        raise OperatorError(f"{channel}: channel fault must be acknowledged first")
