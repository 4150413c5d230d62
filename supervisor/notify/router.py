"""Which route tells what, and when: filters, flood windows, quiet hours, escalations.

Pure and clock-free: ``offer`` takes a notice, ``due(wall)`` returns the messages whose
time has come. The notifier calls both from its task (never from the scan), and the tests
call them with the times they choose (docs/notifications.md "Routing").

- A route takes a notice when its kind, priority and channel pass the route's filters.
- Flood window: the first notice a route takes opens a window of ``summary_window_s``;
  everything the route takes inside it goes out as ONE message when it closes (an e-stop
  that trips every channel is one summary, not fifty).
- Quiet hours: a notice below the window's priority waits in the route's night list and
  goes out, as one summary, at the first ``due`` after the window ends.
- Escalation: an alarm activation the route took, still unacknowledged
  ``escalate_after_s`` later, is one escalation message (once per activation).
"""

from __future__ import annotations

import datetime
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final

from supervisor.config.notifications import PRIORITIES, EmailRoute, QuietHours, WebhookRoute

__all__ = ["PRIORITY_OF", "Notice", "Outgoing", "Router", "message_key"]

PRIORITY_OF: Final = {name: rank for rank, name in enumerate(PRIORITIES)}


@dataclass(frozen=True, slots=True)
class Notice:
    """One event worth telling someone: an alarm's activation (or its acknowledgement,
    which only stops an escalation), a test's end."""

    wall: float  # Unix time (s) of the event
    kind: str  # "alarm" | "ack" | "test_end"
    source: str  # the alarm id, or the channel for a test end
    channel: str  # "" for the bench
    priority: str  # one of PRIORITIES (a test end: "low")
    text: str  # one line, human readable

    def as_json(self) -> dict[str, object]:
        return {
            "time": _iso(self.wall),
            "kind": self.kind,
            "source": self.source,
            "channel": self.channel,
            "priority": self.priority,
            "text": self.text,
        }

    def identity(self) -> str:
        """What tells this event from any other (its key's material)."""
        return f"{self.kind}|{self.source}|{self.channel}|{self.wall:.6f}"


@dataclass(frozen=True, slots=True)
class Outgoing:
    """A message to send on one route: one notice, a summary of several, an escalation."""

    route: str
    key: str  # the idempotency key (Idempotency-Key header, Message-ID)
    kind: str  # "alarm" | "test_end" | "summary" | "escalation" | "test"
    priority: str
    subject: str
    text: str  # the body, one line per notice
    notices: tuple[Notice, ...]
    escalation: bool = False


def message_key(bench: str, route: str, kind: str, notices: Sequence[Notice]) -> str:
    """The same notices on the same route give the same key, in any process: a message
    enqueued twice (a restart between routing and commit) is still delivered once."""
    h = hashlib.sha256(f"{bench}\n{route}\n{kind}".encode())
    for n in notices:
        h.update(b"\n" + n.identity().encode())
    return h.hexdigest()[:32]


def _iso(wall: float) -> str:
    return (
        datetime.datetime.fromtimestamp(wall, datetime.UTC)
        .isoformat(timespec="milliseconds")
        .replace("+00:00", "Z")
    )


def in_quiet_hours(q: QuietHours, wall: float, zone: datetime.tzinfo | None) -> bool:
    """Is ``wall`` inside ``q``'s local window (``zone``; None: the machine's)?"""
    local = datetime.datetime.fromtimestamp(wall, zone)
    minute = local.hour * 60 + local.minute
    start, end = q.minutes()
    if start == end:
        return False
    if start < end:
        return start <= minute < end
    return minute >= start or minute < end  # across midnight


@dataclass
class _RouteState:
    cfg: EmailRoute | WebhookRoute
    window: list[Notice] = field(default_factory=list)
    window_end: float | None = None
    night: list[Notice] = field(default_factory=list)
    escalations: dict[str, Notice] = field(default_factory=dict)  # alarm id → activation

    def takes(self, n: Notice) -> bool:
        cfg = self.cfg
        kind = "alarm" if n.kind == "ack" else n.kind
        if kind not in cfg.kinds:
            return False
        if n.kind == "alarm" and PRIORITY_OF[n.priority] < PRIORITY_OF[cfg.min_priority]:
            return False
        return cfg.channels is None or n.channel == "" or n.channel in cfg.channels


