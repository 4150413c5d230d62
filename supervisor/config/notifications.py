"""The I/O map's ``notifications:`` section: where alarms and test ends are sent (issue 34,
docs/notifications.md, ``supervisor.notify``).

Routes are e-mail (SMTP, STARTTLS and login) or webhooks (an HTTP POST whose body is the
documented JSON payload, or a template: ntfy, Slack and Teams are templates, not code).
Secrets are never in this file: a password, a header's token or a URL that holds a key
come from a file (``*_file``) or an environment variable (``*_env``), read at ``check`` so
that a missing one is refused with its position, and read again when the bench starts.
"""

from __future__ import annotations

import datetime
import re
import urllib.parse
import zoneinfo
from typing import Annotated, Final, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from supervisor.config.secrets import read_secret_env, read_secret_file

__all__ = [
    "PRIORITIES",
    "EmailRoute",
    "HeaderSecret",
    "NotificationsConfig",
    "QuietHours",
    "Route",
    "WebhookRoute",
]

Priority = Literal["low", "medium", "high", "critical"]
PRIORITIES: Final = ("low", "medium", "high", "critical")
"""In increasing order (the alarm model's severities)."""
EventKind = Literal["alarm", "test_end"]
ENV_PATTERN: Final = r"^[A-Za-z_][A-Za-z0-9_]*$"
_HHMM = re.compile(r"([01]\d|2[0-3]):[0-5]\d")
_ADDRESS = re.compile(r"[^@\s<>,;]+@[^@\s<>,;]+")
_SECRET_HEADER = re.compile(r"authorization|token|key|secret|password|cookie", re.IGNORECASE)
NAME_PATTERN: Final = r"^[A-Za-z_][A-Za-z0-9_]*$"  # models.NAME_PATTERN (models imports us)


class Strict(BaseModel):
    """As ``models.Strict`` (``models`` imports this module, so it cannot be imported)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


def http_url(v: str) -> str:
    """``v`` if it is an http(s) URL with a host (ValueError saying what is wrong)."""
    parts = urllib.parse.urlsplit(v)
    try:
        parts.port  # noqa: B018 - raises ValueError for a port that is not a number
    except ValueError:
        raise ValueError("the port must be a number from 1 to 65535") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError("expected http://host[:port]/path or https://host[:port]/path")
    if any(c.isspace() for c in v):
        raise ValueError("a URL holds no white space")
    return v


class QuietHours(Strict):
    """A local-time window in which notices below ``below`` wait: they go out, as one
    summary, when the window ends (never dropped)."""

    start: str = Field(description="HH:MM, local time (the section's timezone).")
    end: str = Field(description="HH:MM; before start: the window spans midnight.")
    below: Priority = Field(
        "high", description="Notices of a lower priority wait; this one and above go at once."
    )

    @field_validator("start", "end")
    @classmethod
    def _hhmm(cls, v: str) -> str:
        if not _HHMM.fullmatch(v):
            raise ValueError("expected a time of day as HH:MM (00:00 to 23:59)")
        return v

    def minutes(self) -> tuple[int, int]:
        h1, m1 = self.start.split(":")
        h2, m2 = self.end.split(":")
        return int(h1) * 60 + int(m1), int(h2) * 60 + int(m2)


class HeaderSecret(Strict):
    """A header's value read from a file or an environment variable."""

    file: str | None = None
    env: str | None = Field(None, pattern=ENV_PATTERN)

    @model_validator(mode="after")
    def _one(self) -> HeaderSecret:
        if (self.file is None) == (self.env is None):
            raise ValueError("give exactly one of file or env")
        self.value()  # refused now when missing
        return self

    def value(self) -> str:
        if self.file is not None:
            return read_secret_file(self.file, "header file")
        assert self.env is not None
        return read_secret_env(self.env)


