"""Real receivers for the notification tests (issue 34): an SMTP server (aiosmtpd) that
takes STARTTLS with a self-signed certificate made here and AUTH LOGIN, and an HTTP
receiver (aiohttp) — both on loopback, on free ports, in threads of their own so that a
test may block (a ``supervisor run`` child process, ``urllib``) while they answer.

Each counts what it took by idempotency key (the webhook's ``Idempotency-Key`` header, the
mail's ``Message-ID``): ``duplicates`` is what a receiver that deduplicates would have
dropped. ``stop()`` closes the port (a client is refused), ``start()`` listens again on
the same port.
"""

from __future__ import annotations

import asyncio
import datetime
import email
import email.policy
import ipaddress
import json
import ssl
import threading
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from aiohttp import web
from aiosmtpd.controller import Controller
from aiosmtpd.smtp import AuthResult, LoginPassword
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from supervisor.bench.ports import free_port

USER, PASSWORD = "bench", "s3cret-pw"


def self_signed(folder: Path) -> tuple[Path, Path]:
    """A certificate for 127.0.0.1 and localhost, its own CA: (cert.pem, key.pem)."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "notify test SMTP")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = folder / "smtp-cert.pem", folder / "smtp-key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return cert_path, key_path


@dataclass
class Taken:
    """What a receiver took, by idempotency key."""

    bodies: dict[str, Any] = field(default_factory=dict)  # first copy of each key
    counts: Counter[str] = field(default_factory=Counter)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, key: str, body: Any) -> None:
        with self.lock:
            self.counts[key] += 1
            self.bodies.setdefault(key, body)

    @property
    def unique(self) -> int:
        with self.lock:
            return len(self.counts)

    @property
    def duplicates(self) -> int:
        with self.lock:
            return sum(n - 1 for n in self.counts.values())


class SmtpReceiver:
    """aiosmtpd with STARTTLS required and AUTH LOGIN only (PLAIN excluded)."""

    def __init__(self, folder: Path) -> None:
        self.cert, key = self_signed(folder)
        self.tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        self.tls.load_cert_chain(self.cert, key)
        self.port = free_port()
        self.taken = Taken()
        self.logins: list[tuple[str, str, bool]] = []  # (mechanism, user, over TLS)
        self._controller: Controller | None = None

    def _authenticate(
        self, server: Any, session: Any, envelope: Any, mechanism: str, data: Any
    ) -> AuthResult:
        ok = isinstance(data, LoginPassword) and (data.login, data.password) == (
            USER.encode(),
            PASSWORD.encode(),
        )
        user = data.login.decode() if isinstance(data, LoginPassword) else "?"
        self.logins.append((mechanism, user, session.ssl is not None))
        return AuthResult(success=ok, handled=False)  # False: the server says 535

    async def handle_DATA(self, server: Any, session: Any, envelope: Any) -> str:
        msg = email.message_from_bytes(envelope.content, policy=email.policy.default)
        key = str(msg["Message-ID"]).strip("<>").split("@")[0]
        self.taken.add(key, msg)
        return "250 Message accepted"

    def start(self) -> None:
        self._controller = Controller(
            self,
            hostname="127.0.0.1",
            port=self.port,
            tls_context=self.tls,
            require_starttls=True,
            auth_required=True,
            auth_require_tls=True,
            auth_exclude_mechanism=["PLAIN"],
            authenticator=self._authenticate,
        )
        self._controller.start()

    def stop(self) -> None:
        if self._controller is not None:
            self._controller.stop()
            self._controller = None


class WebhookReceiver:
    """aiohttp on loopback: ``POST /hook`` answers 200 and keeps the body by its key."""

    def __init__(self) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}/hook"
        self.taken = Taken()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()
        self._runner: web.AppRunner | None = None

    async def _hook(self, request: web.Request) -> web.Response:
        key = request.headers.get("Idempotency-Key", "")
        body = await request.read()
        try:
            parsed: Any = json.loads(body)
        except ValueError:
            parsed = body.decode("utf-8", "replace")
        self.taken.add(key, {"body": parsed, "headers": dict(request.headers)})
        return web.json_response({"ok": True})

    async def _start(self) -> None:
        app = web.Application()
        app.router.add_post("/hook", self._hook)
        self._runner = web.AppRunner(app)
        await self._runner.setup()
        await web.TCPSite(self._runner, "127.0.0.1", self.port).start()

    async def _stop(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    def start(self) -> None:
        asyncio.run_coroutine_threadsafe(self._start(), self._loop).result(10)

    def stop(self) -> None:
        asyncio.run_coroutine_threadsafe(self._stop(), self._loop).result(10)

    def close(self) -> None:
        self.stop()
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)
        self._loop.close()


def routes(smtp: SmtpReceiver, hook: WebhookReceiver, password_file: Path) -> list[dict[str, Any]]:
    """An e-mail route to ``smtp`` (STARTTLS with its certificate, login) and a JSON webhook
    route to ``hook``, as the I/O map writes them."""
    return [
        {
            "name": "mail",
            "type": "email",
            "host": "127.0.0.1",
            "port": smtp.port,
            "ca_file": str(smtp.cert),
            "user": USER,
            "password_file": str(password_file),
            "from": "bench@lab.test",
            "to": ["oncall@lab.test"],
            "timeout_s": 5.0,
        },
        {"name": "hook", "type": "webhook", "url": hook.url, "timeout_s": 5.0},
    ]
