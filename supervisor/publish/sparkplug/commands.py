"""Commands over Sparkplug (docs/sparkplug.md "Commands"): what a DCMD may ask of a
channel, and the primary host application's STATE that allows it (Sparkplug 3.0).

Each channel's DBIRTH announces one Boolean metric per command, ``Command/<verb>``
(false), and a String ``Command/last_result``: a host application writes a command by
sending a DCMD with that metric set to true — Sparkplug's usual form of a command (the
specification's own ``Node Control/Rebirth`` is one), so that a generic host (Ignition's
"write to a tag") needs nothing of this bench's. The edge node answers in DDATA with
``Command/last_result`` ("start: accepted", "start: refused: <reason>").

A command is run only while the configured primary host application says it is online
(retained ``spBv1.0/STATE/<host id>``, JSON ``{"online": true, "timestamp": ms}``): the
actor of the one command path is then ``sparkplug:<host id>`` — the only host a bench
takes orders from. A STATE older than the last one seen is ignored (chapter 5: a late
retained message of a previous session of the host).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Final

from supervisor.core.quality import Quality
from supervisor.publish.sparkplug.node import NAMESPACE, Metric

__all__ = [
    "ACTOR_PREFIX",
    "COMMAND_PREFIX",
    "LAST_RESULT",
    "VERBS",
    "CommandHandler",
    "CommandSettings",
    "HostState",
    "Reply",
    "command_metrics",
    "requested",
    "state_topic",
]

log = logging.getLogger(__name__)

COMMAND_PREFIX: Final = "Command/"
LAST_RESULT: Final = "Command/last_result"
VERBS: Final = ("start", "hold", "resume", "stop", "abort", "reset", "acknowledge")
"""The channel commands a DCMD may give (the command path's verbs of the same names)."""
ACTOR_PREFIX: Final = "sparkplug:"

Reply = Callable[[bool, str], None]
"""``(accepted, reason)``: the command path's answer, from any thread."""
CommandHandler = Callable[[str, str, str, Reply], None]
"""``(channel, verb, actor, reply)``: the composition root runs the command through the
one command path (on its event loop) and calls ``reply``; it must not block."""


@dataclass(frozen=True, slots=True)
class CommandSettings:
    """The ``sparkplug.commands`` section: off by default."""

    enabled: bool = False
    primary_host: str | None = None
    """The primary host application's id: the edge node waits for its STATE online
    before its NBIRTH, and takes commands only from it (and only while it is online)."""


def state_topic(host_id: str) -> str:
    return f"{NAMESPACE}/STATE/{host_id}"


class HostState:
    """The primary host application's STATE, as the current session saw it."""

    def __init__(self, host_id: str) -> None:
        self.host_id = host_id
        self.online = False
        self.timestamp_ms = -1

    def update(self, payload: bytes) -> bool | None:
        """The STATE in ``payload`` → whether the host is online now; None when the
        message is ignored (not a STATE, or older than the last one)."""
        try:
            doc: Any = json.loads(payload)
        except (ValueError, UnicodeDecodeError):
            doc = None
        if not isinstance(doc, dict) or not isinstance(doc.get("online"), bool):
            log.warning("Sparkplug STATE of %s: not a STATE payload: %.80r", self.host_id, payload)
            return None
        ts = doc.get("timestamp")
        ts_ms = ts if isinstance(ts, int) and not isinstance(ts, bool) else 0
        if ts_ms < self.timestamp_ms:
            log.info(
                "Sparkplug STATE of %s ignored: timestamp %d older than %d",
                self.host_id,
                ts_ms,
                self.timestamp_ms,
            )
            return None
        self.timestamp_ms = ts_ms
        self.online = doc["online"]
        return self.online


def command_metrics(channels: Iterable[str], now_ms: int) -> dict[str, Metric]:
    """Each channel's command metrics as its DBIRTH announces them (tag-like names:
    ``<channel>.Command/<verb>``, placed in the channel's device by the layout)."""
    out: dict[str, Metric] = {}
    for ch in channels:
        for verb in VERBS:
            out[f"{ch}.{COMMAND_PREFIX}{verb}"] = Metric("bool", "", False, Quality.GOOD, now_ms)
        out[f"{ch}.{LAST_RESULT}"] = Metric("str", "", "", Quality.GOOD, now_ms)
    return out


def requested(payload: Any) -> list[tuple[str, str | None]]:
    """A DCMD's metrics → ``(metric name, verb)`` for each that asks something: a verb
    when it is ``Command/<verb>`` set to true, None for anything else (refused)."""
    out: list[tuple[str, str | None]] = []
    for m in payload.metrics:
        name = str(m.name)
        verb = name[len(COMMAND_PREFIX) :] if name.startswith(COMMAND_PREFIX) else ""
        if verb in VERBS and m.HasField("boolean_value"):
            if m.boolean_value:
                out.append((name, verb))
            continue  # false: nothing asked (a host that writes the birth's value back)
        out.append((name, None))
    return out
