"""Who may connect: users with their passwords (hashed in the users file), anonymous
sessions only when allowed, Basic256Sha256 Sign and SignAndEncrypt endpoints with the
server's own certificate, the None policy switched off on request, and client certificates
accepted only from the trust list.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from asyncua import Client, ua
from cryptography import x509
from opcuarig import PASSWORDS, call, client_certificate, opcua_rig, text, trust

from supervisor.publish.opcua import OpcUaSettings

pytestmark = pytest.mark.integration
S = ua.StatusCodes
MODE = ua.MessageSecurityMode


async def test_users_log_in_with_their_own_password_only(tmp_path: Path) -> None:
    async with opcua_rig(tmp_path) as rig:
        async with rig.client("alice") as c:
            assert await rig.ns(c) > 0
        for user, password in (("alice", "wrong"), ("mallory", "x"), ("alice", "")):
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                async with rig.client(user, password):
                    pass
        text_of_file = rig.settings.users_file.read_text(encoding="utf-8")
        assert "scrypt$" in text_of_file
        assert not any(pw in text_of_file for pw in PASSWORDS.values())


async def test_the_endpoints_offer_none_sign_and_sign_and_encrypt(tmp_path: Path) -> None:
    async with opcua_rig(tmp_path) as rig:
        client = Client(rig.server.endpoint)
        endpoints = await client.connect_and_get_server_endpoints()
        offered = {(e.SecurityPolicyUri.rsplit("#", 1)[1], e.SecurityMode) for e in endpoints}
        assert offered == {
            ("None", MODE.None_),
            ("Basic256Sha256", MODE.Sign),
            ("Basic256Sha256", MODE.SignAndEncrypt),
        }
        own = rig.settings.pki_dir / "own" / "cert.der"
        assert all(e.ServerCertificate == own.read_bytes() for e in endpoints)
        cert = x509.load_der_x509_certificate(own.read_bytes())
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert san.get_values_for_type(x509.UniformResourceIdentifier) == [rig.server.namespace]
        none = next(e for e in endpoints if e.SecurityMode == MODE.None_)
        password_policy = next(
            t for t in none.UserIdentityTokens if t.TokenType == ua.UserTokenType.UserName
        )
        # Even on the None endpoint a password travels encrypted with the server's key.
        assert password_policy.SecurityPolicyUri.endswith("#Basic256Sha256")


async def test_the_none_policy_and_anonymous_sessions_can_be_switched_off(tmp_path: Path) -> None:
    def secure_only(s: OpcUaSettings) -> OpcUaSettings:
        return dataclasses.replace(s, security=("sign_and_encrypt",), anonymous=False)

    async with opcua_rig(tmp_path, change=secure_only) as rig:
        client = Client(rig.server.endpoint)
        endpoints = await client.connect_and_get_server_endpoints()
        assert [e.SecurityMode for e in endpoints] == [MODE.SignAndEncrypt]
        tokens = {t.TokenType for t in endpoints[0].UserIdentityTokens}
        assert tokens == {ua.UserTokenType.UserName}
        with pytest.raises(ua.UaError):
            async with rig.client("alice"):  # no security: no such endpoint
                pass
        cert, _ = await client_certificate(tmp_path)
        trust(rig, cert)
        with pytest.raises(ua.uaerrors.BadIdentityTokenRejected):
            async with rig.client(None, secure=MODE.SignAndEncrypt):
                pass
        async with rig.client("alice", secure=MODE.SignAndEncrypt) as c:
            ns = await rig.ns(c)
            res = await call(
                c,
                ua.NodeId("/Bench/Channels/ch0", ns),
                ua.NodeId("/Bench/Channels/ch0/SetMode", ns),
                ua.Variant("Auto", ua.VariantType.String),
            )
            assert res.StatusCode.is_good(), text(res)


async def test_a_client_certificate_is_refused_until_it_is_in_the_trust_list(
    tmp_path: Path,
) -> None:
    async with opcua_rig(tmp_path) as rig:
        cert, _ = await client_certificate(tmp_path)
        for mode in (MODE.Sign, MODE.SignAndEncrypt):
            with pytest.raises(ua.uaerrors.BadCertificateUntrusted):
                async with rig.client("alice", secure=mode):
                    pass
        rejected = list((rig.settings.pki_dir / "rejected").iterdir())
        assert [r.read_bytes() for r in rejected] == [cert.read_bytes()]
        # The administrator trusts it by moving it: no restart.
        rejected[0].rename(rig.settings.pki_dir / "trusted" / rejected[0].name)
        for mode in (MODE.Sign, MODE.SignAndEncrypt):
            async with rig.client("alice", secure=mode) as c:
                ns = await rig.ns(c)
                value = await c.get_node(ua.NodeId("ch0.voltage", ns)).read_value()
                assert value == rig.bench.db["ch0.voltage"].value
        # Another client's certificate is still refused.
        other, _ = await client_certificate(tmp_path, "other")
        with pytest.raises(ua.uaerrors.BadCertificateUntrusted):
            async with rig.client(
                "alice", secure=MODE.SignAndEncrypt, cert=(other, tmp_path / "other-key.pem")
            ):
                pass
