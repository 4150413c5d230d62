"""Sending one message: e-mail over SMTP (STARTTLS, login) or a webhook's POST.

The webhook's body is the documented JSON payload (``payload``) or a template; ntfy,
Slack and Teams are templates in ``FORMATS`` — data, not code per vendor: a service that
takes a JSON POST is one more template in the I/O map (``format: template``). Every
message carries its idempotency key: the ``Idempotency-Key`` header of a webhook, the
``Message-ID`` of a mail, so that a receiver can drop the one a restart sent again.
"""

from __future__ import annotations

import asyncio
import email.utils
import json
import smtplib
import ssl
import string
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from email.message import EmailMessage
from typing import Final

import aiohttp

from supervisor.config.notifications import EmailRoute, WebhookRoute
from supervisor.notify.router import Outgoing

__all__ = [
    "FORMATS",
    "PAYLOAD_VERSION",
    "DeliveryError",
    "Format",
    "Sender",
    "email_message",
    "payload",
    "sender_of",
    "webhook_request",
]

PAYLOAD_VERSION: Final = 1
Sender = Callable[[Outgoing], Awaitable[None]]
"""Delivers one message or raises (``DeliveryError`` and the like) saying why not."""

_NTFY_PRIORITY: Final = {"low": "2", "medium": "3", "high": "4", "critical": "5"}


class DeliveryError(Exception):
    """A server refused the message, or could not be reached."""


@dataclass(frozen=True)
class Format:
    """A webhook body: a ``string.Template`` over the message's fields (JSON-quoted when
    ``content_type`` is JSON), and headers made the same way."""

    body: str
    content_type: str = "application/json"
    headers: Mapping[str, str] | None = None


FORMATS: Final[Mapping[str, Format]] = {
    "ntfy": Format(
        "$text",
        "text/plain; charset=utf-8",
        {"Title": "$subject", "Priority": "$ntfy_priority", "Tags": "$kind"},
    ),
    "slack": Format('{"text": $message}'),
    "teams": Format(
        '{"@type": "MessageCard", "@context": "https://schema.org/extensions",'
        ' "summary": $subject, "title": $subject, "text": $text}'
    ),
}
"""The built-in templates (``format:`` in a webhook route)."""


def payload(bench: str, m: Outgoing) -> dict[str, object]:
    """The JSON payload (``format: json``; docs/notifications.md "The payload")."""
    return {
        "version": PAYLOAD_VERSION,
        "bench": bench,
        "route": m.route,
        "key": m.key,
        "kind": m.kind,
        "priority": m.priority,
        "escalation": m.escalation,
        "subject": m.subject,
        "text": m.text,
        "events": [n.as_json() for n in m.notices],
    }


def _fields(bench: str, m: Outgoing) -> dict[str, str]:
    return {
        "subject": m.subject,
        "text": m.text,
        "message": f"{m.subject}\n{m.text}",
        "priority": m.priority,
        "ntfy_priority": _NTFY_PRIORITY.get(m.priority, "3"),
        "kind": m.kind,
        "bench": bench,
        "count": str(len(m.notices)),
        "key": m.key,
    }


def _header_text(text: str) -> str:
    # A header is one line of Latin-1: a summary's lines joined, other characters as '?'.
    return " ".join(text.split()).encode("latin-1", "replace").decode("latin-1")


def webhook_request(
    route: WebhookRoute, bench: str, m: Outgoing
) -> tuple[str, bytes, dict[str, str]]:
    """(URL, body, headers) of ``m`` on ``route``."""
    url = route.escalate_url if m.escalation and route.escalate_url else route.target()
    if route.format == "json":
        fmt = Format(json.dumps(payload(bench, m), ensure_ascii=False))
        body = fmt.body
    else:
        fmt = (
            FORMATS[route.format]
            if route.format != "template"
            else Format(route.template or "", route.content_type)
        )
        fields = _fields(bench, m)
        quoted = (
            {k: json.dumps(v, ensure_ascii=False) for k, v in fields.items()}
            if "json" in fmt.content_type
            else fields
        )
        body = string.Template(fmt.body).safe_substitute(quoted)
    headers = {
        k: _header_text(string.Template(v).safe_substitute(_fields(bench, m)))
        for k, v in (fmt.headers or {}).items()
    }
    headers.update(route.header_values())
    headers["Content-Type"] = fmt.content_type
    headers["Idempotency-Key"] = m.key
    return url, body.encode("utf-8"), headers


def email_message(route: EmailRoute, bench: str, m: Outgoing) -> EmailMessage:
    msg = EmailMessage()
    msg["Subject"] = " ".join(m.subject.split())
    msg["From"] = route.sender
    msg["To"] = ", ".join(route.escalate_to if m.escalation else route.to)
    msg["Date"] = email.utils.formatdate(localtime=False)
    msg["Message-ID"] = f"<{m.key}@{bench}.notify>"
    msg["X-Idempotency-Key"] = m.key
    if m.priority in ("high", "critical"):
        msg["X-Priority"] = "1"
    msg.set_content(m.text + "\n")
    return msg


def send_email(route: EmailRoute, bench: str, m: Outgoing) -> None:
    """Blocking (smtplib): run it in a thread."""
    password = route.password()  # read now: a file changed since the start is used
    msg = email_message(route, bench, m)
    try:
        with smtplib.SMTP(route.host, route.port, timeout=route.timeout_s) as smtp:
            smtp.ehlo()
            if route.starttls:
                if not smtp.has_extn("starttls"):
                    raise DeliveryError(f"{route.host}:{route.port} offers no STARTTLS")
                smtp.starttls(context=ssl.create_default_context(cafile=route.ca_file))
                smtp.ehlo()
            if route.user is not None:
                assert password is not None  # the config requires one with a user
                smtp.login(route.user, password)
            smtp.send_message(msg)
    except smtplib.SMTPAuthenticationError as exc:
        raise DeliveryError(f"login refused for {route.user}: {exc.smtp_code}") from None
    except (smtplib.SMTPException, OSError) as exc:
        raise DeliveryError(f"{route.host}:{route.port}: {type(exc).__name__}: {exc}") from None


async def post_webhook(
    session: aiohttp.ClientSession, route: WebhookRoute, bench: str, m: Outgoing
) -> None:
    url, body, headers = webhook_request(route, bench, m)
    try:
        async with session.post(
            url,
            data=body,
            headers=headers,
            timeout=aiohttp.ClientTimeout(total=route.timeout_s),
            allow_redirects=False,
        ) as resp:
            if resp.status >= 300:
                text = (await resp.text(errors="replace"))[:200]
                raise DeliveryError(f"HTTP {resp.status}: {text}")
    except (aiohttp.ClientError, TimeoutError) as exc:
        raise DeliveryError(f"{type(exc).__name__}: {exc}") from None


def sender_of(
    route: EmailRoute | WebhookRoute,
    bench: str,
    session: Callable[[], aiohttp.ClientSession],
) -> Sender:
    """The sender of ``route``; ``session``: the notifier's HTTP session (made lazily)."""
    if isinstance(route, EmailRoute):

        async def mail(m: Outgoing) -> None:
            await asyncio.to_thread(send_email, route, bench, m)

        return mail

    async def post(m: Outgoing) -> None:
        await post_webhook(session(), route, bench, m)

    return post
