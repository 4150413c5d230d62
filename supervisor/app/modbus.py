"""A bench's Modbus TCP server, wired (issue 36; docs/adr/0032-modbus-server.md): the
register map planned from the I/O map, the scan's copy of its changes, the one command path
for writes and the alarm model's trips and acknowledgements for the status registers meet
the server here (the server itself imports none of them, ADR 0003).

- A write becomes a ``write`` command on the one command path (ADR 0008, through
  ``command_path_of`` as OPC UA's writes do) with the actor ``modbus:<client address>``:
  a write of a channel's command tag (mode, manual current, enable, ack, command) is that
  channel's command, checked like any (state table, Auto/Manual, interlocks, limits).
- Modbus has no authentication: only the addresses in ``modbus_server.writers`` may write.
  The command path's role hook refuses any other (``ModbusRoles``), so such a write is
  refused and recorded with its actor like any refused command.
"""

from __future__ import annotations

from typing import Any

from supervisor.app.bench import Bench
from supervisor.app.opcua import command_path_of
from supervisor.commands import Command, Roles
from supervisor.core.driver import Value
from supervisor.publish.modbus.image import BIT
from supervisor.publish.modbus.regmap import plan
from supervisor.publish.modbus.server import ACTOR_PREFIX, ModbusFeed, ModbusServer, WriteAnswer
from supervisor.publish.opcua import Request
from supervisor.safety import AlarmEvent, AlarmManager
from supervisor.tags import Access

__all__ = ["ModbusRoles", "build_modbus"]


class ModbusRoles:
    """The command path's role hook for Modbus actors: a writer's address operates, any
    other may not write; every other actor is asked of ``fallback``."""

    def __init__(self, writers: list[str], fallback: Roles) -> None:
        self.writers = frozenset(writers)
        self.fallback = fallback

    def access_of(self, actor: str) -> Access:
        if not actor.startswith(ACTOR_PREFIX):
            return self.fallback.access_of(actor)
        return Access.OPERATOR if actor[len(ACTOR_PREFIX) :] in self.writers else Access.READ_ONLY

    def refuses(self, command: Command) -> str:
        actor = command.actor
        if not actor.startswith(ACTOR_PREFIX):
            return self.fallback.refuses(command)
        address = actor[len(ACTOR_PREFIX) :]
        if address in self.writers:
            return ""
        return f"{address} is not a Modbus writer (modbus_server.writers)"


def build_modbus(bench: Bench) -> ModbusServer | None:
    """The Modbus TCP server of ``bench`` (None when its I/O map has no ``modbus_server:``);
    not started: ``await server.start()`` before the scan runs, ``await server.stop()``
    after the bench's shutdown."""
    cfg = bench.cfg.modbus_server
    if cfg is None:
        return None
    regmap = plan(bench.cfg, bench.db)
    # The scan's copy of its changes that the historian, InfluxDB and OPC UA read (from
    # now: the server starts with every tag).
    feed = ModbusFeed(bench.db, bench.changes.reader() if bench.changes is not None else None)
    bench.engine.publishers.append(feed)
    bench.commands.roles = ModbusRoles(cfg.writers, bench.commands.roles)
    operate = command_path_of(bench)

    async def write(tag: str, value: Value, actor: str) -> WriteAnswer:
        answer = await operate(Request("bench", "", "write", {"tag": tag, "value": value}, actor))
        return WriteAnswer(answer.accepted, answer.reason, answer.refusal)

    server = ModbusServer(
        regmap,
        bench.db,
        feed,
        write,
        host=cfg.host,
        port=cfg.port,
        writes=cfg.writes,
        max_clients=cfg.max_clients,
        gate=bench.gate,
        period_s=bench.cfg.scan.period_s,
    )
    if bench.alarms is not None:
        _listen(bench.alarms, server)
    return server


def alarm_flags(alarms: AlarmManager) -> dict[str, int]:
    """Each alarm group's (a channel's, "" the bench's) tripped and unacknowledged bits."""
    out: dict[str, int] = {}
    for a in alarms:
        bits = (BIT["tripped"] if a.tripped else 0) | (0 if a.acked else BIT["unacked"])
        if bits:
            out[a.group] = out.get(a.group, 0) | bits
    return out


def _listen(alarms: AlarmManager, server: ModbusServer) -> None:
    # Transitions are rare (a trip, an acknowledge): the few dozen alarms are looked at
    # then, and the server's thread reads the dict it is handed.
    def on_alarm(_: AlarmEvent | Any) -> None:
        server.on_alarms(alarm_flags(alarms))

    server.on_alarms(alarm_flags(alarms))
    alarms.listeners.append(on_alarm)
