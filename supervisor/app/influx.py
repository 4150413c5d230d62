"""Wire the InfluxDB writer into a bench: the I/O map's ``influxdb:`` section → the writer
(``supervisor.publish.influx``), its alarms on the bench's alarm model, its events from the
bench's event feed."""

from __future__ import annotations

import logging
from pathlib import Path

from supervisor.config.models import BenchConfig, InfluxConfig
from supervisor.core.clock import Clock
from supervisor.core.errors import ConfigError
from supervisor.publish.changes import SharedChanges
from supervisor.publish.influx import (
    ALARMS,
    SPOOL_NAME,
    AlarmHook,
    InfluxSettings,
    InfluxWriter,
)
from supervisor.safety import AlarmManager, Severity
from supervisor.tags import TagDB

__all__ = ["build_influx", "influx_settings"]

log = logging.getLogger(__name__)


def influx_settings(cfg: InfluxConfig, state_dir: str | Path) -> InfluxSettings:
    """The writer's settings; ConfigError when the token cannot be read now (the file or
    the variable went away since the I/O map was checked)."""
    try:
        token = cfg.token()
    except ValueError as exc:
        raise ConfigError(f"influxdb: {exc}") from None
    return InfluxSettings(
        url=cfg.url,
        org=cfg.org,
        bucket=cfg.bucket,
        token=token,
        spool_path=Path(state_dir) / SPOOL_NAME,
        batch_size=cfg.batch_size,
        flush_interval_s=cfg.flush_interval_s,
        timeout_s=cfg.timeout_s,
        retry_max_s=cfg.retry_max_s,
        alarm_after_s=cfg.alarm_after_s,
        stop_flush_s=cfg.stop_flush_s,
        spool_max_bytes=cfg.spool_max_bytes,
        commit_interval_s=cfg.spool_commit_interval_s,
    )


def _alarm_hook(alarms: AlarmManager) -> AlarmHook:
    declared = {
        spec.id: alarms.declare(spec.id, severity=Severity.named(spec.severity)) for spec in ALARMS
    }

    def set_alarm(alarm_id: str, active: bool, message: str) -> None:
        alarms.set(declared[alarm_id], active, message)

    return set_alarm


def build_influx(
    cfg: BenchConfig,
    db: TagDB,
    clock: Clock,
    alarms: AlarmManager | None,
    changes: SharedChanges | None = None,
) -> InfluxWriter | None:
    """The writer for ``cfg.influxdb`` (None when the I/O map has none); not started.
    ``changes``: the change feed it shares with the historian (else one of its own)."""
    if cfg.influxdb is None:
        return None
    settings = influx_settings(cfg.influxdb, cfg.state_dir)
    return InfluxWriter(
        db,
        clock,
        settings,
        bench=cfg.bench,
        channels=[c.name for c in cfg.channels],
        alarm=_alarm_hook(alarms) if alarms is not None else None,
        changes=changes.reader() if changes is not None else None,
    )
