"""Who is on the HMI: login, sessions and roles (issue 12 "Access", docs/adr/0016).

The users are the OPC UA users (``supervisor.config.users.UserStore``, one file): a
**viewer** sees, an **operator** also commands the channels and acknowledges alarms, an
**engineer** also writes engineer tags and saves recipes.

- ``POST /api/login {"user", "password"}`` opens a session: a random token (256 bits) in an
  HttpOnly, SameSite=Strict cookie ``bench_session`` (the page's scripts never see it, and
  no other site's page can send it; a page on another port of the same host is the same
  site: ``supervisor.hmi.csrf`` refuses its commands by their origin). Sessions live in
  this process only: a restart logs everyone out, which the page survives (it goes back to
  login, keeping its place).
- A session expires after ``hmi.session_timeout_s`` without a request (ISA-101 panels are
  shared: a shift left logged in must not command the next one's bench).
- A wrong user and a wrong password get the same answer (401, "wrong user name or
  password") after the same work (an unknown user is checked against a dummy hash): the
  answer never tells which part was wrong, nor does its time.
- Failed logins are throttled per user and per client address by the bench's one
  ``LoginThrottle`` (``supervisor.core.logins``, shared with OPC UA): past the limit a try
  is refused before its password is checked with 429, ``Retry-After`` and the reason.
- At most ``MAX_SESSIONS_PER_USER`` sessions per user (a new one closes that user's own
  oldest) and ``MAX_SESSIONS`` in all (then 503): one user's logins never close another's
  session.
- Without a session a GET answers as an anonymous viewer when ``hmi.anonymous_read``, else
  401; a write or command always 401. A viewer's command is refused by the command path's
  role hook (``HmiRoles``): 403 with "viewer may not ...". The actor of a command is
  ``hmi:<user>``.
- With ``hmi.login`` false (the default: loopback-only benches and the tests) everyone
  operates, as the actor ``operator``: the behaviour the API had before logins.

A login checks a scrypt hash (about 50 ms): in a worker thread, never on the scan's loop.
"""

from __future__ import annotations

import asyncio
import logging
import math
import secrets
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Final

from aiohttp import web

from supervisor.audit import AuditLog
from supervisor.commands import Command, Verb
from supervisor.commands.roles import Roles
from supervisor.config.users import ANONYMOUS, ROLE_ACCESS, ROLES, Role, User, UserStore
from supervisor.core.logins import LoginThrottle
from supervisor.hmi.body import BodyError, read_json
from supervisor.hmi.server import ACTOR_KEY, json_dumps
from supervisor.tags import Access

log = logging.getLogger(__name__)

COOKIE: Final = "bench_session"
ACTOR_PREFIX: Final = "hmi:"
LOGIN_OFF_ACTOR: Final = "operator"
"""The actor of every command when ``hmi.login`` is false (what the API always used)."""
MAX_SESSIONS: Final = 1000
"""Open sessions kept at most (a script logging in in a loop must not grow the process);
past it a new login is refused (503), never another user's session closed."""
MAX_SESSIONS_PER_USER: Final = 8
"""Open sessions of one user at most (a few panels and browsers); a new login past it
closes that user's own least recently used session, nobody else's (issue 27: a viewer
logging in 1001 times evicted every other session, the operator's included)."""
MAX_CREDENTIAL_CHARS: Final = 1024
LOGIN_CHECKS: Final = 2
"""Password checks (scrypt, ~50 ms of one core each) running at once at most."""
WRONG_CREDENTIALS: Final = "wrong user name or password"
OPEN_PATHS: Final = frozenset({"/api/login", "/api/logout", "/api/session"})
"""API paths answered without a session (they are how one gets or sees one)."""


@dataclass(slots=True)
class Session:
    token: str
    user: str
    role: Role
    last_t: float  # Clock.now() of its last request


@dataclass(frozen=True, slots=True)
class Principal:
    """Who sends a request: a logged-in user, an anonymous viewer, or (login off) anyone."""

    user: str
    role: Role
    actor: str
    session: Session | None = None


PRINCIPAL_KEY: Final = web.RequestKey[Principal]("hmi.principal")
"""Where the middleware leaves the request's ``Principal`` (``request[PRINCIPAL_KEY]``)."""
VALID_KEY: Final = web.RequestKey[Callable[[], bool]]("hmi.valid")
"""``request[VALID_KEY]()``: is the request's session still open (a long-lived WebSocket)."""