class _Route(Strict):
    name: str = Field(pattern=NAME_PATTERN, description="The route's name (logs, tags, tests).")
    kinds: list[EventKind] = Field(
        ["alarm", "test_end"], min_length=1, description="Which events: alarm, test_end."
    )
    min_priority: Priority = Field(
        "low", description="Alarms below this priority are not sent (test ends pass by `kinds`)."
    )
    channels: list[str] | None = Field(
        None, description="Only events of these channels (and bench-wide ones); null: all."
    )
    summary_window_s: float = Field(
        2.0,
        ge=0,
        le=3600,
        description="Events of this route within this long of the first become one"
        " message (an e-stop tripping every channel: one summary, not fifty).",
    )
    escalate_after_s: float | None = Field(
        None,
        gt=0,
        le=7 * 86400,
        description="An alarm still unacknowledged this long after it activated is sent to"
        " the escalation recipients (once per activation).",
    )
    quiet_hours: QuietHours | None = None
    timeout_s: float = Field(10.0, gt=0, le=300, description="One delivery attempt at most.")


class EmailRoute(_Route):
    """SMTP with STARTTLS (on by default) and login."""

    type: Literal["email"]
    host: str = Field(min_length=1, description="The SMTP server.")
    port: int = Field(587, ge=1, le=65535)
    starttls: bool = Field(True, description="Upgrade to TLS before login (refused if absent).")
    ca_file: str | None = Field(
        None, description="PEM file of the CA that signed the server's certificate (a lab CA)."
    )
    user: str | None = Field(None, min_length=1, description="Login (AUTH); null: no login.")
    password_file: str | None = None
    password_env: str | None = Field(None, pattern=ENV_PATTERN)
    sender: str = Field(alias="from", description="The From address.")
    to: list[str] = Field(min_length=1, description="Recipients.")
    escalate_to: list[str] = Field([], description="Recipients of escalations.")

    @field_validator("sender")
    @classmethod
    def _one_address(cls, v: str) -> str:
        if not _ADDRESS.fullmatch(v):
            raise ValueError(f"{v!r} is not a mail address (name@domain)")
        return v

    @field_validator("to", "escalate_to")
    @classmethod
    def _addresses(cls, v: list[str]) -> list[str]:
        for a in v:
            cls._one_address(a)
        return v

    @field_validator("password_file")
    @classmethod
    def _password_file(cls, v: str | None) -> str | None:
        if v is not None:
            read_secret_file(v, "password file")
        return v

    @field_validator("password_env")
    @classmethod
    def _password_env(cls, v: str | None) -> str | None:
        if v is not None:
            read_secret_env(v)
        return v

    @model_validator(mode="after")
    def _login(self) -> EmailRoute:
        given = (self.password_file is not None) + (self.password_env is not None)
        if self.user is not None and given != 1:
            raise ValueError("a user needs exactly one of password_file or password_env")
        if self.user is None and given:
            raise ValueError("a password without a user: give user too")
        if self.escalate_after_s is not None and not self.escalate_to:
            raise ValueError("escalate_after_s needs escalate_to (who is told)")
        return self

    def password(self) -> str | None:
        if self.password_file is not None:
            return read_secret_file(self.password_file, "password file")
        if self.password_env is not None:
            return read_secret_env(self.password_env)
        return None


