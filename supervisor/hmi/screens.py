"""The operator screens on the HTTP API: access, live data, layout and the page's files
(docs/adr/0016-hmi-sessions-live-data.md). ``install_screens`` adds them to an ``HttpApi``
before it starts; its routes and answers stay as they were."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from supervisor.config.models import HmiConfig
from supervisor.config.users import UserStore
from supervisor.core.logins import LoginThrottle
from supervisor.hmi.auth import HmiAccess, HmiRoles, Sessions
from supervisor.hmi.commands_api import add_command_bar_route
from supervisor.hmi.layout import BenchView, Layout
from supervisor.hmi.live import QUEUE_SIZE, LiveHub
from supervisor.hmi.server import HttpApi
from supervisor.hmi.static import StaticFiles

DEFAULT_ROOT = Path(__file__).resolve().parents[2] / "hmi"
"""The front end's directory: ``hmi/`` of the checkout (the package is installed editable,
``make``), wherever the supervisor is started from."""


@dataclass
class Screens:
    access: HmiAccess
    sessions: Sessions
    live: LiveHub
    layout: Layout | None
    static: StaticFiles


def install_screens(
    api: HttpApi,
    cfg: HmiConfig,
    users: UserStore | None,
    bench: BenchView | None = None,
    root: Path = DEFAULT_ROOT,
    queue_size: int = QUEUE_SIZE,
    throttle: LoginThrottle | None = None,
) -> Screens:
    """Add login, ``/api/ws``, ``/api/bench|diagnostics``, a channel's program and command
    bar, and the static files to ``api``; the command path's role hook learns the HMI's users. The
    caller gives ``screens.live`` to the scan (a publisher) and to the bench's events.
    ``throttle``: the bench's failed-login counts, shared with OPC UA (else its own)."""
    sessions = Sessions(cfg.session_timeout_s, api.clock.now)
    throttle = throttle or LoginThrottle(api.clock.now)
    access = HmiAccess(users, sessions, cfg.login, cfg.anonymous_read, throttle)
    access.alarm_sound_repeat_s = cfg.alarm_sound_repeat_s  # the page's (alarmsound.js)
    access.install(api.app)
    api.commands.roles = HmiRoles(users, api.commands.roles)
    live = LiveHub(
        api.db,
        api.clock,
        cfg.publish_period_s,
        api.commands.alarms,
        queue_size,
        max_clients=cfg.max_websockets,
    )
    live.install(api.app)
    # What a channel's command bar may give now (issue 33): a button follows the state.
    add_command_bar_route(api.app, api.commands, api.actor)
    layout = None
    if bench is not None:
        layout = Layout(bench, api.clock)
        layout.install(api.app)
    static = StaticFiles(root)
    static.install(api.app)
    return Screens(access, sessions, live, layout, static)
