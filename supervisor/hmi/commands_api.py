"""``GET /api/channels/{channel}/commands``: what a channel's command bar may give now, for
the user asking (issue 33, finding 2). Each button of the bar (``CHANNEL_BAR``: load, the
chain's commands, acknowledge, auto and manual, the manual setpoint, enable on and off; and
force) with the command path's answer ahead (``CommandPath.available``): accepted, or
refused with the kind and the reason ``execute`` would give. The screen enables a button
only when it would be accepted and shows the reason as its tooltip when not; the answer is
advice, never a permission: the command itself is checked again when it is given.

The answer also names the channel's state and test (recipe, test id), which the
confirmation dialogs of the screen quote.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from aiohttp import web

from supervisor.commands import CommandPath, Result


def _button(r: Result) -> dict[str, Any]:
    # The status the command would be answered with: the screen words a refusal ahead as
    # it words one sent ("Refused (409): …").
    return {
        "accepted": r.accepted,
        "kind": r.kind.value,
        "reason": r.reason,
        "status": r.http_status,
    }


def add_command_bar_route(
    app: web.Application, commands: CommandPath, actor: Callable[[web.Request], str]
) -> None:
    """Add the route; ``actor``: who a request is (the login middleware's user)."""

    async def bar(request: web.Request) -> web.Response:
        channel = request.match_info["channel"]
        runner = commands.runners.get(channel)
        if runner is None:
            known = ", ".join(commands.runners) or "none"
            reason = f"unknown channel {channel!r} (channels: {known})"
            body = {"accepted": False, "kind": "not found", "reason": reason}
            return web.json_response(body, status=404)
        who = actor(request)
        answers = commands.available(channel, who)
        db = commands.db
        return web.json_response(
            {
                "channel": channel,
                "actor": who,
                "state": runner.state.value,
                "recipe": runner.program.name if runner.program is not None else "",
                "test_id": str(db[f"{channel}.chain.test_id"].value or ""),
                "commands": {key: _button(r) for key, r in answers.items()},
            }
        )

    app.add_routes([web.get("/api/channels/{channel}/commands", bar)])