ANONYMOUS_VIEWER: Final = Principal(ANONYMOUS, "viewer", ACTOR_PREFIX + ANONYMOUS)
LOGIN_OFF: Final = Principal(ANONYMOUS, "operator", LOGIN_OFF_ACTOR)


class SessionsFull(Exception):
    """No room for one more session: the table is full of other users' live sessions."""


class Sessions:
    """The open sessions, expiring ``timeout_s`` after their last use (``now``: the clock's
    ``now``, so that a test moves it). At most ``per_user`` per user (a new one closes the
    user's own least recently used) and ``max_sessions`` in all (``open`` raises
    ``SessionsFull`` rather than close another user's live session)."""

    def __init__(
        self,
        timeout_s: float,
        now: Callable[[], float],
        max_sessions: int = MAX_SESSIONS,
        per_user: int = MAX_SESSIONS_PER_USER,
    ) -> None:
        self.timeout_s = timeout_s
        self._now = now
        self._max = max_sessions
        self._per_user = per_user
        self._open: OrderedDict[str, Session] = OrderedDict()

    def open(self, user: User) -> Session:
        now = self._now()
        # Least recently used first: the order the table keeps.
        own = [t for t, s in self._open.items() if s.user == user.name]
        for token in own[: max(0, len(own) - self._per_user + 1)]:
            del self._open[token]
        if len(self._open) >= self._max:
            for token in [t for t, s in self._open.items() if now - s.last_t >= self.timeout_s]:
                del self._open[token]
        if len(self._open) >= self._max:
            raise SessionsFull(
                f"{len(self._open)} sessions are open, the most this bench keeps: try again"
                " when one is closed or expired"
            )
        token = secrets.token_urlsafe(32)
        session = Session(token, user.name, user.role, now)
        self._open[token] = session
        return session

    def get(self, token: str | None, touch: bool = True) -> Session | None:
        """The live session of ``token`` (its expiry pushed back when ``touch``), or None."""
        if not token:
            return None
        session = self._open.get(token)
        if session is None:
            return None
        now = self._now()
        if now - session.last_t >= self.timeout_s:
            del self._open[token]
            log.info("hmi: session of %s expired (%g s unused)", session.user, self.timeout_s)
            return None
        if touch:
            session.last_t = now
            self._open.move_to_end(token)
        return session

    def expires_s(self, session: Session) -> float:
        """Seconds left before ``session`` expires if unused."""
        return max(0.0, self.timeout_s - (self._now() - session.last_t))

    def close(self, token: str | None) -> Session | None:
        return self._open.pop(token, None) if token else None

    def __len__(self) -> int:
        return len(self._open)


class HmiRoles:
    """The command path's role hook for HMI actors (``hmi:<user>``): the user's role from
    the users file now (a user demoted or removed since they logged in loses it at once);
    any other actor is asked of ``fallback`` (OPC UA's hook, the command line...)."""

    def __init__(self, users: UserStore | None, fallback: Roles) -> None:
        self.users = users
        self.fallback = fallback

    def role(self, actor: str) -> Role:
        name = actor[len(ACTOR_PREFIX) :]
        if name == ANONYMOUS or self.users is None:
            return "viewer"
        return self.users.role_of(name) or "viewer"

    def access_of(self, actor: str) -> Access:
        if not actor.startswith(ACTOR_PREFIX):
            return self.fallback.access_of(actor)
        return ROLE_ACCESS[self.role(actor)]

    def refuses(self, command: Command) -> str:
        actor = command.actor
        if not actor.startswith(ACTOR_PREFIX):
            return self.fallback.refuses(command)
        if self.role(actor) != "viewer":
            return ""
        who = "not logged in" if actor.endswith(":" + ANONYMOUS) else f"{actor} is a viewer"
        if command.verb is Verb.WRITE:
            what = f"write {command.args.get('tag')}"
        else:
            what = f"{command.verb.value} {command.target}"
        return f"viewer may not {what} ({who}): log in as an operator"


def principal(request: web.Request) -> Principal:
    """Who sent ``request`` (set by ``HmiAccess``'s middleware; anyone operates without it)."""
    found: Principal = request.get(PRINCIPAL_KEY, LOGIN_OFF)
    return found


