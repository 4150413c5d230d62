"""A bench's operator screens, wired (the composition root: the users file, the scan's
publisher list and the bench's events meet the HMI here; ``supervisor.hmi`` imports none
of them, ADR 0003)."""

from __future__ import annotations

from pathlib import Path

from supervisor.app.bench import Bench
from supervisor.app.events import EventFeed
from supervisor.app.logins import login_throttle
from supervisor.audit import audit_path
from supervisor.config.models import HmiConfig
from supervisor.config.users import UserStore
from supervisor.hmi import HttpApi
from supervisor.hmi.audit_api import add_audit_routes
from supervisor.hmi.journal_api import add_journal_routes
from supervisor.hmi.live import QUEUE_SIZE
from supervisor.hmi.screens import DEFAULT_ROOT, Screens, install_screens
from supervisor.publish.opcua import OpcUaSettings

__all__ = ["build_screens"]


def build_screens(
    bench: Bench,
    api: HttpApi,
    root: Path = DEFAULT_ROOT,
    queue_size: int = QUEUE_SIZE,
    cfg: HmiConfig | None = None,
) -> Screens:
    """The screens of ``bench`` on ``api`` (before ``api.start()``). The users are the OPC UA
    users (one file, ``opcua.users_file`` or ``<state_dir>/opcua/users.yaml``). Raises
    ``ConfigError`` for a bad users file. ``cfg``: instead of the I/O map's ``hmi:``
    (tests)."""
    cfg = cfg or bench.cfg.hmi
    users = UserStore(OpcUaSettings.of(bench.cfg).users_file) if cfg.login else None
    # Failed logins are counted with OPC UA's: one throttle per bench.
    throttle = login_throttle(bench) if cfg.login else None
    screens = install_screens(api, cfg, users, bench, root, queue_size, throttle)
    # The audit trail: its logins recorded; read by engineers (the bench's file, whoever
    # writes it: a bench built without its log still shows what the file holds).
    screens.access.audit = bench.audit
    add_audit_routes(api.app, audit_path(bench.cfg.state_dir))
    # The alarm journal: the historian's alarm events when it records (ADR 0048).
    if bench.alarms is not None:
        add_journal_routes(
            api.app,
            bench.alarms,
            lambda: bench.historian.query if bench.historian is not None else None,
            lambda group: group if group in bench.runners else "",
        )
    bench.engine.publishers.append(screens.live)
    events = EventFeed()
    events.sinks.append(screens.live)
    events.attach(bench)
    return screens
