"""Issue 27, findings 5 and 6: a password never crosses the network in clear, and a request
runs as the session whose authentication token it carries.

- Over the None security policy (and Sign) a UserName token must be encrypted with the
  server's key (its UserTokenPolicy names Basic256Sha256 even when only None is offered); a
  password sent in clear is refused with Bad_IdentityTokenInvalid and the reason in the log.
  Inside a SignAndEncrypt channel the channel itself encrypts it.
- asyncua keeps one session per connection: a second CreateSession on a connection whose
  session is activated is refused (Bad_TooManySessions), and a request whose authentication
  token is not its connection's session's is refused (Bad_SessionIdInvalid), so a viewer
  never acts as the operator who logged in on the same secure channel.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyNone
from opcuarig import PASSWORDS, Rig, call, client_certificate, opcua_rig, text, trust

from supervisor.publish.opcua import OpcUaSettings

pytestmark = pytest.mark.integration
S = ua.StatusCodes
MODE = ua.MessageSecurityMode
VT = ua.VariantType


def in_clear(c: Client) -> None:
    """Make ``c`` send its password unencrypted, whatever the server's token policy asks
    (what a careless or hostile client does)."""

    def server_policy(token_type: ua.UserTokenType) -> ua.UserTokenPolicy:
        return ua.UserTokenPolicy(
            PolicyId="username", TokenType=token_type, SecurityPolicyUri=SecurityPolicyNone.URI
        )

    c.server_policy = server_policy  # type: ignore[method-assign]


async def login(rig: Rig, user: str, mode: ua.MessageSecurityMode, clear: bool) -> Client:
    c = Client(rig.server.endpoint, timeout=10)
    c.application_uri = "urn:bench-supervisor:test-client"
    c.set_user(user)
    c.set_password(PASSWORDS[user])
    if mode is not MODE.None_:
        from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

        cert, key = await client_certificate(rig.tmp)
        trust(rig, cert)
        await c.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key), mode=mode)
    if clear:
        in_clear(c)
    await c.connect()
    return c


@pytest.mark.parametrize("mode", [MODE.None_, MODE.Sign])
async def test_a_password_sent_in_clear_is_refused_with_bad_identity_token_invalid(
    tmp_path: Path, mode: ua.MessageSecurityMode, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    async with opcua_rig(tmp_path) as rig:
        with pytest.raises(ua.uaerrors.BadIdentityTokenInvalid):
            c = await login(rig, "alice", mode, clear=True)
            await c.disconnect()
        reasons = [r.getMessage() for r in caplog.records if "in clear" in r.getMessage()]
        assert reasons, caplog.text
        assert "'alice'" in reasons[0] and "encrypt" in reasons[0]
        # The client gets the reason too, in the fault's diagnostics (asyncua logs them).
        assert any(
            r.name.startswith("asyncua.client")
            for r in caplog.records
            if "in clear" in r.getMessage()
        )
        assert PASSWORDS["alice"] not in caplog.text
        # The same user with the password encrypted as the token policy asks logs in.
        c = await login(rig, "alice", mode, clear=False)
        await c.disconnect()


async def test_inside_a_sign_and_encrypt_channel_the_channel_encrypts_the_password(
    tmp_path: Path,
) -> None:
    async with opcua_rig(tmp_path) as rig:
        c = await login(rig, "alice", MODE.SignAndEncrypt, clear=True)
        await c.disconnect()


async def test_with_only_the_none_policy_a_password_is_still_encrypted(tmp_path: Path) -> None:
    def none_only(s: OpcUaSettings) -> OpcUaSettings:
        return dataclasses.replace(s, security=("none",))

    async with opcua_rig(tmp_path, change=none_only) as rig:
        endpoints = await Client(rig.server.endpoint).connect_and_get_server_endpoints()
        assert [e.SecurityMode for e in endpoints] == [MODE.None_]
        tokens = {t.TokenType: t.SecurityPolicyUri for t in endpoints[0].UserIdentityTokens}
        assert tokens[ua.UserTokenType.UserName].endswith("#Basic256Sha256")
        assert tokens[ua.UserTokenType.Anonymous] == SecurityPolicyNone.URI
        async with rig.client("alice") as c:  # encrypted with the server's key
            assert await rig.ns(c) > 0
        async with rig.client(None) as c:  # anonymous over None on loopback: still there
            assert await rig.ns(c) > 0
        with pytest.raises(ua.uaerrors.BadIdentityTokenInvalid):
            c = await login(rig, "alice", MODE.None_, clear=True)
            await c.disconnect()


async def set_manual_current(rig: Rig, c: Client, current_a: float) -> ua.CallMethodResult:
    ns = await rig.ns(c)
    return await call(
        c,
        ua.NodeId("/Bench/Channels/ch0", ns),
        ua.NodeId("/Bench/Channels/ch0/SetManualCurrent", ns),
        ua.Variant(current_a, VT.Double),
    )


async def test_a_viewer_never_acts_as_an_operator_who_logs_in_on_the_same_channel(
    tmp_path: Path,
) -> None:
    async with opcua_rig(tmp_path) as rig, rig.client("bob") as c:  # bob: a viewer
        protocol = c.uaclient.protocol
        assert protocol is not None
        viewer_token = protocol.authentication_token
        # A second session on the same secure channel, as the operator.
        with pytest.raises(ua.uaerrors.BadTooManySessions):
            await c.create_session()
            await c.activate_session("alice", PASSWORDS["alice"])
        # The viewer's request, with the viewer's token: the viewer's, refused.
        protocol.authentication_token = viewer_token
        res = await set_manual_current(rig, c, 0.1)
        assert res.StatusCode.value == S.BadUserAccessDenied, text(res)
        assert "opcua:bob may only read" in text(res)
        actors = {e.actor for e in rig.bench.commands.log}
        assert "opcua:alice" not in actors
        assert rig.bench.db["ch0.manual_current"].value != 0.1


async def test_a_request_with_another_sessions_token_is_refused(tmp_path: Path) -> None:
    async with opcua_rig(tmp_path) as rig:
        async with rig.client("alice") as operator, rig.client("bob") as viewer:
            assert operator.uaclient.protocol is not None and viewer.uaclient.protocol is not None
            mine = viewer.uaclient.protocol.authentication_token
            viewer.uaclient.protocol.authentication_token = (
                operator.uaclient.protocol.authentication_token
            )
            with pytest.raises(ua.uaerrors.BadSessionIdInvalid):
                await set_manual_current(rig, viewer, 0.1)
            viewer.uaclient.protocol.authentication_token = mine
            assert not [e for e in rig.bench.commands.log if e.kind.value != "forbidden"]
            # Each session goes on as itself.
            res = await set_manual_current(rig, operator, 0.1)
            assert res.StatusCode.is_good(), text(res)
            res = await set_manual_current(rig, viewer, 0.2)
            assert res.StatusCode.value == S.BadUserAccessDenied, text(res)
        assert [(e.actor, e.accepted) for e in rig.bench.commands.log] == [
            ("opcua:alice", True),
            ("opcua:bob", False),
        ]


async def test_a_session_never_activated_is_replaced_by_the_next_one(tmp_path: Path) -> None:
    async with opcua_rig(tmp_path) as rig:
        c = Client(rig.server.endpoint, timeout=10)
        await c.connect_socket()
        try:
            await c.send_hello()
            await c.open_secure_channel()
            await c.create_session()  # then no ActivateSession: a login given up
            await c.create_session()
            await c.activate_session("alice", PASSWORDS["alice"])
            res = await set_manual_current(rig, c, 0.1)
            assert res.StatusCode.is_good(), text(res)
            await c.close_session()
        finally:
            c.disconnect_socket()
        assert [(e.actor, e.accepted) for e in rig.bench.commands.log] == [("opcua:alice", True)]
