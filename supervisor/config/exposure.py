"""What an I/O map exposes to the network (issue 27, finding 5; docs/adr/0014-opcua-server.md
"Security"): ``supervisor check`` prints these as warnings (exit 0). A listener on loopback
is this machine's only; one elsewhere is reachable by the lab network, where what travels
in clear or without a login is anyone's. An HTTP listener off loopback without login is
already an error (``HmiConfig``)."""

from __future__ import annotations

from supervisor.config.models import BenchConfig, is_loopback


def exposure_warnings(cfg: BenchConfig) -> list[str]:
    """One line per listener off loopback that serves without a login or in clear."""
    out: list[str] = []
    hmi = cfg.hmi
    if not is_loopback(hmi.host):
        what = [
            "the HTTP API speaks plain HTTP: logins and session cookies cross the network"
            " in clear (put a TLS reverse proxy in front)"
        ]
        if hmi.login and hmi.anonymous_read:
            what.append("visitors see the bench without logging in (set hmi.anonymous_read: false)")
        out.append(
            f"hmi: host {hmi.host!r} is not loopback: {'; '.join(what)}; or set hmi.host: 127.0.0.1"
        )
    o = cfg.opcua
    if o.enabled and not is_loopback(o.host) and "none" in o.security_modes:
        what = [
            "the None security policy is offered: messages cross the network unsigned and"
            " in clear (passwords stay encrypted with the server's certificate)"
        ]
        if o.anonymous:
            what.append("anonymous sessions read the bench without a login or a certificate")
        out.append(
            f"opcua: host {o.host!r} is not loopback: {'; '.join(what)}; leave none out of"
            " opcua.security (clients then need a certificate in the server's pki/trusted)"
            " or set opcua.host: 127.0.0.1"
        )
    m = cfg.modbus_server
    if m is not None and not is_loopback(m.host):
        risk = "Modbus has neither login nor encryption: anyone on the network reads the bench"
        if m.writes:
            risk += (
                "; writes are taken from the writers' IP addresses alone, which another host"
                " can take"
            )
        out.append(
            f"modbus_server: host {m.host!r} is not loopback: {risk}; keep it on a network you"
            " trust or set modbus_server.host: 127.0.0.1"
        )
    return out
