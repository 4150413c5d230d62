"""The one reader of a request's JSON body, for every route (issue 28, finding 6).

Each route read its body its own way (``request.json()``, a decode and ``json.loads``),
and each let something through as a 500: 100,000 nested ``[`` (``RecursionError``), a
``charset`` Python does not know, ``Content-Encoding: gzip`` on a plain body, a lone
surrogate (``"\\ud800"``) that later killed the historian's writer. Here, in order, each
refused with one reason naming what was received:

- ``Content-Encoding`` other than ``identity``: 415 (the API takes JSON as it is);
- a ``charset`` other than UTF-8 (JSON is UTF-8, RFC 8259 section 8.1): 415;
- more than ``limit_bytes``: 413;
- bytes that are not UTF-8, text that is not JSON, ``NaN``/``Infinity``: 400;
- nesting deeper than ``MAX_DEPTH`` (no body of this API needs more than 3): 400;
- a string, key or value, with a character UTF-8 cannot encode (a lone surrogate): 400,
  naming the member. Nothing that cannot be stored reaches the bench
  (``supervisor.core.encoding``: the writers escape whatever still comes).
"""

from __future__ import annotations

import codecs
import json
from typing import Any, Final

from aiohttp import hdrs, web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.web_protocol import RequestPayloadError

from supervisor.core.encoding import unencodable_at

MAX_JSON_BYTES: Final = 1024**2
"""A command's or a login's body: aiohttp's own default ``client_max_size``."""
MAX_DEPTH: Final = 32
"""Arrays and objects inside one another (a recipe load's parameters are at depth 2)."""


class BodyError(Exception):
    """A body refused: ``status`` (400, 413, 415) and ``reason``."""

    def __init__(self, status: int, reason: str, *, close: bool = False) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason
        self.close = close
        """Close the connection after the answer: the rest of the body cannot be read."""

    def response(self, **extra: Any) -> web.Response:
        kind = {413: "request entity too large", 415: "unsupported media type"}.get(
            self.status, "bad argument"
        )
        body = {"accepted": False, "reason": self.reason, "kind": kind, **extra}
        resp = web.json_response(body, status=self.status)
        if self.close:
            # The connection closes after the answer: aiohttp would otherwise read the
            # rest of the body to reuse it, and a body that cannot be decoded (gzip
            # declared, plain sent) would drop the connection without the answer.
            resp.force_close()
        return resp


def _no_constant(name: str) -> Any:
    # json.loads takes NaN, Infinity and -Infinity, which RFC 8259 does not.
    raise ValueError(f"{name} is not JSON")


def _check_headers(request: web.Request) -> None:
    encoding = request.headers.get(hdrs.CONTENT_ENCODING, "identity").strip().lower()
    if encoding not in ("", "identity"):
        raise BodyError(
            415,
            f"Content-Encoding {encoding[:40]!r} is not accepted: send the JSON body as it is",
            close=True,
        )
    charset = request.charset
    if charset is not None:
        try:
            name = codecs.lookup(charset).name
        except LookupError:
            name = ""
        if name != "utf-8":
            raise BodyError(
                415, f"charset {charset[:40]!r} is not accepted: a JSON body is UTF-8 (RFC 8259)"
            )


async def read_bytes(request: web.Request, limit_bytes: int, too_large: str = "") -> bytes:
    """The body, refused 413 past ``limit_bytes`` (``too_large``: the reason to give)."""
    _check_headers(request)
    # aiohttp's own words when it refused such a body (clients and tests know them).
    reason = too_large or f"Maximum request body size {limit_bytes} exceeded"
    # Read up to the limit even when the declared length is over it, as aiohttp's own
    # ``read`` did: an answer before the body is read would leave the client writing into
    # a connection the server no longer reads.
    data = bytearray()
    try:
        async for chunk in request.content.iter_chunked(64 * 1024):
            data += chunk
            if len(data) > limit_bytes:
                raise BodyError(413, reason)
    except (RequestPayloadError, HttpProcessingError) as exc:  # a broken chunk, say
        raise BodyError(400, f"the body could not be read: {exc}") from None
    return bytes(data)


def _member(path: list[str | int]) -> str:
    text = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path).lstrip(".")
    return text or "the body"


def _check_tree(doc: Any) -> None:
    """Depth and storable strings, without recursion (a depth check must not overflow)."""
    stack: list[tuple[Any, list[str | int]]] = [(doc, [])]
    while stack:
        value, path = stack.pop()
        if len(path) > MAX_DEPTH:
            raise BodyError(400, f"the body is nested deeper than {MAX_DEPTH} levels")
        if isinstance(value, str):
            _check_text(value, path, "its value")
        elif isinstance(value, dict):
            for key, item in value.items():
                _check_text(key, path, f"member name {key!r}")
                stack.append((item, [*path, key]))
        elif isinstance(value, list):
            stack.extend((item, [*path, i]) for i, item in enumerate(value))


def _check_text(text: str, path: list[str | int], what: str) -> None:
    at = unencodable_at(text)
    if at is not None:
        code = f"U+{ord(text[at]):04X}"
        raise BodyError(
            400,
            f"{_member(path)}: {what} holds a lone surrogate ({code} at character {at}),"
            " which is not text and cannot be stored",
        )


async def read_json(
    request: web.Request,
    *,
    limit_bytes: int = MAX_JSON_BYTES,
    too_large: str = "",
    empty: Any = None,
    shape: str = "",
) -> Any:
    """The request's JSON document, checked as the module says. ``empty``: what an empty
    body gives (None: an empty body is refused, it is not JSON). ``shape``: the body the
    route expects (``{"value": ...}``), said when the body is not JSON."""
    prefix = f"body must be JSON {shape}: " if shape else ""
    data = await read_bytes(request, limit_bytes, too_large)
    if empty is not None and not data.strip():
        return empty
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise BodyError(400, f"{prefix}the body is not UTF-8: {exc}") from None
    try:
        doc = json.loads(text, parse_constant=_no_constant)
    except RecursionError:
        raise BodyError(400, f"the body is nested deeper than {MAX_DEPTH} levels") from None
    except ValueError as exc:
        raise BodyError(400, f"{prefix}the body is not JSON: {exc}") from None
    _check_tree(doc)
    return doc


async def read_json_object(
    request: web.Request,
    *,
    limit_bytes: int = MAX_JSON_BYTES,
    too_large: str = "",
    empty_ok: bool = False,
    what: str = "the body",
    shape: str = "",
) -> dict[str, Any]:
    """``read_json``, refused 400 unless an object (``{}`` for an empty body when
    ``empty_ok``)."""
    doc = await read_json(
        request,
        limit_bytes=limit_bytes,
        too_large=too_large,
        empty={} if empty_ok else None,
        shape=shape,
    )
    if not isinstance(doc, dict):
        must = f"body must be JSON {shape}" if shape else f"{what} must be a JSON object"
        raise BodyError(400, f"{must}, not {type(doc).__name__}")
    return doc


def refuse_unknown(body: dict[str, Any], allowed: tuple[str, ...], what: str) -> None:
    """400 naming the members of ``body`` not in ``allowed`` (a typo is never ignored)."""
    unknown = sorted(set(body) - set(allowed))
    if unknown:
        expected = ", ".join(allowed) if allowed else "no member"
        raise BodyError(
            400, f"{what}: unknown member {', '.join(map(repr, unknown))} (expected: {expected})"
        )
