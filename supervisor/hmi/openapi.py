"""The HTTP API's OpenAPI 3.1 description (``openapi.yaml`` beside this module, a reviewed
file), served as JSON at ``GET /api/openapi.json``. Kept true by tests: every route of the
application is in it and nothing else (tests/unit/test_openapi_routes.py), and schemathesis
checks the answers of a real ``supervisor run`` against it
(tests/security/test_openapi_schemathesis.py)."""

from __future__ import annotations

import functools
import json
from importlib import resources
from typing import Any, Final

import yaml
from aiohttp import web

PATH: Final = "/api/openapi.json"


@functools.cache
def description() -> dict[str, Any]:
    """The description as a mapping (read once)."""
    text = resources.files(__package__).joinpath("openapi.yaml").read_text(encoding="utf-8")
    data: dict[str, Any] = yaml.safe_load(text)
    return data


@functools.cache
def description_json() -> str:
    return json.dumps(description(), ensure_ascii=False)


async def _serve(request: web.Request) -> web.Response:
    return web.Response(text=description_json(), content_type="application/json")


def add_openapi_route(app: web.Application) -> None:
    app.add_routes([web.get(PATH, _serve)])
