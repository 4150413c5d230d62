"""The alarm model (ISA-18.2): one place that knows every alarm, its state and its history.

An alarm is raised and cleared by the checks that own it (interlocks, channel guards, tag
limits), evaluated every scan; people acknowledge, reset and shelve it. States, from
``Alarm.state``:

- ``normal``: condition absent, nothing to acknowledge;
- ``active, unacknowledged`` / ``active, acknowledged``: condition present;
- ``returned, unacknowledged``: the condition went away before anyone acknowledged it;
- ``latched`` (trips only): condition gone and acknowledged, the trip still holds its
  channel until someone resets it. A reset is refused while the cause is still present.

A trip is a latched alarm (``latched=True``): its channel stays safe until the alarm is
acknowledged AND reset. The first trip of a group (a channel) since the group was last
clear is marked first-out. Shelving hides a nuisance alarm for a while (it is still
evaluated and logged); a trip cannot be shelved. Every transition goes to the log (time,
actor) and to the listeners (result files, historian, OPC UA events).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum

from supervisor.core.clock import Clock
from supervisor.core.errors import OperatorError

log = logging.getLogger(__name__)

LOG_LENGTH = 2000
"""Transitions kept in memory (the historian keeps them all)."""


class Severity(IntEnum):
    """On the OPC UA 1–1000 scale, so clients and screens can use the number as it is."""

    LOW = 200
    MEDIUM = 500
    HIGH = 700
    CRITICAL = 900

    @classmethod
    def named(cls, name: str) -> Severity:
        return cls[name.upper()]


class AlarmState(StrEnum):
    NORMAL = "normal"
    ACTIVE_UNACKED = "active, unacknowledged"
    ACTIVE_ACKED = "active, acknowledged"
    RETURNED_UNACKED = "returned, unacknowledged"
    LATCHED = "latched"  # a trip whose cause is gone, acknowledged, awaiting reset


class Transition(StrEnum):
    ACTIVATED = "activated"
    CLEARED = "cleared"
    ACKNOWLEDGED = "acknowledged"
    RESET = "reset"
    SHELVED = "shelved"
    UNSHELVED = "unshelved"
    SILENCED = "silenced"  # an operator's screen stopped sounding it (no state change)


class AlarmText(str):
    """An alarm's message as an operator reads it ("Emergency stop pressed (e-stop circuit
    open)"), carrying what a screen needs to say it in another language — ``code``, the
    kind of message, stable across releases ("estop.pressed"), and ``params``, the figures
    and names in it — and ``detail``, the tags behind it ("estop.ok is false") for the
    engineer. A plain ``str`` everywhere else (logs, events, result files, OPC UA)."""

    code: str
    params: dict[str, object]
    detail: str

    def __new__(
        cls, text: str, code: str, params: Mapping[str, object] | None = None, detail: str = ""
    ) -> AlarmText:
        self = super().__new__(cls, text)
        self.code = code
        self.params = dict(params or {})
        self.detail = detail
        return self


def signal_name(tag: object) -> str:
    """A signal as an operator knows it: its description from the I/O map when it has
    one ("e-stop circuit closed"), else its tag name."""
    spec = getattr(tag, "spec", None)
    described = getattr(spec, "description", "") if spec is not None else ""
    return str(described or getattr(tag, "name", tag))


@dataclass
class Alarm:
    """One alarm's declaration and state: a plain record, changed only through its
    :class:`AlarmManager`, which counts each change (``AlarmManager.writes``)."""

    id: str
    group: str  # a channel name, or "" for the whole bench
    severity: Severity
    latched: bool  # a trip: holds its group until acknowledged and reset
    affects: tuple[str, ...] | None = None  # a bench-wide trip's channels (None: all)
    message: str = ""
    code: str = ""  # the kind of its message (AlarmText.code); "" for a plain text
    params: dict[str, object] = field(default_factory=dict)  # the message's figures, names
    detail: str = ""  # the tags behind the message, for the engineer
    action: str = "hold"  # what a trip does to its channels: "hold" or "abort"
    active: bool = False  # the condition is present now
    acked: bool = True
    tripped: bool = False  # a trip that has not been reset yet
    first_out: bool = False
    activated_t: float | None = None
    shelved_until: float | None = None
    acked_by: str = ""

    @property
    def state(self) -> AlarmState:
        if self.active:
            return AlarmState.ACTIVE_ACKED if self.acked else AlarmState.ACTIVE_UNACKED
        if not self.acked:
            return AlarmState.RETURNED_UNACKED
        return AlarmState.LATCHED if self.tripped else AlarmState.NORMAL

    @property
    def in_alarm(self) -> bool:
        """Annunciated: not normal (shelving aside)."""
        return self.state is not AlarmState.NORMAL

    def shelved(self, now: float) -> bool:
        return self.shelved_until is not None and now < self.shelved_until


@dataclass(frozen=True, slots=True)
class AlarmEvent:
    t: float  # Clock.now()
    wall: float
    alarm_id: str
    group: str
    transition: Transition
    state: AlarmState
    severity: Severity
    message: str
    actor: str = ""
    # The message's kind and figures (``AlarmText``) for an activation or a clear: what a
    # screen needs to say the journal's entry in its language ("" and {}: free text).
    code: str = ""
    params: Mapping[str, object] = field(default_factory=dict)


@dataclass
class AlarmManager:
    clock: Clock
    listeners: list[Callable[[AlarmEvent], None]] = field(default_factory=list)
    history: deque[AlarmEvent] = field(default_factory=lambda: deque(maxlen=LOG_LENGTH))
    _alarms: dict[str, Alarm] = field(default_factory=dict)
    # Per channel, the alarms that can hold it (its own, the bench-wide ones reaching it),
    # with the number of alarms declared when the list was made: ``trips`` runs every scan
    # for every channel, and an alarm's group and reach never change once declared.
    _reach: dict[str, tuple[int, list[Alarm]]] = field(default_factory=dict)
    writes: int = 0
    """Changes to its alarms so far, declarations included: a check that finds the count
    it saw at its last evaluation knows that no alarm changed since, without reading each
    one (the channel guard, every scan). Every method that changes an alarm counts it."""

    # --- declaration ------------------------------------------------------------------
    def declare(
        self,
        alarm_id: str,
        *,
        group: str = "",
        severity: Severity = Severity.HIGH,
        latched: bool = False,
        action: str = "hold",
        affects: tuple[str, ...] | None = None,
    ) -> Alarm:
        """An alarm its owner will raise and clear (declared once, at wiring)."""
        if alarm_id in self._alarms:
            raise ValueError(f"alarm {alarm_id!r} is declared twice")
        alarm = Alarm(alarm_id, group, severity, latched, affects, action=action)
        self._alarms[alarm_id] = alarm
        self.writes += 1  # one alarm more: the alarms that reach a channel may change
        return alarm

    def __getitem__(self, alarm_id: str) -> Alarm:
        try:
            return self._alarms[alarm_id]
        except KeyError:
            raise OperatorError(f"unknown alarm {alarm_id!r}") from None

    def __iter__(self) -> Iterator[Alarm]:
        return iter(self._alarms.values())

    def __contains__(self, alarm_id: object) -> bool:
        return alarm_id in self._alarms

    # --- evaluation (by the owning check, every scan) ----------------------------------
    def set(self, alarm: Alarm, active: bool, message: str = "") -> None:
        """The condition as its owner sees it this scan (idempotent; only edges log)."""
        now = self.clock.now()
        if alarm.shelved_until is not None and now >= alarm.shelved_until:
            alarm.shelved_until = None
            self.writes += 1
            self._event(alarm, Transition.UNSHELVED, "shelving expired")
        if active and message and message != alarm.message:
            # Not written again when the same: an alarm that stays active with the same
            # message (an interlock held) does not count as a change every scan.
            alarm.message = str(message)  # a plain str for the events, logs and files
            alarm.code = getattr(message, "code", "")
            alarm.params = getattr(message, "params", {})
            alarm.detail = getattr(message, "detail", "")
            self.writes += 1
        if active == alarm.active:
            return
        alarm.active = active
        self.writes += 1
        if active:
            alarm.acked = False
            alarm.activated_t = now
            if alarm.latched and not alarm.tripped:
                alarm.tripped = True
                # First-out: the first trip of its group since the group was last clear.
                alarm.first_out = not any(
                    a.tripped and a is not alarm and a.group == alarm.group
                    for a in self._alarms.values()
                )
            self._event(alarm, Transition.ACTIVATED, alarm.message, coded=True)
        else:
            self._event(alarm, Transition.CLEARED, alarm.message, coded=True)

    # --- people -----------------------------------------------------------------------
    def acknowledge(self, alarm_id: str, actor: str) -> Alarm:
        alarm = self[alarm_id]
        if alarm.acked:
            raise OperatorError(f"alarm {alarm_id} is not waiting for an acknowledgement")
        alarm.acked = True
        alarm.acked_by = actor
        self.writes += 1
        self._event(alarm, Transition.ACKNOWLEDGED, alarm.message, actor)
        return alarm

    def reset_refusal(self, alarm_id: str) -> str:
        """Why ``reset`` would refuse now, "" when it would not (a screen's button asks)."""
        alarm = self[alarm_id]
        if not alarm.tripped:
            return f"alarm {alarm_id} is not a trip waiting for a reset"
        if alarm.active:
            return f"cannot reset {alarm_id}: the cause is still present ({alarm.message})"
        return ""

    def reset(self, alarm_id: str, actor: str) -> Alarm:
        """Release a trip (acknowledging it if needed); refused while its cause is present."""
        why = self.reset_refusal(alarm_id)
        if why:
            raise OperatorError(why)
        alarm = self[alarm_id]
        if not alarm.acked:
            self.acknowledge(alarm_id, actor)
        alarm.tripped = False
        alarm.first_out = False
        self.writes += 1
        self._event(alarm, Transition.RESET, alarm.message, actor)
        return alarm

    def shelve(self, alarm_id: str, duration_s: float, actor: str) -> Alarm:
        alarm = self[alarm_id]
        if alarm.latched:
            raise OperatorError(
                f"alarm {alarm_id} is a trip: it protects its channel and cannot be shelved"
            )
        if not 0 < duration_s <= 7 * 86400:
            raise OperatorError(f"shelving lasts between 0 s and 7 days, not {duration_s:g} s")
        alarm.shelved_until = self.clock.now() + duration_s
        self.writes += 1
        self._event(alarm, Transition.SHELVED, f"for {duration_s:g} s", actor)
        return alarm

    def unshelve(self, alarm_id: str, actor: str) -> Alarm:
        alarm = self[alarm_id]
        if alarm.shelved_until is None:
            raise OperatorError(f"alarm {alarm_id} is not shelved")
        alarm.shelved_until = None
        self.writes += 1
        self._event(alarm, Transition.UNSHELVED, "by request", actor)
        return alarm

    def silence(self, alarm_ids: Iterable[str], actor: str) -> list[Alarm]:
        """Record that ``actor`` silenced the audible alert of these alarms on their own
        screen (issue 33 finding 7). Silencing is not acknowledging (ISA-18.2): the alarm
        keeps its state and stays annunciated, and another operator's screen still sounds
        it; the record says who silenced what and when, beside the acknowledgements. Only
        the alarms still waiting for an acknowledgement are recorded (one acknowledged in
        the meantime no longer sounds anywhere). An unknown id raises ``OperatorError``
        before anything is recorded."""
        wanted = [self[alarm_id] for alarm_id in dict.fromkeys(alarm_ids)]
        silenced = [a for a in wanted if not a.acked]
        for alarm in silenced:
            self._event(alarm, Transition.SILENCED, "audible alert silenced on their screen", actor)
        return silenced

    # --- restart ----------------------------------------------------------------------
    def restore(
        self,
        alarm_id: str,
        *,
        message: str,
        acked: bool,
        tripped: bool,
        first_out: bool,
        acked_by: str = "",
        activated_t: float | None = None,
    ) -> Alarm:
        """An alarm as it was saved before a restart (``app/retained.py``), its condition
        absent: its owner evaluates the condition again from the first scan, and if it is
        still present the alarm activates again and needs a new acknowledge. Only a trip
        stays tripped, and only a tripped alarm can be first-out."""
        alarm = self[alarm_id]
        alarm.active = False
        alarm.message = message
        alarm.acked = acked
        alarm.tripped = tripped and alarm.latched
        alarm.first_out = first_out and alarm.tripped
        alarm.acked_by = acked_by
        alarm.activated_t = activated_t
        self.writes += 1
        return alarm

    # --- views ------------------------------------------------------------------------
    def in_alarm(self, group: str | None = None) -> list[Alarm]:
        """Annunciated alarms (not shelved), optionally of one group, first-out first."""
        now = self.clock.now()
        out = [
            a
            for a in self._alarms.values()
            if a.in_alarm and not a.shelved(now) and (group is None or a.group == group)
        ]
        out.sort(key=lambda a: (not a.first_out, a.activated_t or 0.0))
        return out

    def trips(self, channel: str) -> list[Alarm]:
        """Trips holding ``channel``: its own and the bench-wide ones that reach it,
        first-out first."""
        reach = self._reach.get(channel)
        if reach is None or reach[0] != len(self._alarms):
            reach = self._reach[channel] = (len(self._alarms), self._reaching(channel))
        out = [a for a in reach[1] if a.tripped]
        if len(out) > 1:
            out.sort(key=lambda a: (not a.first_out, a.activated_t or 0.0))
        return out

    def _reaching(self, channel: str) -> list[Alarm]:
        """The alarms that hold ``channel`` when tripped, in declaration order."""
        return [
            a
            for a in self._alarms.values()
            if a.group == channel or (a.group == "" and (a.affects is None or channel in a.affects))
        ]

    def _event(
        self,
        alarm: Alarm,
        transition: Transition,
        message: str,
        actor: str = "",
        coded: bool = False,
    ) -> None:
        """``coded``: the message is the alarm's own (its ``code`` and ``params`` go along)."""
        now = self.clock.now()
        ev = AlarmEvent(
            now,
            self.clock.to_wall(now),
            alarm.id,
            alarm.group,
            transition,
            alarm.state,
            alarm.severity,
            message,
            actor,
            alarm.code if coded else "",
            dict(alarm.params) if coded and alarm.code else {},
        )
        self.history.append(ev)
        by = f" by {actor}" if actor else ""
        level = logging.WARNING if transition is Transition.ACTIVATED else logging.INFO
        log.log(level, "alarm %s %s%s: %s", alarm.id, transition.value, by, message)
        for fn in self.listeners:
            try:
                fn(ev)
            except Exception:
                log.exception("alarm listener failed")
