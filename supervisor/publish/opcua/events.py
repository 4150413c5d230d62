"""Events: chain steps and operator commands (BenchEventType), alarms (AlarmConditionType).

A ``BenchEvent`` (supervisor.core.records) becomes a **ChainEventType** event (a step,
state or message of a chain) or a **CommandEventType** event (an operator command,
accepted or refused, with its actor), both subtypes of **BenchEventType** whose properties
say where and who (``Channel``, ``Kind``, ``Source``, ``Actor``, ``TestId``, ``Recipe``).
Each is notified on its channel's object (or the Bench object) and on the Server object,
where SCADA clients usually subscribe.

An alarm transition becomes an **AlarmConditionType** event (Part 9) carrying ConditionName
(the alarm id), ConditionId (its object under Bench/Alarms), ActiveState, AckedState,
Severity, Retain (true until the alarm is back to normal, ISA-18.2, and while it is
shelved), ConfirmedState (false while a trip waits for its reset), the shelving state
(ShelvingState/CurrentState, UnshelveTime, SuppressedOrShelved) and the message; the state
machine stays in the alarm model (``supervisor.safety``), never in OPC UA (ADR 0015).

``ConditionRefresh`` (Part 9 §5.5.7) replays the last event of each condition whose state
is retained, between a RefreshStartEvent and a RefreshEndEvent, to the calling
subscription's monitored items on the Server object and on the condition's source. asyncua
replays the last retained event it happened to be given, so a condition whose closing event
never reached the server (lost in the feed's bounded queue, or still on its way while the
client refreshes) was replayed as open although the alarm model had closed it (issue 31,
finding 8). Before each refresh the server therefore hands the alarm model's current views
in (``stale``): a view newer than the last one sent, in another state, is sent first, so a
refresh replays exactly the conditions retained now.

Each condition remembers the EventIds it sent (``Occurrences``): Acknowledge and Confirm
name the event the operator saw, and only an event of the occurrence still waiting (sent
since the condition was last acknowledged, or confirmed) may be acknowledged (confirmed)
with it (Part 9 §5.7.3, issue 31 finding 3): an EventId this condition never sent (or
sent so long ago it was forgotten) is Bad_EventIdUnknown; one of an occurrence already
acknowledged Bad_ConditionBranchAlreadyAcked, even when a new occurrence now waits: the
operator never saw that one.
"""

from __future__ import annotations

import copy
import dataclasses
import time
import uuid
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Final, Literal

from asyncua import Server, ua

from supervisor.core.records import BenchEvent
from supervisor.publish.opcua.feed import AlarmView
from supervisor.publish.opcua.space import Built

VT = ua.VariantType
LT = VT.LocalizedText
SEVERITY_CHAIN = 100
SEVERITY_COMMAND = 200
SEVERITY_REFUSED = 400
"""Event severities (1..1000): steps are information, a refused command is worth a look."""
REMEMBERED: Final = 1024
"""EventIds kept per condition: an alarm list acknowledges what it shows, the last few."""

Waiting = Literal["acked", "confirmed"]
"""What an Acknowledge or a Confirm changes: AckedState, ConfirmedState."""
ALREADY: Final = {
    "acked": ua.StatusCodes.BadConditionBranchAlreadyAcked,
    "confirmed": ua.StatusCodes.BadConditionBranchAlreadyConfirmed,
}


def _state(a: AlarmView) -> tuple[object, ...]:
    return (a.state, a.active, a.acked, a.tripped, a.shelved)


def stale(sent: Mapping[str, AlarmView], current: Iterable[AlarmView]) -> list[AlarmView]:
    """The alarms of ``current`` (the alarm model's views now) whose state the server has
    not sent (``sent``: the last view sent per alarm): one as new as the last sent or newer,
    in another state; one never sent that is retained. A view older than the last sent (the
    snapshot the server's process was started with, ADR 0029) changes nothing."""
    out = []
    for v in current:
        last = sent.get(v.id)
        if last is None:
            if v.retained:
                out.append(v)
        elif v.wall >= last.wall and _state(v) != _state(last):
            out.append(v)
    return out


async def _mark(items: Any, generator: Any, targets: list[int]) -> None:
    """A RefreshStartEvent or RefreshEndEvent (asyncua's generator of it) to ``targets``."""
    if generator is None:
        return
    _stamp(generator.event, time.time())
    for m in targets:
        await items._trigger_event(generator.event, m)


