"""One feed of bench events for the publishers (historian, InfluxDB, OPC UA events).

Three sources emit their own event types to their own listeners: each step chain
(``ChainEvent``), the alarm model (``AlarmEvent``) and the command path (``CommandEvent``).
A publisher wants them all, in one shape, with the test and recipe they belong to; this
module is the one place that converts them (``BenchEvent``, ``supervisor.core.records``),
so that the historian and the InfluxDB writer never disagree on what an event is.
"""

from __future__ import annotations

import logging

from supervisor.chains.engine import ChainRunner
from supervisor.commands.model import CommandEvent
from supervisor.core.records import BenchEvent, ChainEvent, EventSink, storable_event
from supervisor.safety.alarms import AlarmEvent

__all__ = ["EventFeed"]

log = logging.getLogger(__name__)


class EventFeed:
    """Fans the bench's events out to sinks; ``attach`` it once the bench is built."""

    def __init__(self) -> None:
        self.sinks: list[EventSink] = []
        self._runners: dict[str, ChainRunner] = {}

    def attach(self, bench: object) -> None:
        """Listen to ``bench`` (an ``supervisor.app.bench.Bench``; typed loosely so that
        the bench module can import this one)."""
        runners: dict[str, ChainRunner] = getattr(bench, "runners", {})
        self._runners = runners
        for runner in runners.values():
            runner.listeners.append(self.on_chain)
        alarms = getattr(bench, "alarms", None)
        if alarms is not None:
            alarms.listeners.append(self.on_alarm)
        commands = getattr(bench, "commands", None)
        if commands is not None:
            commands.listeners.append(self.on_command)

    # --- conversions ---------------------------------------------------------------
    def on_chain(self, ev: ChainEvent) -> None:
        if ev.echo:  # the command path's own event carries the actor
            return
        test_id, recipe = self._test_of(ev.channel)
        self._emit(
            BenchEvent(
                ev.t,
                ev.wall,
                ev.kind,
                ev.channel,
                ev.step_id,
                ev.text,
                actor="recipe",
                test_id=test_id,
                recipe=recipe,
            )
        )

    def on_alarm(self, ev: AlarmEvent) -> None:
        channel = ev.group if ev.group in self._runners else ""
        test_id, recipe = self._test_of(channel)
        self._emit(
            BenchEvent(
                ev.t,
                ev.wall,
                "alarm",
                channel,
                ev.alarm_id,
                f"{ev.alarm_id} {ev.transition}: {ev.message}",
                actor=ev.actor or "safety",
                severity=int(ev.severity),
                test_id=test_id,
                recipe=recipe,
            )
        )

    def on_command(self, ev: CommandEvent) -> None:
        test_id, recipe = self._test_of(ev.channel)
        self._emit(
            BenchEvent(
                ev.t,
                ev.wall,
                "command",
                ev.channel,
                ev.target,
                ev.text,
                actor=ev.actor,
                test_id=test_id,
                recipe=recipe,
            )
        )

    # --- helpers -------------------------------------------------------------------
    def _test_of(self, channel: str) -> tuple[str, str]:
        runner = self._runners.get(channel)
        if runner is None or runner.program is None:
            return "", ""
        return runner.test_id, runner.program.name

    def _emit(self, event: BenchEvent) -> None:
        # Every sink is a writer (SQLite, line protocol, OPC UA): a text it cannot encode
        # (a refused value quoted in a command's text) is escaped once, here
        # (``supervisor.core.encoding``).
        event = storable_event(event)
        for sink in self.sinks:
            try:
                sink.on_event(event)
            except Exception:  # a publisher's fault never reaches the scan
                log.exception("event sink %r failed on %s event", sink, event.kind)
