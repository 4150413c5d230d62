"""Issue 32, finding 5: a load profile CSV from the screens onto a channel, through the
HTTP API (hmi/profiles_api.py) on loopback: preview (table, chart, notices, the recipe
made of it), refusal at the first error's file, line and column, the load onto a channel
by an operator (not a viewer) through the command path, and the start that follows.

The bench of the command-path tests (four Chadèche channels, virtual clock)."""

from __future__ import annotations

import base64
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from commandrig import started_bench

from supervisor.app import Bench
from supervisor.app.preview import preview_in_child
from supervisor.hmi import HttpApi
from supervisor.hmi.recipes_api import RecipesConfig

pytestmark = pytest.mark.integration

JSON = {"Content-Type": "application/json"}
# Seed 002 figure 21's columns, its Unix times; currents within a Chadèche board's 0.4 A.
FIGURE_21 = (
    "Time,Voltage,Current,Temperature,BMS Faults,Cell Voltage,Cell Temperature\n"
    "1736943899.5500178,1.3,0.1,25,No faults,1.3,25\n"
    "1736943899.8000193,1.3,0.2,26,No faults,1.3,26\n"
    "1736943900.0500205,1.4,0.3,27,No faults,1.4,27\n"
)


@dataclass
class Client:
    bench: Bench
    session: aiohttp.ClientSession
    base: str
    folder: Path
    role: str = "operator"

    async def call(self, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        headers = {"X-Test-Role": self.role, **JSON}
        async with self.session.request(
            method, self.base + path, json=body, headers=headers
        ) as resp:
            return resp.status, await resp.json()


def header_role(request: Any) -> str | None:
    role: str | None = request.headers.get("X-Test-Role")
    return role


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[Client]:
    bench = await started_bench(tmp_path)
    folders = bench.commands.recipe_folders
    assert folders is not None
    config = RecipesConfig(
        folders.folders[0],
        preview_in_child,
        target_of=bench.target,
        channels=bench.runners,
        role_of=header_role,
        folders=folders,
    )
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, commands=bench.commands, recipes=config)
    await api.start()
    try:
        async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=120)) as session:
            yield Client(bench, session, api.url, folders.folders[0])
    finally:
        await api.stop()
        await bench.shutdown()


def upload(text: str, name: str = "sample_profile.csv", **more: Any) -> dict[str, Any]:
    return {"csv_base64": base64.b64encode(text.encode()).decode(), "name": name, **more}


async def test_a_preview_shows_the_table_the_chart_the_notices_and_the_recipe(
    client: Client,
) -> None:
    status, body = await client.call("POST", "/profiles/preview", upload(FIGURE_21))
    assert status == 200, body
    assert body["recipe"] == "sample_profile"
    assert body["rows"] == 3
    assert [r["current_a"] for r in body["table"]] == [0.1, 0.2, 0.3]
    assert body["chart"]["t_s"] == pytest.approx([0.0, 0.25, 0.5], abs=1e-5)
    assert any("Unix timestamps" in n for n in body["notices"])
    assert "profile:" in body["text"] and "# note: times are Unix timestamps" in body["text"]


async def test_a_broken_profile_is_refused_at_its_file_line_and_column(client: Client) -> None:
    broken = "Time (s),Current (A)\n0,0.1\n1,0.2x\n2,0\n"
    status, body = await client.call("POST", "/profiles/preview", upload(broken, "b.csv"))
    assert status == 422
    first = body["errors"][0]
    assert (first["file"], first["line"], first["column"]) == ("b.csv", 3, 3)
    assert "'0.2x' is not a number" in first["message"]
    status, body = await client.call("POST", "/profiles/preview", upload("Zeit,Strom\n0,1\n"))
    assert status == 422
    assert "column 'Zeit' is not a column of a load profile" in body["errors"][0]["message"]


async def test_a_profile_over_the_channel_s_limits_is_refused_when_a_channel_is_named(
    client: Client,
) -> None:
    status, body = await client.call(
        "POST", "/profiles/preview", upload("t,i\n0,2\n10,0\n", channel="ch0")
    )
    assert status == 422
    assert "channel ch0 allows" in body["reason"]


async def test_an_operator_loads_a_profile_onto_a_channel_and_starts_it(client: Client) -> None:
    status, body = await client.call("POST", "/profiles/load", upload(FIGURE_21, channel="ch1"))
    assert status == 200, body
    assert body["accepted"] and body["file"] == "profiles/sample_profile.yaml"
    assert (client.folder / "profiles" / "sample_profile.yaml").is_file()
    assert (client.folder / "profiles" / "sample_profile.csv").read_text() == FIGURE_21
    program = client.bench.runners["ch1"].program
    assert program is not None and program.name == "sample_profile"
    assert [p.current_a for p in program.steps[0].profile] == [0.1, 0.2, 0.3]
    status, body = await client.call("POST", "/channels/ch1/commands/start", {})
    assert status == 200 and body["accepted"], body
    # The uploaded CSV is then one of the folder's profiles, to pick again.
    status, listing = await client.call("GET", "/profiles")
    assert "profiles/sample_profile.csv" in [p["name"] for p in listing["profiles"]]
    status, again = await client.call(
        "POST", "/profiles/preview", {"file": "profiles/sample_profile.csv"}
    )
    assert status == 200 and again["rows"] == 3


async def test_a_viewer_may_not_load_a_profile_and_nothing_is_written(client: Client) -> None:
    client.role = "viewer"
    status, body = await client.call("POST", "/profiles/load", upload(FIGURE_21, channel="ch1"))
    assert status == 403
    assert "viewer may not load a profile" in body["reason"]
    assert not (client.folder / "profiles").exists()
    assert client.bench.runners["ch1"].program is None


async def test_a_file_outside_the_listing_is_refused_before_it_is_opened(client: Client) -> None:
    for name in ("../x.csv", "profiles/../../x.csv", "/etc/passwd", "recipe.yaml"):
        status, body = await client.call("POST", "/profiles/preview", {"file": name})
        assert status == 400, (name, body)


async def test_a_load_from_another_origin_or_not_declared_json_is_refused(
    client: Client,
) -> None:
    body = upload(FIGURE_21, channel="ch1")
    foreign = {"X-Test-Role": "operator", **JSON, "Origin": "http://elsewhere.invalid"}
    async with client.session.post(
        client.base + "/profiles/load", json=body, headers=foreign
    ) as resp:
        assert resp.status == 403
    plain = {"X-Test-Role": "operator", "Content-Type": "text/plain"}
    async with client.session.post(
        client.base + "/profiles/load", data=b"{}", headers=plain
    ) as resp:
        assert resp.status == 415
    assert not (client.folder / "profiles").exists()
    assert client.bench.runners["ch1"].program is None