@dataclass
class Occurrences:
    """The EventIds one condition sent, and which of them name the occurrence that still
    waits for an acknowledgement (a confirmation): those sent while AckedState
    (ConfirmedState) was false and since it was last true. An occurrence ends, for
    Acknowledge, with the first event that is acknowledged: its ``epoch`` moves on."""

    sent: OrderedDict[bytes, tuple[int, int, bool, bool]] = dataclasses.field(
        default_factory=OrderedDict
    )
    """EventId → (acked epoch, confirmed epoch, acked, confirmed) when it was sent."""
    epoch: dict[str, int] = dataclasses.field(default_factory=lambda: {"acked": 0, "confirmed": 0})

    def record(self, event_id: bytes, acked: bool, confirmed: bool) -> None:
        if acked:
            self.epoch["acked"] += 1
        if confirmed:
            self.epoch["confirmed"] += 1
        self.sent[event_id] = (self.epoch["acked"], self.epoch["confirmed"], acked, confirmed)
        while len(self.sent) > REMEMBERED:
            self.sent.popitem(last=False)

    def refusal(self, event_id: bytes, what: Waiting) -> tuple[int, str] | None:
        """Why ``event_id`` does not name the occurrence waiting for ``what`` (None: it
        does)."""
        known = self.sent.get(event_id)
        if known is None:
            return ua.StatusCodes.BadEventIdUnknown, "this condition never sent that EventId"
        acked_epoch, confirmed_epoch, acked, confirmed = known
        epoch, done = (acked_epoch, acked) if what == "acked" else (confirmed_epoch, confirmed)
        if done or epoch != self.epoch[what]:
            word = "acknowledged" if what == "acked" else "confirmed"
            return ALREADY[what], f"the occurrence of that EventId was {word} already"
        return None


def _utc(wall: float) -> datetime:
    return datetime.fromtimestamp(wall, UTC)


def _stamp(event: Any, wall: float) -> None:
    """What ``EventGenerator.trigger`` sets before an event goes out."""
    event.EventId = ua.Variant(uuid.uuid4().hex.encode("utf-8"), ua.VariantType.ByteString)
    event.Time = _utc(wall)
    event.ReceiveTime = datetime.now(UTC)
    local = ua.uaprotocol_auto.TimeZoneDataType()
    lt = time.localtime(wall)
    local.Offset = lt.tm_gmtoff // 60
    local.DaylightSavingInOffset = bool(lt.tm_isdst > 0)
    event.LocalTime = local


