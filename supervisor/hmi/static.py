"""The screens' files, served by the supervisor itself: an isolated lab network has no CDN
(issue 12 "Front end with no CDN").

- ``GET /`` → ``hmi/index.html``;
- ``GET /static/<path>`` → ``hmi/<path>`` (the app's own code);
- ``GET /vendor/uplot/<path>`` → ``hmi/node_modules/uplot/dist/<path>``, which ``npm ci``
  in ``hmi/`` installs at set-up time (``make hmi``): never copied into the repository.

Text files (the page, scripts, styles, uPlot) go out gzip to a browser that takes it
(issue 33): each compressed once at the best level and kept while the file is unchanged
(its modification time and size), with its own ``ETag`` so that the check at every load
(``no-cache``) is still answered 304 Not Modified; a client that does not take gzip, or asks
for a range, gets the file as it is (:mod:`supervisor.hmi.compress`).

A file that is not there is a 404; the front end or uPlot not installed at all is a 503
whose page says what to run. Nothing outside those directories is served (a path that
resolves out of its root, through ``..`` or a symbolic link, is a 404).
"""

from __future__ import annotations

import asyncio
import mimetypes
from dataclasses import dataclass
from email.utils import formatdate
from pathlib import Path
from typing import Final

from aiohttp import hdrs, web

from supervisor.hmi.compress import (
    STATIC_LEVEL,
    VARY,
    accepts_gzip,
    compressible,
    gzip_bytes,
    gzip_response,
)

NOT_INSTALLED: Final = (
    "<!doctype html><meta charset=utf-8><title>HMI not installed</title>"
    "<h1>The operator screens are not installed</h1>"
    "<p>{what} is missing. Run <code>make hmi</code> (it runs <code>npm ci</code> in"
    " <code>hmi/</code>), then reload this page. The JSON API under <code>/api/</code>"
    " works without it.</p>"
)
NO_STORE: Final = {"Cache-Control": "no-cache"}
"""The page and its scripts are checked again at every load: a new supervisor's front end
never runs against an old cached script."""


@dataclass(frozen=True)
class Packed:
    """A file's gzip, for the file as it was when read (its ``stat``'s time and size)."""

    mtime_ns: int
    size: int
    gz: bytes

    @property
    def etag(self) -> str:
        # Not the plain file's ETag (aiohttp's "<mtime>-<size>"): other bytes, other tag.
        return f"{self.mtime_ns:x}-{self.size:x}-gzip"


def _read_packed(path: Path) -> Packed | None:
    """``path``'s gzip, or None when the file changed while it was read (served plain)."""
    before = path.stat()
    data = path.read_bytes()
    after = path.stat()
    if (before.st_mtime_ns, before.st_size) != (after.st_mtime_ns, after.st_size):
        return None
    return Packed(after.st_mtime_ns, after.st_size, gzip_bytes(data, STATIC_LEVEL))


def _unavailable(what: str) -> web.Response:
    return web.Response(status=503, text=NOT_INSTALLED.format(what=what), content_type="text/html")


class StaticFiles:
    def __init__(self, root: Path, index: str = "index.html") -> None:
        self.root = root
        self.index = index
        """The page ``GET /`` answers (the fleet's is ``fleet.html``: supervisor.fleet)."""
        self.uplot = root / "node_modules" / "uplot" / "dist"
        self.packed: dict[Path, Packed] = {}
        """Each text file's gzip as last served (bounded by the files under the roots)."""

    def install(self, app: web.Application) -> None:
        app.add_routes(
            [
                web.get("/", self._index),
                web.get("/static/{path:.*}", self._static),
                web.get("/vendor/uplot/{path:.*}", self._uplot),
            ]
        )

    async def _index(self, request: web.Request) -> web.StreamResponse:
        index = self.root / self.index
        if not index.is_file():
            return _unavailable(f"{index}")
        return await self._send(request, index)

    async def _static(self, request: web.Request) -> web.StreamResponse:
        if not (self.root / self.index).is_file():
            return _unavailable(f"{self.root / self.index}")
        return await self._send(request, self._file(self.root, request.match_info["path"]))

    async def _uplot(self, request: web.Request) -> web.StreamResponse:
        if not self.uplot.is_dir():
            return _unavailable(f"uPlot ({self.uplot})")
        return await self._send(request, self._file(self.uplot, request.match_info["path"]))

    @staticmethod
    def _file(root: Path, relative: str) -> Path:
        base = root.resolve()
        try:
            path = (base / relative).resolve()
            found = path.is_relative_to(base) and path.is_file()
        except (OSError, RuntimeError, ValueError):  # ValueError: a NUL byte (``%00``)
            raise web.HTTPNotFound() from None
        # No way out of the root (``..``, a symbolic link elsewhere, an absolute path).
        if not found:
            raise web.HTTPNotFound()
        return path

    async def _send(self, request: web.Request, path: Path) -> web.StreamResponse:
        """``path`` as the answer: its gzip when the client takes it, else the file."""
        # One content type for both answers (aiohttp's own table differs from Python's).
        content_type = mimetypes.guess_type(path)[0] or "application/octet-stream"
        plain_headers = {**NO_STORE, "Content-Type": content_type}
        if compressible(content_type):
            plain_headers.update(VARY)
        if hdrs.RANGE in request.headers or not (
            compressible(content_type) and accepts_gzip(request)
        ):
            return web.FileResponse(path, headers=plain_headers)
        packed = await self._packed(path)
        if packed is None:
            return web.FileResponse(path, headers=plain_headers)
        headers = {
            **NO_STORE,
            "ETag": f'"{packed.etag}"',
            "Last-Modified": formatdate(packed.mtime_ns / 1e9, usegmt=True),
        }
        if any(tag.value == packed.etag for tag in request.if_none_match or ()):
            return web.Response(status=304, headers={**headers, **VARY})
        return gzip_response(packed.gz, content_type, headers)

    async def _packed(self, path: Path) -> Packed | None:
        """The file's gzip, compressed again only when the file changed (in a worker
        thread: the scan shares this event loop)."""
        packed = self._kept(path)
        if packed is not None:
            return packed
        packed = await asyncio.get_running_loop().run_in_executor(None, _read_packed, path)
        if packed is not None:
            self.packed[path] = packed
        return packed

    def _kept(self, path: Path) -> Packed | None:
        """The kept gzip of ``path`` if the file is unchanged since (a ``stat``, like the
        plain path's)."""
        packed = self.packed.get(path)
        if packed is None:
            return None
        st = path.stat()
        return packed if (packed.mtime_ns, packed.size) == (st.st_mtime_ns, st.st_size) else None
