"""Who may connect and what they may do (docs/adr/0014-opcua-server.md, "Security").

- **Users**: user name and password checked against the users file (``users.py``); an
  anonymous session is allowed when the I/O map says so, as a viewer. The session's user
  becomes the command path's actor ``opcua:<name>`` (``opcua:anonymous``), and
  ``OpcUaRoles`` is the command path's role hook for those actors: a viewer may give no
  command, an operator the channel commands and operator writes, an engineer everything.
  Other actors (the HTTP API, the command line) keep the role hook they had.
- **Who is calling**: asyncua hands a method handler neither the session nor its user; its
  permission ruleset does see the user of every request, just before the request runs on
  the same task. ``SessionRules`` puts that user in a context variable there, and the
  method and write handlers read it (``current_user``).
- **Certificates**: a self-signed certificate made on first start (its URI is the
  application URI, as OPC UA requires), Basic256Sha256 Sign and SignAndEncrypt endpoints,
  and a trust list: a client certificate is accepted only when it (or its issuer) is in
  ``<pki>/trusted``; a refused one is saved in ``<pki>/rejected`` so an administrator can
  trust it by moving the file (read again at the next connection, no restart). On a None
  channel the client's certificate is ignored (Part 4 §5.7.2.2: nothing is signed with it),
  trusted or not. A refusal is one WARNING line per certificate and window, not one per retry.
"""

from __future__ import annotations

import contextvars
import hashlib
import logging
import socket
import sys
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Protocol

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.permission_rules import ADMIN_TYPES, USER_TYPES, PermissionRuleset, UserRole
from asyncua.crypto.permission_rules import User as UaUser
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from asyncua.server.internal_session import InternalSession
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from supervisor.config.users import ANONYMOUS, ROLE_ACCESS, UserStore
from supervisor.core.logins import LoginThrottle
from supervisor.tags import Access

log = logging.getLogger(__name__)

ACTOR_PREFIX: Final = "opcua:"


@dataclass
class SessionUser(UaUser):  # type: ignore[misc]
    """asyncua's session user, with the project's role."""

    access_role: str = "viewer"

    @property
    def actor(self) -> str:
        return ACTOR_PREFIX + (self.name or ANONYMOUS)


_current: contextvars.ContextVar[UaUser | None] = contextvars.ContextVar(
    "opcua_session_user", default=None
)


def current_user() -> UaUser | None:
    """The user of the request being served (set by ``SessionRules``)."""
    return _current.get()


_channel_mode: contextvars.ContextVar[ua.MessageSecurityMode] = contextvars.ContextVar(
    "opcua_channel_mode", default=ua.MessageSecurityMode.Invalid
)


def serving_on(mode: ua.MessageSecurityMode) -> None:
    """Say on which kind of secure channel the request being served came (set by the
    connection's processor, ``sessions.py``, before asyncua serves it: the certificate
    validator asyncua calls is not told)."""
    _channel_mode.set(mode)


def actor_of(user: UaUser | None) -> str:
    if isinstance(user, SessionUser):
        return user.actor
    return ACTOR_PREFIX + ANONYMOUS


class SessionRules(PermissionRuleset):  # type: ignore[misc]
    """Lets every session read, browse, subscribe, write and call (the handlers decide per
    node, with per-item status codes), none change the address space; and records who
    sends each request for the handlers."""

    def __init__(self) -> None:
        self._allowed = {ua.NodeId(t) for t in USER_TYPES}
        self._never = {ua.NodeId(t) for t in ADMIN_TYPES}

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        _current.set(user)
        return action_type_id in self._allowed and action_type_id not in self._never


def _peer_address() -> str:
    """The client address of the session being activated ("" when not found).

    asyncua hands its user manager neither the session nor the connection; the session
    (whose ``name`` is the connection's peer address) is ``self`` of the
    ``activate_session`` frame that calls it, a few frames up."""
    frame = sys._getframe(1)
    for _ in range(8):
        frame = frame.f_back  # type: ignore[assignment]
        if frame is None:
            break
        found = frame.f_locals.get("self")
        if isinstance(found, InternalSession):
            name = found.name
            if isinstance(name, tuple | list) and name:
                return str(name[0])
            return str(name or "")
    return ""