class EventPublisher:
    """Fires events into asyncua's subscriptions (runs on the server's loop)."""

    def __init__(self, server: Server, built: Built, bench: str) -> None:
        self.server = server
        self.built = built
        self.bench = bench
        self._templates: dict[str, Any] = {}
        self._server_node = ua.NodeId(ua.ObjectIds.Server)
        self._occurrences: dict[ua.NodeId, Occurrences] = {}
        self._sent: dict[str, AlarmView] = {}  # alarm id → the last view sent as an event
        # condition → its last event, as notified on its source and on the Server, while
        # it is retained: what ConditionRefresh replays.
        self._retained: dict[ua.NodeId, tuple[Any, Any]] = {}

    def stale(self, current: Iterable[AlarmView]) -> list[AlarmView]:
        """The views of ``current`` to send before a refresh (module function ``stale``)."""
        return stale(self._sent, current)

    async def refresh(self, subscription_id: int, item: int | None) -> int:
        """Replay the retained conditions to a subscription (``item``: to that monitored
        item only, ConditionRefresh2): RefreshStartEvent, the last event of each retained
        condition, RefreshEndEvent. The status code of the call."""
        subs = self.server.iserver.subscription_service
        sub = subs.subscriptions.get(subscription_id)
        if sub is None:
            return int(ua.StatusCodes.BadSubscriptionIdInvalid)
        items = sub.monitored_item_srv
        if item is not None and item not in items._monitored_items:
            return int(ua.StatusCodes.BadMonitoredItemIdInvalid)
        # Start and End go to each of the subscription's event items (or the one named);
        # a condition's events to the items on its emitting node, as live ones do.
        every = [m for ms in items._monitored_events.values() for m in ms]
        targets = every if item is None else [item]
        marks = subs.standard_events
        await _mark(items, marks.get(ua.ObjectIds.RefreshStartEventType), targets)
        for pair in list(self._retained.values()):  # a snapshot: events go on meanwhile
            for event in pair:
                for m in items._monitored_events.get(event.emitting_node, ()):
                    if m in targets:
                        await items._trigger_event(event, m)
        await _mark(items, marks.get(ua.ObjectIds.RefreshEndEventType), targets)
        return int(ua.StatusCodes.Good)

    def refusal(
        self, condition: ua.NodeId, event_id: object, what: Waiting
    ) -> tuple[int, str] | None:
        """Why an Acknowledge (``acked``) or a Confirm (``confirmed``) of ``condition``
        naming ``event_id`` is refused (None: ``event_id`` names its waiting occurrence)."""
        occurrences = self._occurrences.get(condition)
        if occurrences is None or not isinstance(event_id, bytes):
            return ua.StatusCodes.BadEventIdUnknown, "this condition never sent that EventId"
        return occurrences.refusal(event_id, what)

    async def init(self) -> None:
        """One event object per type, copied for each event (a generator's event object is
        stateful, and asyncua keeps a reference to each retained condition)."""
        for key, etype in (
            ("chain", self.built.chain_event),
            ("command", self.built.command_event),
            ("alarm", ua.NodeId(ua.ObjectIds.AlarmConditionType)),
        ):
            gen = await self.server.get_event_generator(etype, self.built.bench)
            self._templates[key] = gen.event
        # The channel objects and the Server also generate these (GeneratesEvent refs).
        for node in (*self.built.channels.values(), self._server_node):
            for key in ("chain", "command", "alarm"):
                ref = ua.AddReferencesItem()
                ref.IsForward = True
                ref.ReferenceTypeId = ua.NodeId(ua.ObjectIds.GeneratesEvent)
                ref.SourceNodeId = node
                ref.TargetNodeClass = ua.NodeClass.ObjectType
                ref.TargetNodeId = self._templates[key].EventType
                await self.server.iserver.isession.add_references([ref])

    def _source(self, channel: str) -> tuple[ua.NodeId, str]:
        node = self.built.channels.get(channel)
        return (node, channel) if node is not None else (self.built.bench, self.bench)

    async def _fire(self, event: Any) -> Any:
        """Notify on the source's object, then on the Server object (that copy returned)."""
        subs = self.server.iserver.subscription_service
        event.emitting_node = event.SourceNode
        await subs.trigger_event(event)
        at_server = copy.copy(event)
        at_server.emitting_node = self._server_node
        await subs.trigger_event(at_server)
        return at_server

    async def bench_event(self, ev: BenchEvent) -> None:
        key = "command" if ev.kind == "command" else "chain"
        event = copy.deepcopy(self._templates[key])
        source, name = self._source(ev.channel)
        event.SourceNode = source
        event.SourceName = name
        event.Message = ua.LocalizedText(ev.text)
        refused = key == "command" and ": refused" in ev.text
        event.Severity = (
            SEVERITY_REFUSED
            if refused
            else SEVERITY_COMMAND
            if key == "command"
            else SEVERITY_CHAIN
        )
        for field, value in (
            ("Channel", ev.channel),
            ("Kind", ev.kind),
            ("Source", ev.source),
            ("Actor", ev.actor),
            ("TestId", ev.test_id),
            ("Recipe", ev.recipe),
        ):
            setattr(event, field, value)
        _stamp(event, ev.wall)
        await self._fire(event)

    async def alarm(self, a: AlarmView) -> None:
        event = copy.deepcopy(self._templates["alarm"])
        source, name = self._source(a.group)
        condition = self.built.alarms.get(a.id)
        event.SourceNode = source
        event.SourceName = name
        event.ConditionName = a.id
        event.NodeId = condition  # the ConditionId: the alarm's object
        event.Message = ua.LocalizedText(a.message or a.id)
        event.Severity = max(1, min(1000, a.severity))
        event.LastSeverity = event.Severity
        event.Retain = a.retained
        event.Quality = ua.StatusCode(ua.StatusCodes.Good)
        event.ClientUserId = a.actor
        event.BranchId = ua.NodeId()
        shelving, state_id = (
            ("TimedShelved", ua.ObjectIds.ShelvedStateMachineType_TimedShelved)
            if a.shelved
            else ("Unshelved", ua.ObjectIds.ShelvedStateMachineType_Unshelved)
        )
        for field, value in (
            ("EnabledState", ua.LocalizedText("Enabled")),
            ("EnabledState/Id", True),
            ("ActiveState", ua.LocalizedText("Active" if a.active else "Inactive")),
            ("ActiveState/Id", a.active),
            ("AckedState", ua.LocalizedText("Acknowledged" if a.acked else "Unacknowledged")),
            ("AckedState/Id", a.acked),
        ):
            setattr(event, field, value)
        # Optional fields of AlarmConditionType (declared with their types: asyncua encodes
        # an event's fields by the types it knows). A latched trip is confirmed by its reset
        # (ISA-18.2 reset ~ Part 9 Confirm); the shelving state is the alarm model's.
        for field, value, vt in (
            ("ConfirmedState", ua.LocalizedText("Unconfirmed" if a.tripped else "Confirmed"), LT),
            ("ConfirmedState/Id", not a.tripped, VT.Boolean),
            ("ShelvingState/CurrentState", ua.LocalizedText(shelving), LT),
            ("ShelvingState/CurrentState/Id", ua.NodeId(state_id), VT.NodeId),
            ("ShelvingState/UnshelveTime", a.unshelve_s * 1000.0, VT.Double),
            ("SuppressedOrShelved", a.shelved, VT.Boolean),
        ):
            event.add_property(field, value, vt)
        _stamp(event, a.wall or time.time())
        if condition is None:
            await self._fire(event)
            return
        occurrences = self._occurrences.setdefault(condition, Occurrences())
        occurrences.record(event.EventId.Value, a.acked, not a.tripped)
        self._sent[a.id] = a
        at_server = await self._fire(event)
        if a.retained:
            self._retained[condition] = (event, at_server)
        else:
            self._retained.pop(condition, None)
