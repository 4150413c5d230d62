"""File descriptors kept for the devices (issue 27, finding 3).

Every TCP connection, file and pipe of the process is a descriptor, and the process may
hold at most its soft ``RLIMIT_NOFILE`` (1024 under systemd without ``LimitNOFILE=``). A
flood of 1000 idle HTTP connections took them all: the ADAM and the EA could not reconnect,
``estop.unknown`` tripped every channel. The listeners are capped (HTTP, WebSocket, OPC UA)
and the caps sized so that what they may take, plus the devices' connections, the bench's
files and a margin, stays under the limit: ``DescriptorBudget``.

At start-up ``raise_soft_limit`` lifts the soft limit towards ``WANTED_NOFILE`` (never
above the hard limit, never down); ``DescriptorBudget.check`` then refuses a configuration
whose caps do not fit.
"""

from __future__ import annotations

import resource
from dataclasses import dataclass, field
from typing import Final

WANTED_NOFILE: Final = 8192
"""What ``supervisor run`` raises its soft limit to when the hard limit allows (the
``LimitNOFILE=`` of deploy/bench-supervisor@.service). Not the hard limit itself: a
descriptor above 1023 breaks any library still using ``select()``."""

PER_DEVICE: Final = 4
"""Descriptors per device: its connection, a reconnection overlapping the old one's close,
and with ``sim: true`` the in-process simulator's listening socket and accepted peer."""
FILES: Final = 64
"""The bench's own files and pipes: standard streams, each event loop's epoll and wake-up
pipe (the scan's, OPC UA's, worker threads'), the state and historian SQLite files with
their journals, the InfluxDB spool, open result files, a recipe preview's child."""
MARGIN: Final = 64
"""Left free whatever the count says (a library's own file, a second preview)."""


@dataclass(frozen=True, slots=True)
class NofileLimit:
    soft: int
    hard: int
    before: int
    """The soft limit before ``raise_soft_limit`` (equal to ``soft`` when not raised)."""


def raise_soft_limit(wanted: int = WANTED_NOFILE) -> NofileLimit:
    """The process's ``RLIMIT_NOFILE``, its soft limit first raised to ``wanted`` (at most
    the hard limit; never lowered). A refusal (an odd platform) leaves it as it was."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        except (ValueError, OSError):
            return NofileLimit(soft, hard, soft)
        return NofileLimit(target, hard, soft)
    return NofileLimit(soft, hard, soft)


@dataclass(frozen=True, slots=True)
class DescriptorBudget:
    """What the process may hold at most, by owner."""

    listeners: dict[str, int] = field(default_factory=dict)
    """Each listener's connection cap (``hmi.max_connections``...) plus its accept backlog:
    connections refused beyond a cap are accepted (to be answered) and closed at once,
    at most a backlog of them at a time."""
    devices: int = 0
    files: int = FILES
    margin: int = MARGIN
    apart: dict[str, int] = field(default_factory=dict)
    """Listeners in processes of their own (the OPC UA server, ADR 0029): their caps count
    against their own process's descriptors (each with a margin), not the bench's."""

    @property
    def needed(self) -> int:
        return sum(self.listeners.values()) + self.devices + self.files + self.margin

    def describe(self) -> str:
        parts = [f"{name} {n}" for name, n in self.listeners.items()]
        parts += [f"devices {self.devices}", f"files {self.files}", f"margin {self.margin}"]
        own = "".join(f"; {name} {n} in its own process" for name, n in self.apart.items())
        return f"{self.needed} ({' + '.join(parts)}){own}"

    def problem(self, limit: NofileLimit) -> str | None:
        """None when the budget fits under the soft limit, else what to change."""
        soft = limit.soft
        largest = max([self.needed, *(n + self.margin for n in self.apart.values())])
        if soft == resource.RLIM_INFINITY or largest <= soft:
            return None
        return (
            f"file descriptors: the connection caps need {self.describe()} but the soft"
            f" limit RLIMIT_NOFILE is {soft} (hard {limit.hard}): a flood of clients could"
            " then cost a device its connection. Lower hmi.max_connections or"
            " opcua.max_connections, or raise the limit (LimitNOFILE=8192 in the systemd"
            " unit, `ulimit -n 8192` in a shell)"
        )
