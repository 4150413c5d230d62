"""The safety phase: every check, every scan, in order; a failing check fails safe.

docs/design.md "One scan": derived values, then interlocks and alarms, then the step chains.
A check that raises does not stop the others (caproto: an exception in logic is an alarm,
not a crash): it is counted, logged with its name, and asked to take its own safe action.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from supervisor.safety.guard import ChannelGuard
    from supervisor.safety.interlocks import Estop

log = logging.getLogger(__name__)


class SafetyCheck(Protocol):
    """One interlock, alarm or feedback monitor evaluated every scan."""

    name: str

    def evaluate(self, now: float, dt: float) -> None:
        """Look at this scan's tags; trip, raise or clear what this check owns."""
        ...

    def fail_safe(self, why: str) -> None:
        """The check itself failed: put what it protects in its safe state."""
        ...


class SafetyPhase:
    """The scan's safety phase (``LogicPhase("safety", phase.run)``)."""

    def __init__(self, checks: Sequence[SafetyCheck] = ()) -> None:
        self.checks: list[SafetyCheck] = list(checks)
        self.errors = 0
        self.guards: dict[str, ChannelGuard] = {}  # channel name -> its guard
        self.estop: Estop | None = None  # the bench's e-stop (safety.estop), if it has one

    def run(self, now: float, dt: float) -> None:
        for check in self.checks:
            try:
                check.evaluate(now, dt)
            except Exception as exc:
                self.errors += 1
                log.exception("safety: check %r failed; failing safe", check.name)
                try:
                    check.fail_safe(f"safety check {check.name} failed: {exc}")
                except Exception:
                    log.exception("safety: check %r could not fail safe", check.name)