class Router:
    """Routes notices into messages (see the module's docstring)."""

    def __init__(
        self,
        bench: str,
        routes: Sequence[EmailRoute | WebhookRoute],
        zone: datetime.tzinfo | None = None,
    ) -> None:
        self.bench = bench
        self.zone = zone
        self.routes = {r.name: _RouteState(r) for r in routes}

    def offer(self, n: Notice) -> None:
        for st in self.routes.values():
            if not st.takes(n):
                continue
            if n.kind == "ack":
                st.escalations.pop(n.source, None)
                continue
            if n.kind == "alarm" and st.cfg.escalate_after_s is not None:
                st.escalations[n.source] = n
            q = st.cfg.quiet_hours
            if (
                q is not None
                and PRIORITY_OF[n.priority] < PRIORITY_OF[q.below]
                and in_quiet_hours(q, n.wall, self.zone)
            ):
                st.night.append(n)
                continue
            if st.window_end is None:
                st.window_end = n.wall + st.cfg.summary_window_s
            st.window.append(n)

    def due(self, wall: float) -> list[Outgoing]:
        """The messages whose time has come at ``wall`` (each at most once)."""
        out: list[Outgoing] = []
        for name, st in self.routes.items():
            if st.window_end is not None and wall >= st.window_end:
                out.append(self._message(name, st.window))
                st.window, st.window_end = [], None
            q = st.cfg.quiet_hours
            if st.night and (q is None or not in_quiet_hours(q, wall, self.zone)):
                out.append(self._message(name, st.night))
                st.night = []
            after = st.cfg.escalate_after_s
            if after is not None:
                for alarm_id, n in list(st.escalations.items()):
                    if wall >= n.wall + after:
                        del st.escalations[alarm_id]
                        out.append(self._escalation(name, n, after))
        return out

    def flush(self) -> list[Outgoing]:
        """A stop: every open flood window and every quiet-hours list as its message now
        (a notice held in memory would be lost; escalations are not: nobody can still
        acknowledge before the stop)."""
        out: list[Outgoing] = []
        for name, st in self.routes.items():
            if st.window:
                out.append(self._message(name, st.window))
            if st.night:
                out.append(self._message(name, st.night))
            st.window, st.window_end, st.night = [], None, []
        return out

    def held(self) -> set[str]:
        """The identities of the notices still waiting here (in a window, for the end of
        quiet hours, for an escalation): what the queue must keep across a restart."""
        ids: set[str] = set()
        for st in self.routes.values():
            ids.update(n.identity() for n in st.window)
            ids.update(n.identity() for n in st.night)
            ids.update(n.identity() for n in st.escalations.values())
        return ids

    def next_due(self) -> float | None:
        """The earliest wall time at which ``due`` has something (None: nothing waits but
        quiet hours' notices, which ``due`` checks each time)."""
        times = [st.window_end for st in self.routes.values() if st.window_end is not None]
        for st in self.routes.values():
            after = st.cfg.escalate_after_s
            if after is not None:
                times += [n.wall + after for n in st.escalations.values()]
        return min(times) if times else None

    # --- the messages -------------------------------------------------------------------
    def _message(self, route: str, notices: list[Notice]) -> Outgoing:
        top = max(notices, key=lambda n: PRIORITY_OF[n.priority]).priority
        if len(notices) == 1:
            n = notices[0]
            kind = n.kind
            subject = f"[{self.bench}] {_what(n)}: {n.text}"
        else:
            kind = "summary"
            alarms = sum(n.kind == "alarm" for n in notices)
            ends = len(notices) - alarms
            parts = [f"{alarms} alarms" if alarms != 1 else "1 alarm"] if alarms else []
            parts += [f"{ends} test ends" if ends != 1 else "1 test end"] if ends else []
            subject = f"[{self.bench}] {' and '.join(parts)}"
        text = "\n".join(_line(n) for n in notices)
        return Outgoing(
            route,
            message_key(self.bench, route, kind, notices),
            kind,
            top,
            subject,
            text,
            tuple(notices),
        )

    def _escalation(self, route: str, n: Notice, after_s: float) -> Outgoing:
        subject = f"[{self.bench}] ESCALATION: {n.source} unacknowledged for {after_s:g} s"
        return Outgoing(
            route,
            message_key(self.bench, route, "escalation", [n]),
            "escalation",
            n.priority,
            subject,
            f"Still unacknowledged after {after_s:g} s:\n{_line(n)}",
            (n,),
            escalation=True,
        )


def _what(n: Notice) -> str:
    return "test ended" if n.kind == "test_end" else f"{n.priority} alarm"


def _line(n: Notice) -> str:
    where = f" {n.channel}" if n.channel else ""
    return f"{_iso(n.wall)} {n.priority}{where} {n.source}: {n.text}"