def session_role(request: web.Request) -> Role | None:
    """The role a route that is not a command checks (a recipe save): an engineer when
    ``hmi.login`` is off (loopback only, everyone may), None without a session (anonymous
    viewers log in first), else the session user's role."""
    p = principal(request)
    if p is LOGIN_OFF:
        return "engineer"
    return p.role if p.session is not None else None


def session_actor(request: web.Request) -> str:
    """Who to record for a route that is not a command (``hmi:<user>``)."""
    return principal(request).actor


def role_at_least(p: Principal, role: Role) -> bool:
    return ROLES.index(p.role) >= ROLES.index(role)


def refuse_unless(request: web.Request, role: Role, what: str) -> web.Response | None:
    """A 403 (or 401 without a session) unless the request's user has ``role``; None when
    they may, and always None when ``hmi.login`` is off. For the routes that are not
    commands (a recipe save needs an engineer)."""
    p = principal(request)
    if p is LOGIN_OFF or role_at_least(p, role):
        return None  # without logins (loopback only) nobody is refused anything
    if p.session is None and p is not LOGIN_OFF:
        return _answer({"accepted": False, "reason": f"log in as an {role} to {what}"}, 401)
    return _answer(
        {"accepted": False, "reason": f"{p.role} may not {what}: log in as an {role}"}, 403
    )


def _answer(body: dict[str, Any], status: int) -> web.Response:
    return web.json_response(body, status=status, dumps=json_dumps)


Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