class WebhookRoute(_Route):
    """An HTTP POST per message: the JSON payload, or a template (ntfy, Slack, Teams)."""

    type: Literal["webhook"]
    url: str | None = Field(None, description="The URL (no secret in it: else url_file/url_env).")
    url_file: str | None = Field(None, description="A file holding the URL (one with a key).")
    url_env: str | None = Field(None, pattern=ENV_PATTERN)
    escalate_url: str | None = Field(
        None, description="Escalations go here (null: to the route's own URL)."
    )
    format: Literal["json", "ntfy", "slack", "teams", "template"] = Field(
        "json",
        description="json: the documented payload; ntfy, slack, teams: the built-in"
        " templates; template: `template` and `content_type` below.",
    )
    template: str | None = Field(
        None,
        description="The body, with $subject, $text, $priority, $kind, $bench, $count"
        " (JSON-quoted when content_type is JSON).",
    )
    content_type: str = Field("application/json", min_length=1)
    headers: dict[str, Annotated[str, Field(max_length=1000)] | HeaderSecret] = Field(
        {},
        description="Extra headers; a secret (Authorization, a token) as {file: …} or {env: …}.",
    )

    @field_validator("url", "escalate_url")
    @classmethod
    def _url(cls, v: str | None) -> str | None:
        return None if v is None else http_url(v)

    @field_validator("url_file")
    @classmethod
    def _url_file(cls, v: str | None) -> str | None:
        if v is not None:
            http_url(read_secret_file(v, "URL file"))
        return v

    @field_validator("url_env")
    @classmethod
    def _url_env(cls, v: str | None) -> str | None:
        if v is not None:
            http_url(read_secret_env(v))
        return v

    @field_validator("headers")
    @classmethod
    def _no_plain_secret(cls, v: dict[str, str | HeaderSecret]) -> dict[str, str | HeaderSecret]:
        for name, value in v.items():
            if not re.fullmatch(r"[A-Za-z0-9-]+", name):
                raise ValueError(f"header name {name!r}: letters, digits and '-' only")
            if isinstance(value, str) and _SECRET_HEADER.search(name):
                raise ValueError(
                    f"header {name}: a secret is never written here; give {{file: …}} or {{env: …}}"
                )
        return v

    @model_validator(mode="after")
    def _one_url(self) -> WebhookRoute:
        given = sum(x is not None for x in (self.url, self.url_file, self.url_env))
        if given != 1:
            raise ValueError("give exactly one of url, url_file or url_env")
        if (self.format == "template") != (self.template is not None):
            raise ValueError("format: template goes with a template (and only it)")
        return self

    def target(self) -> str:
        """The URL, read now (a file or a variable may have changed)."""
        if self.url is not None:
            return self.url
        if self.url_file is not None:
            return http_url(read_secret_file(self.url_file, "URL file"))
        assert self.url_env is not None
        return http_url(read_secret_env(self.url_env))

    def header_values(self) -> dict[str, str]:
        return {k: v if isinstance(v, str) else v.value() for k, v in self.headers.items()}


Route = Annotated[Union[EmailRoute, WebhookRoute], Field(discriminator="type")]  # noqa: UP007


class NotificationsConfig(Strict):
    """Notifications of alarms and test ends (docs/notifications.md)."""

    timezone: str | None = Field(
        None, description="Quiet hours' time zone (e.g. Europe/Paris); null: the machine's."
    )
    retry_min_s: float = Field(1.0, gt=0, le=3600, description="First wait after a failure.")
    retry_max_s: float = Field(60.0, gt=0, le=86400, description="Longest wait (backoff cap).")
    failing_after_attempts: int = Field(
        3, ge=1, le=1000, description="Raise notify.failing after this many failed attempts…"
    )
    failing_after_s: float = Field(
        60.0, gt=0, le=86400, description="…or once a message has waited this long."
    )
    routes: list[Route] = Field(min_length=1)

    @field_validator("timezone")
    @classmethod
    def _zone(cls, v: str | None) -> str | None:
        if v is not None:
            try:
                zoneinfo.ZoneInfo(v)
            except (zoneinfo.ZoneInfoNotFoundError, ValueError):
                raise ValueError(f"unknown time zone {v!r} (e.g. Europe/Paris, UTC)") from None
        return v

    @model_validator(mode="after")
    def _names(self) -> NotificationsConfig:
        seen: set[str] = set()
        for r in self.routes:
            if r.name in seen:
                raise ValueError(f"two routes are named {r.name!r}")
            seen.add(r.name)
        if self.retry_min_s > self.retry_max_s:
            raise ValueError("retry_min_s is above retry_max_s")
        return self

    def zone(self) -> datetime.tzinfo | None:
        return zoneinfo.ZoneInfo(self.timezone) if self.timezone is not None else None