class PasswordUsers:
    """asyncua's user manager: users of the users file, and anonymous sessions if allowed.

    Password tries go through the bench's ``LoginThrottle`` (shared with the HMI): past the
    limit for the user or the client's address a try is refused (Bad_UserAccessDenied)
    without its password being checked, the right one too, until the delay is over."""

    def __init__(
        self,
        store: UserStore,
        anonymous: bool,
        throttle: LoginThrottle | None = None,
        on_login: Callable[[str, str, str], None] | None = None,
    ) -> None:
        self.store = store
        self.anonymous = anonymous
        self.throttle = throttle
        self.on_login = on_login
        """Told each password's outcome (``failed``/``succeeded``, user, address)."""

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> UaUser | None:
        # ``certificate`` is the secure channel's client certificate, whatever the token;
        # X509 user tokens are not offered (asyncua refuses them before asking here).
        if username is None:
            if not self.anonymous:
                return None
            return SessionUser(role=UserRole.Anonymous, name=None, access_role="viewer")
        address = _peer_address()
        if self.throttle is not None:
            refusal = self.throttle.refusal(username, address)
            if refusal is not None:
                # Logged at debug: a flood must not fill the log (the burst raises
                # ``security.login_burst``). OPC UA has no field for the reason.
                log.debug(
                    "OPC UA login of %r from %s refused: %s", username[:64], address, refusal.reason
                )
                return None
        user = self.store.authenticate(username, password or "")
        if user is None:
            if self.throttle is not None:
                self.throttle.failed(username, address)
            log.warning("OPC UA login refused for user %r from %s", username[:64], address)
            if self.on_login is not None:
                self.on_login("failed", username, address)
            return None
        if self.throttle is not None:
            self.throttle.succeeded(username, address)
        if self.on_login is not None:
            self.on_login("succeeded", user.name, address)
        return SessionUser(role=UserRole.User, name=user.name, access_role=user.role)


class CommandLike(Protocol):
    @property
    def actor(self) -> str: ...


class FallbackRoles(Protocol):
    def access_of(self, actor: str) -> Access: ...

    def refuses(self, command: Any) -> str: ...


class OpcUaRoles:
    """The command path's role hook (``supervisor.commands.Roles``) for OPC UA actors; any
    other actor is asked of ``fallback`` (what the command path had)."""

    def __init__(self, store: UserStore, fallback: FallbackRoles) -> None:
        self.store = store
        self.fallback = fallback

    def _role(self, actor: str) -> str:
        name = actor[len(ACTOR_PREFIX) :]
        if name == ANONYMOUS:
            return "viewer"
        return self.store.role_of(name) or "viewer"  # a user removed since they logged in

    def access_of(self, actor: str) -> Access:
        if not actor.startswith(ACTOR_PREFIX):
            return self.fallback.access_of(actor)
        return ROLE_ACCESS[self._role(actor)]

    def refuses(self, command: Any) -> str:
        actor = str(getattr(command, "actor", ""))
        if not actor.startswith(ACTOR_PREFIX):
            return self.fallback.refuses(command)
        role = self._role(actor)
        if role == "viewer":
            who = "an anonymous session" if actor.endswith(":" + ANONYMOUS) else actor
            return f"{who} may only read (role viewer): log in as an operator"
        return ""


# --- certificates ------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Pki:
    root: Path

    @property
    def cert(self) -> Path:
        return self.root / "own" / "cert.der"

    @property
    def key(self) -> Path:
        return self.root / "own" / "key.pem"

    @property
    def trusted(self) -> Path:
        return self.root / "trusted"

    @property
    def rejected(self) -> Path:
        return self.root / "rejected"

    async def ensure(self, app_uri: str, bench: str) -> None:
        """Make the server's key and self-signed certificate on first start (again when the
        certificate expired or names another application URI)."""
        for d in (self.cert.parent, self.trusted, self.rejected):
            d.mkdir(parents=True, exist_ok=True)
        await setup_self_signed_certificate(
            self.key,
            self.cert,
            app_uri,
            socket.gethostname(),
            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
            {
                "countryName": "FR",
                "organizationName": "bench-supervisor",
                "commonName": f"bench-supervisor {bench}",
            },
        )
        self.key.chmod(0o600)