class HmiAccess:
    """The HMI's access policy on one aiohttp application: the middleware that finds each
    request's ``Principal`` and the login routes."""

    def __init__(
        self,
        users: UserStore | None,
        sessions: Sessions,
        login: bool,
        anonymous_read: bool,
        throttle: LoginThrottle,
    ) -> None:
        if login and users is None:
            raise ValueError("login needs a user store")
        self.users = users
        self.sessions = sessions
        self.login = login
        self.anonymous_read = anonymous_read
        self.throttle = throttle
        self._checks = asyncio.Semaphore(LOGIN_CHECKS)
        self.audit: AuditLog | None = None
        """The bench's audit trail: logins, failed logins and logouts (``app/hmi.py``)."""
        self.alarm_sound_repeat_s = 10.0
        """How often a screen sounds an unacknowledged high-priority alarm again
        (``hmi.alarm_sound_repeat_s``): the page learns it with its session."""

    def install(self, app: web.Application) -> None:
        app.middlewares.append(self._middleware)
        app.add_routes(
            [
                web.post("/api/login", self._login),
                web.post("/api/logout", self._logout),
                web.get("/api/session", self._session),
            ]
        )

    def of(self, request: web.Request, touch: bool = True) -> Principal | None:
        """The principal of ``request``'s session cookie (None: no live session)."""
        if not self.login:
            return LOGIN_OFF
        session = self.sessions.get(request.cookies.get(COOKIE), touch=touch)
        if session is None:
            return None
        return Principal(session.user, session.role, ACTOR_PREFIX + session.user, session)

    @web.middleware
    async def _middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        path = request.path
        # The page itself, its scripts and the login routes: reachable by anyone (the login
        # page has to load before there is a session); nothing there reads or commands.
        if not path.startswith("/api/") or path in OPEN_PATHS:
            return await handler(request)
        found = self.of(request)
        if found is None:
            reading = request.method in ("GET", "HEAD")
            if not (reading and self.anonymous_read):
                why = "log in first" if reading else "log in to command or write"
                return _answer(
                    {
                        "accepted": False,
                        "error": "no session",
                        "reason": f"{why} (no session, or it expired)",
                    },
                    401,
                )
            found = ANONYMOUS_VIEWER
        request[PRINCIPAL_KEY] = found
        if found.session is not None and not self.anonymous_read:
            # A WebSocket outlives its upgrade: it closes when the session expires.
            token = found.session.token
            request[VALID_KEY] = lambda: self.sessions.get(token, touch=False) is not None
        # HttpApi.actor reads this: the command path records it and checks its role.
        request[ACTOR_KEY] = found.actor
        return await handler(request)

    # --- routes -------------------------------------------------------------------------
    def _session_json(self, p: Principal) -> dict[str, Any]:
        sound = {"alarm_sound_repeat_s": self.alarm_sound_repeat_s}
        if p.session is None:
            return {"user": p.user, "role": p.role, "login": self.login, **sound}
        return {
            "user": p.user,
            "role": p.role,
            "expires_s": self.sessions.expires_s(p.session),
            "login": True,
            **sound,
        }

    async def _login(self, request: web.Request) -> web.Response:
        if not self.login:
            return _answer(
                {"error": "login is off", "reason": "hmi.login is false: everyone operates"},
                409,
            )
        try:
            body = await read_json(request)  # a lone surrogate in a password: 400, named
        except BodyError as exc:
            return exc.response()
        if not (
            isinstance(body, dict)
            and isinstance(body.get("user"), str)
            and isinstance(body.get("password"), str)
            and 0 < len(body["user"]) <= MAX_CREDENTIAL_CHARS
            and len(body["password"]) <= MAX_CREDENTIAL_CHARS
        ):
            return _answer(
                {"error": "bad request", "reason": 'body must be {"user": "…", "password": "…"}'},
                400,
            )
        assert self.users is not None
        name, address = body["user"], request.remote or ""
        # scrypt: about 50 ms of CPU, never on the scan's event loop, and at most
        # LOGIN_CHECKS at a time (a burst of logins must not take every core). The
        # throttle is asked once the turn has come: tries queued together are counted.
        user: User | None = None
        async with self._checks:
            refusal = self.throttle.refusal(name, address)
            if refusal is None:
                user = await asyncio.to_thread(self.users.authenticate, name, body["password"])
        if refusal is not None:
            # The password is not checked, the right one is refused too: else the delay
            # would slow no guesser. Logged at debug: a flood must not fill the log (the
            # burst raises ``security.login_burst``).
            log.debug("hmi: login for %r from %s refused: %s", name[:64], address, refusal.reason)
            retry_after_s = max(1, math.ceil(refusal.retry_after_s))
            resp = _answer(
                {
                    "error": "too many failed logins",
                    "reason": refusal.reason,
                    "retry_after_s": retry_after_s,
                },
                429,
            )
            resp.headers["Retry-After"] = str(retry_after_s)
            return resp
        if user is None:
            self._failed(name, address)
            return _answer({"error": "login failed", "reason": WRONG_CREDENTIALS}, 401)
        self.throttle.succeeded(name, address)
        try:
            session = self.sessions.open(user)
        except SessionsFull as exc:
            log.warning("hmi: login of %s refused: %s", user.name, exc)
            return _answer({"error": "too many sessions", "reason": str(exc)}, 503)
        self._logged_in(user, address)
        p = Principal(user.name, user.role, ACTOR_PREFIX + user.name, session)
        resp = _answer(self._session_json(p), 200)
        resp.set_cookie(COOKIE, session.token, httponly=True, samesite="Strict", path="/")
        return resp

    async def _logout(self, request: web.Request) -> web.Response:
        session = self.sessions.close(request.cookies.get(COOKIE))
        if session is not None:
            log.info("hmi: %s logged out", session.user)
            self._audit(session.user, "logout", {"address": request.remote or ""})
        resp = _answer({"accepted": True, "reason": ""}, 200)
        resp.del_cookie(COOKIE, path="/")
        return resp

    def _failed(self, name: str, address: str) -> None:
        self.throttle.failed(name, address)
        log.warning("hmi: failed login for %r from %s", name[:64], address)
        self._audit(name[:64], "login.failed", {"address": address})

    def _logged_in(self, user: User, address: str) -> None:
        log.info("hmi: %s logged in (%s) from %s", user.name, user.role, address)
        self._audit(user.name, "login", {"role": user.role, "address": address})

    def _audit(self, user: str, kind: str, details: dict[str, Any]) -> None:
        # A try refused by the throttle (429) is not recorded one by one: a flood of them
        # costs nothing to send, and the burst alarm says it happens.
        if self.audit is not None:
            self.audit.append(ACTOR_PREFIX + user, kind, user, details)

    async def _session(self, request: web.Request) -> web.Response:
        found = self.of(request)
        if found is None:
            return _answer(
                {
                    "error": "no session",
                    "reason": "not logged in, or the session expired",
                    "login": True,
                    "anonymous_read": self.anonymous_read,
                },
                401,
            )
        return _answer(self._session_json(found), 200)
