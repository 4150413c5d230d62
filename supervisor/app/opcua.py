"""A bench's OPC UA server, wired (the composition root: the command path, the alarm model
and the event feed meet the server here; the server itself imports none of them, ADR 0003).

- Method calls and writes become ``Command``s on the one command path (ADR 0008), with the
  session's user as the actor (``opcua:<name>``); the path's role hook learns the OPC UA
  users (``OpcUaRoles``) and keeps answering the other actors as before.
- The scan publishes changed tags to the server (``OpcUaFeed``, a scan publisher).
- Chain steps and operator commands reach it through an ``EventFeed``; alarm transitions
  from the alarm model's listeners, with the alarm's whole state (``AlarmView``).
"""

from __future__ import annotations

from collections.abc import Callable

from supervisor.app.bench import Bench
from supervisor.app.events import EventFeed
from supervisor.app.logins import login_throttle
from supervisor.audit import AuditLog
from supervisor.commands import Command, Target, Verb
from supervisor.core.clock import Clock
from supervisor.core.logins import LoginThrottle
from supervisor.publish.opcua import (
    ACTOR_PREFIX,
    AlarmView,
    Answer,
    Layout,
    OpcUaFeed,
    OpcUaProcess,
    OpcUaRoles,
    OpcUaServer,
    OpcUaSettings,
    Operate,
    Request,
    UserStore,
    plan,
)
from supervisor.safety import Alarm, AlarmEvent, AlarmManager

__all__ = ["build_opcua"]


def build_opcua(
    bench: Bench,
    settings: OpcUaSettings | None = None,
    *,
    threaded: bool = True,
    process: bool = False,
) -> OpcUaServer | OpcUaProcess:
    """The OPC UA server of ``bench`` (not started: ``await server.start()`` before the scan
    runs, ``await server.stop()`` after the bench's shutdown). Raises ``ConfigError`` for a
    bad users file.

    ``process``: the server in a process of its own (``OpcUaProcess``, ADR 0029: what
    ``supervisor run`` does on a real clock), else on a thread of the bench's process
    (``threaded``) or on its own loop (a virtual clock's tests)."""
    settings = settings or OpcUaSettings.of(bench.cfg)
    users = UserStore(settings.users_file)
    throttle = login_throttle(bench)  # declares its alarm: before the layout is planned
    # Declares opcua.*: before the layout is planned. It reads the scan's copy of its
    # changes that the historian and InfluxDB read (from now: it starts with every tag).
    changes = bench.changes.reader() if bench.changes is not None else None
    feed = OpcUaFeed(bench.db, changes)
    bench.engine.publishers.append(feed)
    alarms = bench.alarms
    layout = plan(bench.cfg, bench.db, [a.id for a in alarms] if alarms is not None else [])
    bench.commands.roles = OpcUaRoles(users, bench.commands.roles)

    operate = command_path_of(bench)

    def views() -> list[AlarmView]:
        return [] if alarms is None else [alarm_view(a, None, bench.clock) for a in alarms]

    # HistoryRead from the embedded historian when the bench records one (record_history
    # before this call); without it no tag is historised.
    history = bench.historian.query if bench.historian is not None else None
    server: OpcUaServer | OpcUaProcess
    if process:
        server = OpcUaProcess(
            settings,
            bench.db,
            layout,
            feed,
            operate,
            views,
            history_file=history.path if history is not None else None,
            throttle=throttle,
        )
    else:
        server = _in_process(
            bench, settings, layout, feed, operate, users, views, threaded, throttle
        )
    if bench.audit is not None:
        server.on_login = audit_login(bench.audit)
    events = EventFeed()
    events.sinks.append(feed)
    events.attach(bench)
    if alarms is not None:
        _listen(alarms, feed, bench.clock)
    return server


def audit_login(audit: AuditLog) -> Callable[[str, str, str], None]:
    """An OPC UA password login into the audit trail (``opcua:<user>``), as the HMI's are.
    Anonymous sessions check no password and are not entries; a try the throttle refused
    before checking its password is not either (docs/audit.md)."""

    def on_login(outcome: str, user: str, address: str) -> None:
        kind = "login" if outcome == "succeeded" else "login.failed"
        audit.append(ACTOR_PREFIX + user[:64], kind, user[:64], {"address": address})

    return on_login


def command_path_of(bench: Bench) -> Operate:
    """A server's request run by the bench's one command path (ADR 0008)."""

    async def operate(req: Request) -> Answer:
        verb = Verb.parse(req.verb)
        if verb is None:
            return Answer(False, f"unknown command {req.verb!r}", "not found")
        if req.kind == "channel":
            command = Command(Target.channel(req.target), verb, dict(req.args), req.actor)
        elif req.kind == "alarm":
            command = Command(Target.alarm(req.target), verb, dict(req.args), req.actor)
        else:
            command = Command(Target.bench(), verb, dict(req.args), req.actor)
        result = await bench.commands.execute_async(command)
        return Answer(result.accepted, result.reason, "" if result.accepted else result.kind.value)

    return operate


def _in_process(
    bench: Bench,
    settings: OpcUaSettings,
    layout: Layout,
    feed: OpcUaFeed,
    operate: Operate,
    users: UserStore,
    views: Callable[[], list[AlarmView]],
    threaded: bool,
    throttle: LoginThrottle,
) -> OpcUaServer:
    history = bench.historian.query if bench.historian is not None else None
    return OpcUaServer(
        settings,
        bench.db,
        bench.clock,
        layout,
        feed,
        operate,
        users,
        views,
        threaded=threaded,
        history=history,
        gate=bench.gate if threaded else None,  # on the scan's own loop it needs none
        throttle=throttle,
    )


def _listen(alarms: AlarmManager, feed: OpcUaFeed, clock: Clock) -> None:
    def on_alarm(ev: AlarmEvent) -> None:
        feed.on_alarm(alarm_view(alarms[ev.alarm_id], ev, clock))

    alarms.listeners.append(on_alarm)


def alarm_view(a: Alarm, ev: AlarmEvent | None, clock: Clock) -> AlarmView:
    """An alarm as the OPC UA server shows it, after the transition ``ev`` (None: now)."""
    now = clock.now()
    shelved = a.shelved(now)
    return AlarmView(
        id=a.id,
        group=a.group,
        severity=int(a.severity),
        message=a.message,
        state=a.state.value,
        active=a.active,
        acked=a.acked,
        latched=a.latched,
        tripped=a.tripped,
        transition=ev.transition.value if ev is not None else "",
        actor=ev.actor if ev is not None else "",
        wall=ev.wall if ev is not None else clock.wall(),
        shelved=shelved,
        unshelve_s=max(0.0, a.shelved_until - now) if shelved and a.shelved_until else 0.0,
    )
