"""The screens' files, served by the supervisor itself: an isolated lab network has no CDN
(issue 12 "Front end with no CDN").

- ``GET /`` → ``hmi/index.html``;
- ``GET /static/<path>`` → ``hmi/<path>`` (the app's own code);
- ``GET /vendor/uplot/<path>`` → ``hmi/node_modules/uplot/dist/<path>``, which ``npm ci``
  in ``hmi/`` installs at set-up time (``make hmi``): never copied into the repository.

A file that is not there is a 404; the front end or uPlot not installed at all is a 503
whose page says what to run. Nothing outside those directories is served (a path that
resolves out of its root, through ``..`` or a symbolic link, is a 404).
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

from aiohttp import web

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


def _unavailable(what: str) -> web.Response:
    return web.Response(status=503, text=NOT_INSTALLED.format(what=what), content_type="text/html")


class StaticFiles:
    def __init__(self, root: Path) -> None:
        self.root = root
        self.uplot = root / "node_modules" / "uplot" / "dist"

    def install(self, app: web.Application) -> None:
        app.add_routes(
            [
                web.get("/", self._index),
                web.get("/static/{path:.*}", self._static),
                web.get("/vendor/uplot/{path:.*}", self._uplot),
            ]
        )

    async def _index(self, request: web.Request) -> web.StreamResponse:
        index = self.root / "index.html"
        if not index.is_file():
            return _unavailable(f"{index}")
        return web.FileResponse(index, headers=NO_STORE)

    async def _static(self, request: web.Request) -> web.StreamResponse:
        if not (self.root / "index.html").is_file():
            return _unavailable(f"{self.root / 'index.html'}")
        return self._file(self.root, request.match_info["path"])

    async def _uplot(self, request: web.Request) -> web.StreamResponse:
        if not self.uplot.is_dir():
            return _unavailable(f"uPlot ({self.uplot})")
        return self._file(self.uplot, request.match_info["path"])

    @staticmethod
    def _file(root: Path, relative: str) -> web.StreamResponse:
        base = root.resolve()
        try:
            path = (base / relative).resolve()
            found = path.is_relative_to(base) and path.is_file()
        except (OSError, RuntimeError, ValueError):  # ValueError: a NUL byte (``%00``)
            raise web.HTTPNotFound() from None
        # No way out of the root (``..``, a symbolic link elsewhere, an absolute path).
        if not found:
            raise web.HTTPNotFound()
        return web.FileResponse(path, headers=NO_STORE)
