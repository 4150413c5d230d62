"""asyncua's server with two holes closed (docs/adr/0014-opcua-server.md, "Security";
issue 27, findings 5 and 6): a small, tested override of asyncua 2.1's ``Server`` and
``UaProcessor``, each change a few lines an upstream patch could carry.

- **No password in clear.** asyncua takes a UserName token's password as it comes: on a
  None (or Sign) channel a client may send it unencrypted, and with only the None policy
  asyncua's own UserTokenPolicy even asks it to. Here the UserTokenPolicy for UserName on a
  None endpoint always names Basic256Sha256 (the client encrypts the password with the
  server's certificate, which is always loaded), and an ActivateSession whose password is not
  encrypted — neither by the token (EncryptionAlgorithm) nor by a SignAndEncrypt channel —
  is refused with Bad_IdentityTokenInvalid, the reason in the log and in the fault's
  diagnostics. Anonymous tokens are unchanged.
- **A request runs as its own session.** asyncua keeps one session per connection
  (``UaProcessor.session``) and never looks at a request's AuthenticationToken: a second
  CreateSession on the same secure channel replaced the first, and the first session's
  requests then ran as the second session's user. Here a request that needs a session must
  carry its connection's session's token (else Bad_SessionIdInvalid), and a second
  CreateSession on a connection whose session is activated is refused
  (Bad_TooManySessions: OPC UA allows several sessions per channel, asyncua does not
  implement it); a session never activated is closed and replaced, as a client retrying a
  refused login does.
- **The None endpoint ignores the client's certificate** (Part 4 §5.7.2.2; issue 31,
  finding 1): asyncua validates the CreateSession's certificate whatever the channel, and
  node-opcua sends one by default. The processor tells the validator (``TrustList``) the
  channel's mode; on None it accepts. A certificate refused on a signed channel is logged
  once by the validator (WARNING, rate-limited): asyncua's own ERROR line per refusal is
  not written (issue 31, finding 8).
- **Operation limits, Browse and BrowseNext** (issue 31, finding 4; ``services.py``): a
  request past its advertised limit is refused (Bad_TooManyOperations); Browse and
  BrowseNext are served by ``services.py`` in slices, with continuation points.
"""

from __future__ import annotations

import logging
import socket
import time
from typing import Any, Final

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto import uacrypto
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.internal_session import SessionState
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary

from supervisor.publish.opcua import services
from supervisor.publish.opcua.security import serving_on

log = logging.getLogger(__name__)

S = ua.StatusCodes
MODE = ua.MessageSecurityMode


def _request(name: str) -> ua.NodeId:
    return ua.NodeId(getattr(ua.ObjectIds, f"{name}Request_Encoding_DefaultBinary"))


CREATE_SESSION: Final = _request("CreateSession")
ACTIVATE_SESSION: Final = _request("ActivateSession")
SESSIONLESS: Final = frozenset(
    _request(n)
    for n in (
        "CreateSession",
        "GetEndpoints",
        "FindServers",
        "RegisterServer",
        "RegisterServer2",
        "CloseSecureChannel",
    )
)
"""Requests served without a session: their AuthenticationToken is not checked (ActivateSession
is checked when the connection has a session: else asyncua looks the session up by it, a
client reconnecting on a new channel, Part 4 §6.7)."""
CERTIFICATE_REFUSALS: Final = frozenset(
    getattr(S, n)
    for n in (
        "BadCertificateUntrusted",
        "BadCertificateInvalid",
        "BadCertificateTimeInvalid",
        "BadCertificateUriInvalid",
        "BadCertificateUseNotAllowed",
        "BadCertificateRevoked",
        "BadCertificateIssuerRevoked",
        "BadCertificateChainIncomplete",
        "BadSecurityChecksFailed",
    )
)
"""What the certificate validator refuses a CreateSession with (it logs why, once)."""


def password_in_clear(token: object, channel_mode: ua.MessageSecurityMode) -> bool:
    """Did a UserName token's password cross the network unencrypted? Yes when it has one,
    the token names no encryption and the channel does not encrypt either (None or Sign).
    An empty password reveals nothing: the user manager refuses it as a wrong one."""
    if not isinstance(token, ua.UserNameIdentityToken) or not token.Password:
        return False
    return not token.EncryptionAlgorithm and channel_mode != MODE.SignAndEncrypt


