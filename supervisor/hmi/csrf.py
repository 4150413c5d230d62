"""No command from another page: cross-site request forgery (issue 27, finding 2).

A page of any other origin the operator's browser visits (another port of the same host
included: SameSite cookies do not tell ports apart) can make the browser send a form or a
``fetch(..., {mode: "no-cors"})`` to the bench. OWASP's CSRF cheat sheet ("Verifying
Origin With Standard Headers" and "custom request content type"), for every request that
changes something (POST, PUT, PATCH, DELETE) and the WebSocket's handshake:

- the request's source origin, from ``Origin`` or else ``Referer``, must be the request's
  own (``scheme://Host`` as received) or one of ``hmi.allowed_origins``: 403 otherwise,
  naming the origin received;
- the body must be declared ``application/json``: 415 otherwise. A page can send
  ``text/plain``, a form or no type at all to another origin without asking, never JSON
  (that needs a CORS preflight, which this server never grants), so a client with neither
  header (curl, scripts: browsers send ``Origin`` with such requests) is accepted only
  with it.

Reads (GET, HEAD) are left alone: another origin's page cannot read their answers.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterable
from typing import Any, Final

from aiohttp import hdrs, web

from supervisor.config.models import web_origin

STATE_CHANGING: Final = frozenset({"POST", "PUT", "PATCH", "DELETE"})
JSON_TYPE: Final = "application/json"

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def _refuse(status: int, error: str, reason: str) -> web.Response:
    body: dict[str, Any] = {"accepted": False, "error": error, "reason": reason}
    return web.json_response(body, status=status)


class RequestOrigins:
    """The middleware (``install``) refusing cross-origin commands and non-JSON bodies."""

    def __init__(self, allowed_origins: Iterable[str] = ()) -> None:
        self.allowed = frozenset(o for o in (web_origin(a) for a in allowed_origins) if o)

    def install(self, app: web.Application) -> None:
        # First in the chain: a forged request is refused before a session is looked up.
        app.middlewares.insert(0, self._middleware)

    def refusal(self, request: web.Request) -> web.Response | None:
        """The answer refusing ``request``, or None when it may go on."""
        upgrade = request.headers.get(hdrs.UPGRADE, "").lower() == "websocket"
        if request.method not in STATE_CHANGING and not upgrade:
            return None
        if request.match_info.http_exception is not None:
            return None  # no such route or method (404, 405): nothing runs, nothing changes
        refused = self._foreign(request)
        if refused is not None:
            return refused
        if upgrade:
            return None
        if request.content_type != JSON_TYPE or hdrs.CONTENT_TYPE not in request.headers:
            received = request.headers.get(hdrs.CONTENT_TYPE, "none")
            return _refuse(
                415,
                "unsupported media type",
                f"{request.method} {request.path} needs Content-Type: {JSON_TYPE}, a body or"
                f" not (received {received[:100]!r})",
            )
        return None

    def _foreign(self, request: web.Request) -> web.Response | None:
        """403 when the request comes from a page of another origin."""
        origin = request.headers.get(hdrs.ORIGIN)
        source = "Origin"
        if origin is None:
            referer = request.headers.get(hdrs.REFERER)
            if referer is None:
                return None  # not a browser's page (curl, a script): JSON type required
            origin, source = referer, "Referer"
        own = web_origin(f"{request.scheme}://{request.host}")
        found = web_origin(origin)
        if found is not None and (found == own or found in self.allowed):
            return None
        allowed = ", ".join(sorted({own or "?", *self.allowed}))
        return _refuse(
            403,
            "cross-origin request",
            f"{request.method} {request.path} refused: it comes from a page of another origin"
            f" ({source} {origin[:200]!r}); allowed: {allowed} (hmi.allowed_origins)",
        )

    @web.middleware
    async def _middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        refused = self.refusal(request)
        if refused is not None:
            return refused
        return await handler(request)
