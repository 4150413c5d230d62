"""The OpenAPI description (supervisor/hmi/openapi.yaml) is the API's: every route of the
application that ``supervisor run`` assembles is described, with its method and path
template, and nothing else; it is served as JSON at ``/api/openapi.json``; it is a valid
OpenAPI 3.1 document (schemathesis loads it). What each answer looks like is checked by
tests/security/test_openapi_schemathesis.py against a real run."""

from __future__ import annotations

import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from commandrig import started_bench

from supervisor.app import Bench
from supervisor.app.hmi import build_screens
from supervisor.commands import ResultKind
from supervisor.config.models import HmiConfig
from supervisor.hmi import HttpApi
from supervisor.hmi.openapi import description
from supervisor.hmi.recipes_api import RecipesConfig
from supervisor.hmi.tests_api import TestsConfig

pytestmark = pytest.mark.integration

METHODS = ("get", "put", "post", "delete", "patch", "head", "options", "trace")


@pytest.fixture
async def full_api(tmp_path: Path) -> AsyncIterator[tuple[Bench, HttpApi]]:
    """Every route ``supervisor run`` serves on a simulated bench: history, recipes,
    results, the simulation's e-stop and state, the screens (as supervisor/app/service.py
    assembles)."""
    bench = await started_bench(tmp_path)
    api = HttpApi(
        bench.db,
        bench.clock,
        "127.0.0.1",
        0,
        estop=lambda pressed: None,
        commands=bench.commands,
        sim_state=dict,
        history=object(),  # type: ignore[arg-type]  # registered, never asked here
        recipes=RecipesConfig(tmp_path / "recipes"),
        tests=TestsConfig(tmp_path / "results"),
    )
    build_screens(bench, api, root=tmp_path / "no-hmi", cfg=HmiConfig(login=False))
    try:
        yield bench, api
    finally:
        await api.stop()
        await bench.shutdown()


def template(path: str) -> str:
    """aiohttp's ``/static/{path:.*}`` as OpenAPI writes it: ``/static/{path}``."""
    return re.sub(r"\{(\w+):[^}]*\}", r"{\1}", path)


def app_routes(api: HttpApi) -> set[tuple[str, str]]:
    out = set()
    for route in api.app.router.routes():
        if route.method == "HEAD":  # aiohttp's own, beside each GET
            continue
        info = route.resource.get_info() if route.resource is not None else {}
        path = info.get("path") or info.get("formatter")
        assert path, f"a route without a path: {route}"
        out.add((route.method, template(path)))
    return out


def described_routes(doc: dict[str, Any]) -> set[tuple[str, str]]:
    return {
        (method.upper(), path)
        for path, item in doc["paths"].items()
        for method in item
        if method in METHODS
    }


async def test_every_route_of_the_api_is_described_and_nothing_else(
    full_api: tuple[Bench, HttpApi],
) -> None:
    _, api = full_api
    served, described = app_routes(api), described_routes(description())
    assert served - described == set(), "routes missing from supervisor/hmi/openapi.yaml"
    assert described - served == set(), "described in openapi.yaml, served by no route"
    assert len(served) >= 29


async def test_the_description_is_served_as_json(full_api: tuple[Bench, HttpApi]) -> None:
    _, api = full_api
    await api.start()
    async with (
        aiohttp.ClientSession() as s,
        s.get(f"http://127.0.0.1:{api.port}/api/openapi.json") as resp,
    ):
        assert resp.status == 200
        assert resp.content_type == "application/json"
        assert await resp.json() == description()


def test_the_description_is_a_valid_openapi_3_1_document() -> None:
    import schemathesis

    doc = description()
    assert doc["openapi"].startswith("3.1")
    schema = schemathesis.openapi.from_dict(doc)
    operations = [op.ok() for op in schema.get_all_operations()]  # each one resolves
    assert len(operations) == len(described_routes(doc))


def test_an_answer_s_kind_is_described_with_every_kind_the_command_path_answers() -> None:
    """A new refusal kind (``out of range``, issue 26) is a new value clients see: the
    description names each one, so that schemathesis does not find it first."""
    kind = description()["components"]["schemas"]["Answer"]["properties"]["kind"]
    assert set(kind["enum"]) == {k.value for k in ResultKind}
