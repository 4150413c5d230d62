"""What an operator asks (``Command``), what the bench answers (``Result``), what is kept
(``CommandEvent``): plain data, so that every client — HTTP, the command line, OPC UA
methods later — builds the same command and gets the same answer.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from supervisor.tags.spec import clipped_repr, finite_float


class TargetKind(StrEnum):
    CHANNEL = "channel"
    ALARM = "alarm"
    BENCH = "bench"


@dataclass(frozen=True, slots=True)
class Target:
    """What a command is about: a channel (``ch0``), an alarm (its id) or the bench."""

    kind: TargetKind
    name: str = ""

    @classmethod
    def channel(cls, name: str) -> Target:
        return cls(TargetKind.CHANNEL, name)

    @classmethod
    def alarm(cls, alarm_id: str) -> Target:
        return cls(TargetKind.ALARM, alarm_id)

    @classmethod
    def bench(cls) -> Target:
        return cls(TargetKind.BENCH)

    def __str__(self) -> str:
        if self.kind is TargetKind.CHANNEL:
            return self.name
        if self.kind is TargetKind.ALARM:
            return f"alarm {self.name}"
        return "bench"


class Verb(StrEnum):
    # The chain's ISA-88 commands (chains/states.py), and loading its recipe.
    LOAD = "load"
    START = "start"
    HOLD = "hold"
    RESUME = "resume"
    ADVANCE = "advance"
    STOP = "stop"
    ABORT = "abort"
    RESET = "reset"
    # Alarms (ISA-18.2): of a channel (all that hold it) or of one alarm.
    ACKNOWLEDGE = "acknowledge"
    SHELVE = "shelve"
    UNSHELVE = "unshelve"
    # The channel's Manual mode.
    MODE = "mode"
    MANUAL_CURRENT = "manual_current"
    ENABLE = "enable"
    # Any other operator tag.
    WRITE = "write"
    # Commissioning overrides of a tag (engineer only; never a tag the safety phase uses).
    FORCE = "force"
    UNFORCE = "unforce"
    # The bench-wide software e-stop (seed 002 §1.5): press it, and reset it once
    # acknowledged (the hardware e-stop's rule).
    ESTOP = "estop"
    ESTOP_RESET = "estop_reset"

    @classmethod
    def parse(cls, text: str) -> Verb | None:
        """The verb named ``text`` (``ack`` is the chain's old name of acknowledge)."""
        text = ALIASES.get(text, text)
        try:
            return cls(text)
        except ValueError:
            return None


ALIASES = {"ack": "acknowledge"}

CHAIN_VERBS = (
    Verb.START,
    Verb.HOLD,
    Verb.RESUME,
    Verb.ADVANCE,
    Verb.STOP,
    Verb.ABORT,
    Verb.RESET,
)
CHANNEL_VERBS = (
    Verb.LOAD,
    *CHAIN_VERBS,
    Verb.ACKNOWLEDGE,
    Verb.MODE,
    Verb.MANUAL_CURRENT,
    Verb.ENABLE,
    Verb.WRITE,
)
CHANNEL_BAR: tuple[tuple[str, Verb, Mapping[str, Any]], ...] = (
    ("load", Verb.LOAD, {}),
    *((v.value, v, {}) for v in CHAIN_VERBS),
    ("acknowledge", Verb.ACKNOWLEDGE, {}),
    ("mode_auto", Verb.MODE, {"value": "auto"}),
    ("mode_manual", Verb.MODE, {"value": "manual"}),
    ("manual_current", Verb.MANUAL_CURRENT, {}),
    ("enable_on", Verb.ENABLE, {"value": True}),
    ("enable_off", Verb.ENABLE, {"value": False}),
)
"""A channel's command bar on the screens: each button's key, verb and the arguments it
always sends (``CommandPath.available`` answers for each; issue 33, finding 2)."""
ALARM_VERBS = (Verb.ACKNOWLEDGE, Verb.RESET, Verb.SHELVE, Verb.UNSHELVE)
BENCH_VERBS = (Verb.WRITE, Verb.FORCE, Verb.UNFORCE, Verb.ESTOP, Verb.ESTOP_RESET)
ESTOP_VERBS = (Verb.ESTOP, Verb.ESTOP_RESET)


@dataclass(frozen=True, slots=True)
class Command:
    """``verb`` on ``target`` with its arguments, asked by ``actor`` (who: "operator",
    "command line", the HTTP client's user once there are users)."""

    target: Target
    verb: Verb
    args: Mapping[str, Any] = field(default_factory=dict)
    actor: str = "operator"
    local: bool = False
    """Given in this host's shell (``supervisor run --recipe``), not over the network: its
    recipe is read wherever the shell's user can read (ADR 0026); a network client's is
    confined to the recipe folders."""

    @classmethod
    def channel(cls, name: str, verb: Verb, actor: str = "operator", **args: Any) -> Command:
        return cls(Target.channel(name), verb, args, actor)

    @classmethod
    def alarm(cls, alarm_id: str, verb: Verb, actor: str = "operator", **args: Any) -> Command:
        return cls(Target.alarm(alarm_id), verb, args, actor)

    @classmethod
    def write(cls, tag: str, value: Any, actor: str = "operator") -> Command:
        """The write of an operator tag (a channel's command tags become their verbs)."""
        return cls(Target.bench(), Verb.WRITE, {"tag": tag, "value": value}, actor)

    @classmethod
    def force(cls, tag: str, value: Any, actor: str = "operator") -> Command:
        """Force ``tag`` to ``value`` (a text is read as the tag's type) until unforced."""
        return cls(Target.bench(), Verb.FORCE, {"tag": tag, "value": value}, actor)

    @classmethod
    def unforce(cls, tag: str, actor: str = "operator") -> Command:
        return cls(Target.bench(), Verb.UNFORCE, {"tag": tag}, actor)

    @classmethod
    def estop(cls, actor: str = "operator") -> Command:
        """Press the bench-wide software e-stop: every channel tripped, as by the button."""
        return cls(Target.bench(), Verb.ESTOP, {}, actor)

    @classmethod
    def estop_reset(cls, actor: str = "operator") -> Command:
        """Release the software e-stop and reset the ``estop`` trip (acknowledged first)."""
        return cls(Target.bench(), Verb.ESTOP_RESET, {}, actor)

    def describe(self) -> str:
        """``mode manual (keep setpoint)``, ``manual_current 0.3 A``, ``write x := 1``."""
        a = self.args
        v = self.verb
        extra = ""
        if v is Verb.WRITE or v is Verb.FORCE:
            extra = f" {a.get('tag')} := {clipped_repr(a.get('value'))}"
        elif v is Verb.UNFORCE:
            extra = f" {a.get('tag')}"
        elif v is Verb.MODE:
            extra = f" {a.get('value')}" + (" (keep setpoint)" if a.get("keep_setpoint") else "")
        elif v is Verb.MANUAL_CURRENT:
            x = a.get("value")
            extra = f" {x:g} A" if _is_number(x) else f" {clipped_repr(x)}"
        elif v is Verb.ENABLE:
            x = a.get("value")
            extra = (" on" if x else " off") if isinstance(x, bool) else f" {clipped_repr(x)}"
        elif v in (Verb.LOAD, Verb.START) and a.get("recipe"):
            extra = f" {a['recipe']}"
            params = a.get("parameters")
            if isinstance(params, Mapping) and params:
                extra += " " + ", ".join(f"{k}={p}" for k, p in params.items())
        elif v is Verb.SHELVE and "duration_s" in a:
            extra = f" for {a['duration_s']} s"
        return f"{v.value}{extra}"


class ResultKind(StrEnum):
    """Why a command was refused, as a client must act on it (and its HTTP status)."""

    ACCEPTED = "accepted"
    BAD_ARGUMENT = "bad argument"  # the wrong type or value of an argument
    FORBIDDEN = "forbidden"  # a read-only tag, or the actor's role does not permit it
    NOT_FOUND = "not found"  # unknown tag, channel, alarm, recipe file or verb
    REFUSED = "refused"  # not in this state, or an interlock (trip, alarm) forbids it
    # A value of the right type beyond what the channel may ever do (its hard limits):
    # refused like a state (409), and told apart over OPC UA (Bad_OutOfRange).
    OUT_OF_RANGE = "out of range"
    INVALID_RECIPE = "invalid recipe"  # the recipe was read and refused (file:line:col)
    TIMEOUT = "timeout"  # reading and compiling a recipe took longer than its time limit
    INTERNAL = "internal error"  # a bug: logged with its traceback


HTTP_STATUS: Mapping[ResultKind, int] = {
    ResultKind.ACCEPTED: 200,
    ResultKind.BAD_ARGUMENT: 400,
    ResultKind.FORBIDDEN: 403,
    ResultKind.NOT_FOUND: 404,
    ResultKind.REFUSED: 409,
    ResultKind.OUT_OF_RANGE: 409,
    ResultKind.INVALID_RECIPE: 422,
    ResultKind.TIMEOUT: 503,  # the server could not do it in time; the request was valid
    ResultKind.INTERNAL: 500,
}


@dataclass(frozen=True, slots=True)
class Result:
    """Accepted or refused, and why (a refusal's reason says what to do instead)."""

    accepted: bool
    reason: str
    kind: ResultKind = ResultKind.ACCEPTED
    details: tuple[str, ...] = ()  # e.g. every error of a refused recipe, file:line:col
    data: Mapping[str, Any] = field(default_factory=dict)  # e.g. the test id of a load
    tag: str | None = None  # the tag the command wrote (answers show its value)

    @classmethod
    def ok(cls, reason: str, tag: str | None = None, **data: Any) -> Result:
        return cls(True, reason, ResultKind.ACCEPTED, data=data, tag=tag)

    @classmethod
    def refused(cls, kind: ResultKind, reason: str, details: tuple[str, ...] = ()) -> Result:
        assert kind is not ResultKind.ACCEPTED
        return cls(False, reason, kind, details)

    @property
    def http_status(self) -> int:
        return HTTP_STATUS[self.kind]

    def as_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "accepted": self.accepted,
            "reason": self.reason,
            "kind": self.kind.value,
            **self.data,
        }
        if self.details:
            out["details"] = list(self.details)
        return out


@dataclass(frozen=True, slots=True)
class CommandEvent:
    """The record of one command, accepted or refused (docs/design.md "Safety": the actor)."""

    t: float  # Clock.now()
    wall: float
    actor: str
    target: str
    command: str  # Command.describe()
    accepted: bool
    kind: ResultKind
    reason: str
    channel: str = ""  # the channel it concerns ("" when none)

    @property
    def text(self) -> str:
        if self.accepted or self.kind is ResultKind.REFUSED:
            verdict = self.kind.value
        else:
            verdict = f"refused ({self.kind.value})"
        return f"{self.command} by {self.actor}: {verdict}: {self.reason}"

    def as_json(self) -> dict[str, Any]:
        return {
            "time": self.wall,
            "actor": self.actor,
            "target": self.target,
            "command": self.command,
            "accepted": self.accepted,
            "kind": self.kind.value,
            "reason": self.reason,
            "channel": self.channel,
        }


def _is_number(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and finite_float(x) is not None
