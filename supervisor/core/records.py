"""What a step chain tells the world: events and result samples (plain data).

They live below every layer that produces or consumes them, so that the chain engine
(``supervisor.chains``) emits them and the publishers (``supervisor.publish``: result
files, the Chadèche display line) take them without importing each other (STYLE.md,
layers).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Protocol

from supervisor.core.encoding import storable_text


@dataclass(frozen=True, slots=True)
class ChainEvent:
    t: float  # Clock.now()
    wall: float
    channel: str
    kind: str  # "state" | "step" | "alarm" | "message"
    text: str
    step_index: int = -1
    step_id: str = ""
    cycle: int = 0
    # An operator command the command path reported first (with its actor): publishers
    # of bench events take it from there and skip this echo.
    echo: bool = False


@dataclass(frozen=True, slots=True)
class Record:
    """One result sample (BDF columns), emitted when a logging rule says so.

    The same type carries a periodic snapshot for displays (``reason == "sample"``).
    """

    t: float
    wall: float
    test_time_s: float
    step_time_s: float
    cycle_time_s: float
    cycle: int
    step_count: int  # increments at every step start, never resets (BDF)
    step_index: int
    step_id: str
    step_type: str
    voltage_v: float | None
    current_a: float | None
    power_w: float | None
    temperature_c: float | None
    charge_ah: float  # counter incl. the initial charge
    charged_ah: float
    discharged_ah: float
    charged_wh: float
    discharged_wh: float
    cycle_charged_ah: float
    cycle_discharged_ah: float
    cycle_charged_wh: float
    cycle_discharged_wh: float
    setpoint_a: float
    step_remaining_s: float | None
    reason: str  # "period" | "delta_v" | "delta_i" | "step change" | "end" | "sample"
    # What the channel sends to its source (after its clamp and trips). The chain runs
    # before the channel in a scan, so during the scan this is the last scan's command.
    current_cmd_a: float = 0.0
    # The voltage tag's last value whatever its quality (0.0 when it has none): the
    # Chadèche display (seed 000 §III.E.1) shows it; ``voltage_v`` is None when not GOOD.
    last_voltage_v: float = 0.0
    # The values of the channel's recorded tags (``ChannelPort.record``) at this scan, in
    # its order, None for one that is not GOOD: the result files' auxiliary columns.
    aux: tuple[object, ...] = ()


class Sampler(Protocol):
    """A periodic observer of a running test (e.g. a display line).

    The chain asks ``due(now)`` every scan and builds a snapshot only when it is due:
    building a Record every scan would cost the dry run its speed.
    """

    def due(self, now: float) -> bool: ...

    def on_sample(self, rec: Record) -> None: ...


@dataclass(frozen=True, slots=True)
class BenchEvent:
    """One thing that happened on the bench, for the historian, InfluxDB annotations and
    OPC UA events: a step or state change of a chain, an alarm transition, an operator
    command (accepted or refused, with its actor).

    One flat type for every source so that each publisher stores and forwards events the
    same way; ``supervisor.app.events`` converts the sources' own events into it.
    """

    t: float  # Clock.now() of the source
    wall: float  # Unix time (s), what is stored and plotted
    kind: str  # "step" | "state" | "message" | "alarm" | "command"
    channel: str  # "" when it concerns the bench, not one channel
    source: str  # the step id, the alarm id or the command's target
    text: str  # one line, human readable
    actor: str = ""  # who: an operator, "recipe", "safety", "" when nobody
    severity: int = 0  # ISA-18.2 priority of an alarm (0 for anything else)
    test_id: str = ""
    recipe: str = ""


_EVENT_TEXTS = ("kind", "channel", "source", "text", "actor", "test_id", "recipe")


def storable_event(event: BenchEvent) -> BenchEvent:
    """``event`` with each of its texts storable by every writer (``core/encoding.py``);
    ``event`` itself, the usual case, when they all are."""
    changes: dict[str, Any] = {}
    for name in _EVENT_TEXTS:
        value = getattr(event, name)
        safe = storable_text(value)
        if safe is not value:
            changes[name] = safe
    return dataclasses.replace(event, **changes) if changes else event


class EventSink(Protocol):
    """Takes bench events; must return quickly (queue, never wait): it is called from the
    scan or the command path."""

    def on_event(self, event: BenchEvent) -> None: ...
