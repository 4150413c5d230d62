"""gzip for the screens' files and the tag list (issue 33: the first load was 198 KB, none
of it compressed; docs/adr/0041-compressed-first-load.md).

The screens' files (:mod:`supervisor.hmi.static`) are compressed once each, at the best
level, and kept while the file is unchanged; the tag list (``GET /api/tags``) is new at every
database version, so it is compressed at the fastest level (1: 0.7 ms for 1000 tags, 171 KB
to 14 KB; level 6 is 3 times slower for 10 % less), in a worker thread when it is large
(zlib lets go of the GIL: the scan sharing the event loop is not held up by it), once per
version whatever the number of clients.

A client that does not say it accepts gzip gets the plain bytes, as before; both answers
carry ``Vary: Accept-Encoding`` so that no cache between them mixes them up."""

from __future__ import annotations

import asyncio
import zlib
from collections.abc import Awaitable, Callable, Hashable
from typing import Final

from aiohttp import hdrs, web

GZIP_MIN_BYTES: Final = 1024
"""A smaller body is sent as it is: its gzip header and the work cost more than it saves."""
OFF_LOOP_BYTES: Final = 32 * 1024
"""From this size on, the deflate runs in a worker thread, not in the event loop's turn."""
LIVE_LEVEL: Final = 1
"""The tag list's level: compressed anew at each version (see the module's docstring)."""
STATIC_LEVEL: Final = 9
"""The files' level: compressed once per file and kept."""
VARY: Final[dict[str, str]] = {"Vary": "Accept-Encoding"}
COMPRESSIBLE: Final = (
    "text/",
    "application/javascript",
    "application/json",
    "application/xml",
    "image/svg+xml",
)
"""Content types worth compressing (text); images, fonts and archives are already packed."""


def accepts_gzip(request: web.BaseRequest) -> bool:
    """Whether the request's ``Accept-Encoding`` takes gzip (``gzip`` or ``*``, not at
    ``q=0``)."""
    for item in request.headers.get(hdrs.ACCEPT_ENCODING, "").split(","):
        name, _, params = item.strip().partition(";")
        if name.strip().lower() not in ("gzip", "x-gzip", "*"):
            continue
        q = params.strip().lower().removeprefix("q=").strip() if params else "1"
        try:
            return float(q) > 0
        except ValueError:
            return False
    return False


def compressible(content_type: str | None) -> bool:
    return content_type is not None and content_type.startswith(COMPRESSIBLE)


def gzip_bytes(data: bytes, level: int) -> bytes:
    """``data`` as a gzip member (RFC 1952; its time field 0: the same bytes every time)."""
    return zlib.compress(data, level, wbits=31)


async def gzip_off_loop(data: bytes, level: int) -> bytes:
    """:func:`gzip_bytes`, in a worker thread from :data:`OFF_LOOP_BYTES` on."""
    if len(data) < OFF_LOOP_BYTES:
        return gzip_bytes(data, level)
    return await asyncio.get_running_loop().run_in_executor(None, gzip_bytes, data, level)


class GzipMemo:
    """The gzip of the latest text asked for under a key (a tag image's database version):
    every request at that version gets the same bytes, compressed once, even those that
    arrive while it is being compressed."""

    def __init__(self, level: int = LIVE_LEVEL) -> None:
        self.level = level
        self.compressed = 0
        """Texts compressed so far (each serves every request under its key)."""
        self._latest: tuple[Hashable, asyncio.Future[bytes]] | None = None

    async def gzip(self, key: Hashable, text: str) -> bytes:
        latest = self._latest
        if latest is None or latest[0] != key:
            self.compressed += 1
            task = asyncio.ensure_future(gzip_off_loop(text.encode(), self.level))
            latest = self._latest = (key, task)
        # Shielded: a request that goes away does not cancel the others' bytes.
        return await asyncio.shield(latest[1])


def gzip_response(
    body: bytes, content_type: str, headers: dict[str, str], charset: str | None = None
) -> web.Response:
    """An answer of gzip ``body`` (already compressed) declared as such."""
    return web.Response(
        body=body,
        content_type=content_type,
        charset=charset,
        headers={**headers, "Content-Encoding": "gzip", **VARY},
    )


async def json_text_response(
    request: web.BaseRequest, text: str, memo: GzipMemo | None = None, key: Hashable = None
) -> web.Response:
    """``text`` (JSON) as the answer, gzip when the client takes it and it is worth it; with
    ``memo`` the compressed bytes are shared by every request under ``key``."""
    if len(text) < GZIP_MIN_BYTES or not accepts_gzip(request):
        return web.Response(text=text, content_type="application/json", headers=VARY)
    if memo is not None:
        body = await memo.gzip(key, text)
    else:
        body = await gzip_off_loop(text.encode(), LIVE_LEVEL)
    return gzip_response(body, "application/json", {}, charset="utf-8")


Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


@web.middleware
async def gzip_json(request: web.Request, handler: Handler) -> web.StreamResponse:
    """The API's other JSON answers (``/api/bench``, history, events, tests, alarms...)
    gzip by aiohttp when the client takes it and the body is worth it (aiohttp compresses a
    body of more than 4 KB in a worker thread). An answer already encoded (the tag list),
    streamed or prepared by its handler (the WebSocket, files) is left as it is."""
    response = await handler(request)
    if (
        isinstance(response, web.Response)
        and not response.prepared
        and response.content_type == "application/json"
        and "Content-Encoding" not in response.headers
        and isinstance(response.body, bytes | bytearray)
        and len(response.body) >= GZIP_MIN_BYTES
    ):
        response.headers.update(VARY)
        if accepts_gzip(request):
            response.enable_compression(web.ContentCoding.gzip)
    return response