VALIDATION: Final = (
    CertificateValidatorOptions.TRUSTED_VALIDATION | CertificateValidatorOptions.PEER_CLIENT
)


REFUSAL_LOG_WINDOW_S: Final = 60.0
"""A refused certificate is logged once per window: a client retrying every second (node-opcua
does by default) would otherwise write a line per retry."""
REFUSAL_LOG_KEYS: Final = 256
"""Certificates remembered at most (a flood of new certificates cannot grow memory)."""


class RefusalLog:
    """One WARNING line per refused certificate (its thumbprint) and window; the next line
    after a window says how many refusals it did not write (``core/logrepeat.py``'s way)."""

    def __init__(
        self, now: Callable[[], float] = time.monotonic, window_s: float = REFUSAL_LOG_WINDOW_S
    ) -> None:
        self.now = now
        self.window_s = window_s
        self._seen: OrderedDict[str, tuple[float, int]] = OrderedDict()

    def should_log(self, thumbprint: str) -> int | None:
        """None: not to be logged (counted); else log it, saying how many were not."""
        now = self.now()
        seen = self._seen.get(thumbprint)
        if seen is not None and now - seen[0] < self.window_s:
            self._seen[thumbprint] = (seen[0], seen[1] + 1)
            return None
        self._seen[thumbprint] = (now, 0)
        self._seen.move_to_end(thumbprint)
        if len(self._seen) > REFUSAL_LOG_KEYS:
            self._seen.popitem(last=False)
        return 0 if seen is None else seen[1]


class TrustList:
    """The certificate validator: the client certificate must be valid now, name the
    client's application URI, allow client use, and be in ``trusted/`` (or be signed by a
    certificate there). Without it asyncua accepts any client certificate. On a None
    channel it accepts any: there the certificate is ignored (Part 4 §5.7.2.2)."""

    def __init__(self, pki: Pki, refusals: RefusalLog | None = None) -> None:
        self.pki = pki
        self.refusals = refusals or RefusalLog()
        self._stamp: tuple[tuple[str, int], ...] | None = None
        self._validator: CertificateValidator | None = None

    def _listing(self) -> tuple[tuple[str, int], ...]:
        try:
            files = sorted(self.pki.trusted.iterdir())
        except OSError:
            return ()
        return tuple((f.name, f.stat().st_mtime_ns) for f in files if f.is_file())

    async def __call__(self, cert: x509.Certificate, app: ua.ApplicationDescription) -> None:
        if _channel_mode.get() == ua.MessageSecurityMode.None_:
            # asyncua validates the CreateSession's certificate whatever the channel; with
            # SecurityPolicy None a client (node-opcua by default) still sends one, and
            # nothing is signed or encrypted with it: an untrusted one must not refuse it.
            return
        stamp = self._listing()
        if stamp != self._stamp:
            self._validator = None
            if stamp:  # an empty trust list trusts nobody (and asyncua cannot build one)
                store = TrustStore([self.pki.trusted], [])
                await store.load()
                self._validator = CertificateValidator(VALIDATION, store)
            self._stamp = stamp
        try:
            if self._validator is None:
                raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
            await self._validator(cert, app)
        except ServiceError as exc:
            der = cert.public_bytes(Encoding.DER)
            thumbprint = hashlib.sha1(der).hexdigest()
            name = f"{thumbprint}.der"
            kept = ""
            try:
                self.pki.rejected.mkdir(parents=True, exist_ok=True)
                (self.pki.rejected / name).write_bytes(der)
            except OSError as err:
                kept = f" (not kept: {err})"
            repeats = self.refusals.should_log(thumbprint)
            if repeats is not None:
                log.warning(
                    "OPC UA client %s (%s) refused: certificate %s, %s; to trust it, move"
                    " %s into %s%s%s",
                    app.ApplicationUri,
                    app.ApplicationName.Text if app.ApplicationName else "",
                    thumbprint,
                    ua.StatusCode(exc.code).name,
                    self.pki.rejected / name,
                    self.pki.trusted,
                    kept,
                    f" [{repeats} more refusals of it in the last {self.refusals.window_s:g} s]"
                    if repeats
                    else "",
                )
            raise
