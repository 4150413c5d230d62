"""Wire the Sparkplug B edge node into a bench: the I/O map's ``sparkplug:`` section → the
publisher (``supervisor.publish.sparkplug``); its bdSeq in the bench's retained state."""

from __future__ import annotations

import asyncio
import logging
import socket
from pathlib import Path
from typing import TYPE_CHECKING

from supervisor.commands import Command, CommandPath, Verb
from supervisor.config.models import BenchConfig
from supervisor.core.clock import Clock
from supervisor.publish.changes import SharedChanges
from supervisor.publish.retain import RetainStore
from supervisor.safety import AlarmManager, Severity
from supervisor.tags import TagDB

if TYPE_CHECKING:  # imported when a bench has the section: paho-mqtt and protobuf cost
    # about 0.1 s of every command's start-up (``supervisor check``) otherwise.
    from supervisor.publish.sparkplug import CommandHandler, Reply, SparkplugPublisher

__all__ = ["build_sparkplug", "command_handler", "keep_bd_seq", "screens_url"]

log = logging.getLogger(__name__)


def build_sparkplug(
    cfg: BenchConfig,
    db: TagDB,
    clock: Clock,
    changes: SharedChanges | None = None,
    alarms: AlarmManager | None = None,
) -> SparkplugPublisher | None:
    """The edge node for ``cfg.sparkplug`` (None when the I/O map has none); not started.
    Its spool in ``<state_dir>``, its alarms on ``alarms``."""
    sp = cfg.sparkplug
    if sp is None:
        return None
    from supervisor.publish.sparkplug import (
        ALARMS,
        SPOOL_NAME,
        CommandSettings,
        SparkplugPublisher,
        SparkplugSettings,
    )

    hook = None
    if alarms is not None:
        declared = {
            spec.id: alarms.declare(spec.id, severity=Severity.named(spec.severity))
            for spec in ALARMS
        }

        def hook(alarm_id: str, active: bool, message: str) -> None:
            alarms.set(declared[alarm_id], active, message)

    settings = SparkplugSettings(
        host=sp.host,
        port=sp.port,
        group=sp.group,
        edge_node=sp.edge_node or cfg.bench,
        keepalive_s=sp.keepalive_s,
        spool_path=Path(cfg.state_dir) / SPOOL_NAME,
        spool_max_bytes=sp.spool_max_mb * 1024 * 1024,
        disconnected_alarm_s=sp.disconnected_alarm_s,
        commands=CommandSettings(sp.commands.enabled, sp.commands.primary_host),
    )
    return SparkplugPublisher(
        db,
        clock,
        settings,
        channels=[c.name for c in cfg.channels],
        devices=list(cfg.devices),
        changes=changes.reader() if changes is not None else None,
        alarm=hook,
        active_alarms=(lambda: len(alarms.in_alarm())) if alarms is not None else None,
    )


def keep_bd_seq(publisher: SparkplugPublisher, store: RetainStore | None) -> None:
    """Keep the bdSeq in ``store`` (the bench's retained state), or in memory without one
    (a bench built without retained state: each start begins at 0 again)."""
    from supervisor.publish.sparkplug import MemoryBdSeq, RetainedBdSeq

    publisher.bd_seq_store = RetainedBdSeq(store) if store is not None else MemoryBdSeq()


def command_handler(path: CommandPath, loop: asyncio.AbstractEventLoop) -> CommandHandler:
    """A DCMD's channel command (from the MQTT thread) run by the bench's one command path
    on ``loop`` (ADR 0008), its answer handed back to the edge node."""

    def handle(channel: str, verb: str, actor: str, reply: Reply) -> None:
        command = Command.channel(channel, Verb(verb), actor)

        async def run() -> None:
            try:
                result = await path.execute_async(command)
            except Exception as exc:  # execute refuses, never raises: a bug
                log.exception("Sparkplug command %s on %s failed", verb, channel)
                reply(False, f"internal error: {exc}")
                return
            reply(result.accepted, result.reason)

        try:
            asyncio.run_coroutine_threadsafe(run(), loop)
        except RuntimeError:  # the loop is closed: the bench is stopping
            reply(False, "the bench is stopping")

    return handle


def screens_url(host: str, port: int) -> str:
    """The HMI's URL as another machine reaches it (``hmi.url``): an address that listens
    on every interface is this host's name."""
    if host in ("", "0.0.0.0", "::"):
        host = socket.getfqdn()
    if ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{port}/"
