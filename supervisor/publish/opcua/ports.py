"""What the OPC UA server asks of the bench, in plain data (ADR 0003: a publisher may not
import the command path; the composition root, ``supervisor.app.opcua``, adapts).

A method call or a write becomes a ``Request`` in the command path's own words (target,
verb, arguments, actor); the bench answers it with an ``Answer`` (accepted, or refused of
a kind, with the reason). ``supervisor.app.opcua`` turns one into a
``supervisor.commands.Command`` and the ``Result`` back into the other.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from typing import Literal

TargetKind = Literal["channel", "alarm", "bench"]


@dataclass(frozen=True, slots=True)
class Request:
    kind: TargetKind
    target: str  # a channel name, an alarm id, or "" for the bench
    verb: str  # the command path's verb ("start", "mode", "write", …)
    args: Mapping[str, object] = field(default_factory=dict)
    actor: str = ""


@dataclass(frozen=True, slots=True)
class Answer:
    accepted: bool
    reason: str
    refusal: str = ""  # the command path's ResultKind value when refused ("refused", …)


Operate = Callable[[Request], Awaitable[Answer]]
"""Runs on the bench's loop; a coroutine so that a recipe to load is compiled off it."""
"""Runs one request through the bench's command path (called on the bench's loop)."""