class SessionBoundProcessor(UaProcessor):  # type: ignore[misc]
    """asyncua's per-connection processor, checking a request's session, a login's password
    and a request's number of operations before asyncua serves it; Browse and BrowseNext
    served by ``services.py``."""

    def __init__(self, *args: Any, browser: services.Browser, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.browser = browser
        self.points = services.ContinuationPoints()

    async def _process_message(self, typeid: Any, requesthdr: Any, seqhdr: Any, body: Any) -> Any:
        serving_on(self._connection.security_policy.Mode)
        session = self.session
        live = session is not None and session.state is not SessionState.Closed
        if typeid == CREATE_SESSION and live:
            if session.is_activated():
                return self._refuse(
                    requesthdr,
                    seqhdr,
                    S.BadTooManySessions,
                    "this secure channel already has an activated session: open another"
                    " connection for another session (one session per connection here)",
                )
            # Never activated (a refused login being retried): it has no user to lose. Its
            # watchdog goes with it (asyncua starts one per CreateSession).
            if self._session_watchdog_task is not None:
                self._session_watchdog_task.cancel()
            await session.close_session(True)
        elif (
            typeid not in SESSIONLESS
            and live
            and requesthdr.AuthenticationToken != session.auth_token
        ):
            return self._refuse(
                requesthdr,
                seqhdr,
                S.BadSessionIdInvalid,
                "the request's authentication token is not this connection's session's",
            )
        if typeid == ACTIVATE_SESSION:
            params = struct_from_binary(ua.ActivateSessionParameters, body.copy())
            mode = self._connection.security_policy.Mode
            token = params.UserIdentityToken
            if password_in_clear(token, mode):
                return self._refuse(
                    requesthdr,
                    seqhdr,
                    S.BadIdentityTokenInvalid,
                    f"login of user {token.UserName!r} refused: its password came in clear"
                    f" over a {mode.name.rstrip('_')} channel; encrypt it with the server's"
                    " certificate as the endpoint's UserTokenPolicy asks (Basic256Sha256),"
                    " or use a SignAndEncrypt endpoint",
                )
        if live and typeid not in SESSIONLESS and session.is_activated():
            reason = services.too_many(typeid, body)
            if reason is not None:
                return self._refuse(requesthdr, seqhdr, S.BadTooManyOperations, reason)
            if typeid in (services.BROWSE, services.BROWSE_NEXT):
                return await self._browse(typeid, requesthdr, seqhdr, body)
        try:
            return await super()._process_message(typeid, requesthdr, seqhdr, body)
        except ServiceError as exc:
            if typeid != CREATE_SESSION or exc.code not in CERTIFICATE_REFUSALS:
                raise
            # Logged by the validator, once per certificate and window: asyncua would add an
            # ERROR line for every retry of the client.
            self._fault(requesthdr, seqhdr, exc.code)
            return True

    async def _browse(self, typeid: Any, requesthdr: Any, seqhdr: Any, body: Any) -> bool:
        """Browse or BrowseNext, served in slices (``services.py``) with asyncua's checks of
        a request: the session's permission (BrowseNext as a Browse) and its activity."""
        session = self.session
        rules = self._connection.security_policy.permissions
        if rules is not None and not rules.check_validity(session.user, services.BROWSE, body):
            raise ua.uaerrors.BadUserAccessDenied
        self.session_last_activity = time.monotonic()
        session.touch()
        serve = services.browse if typeid == services.BROWSE else services.browse_next
        answer = await serve(self.browser, self.points.of(session), body, requesthdr)
        if self._transport.is_closing():
            return False  # the client left while it was browsed
        data = self._connection.message_to_binary(
            answer, message_type=ua.MessageType.SecureMessage, request_id=seqhdr.RequestId
        )
        self._transport.write(data)
        return True

    def _fault(self, requesthdr: Any, seqhdr: Any, code: int) -> None:
        response = ua.ServiceFault()
        response.ResponseHeader.ServiceResult = ua.StatusCode(code)
        self.send_response(requesthdr.RequestHandle, seqhdr, response)

    def _refuse(self, requesthdr: Any, seqhdr: Any, code: int, reason: str) -> bool:
        """Answer a ServiceFault with ``code`` and ``reason`` (in the response header's
        string table, pointed at by its diagnostics, and as their additional info, which
        asyncua clients log: a status code alone carries no text); keep the connection."""
        log.warning("OPC UA client %s: %s (%s)", self.name, reason, ua.StatusCode(code).name)
        response = ua.ServiceFault()
        response.ResponseHeader.ServiceResult = ua.StatusCode(code)
        response.ResponseHeader.StringTable = [reason]
        response.ResponseHeader.ServiceDiagnostics = ua.DiagnosticInfo(
            LocalizedText=0, AdditionalInfo=reason
        )
        self.send_response(requesthdr.RequestHandle, seqhdr, response)
        return True


class SessionBoundProtocol(OPCUAProtocol):  # type: ignore[misc]
    """asyncua's connection, with ``SessionBoundProcessor`` as its processor (asyncua makes
    the processor in ``connection_made``; its message loop, started there, finds the one
    set here when the first message arrives)."""

    processor: UaProcessor | None

    def __init__(self, *args: Any, browser: services.Browser, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.browser = browser

    def connection_made(self, transport: Any) -> None:
        super().connection_made(transport)
        if self.processor is not None:  # None: refused at asyncua's max_connections
            self.processor = SessionBoundProcessor(
                self.iserver, self.transport, self.limits, browser=self.browser
            )
            self.processor.set_policies(self.policies)


class SessionBoundBinaryServer(BinaryServer):  # type: ignore[misc]
    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        # One for the server: a reference type's subtypes are computed once for all clients.
        self.browser = services.Browser(self.iserver.aspace)

    def _make_protocol(self) -> OPCUAProtocol:
        return SessionBoundProtocol(
            iserver=self.iserver,
            policies=self._policies,
            clients=self.clients,
            closing_tasks=self.closing_tasks,
            limits=self.limits,
            browser=self.browser,
        )


class _PlaintextWarning(logging.Filter):
    """asyncua warns that a password "may get transferred in plaintext" when only None is
    offered; ``BenchServer`` then asks for Basic256Sha256 encryption itself: not so."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "password may get transferred in plaintext" not in record.getMessage()


logging.getLogger("asyncua.server.server").addFilter(_PlaintextWarning())


class BenchServer(Server):  # type: ignore[misc]
    """asyncua's ``Server`` serving connections with ``SessionBoundProcessor`` and asking
    for an encrypted password on every endpoint."""

    def _set_endpoints(self, policy: Any, mode: ua.MessageSecurityMode, level: int) -> None:
        super()._set_endpoints(policy, mode, level)
        if mode != MODE.None_:
            return  # Sign: asyncua names the endpoint's policy; SignAndEncrypt: the channel
        endpoint = self.iserver.endpoints[-1]  # the one just added
        tokens = []
        for t in endpoint.UserIdentityTokens:
            if t.TokenType == ua.UserTokenType.UserName:
                if self.iserver.certificate is None or self.iserver.private_key is None:
                    continue  # nothing to encrypt it with: no password login on None
                t.SecurityPolicyUri = SecurityPolicyBasic256Sha256.URI
            tokens.append(t)
        endpoint.UserIdentityTokens = tokens

    async def init(self, shelf_file: Any = None) -> None:
        """asyncua's ``Server.init``, then the operation limits this server enforces written
        under ServerCapabilities (asyncua writes 10,000 for each and enforces none)."""
        await super().init(shelf_file)
        await services.advertise(self)

    async def start(self) -> None:
        """asyncua's ``Server.start`` with ``SessionBoundBinaryServer`` (asyncua names its
        binary server class in this method)."""
        if self.iserver.certificate is not None:
            uacrypto.check_certificate(
                self.iserver.certificate, self._application_uri, socket.gethostname()
            )
        await self._setup_server_nodes()
        await self.iserver.start()
        try:
            host, port = self._get_bind_socket_info()
            self.bserver = SessionBoundBinaryServer(self.iserver, host, port, self.limits)
            self.bserver.set_policies(self._policies)
            await self.bserver.start()
        except Exception:
            await self.iserver.stop()
            raise
