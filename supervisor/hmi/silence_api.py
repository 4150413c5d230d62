"""``POST /api/alarms/silence``: an operator silenced the alarm sound of their own screen
(issue 33 finding 7, docs/adr/0043-alarm-sound.md).

The sound is the screen's (``hmi/js/alarmsound.js``): each logged-in user's page sounds
the unacknowledged alarms of high and critical priority until they are acknowledged or
silenced there. A silence stops that one screen only and changes no alarm; it is recorded
here, with its actor and time, in the alarms' journal beside the acknowledgements
(``AlarmManager.silence``: the history of ``GET /api/alarms``, the log, the event feed).
Any logged-in user may silence (a viewer's screen sounds too: silencing it commands
nothing); without a session the login middleware has already answered 401, and the
same-origin and JSON rules of every POST apply (``supervisor.hmi.csrf``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Final

from aiohttp import web

from supervisor.audit import AuditLog
from supervisor.core.errors import OperatorError
from supervisor.hmi.body import BodyError, read_json_object, refuse_unknown
from supervisor.safety.alarms import AlarmManager

SILENCE_BODY: Final = '{"alarms": ["alarm id", ...]}'


def _alarm_ids(body: dict[str, Any]) -> list[str]:
    """The body's alarm ids, or a 400 naming what is wrong with them."""
    refuse_unknown(body, ("alarms",), "silence")
    ids = body.get("alarms")
    if not isinstance(ids, list) or not all(isinstance(i, str) and i for i in ids):
        raise BodyError(400, f"silence: body must be JSON {SILENCE_BODY}")
    return ids


def _not_found(reason: str) -> web.Response:
    return web.json_response({"accepted": False, "reason": reason, "kind": "not found"}, status=404)


def add_silence_route(
    app: web.Application,
    alarms: Callable[[], AlarmManager | None],
    actor: Callable[[web.Request], str],
    audit: Callable[[], AuditLog | None] = lambda: None,
) -> None:
    """``POST /api/alarms/silence``; ``alarms`` gives the bench's alarm model (None: a
    supervisor without one), ``actor`` who asks (``HttpApi.actor``), ``audit`` the
    bench's audit trail (supervisor.audit; None: none), where a silence is an entry too —
    an operator's action, as an acknowledgement is."""

    async def silence(request: web.Request) -> web.Response:
        try:
            ids = _alarm_ids(await read_json_object(request, shape=SILENCE_BODY))
        except BodyError as exc:
            return exc.response()
        manager = alarms()
        if manager is None:
            return _not_found("this supervisor has no alarms")
        who = actor(request)
        try:
            silenced = manager.silence(ids, who)
        except OperatorError as exc:  # an unknown alarm: nothing recorded
            return _not_found(str(exc))
        names = [a.id for a in silenced]
        trail = audit()
        if trail is not None and names:  # queued: never waits for the disk, never raises
            trail.append(who, "alarm.silence", ",".join(names), {"alarms": names})
        return web.json_response(
            {
                "accepted": True,
                "kind": "accepted",
                "reason": f"silenced by {who}: {', '.join(names) or 'nothing to silence'}",
                "silenced": names,
            }
        )

    app.add_routes([web.post("/api/alarms/silence", silence)])
