"""One write request to InfluxDB's v2 write API, and what its answer means.

``POST <url>/api/v2/write?org=…&bucket=…&precision=ns`` with ``Authorization: Token …``:
the endpoint influxdb-client posts to, served by InfluxDB 2.x and by 1.8 (bucket
``db/rp``, token ``user:password``; docs/adr/0012). Sent with the
standard library's ``http.client`` on one kept-alive connection (docs/adr/0012): the
forwarder needs every status code, the ``Retry-After`` header and a timeout it chose, and
none of the library's own buffering or retrying.
"""

from __future__ import annotations

import contextlib
import email.utils
import http.client
import json
import socket
import time
import urllib.parse
from dataclasses import dataclass
from enum import StrEnum

__all__ = ["Failure", "Outcome", "Reply", "WriteClient", "classify", "parse_retry_after"]

USER_AGENT = "bench-supervisor-influx/1"
STALE_CONNECTION = (http.client.RemoteDisconnected, BrokenPipeError, ConnectionResetError)
"""How a kept-alive connection closed by the other side fails at its next request."""
REASON_CHARS = 300
"""How much of a server's error message is kept (logs, tags, dead letters)."""


class Outcome(StrEnum):
    """What the forwarder does with a batch after a reply."""

    DELIVERED = "delivered"  # 2xx: delete it from the spool
    RETRY = "retry"  # the server is busy or broken (5xx, 408, 429): back off, send again
    SPLIT = "split"  # some line is bad (400, 413, 422): bisect to find it
    CONFIG = "config"  # applies to every point (401, 403, 404, ...): keep, alarm, retry slowly


class Failure(StrEnum):
    """Kinds of failure, each reported once when it starts and once when it ends."""

    UNREACHABLE = "unreachable"  # connection refused, reset, no route, name not found
    TIMEOUT = "timeout"  # no answer within timeout_s
    SERVER = "server error"  # 5xx
    THROTTLED = "throttled"  # 429, 408
    AUTH = "token refused"  # 401, 403
    BUCKET = "bucket not found"  # 404
    REFUSED = "refused"  # another 4xx or a redirect: the configuration is wrong


TRANSIENT = frozenset({Failure.UNREACHABLE, Failure.TIMEOUT, Failure.SERVER, Failure.THROTTLED})
CONFIGURATION = frozenset({Failure.AUTH, Failure.BUCKET, Failure.REFUSED})


@dataclass(frozen=True, slots=True)
class Reply:
    status: int
    reason: str  # the server's error message ("" on success)
    retry_after_s: float | None = None


def classify(status: int) -> tuple[Outcome, Failure | None]:
    if 200 <= status < 300:
        return Outcome.DELIVERED, None
    if status in (408, 429):
        return Outcome.RETRY, Failure.THROTTLED
    if status >= 500:
        return Outcome.RETRY, Failure.SERVER
    if status in (400, 413, 422):
        # 400: a line does not parse or a field changes type (partial write on 1.8);
        # 413: the body is too large (halves are smaller); 422: 2.x, points outside the
        # retention period. Each concerns some lines, not the whole configuration.
        return Outcome.SPLIT, None
    if status in (401, 403):
        return Outcome.CONFIG, Failure.AUTH
    if status == 404:
        return Outcome.CONFIG, Failure.BUCKET
    return Outcome.CONFIG, Failure.REFUSED


def parse_retry_after(value: str | None, now: float | None = None) -> float | None:
    """``Retry-After``: seconds, or an HTTP date (RFC 9110 §10.2.3); None when absent or
    unreadable."""
    if value is None:
        return None
    text = value.strip()
    if text.isdigit():
        return float(text)
    try:
        when = email.utils.parsedate_to_datetime(text)
    except (TypeError, ValueError, IndexError):
        return None
    return max(0.0, when.timestamp() - (time.time() if now is None else now))


def _reason(body: bytes, status: int, phrase: str) -> str:
    """The server's message: ``{"error": …}`` (1.8) or ``{"message": …}`` (2.x)."""
    text = body.decode("utf-8", "replace").strip()
    try:
        doc = json.loads(text)
    except ValueError:
        doc = None
    if isinstance(doc, dict):
        msg = doc.get("error") or doc.get("message")
        if isinstance(msg, str) and msg:
            text = msg
    text = text or phrase
    return f"{status} {text}"[:REASON_CHARS]


class WriteClient:
    """Posts line-protocol bodies to one bucket; not thread-safe (one forwarder uses it)."""

    def __init__(self, url: str, org: str, bucket: str, token: str, timeout_s: float) -> None:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"InfluxDB url {url!r}: expected http://host:port or https://…")
        self.url = url
        self.https = parts.scheme == "https"
        self.host = parts.hostname
        self.port = parts.port or (443 if self.https else 80)
        query = urllib.parse.urlencode({"org": org, "bucket": bucket, "precision": "ns"})
        self.path = f"{parts.path.rstrip('/')}/api/v2/write?{query}"
        self.timeout_s = timeout_s
        self._headers = {
            "Authorization": f"Token {token}",
            "Content-Type": "text/plain; charset=utf-8",
            "User-Agent": USER_AGENT,
        }
        self._conn: http.client.HTTPConnection | None = None

    def write(self, body: bytes, timeout_s: float | None = None) -> Reply:
        """One request. Raises ``TimeoutError`` when no answer comes within the timeout,
        ``OSError`` or ``http.client.HTTPException`` when the server cannot be reached or
        drops the connection.

        A kept-alive connection the server (or a proxy) closed while idle fails before
        any answer: that one is tried again at once on a new connection (a write is
        idempotent: the same points at the same timestamps)."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        reused = self._conn is not None
        try:
            return self._request(body, timeout)
        except STALE_CONNECTION:
            if not reused:
                raise
        return self._request(body, timeout)

    def _request(self, body: bytes, timeout: float) -> Reply:
        conn = self._conn
        if conn is None:
            conn = self._connect(timeout)
        else:
            conn.timeout = timeout
            if conn.sock is not None:
                conn.sock.settimeout(timeout)
        try:
            conn.request("POST", self.path, body=body, headers=self._headers)
            resp = conn.getresponse()
            data = resp.read()
        except BaseException:
            self.close()
            raise
        if resp.will_close:
            self.close()
        status = resp.status
        if 200 <= status < 300:
            return Reply(status, "")
        return Reply(
            status,
            _reason(data, status, resp.reason),
            parse_retry_after(resp.getheader("Retry-After")),
        )

    def _connect(self, timeout: float) -> http.client.HTTPConnection:
        cls = http.client.HTTPSConnection if self.https else http.client.HTTPConnection
        conn = cls(self.host, self.port, timeout=timeout)
        self._conn = conn
        return conn

    def abort(self) -> None:
        """From another thread: end the request in flight (its ``write`` raises)."""
        conn = self._conn
        sock = conn.sock if conn is not None else None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    def close(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            conn.close()


def describe(exc: BaseException) -> tuple[Failure, str]:
    """A transport exception → its failure kind and one line of cause."""
    if isinstance(exc, TimeoutError):
        return Failure.TIMEOUT, "no answer in time (timed out)"
    if isinstance(exc, socket.gaierror):
        return Failure.UNREACHABLE, f"host not found ({exc.strerror or exc})"
    if isinstance(exc, OSError):
        return Failure.UNREACHABLE, exc.strerror or str(exc) or type(exc).__name__
    text = str(exc) or type(exc).__name__
    return Failure.UNREACHABLE, f"{type(exc).__name__}: {text}"
