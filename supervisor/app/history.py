"""Historian wiring: when a bench records history, where, and which alarms say it failed.

The embedded historian (``supervisor.publish.historian``) is the default store of history:
on unless the I/O map configures InfluxDB (``influxdb:``) or switches it off
(``history: {enabled: false}``). Its file is ``<state_dir>/<history.path>``. It is a scan
publisher (the tag changes) and a sink of the bench's ``EventFeed`` (step and state
changes, alarm transitions, operator commands with their actor). Its three alarms are
declared here, in the alarm model, at medium priority (the bench keeps running safely;
the operator must act for the record): ``historian.corrupt`` (a file set aside, waits for
an acknowledge), ``historian.write`` (writes fail: disk full, read-only), and
``historian.overflow`` (samples dropped, the disk slower than the scan) and
``historian.crashed`` (the writer's thread crashed and started again: waits for an
acknowledge).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from supervisor.app.events import EventFeed
from supervisor.config.models import BenchConfig
from supervisor.publish.historian import ALARMS, Historian, writer_settings
from supervisor.safety import Severity

if TYPE_CHECKING:
    from supervisor.app.bench import Bench

ALARM_SEVERITY = Severity.MEDIUM


def history_enabled(cfg: BenchConfig) -> bool:
    """``history.enabled`` when given; otherwise on unless InfluxDB is configured."""
    if cfg.history.enabled is not None:
        return cfg.history.enabled
    return cfg.influxdb is None


def history_path(cfg: BenchConfig) -> Path:
    return Path(cfg.state_dir) / cfg.history.path


def attach_historian(bench: Bench) -> Historian | None:
    """The bench's historian, fed by its scan and its events (None when not enabled).
    Opened by ``Bench.start``, flushed and closed by ``Bench.shutdown``."""
    cfg = bench.cfg
    if not history_enabled(cfg):
        return None
    alarms = bench.alarms
    assert alarms is not None
    declared = {a: alarms.declare(a, severity=ALARM_SEVERITY) for a in ALARMS}

    def hook(alarm_id: str, active: bool, message: str) -> None:
        alarms.set(declared[alarm_id], active, message)

    historian = Historian(
        bench.db,
        bench.clock,
        history_path(cfg),
        writer_settings(cfg.history),
        alarm=hook,
        changes=bench.change_reader(),
    )
    historian.writer.gate = bench.gate
    feed = EventFeed()
    feed.sinks.append(historian)
    feed.attach(bench)
    bench.engine.publishers.append(historian)
    return historian
