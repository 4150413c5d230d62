"""Issue 27, finding 1: recipes asked for over the network load only from the recipe
folders (the I/O map's ``recipes: {folders: [...]}``, ADR 0026). A path outside them —
absolute, through ``..``, or a symbolic link placed in a folder — is refused before it is
opened: 403 over HTTP, Bad_UserAccessDenied over OPC UA, the reason naming the folders,
and no byte of the file in the answer, the command log, ``/api/events`` or
``chN.chain.last_event`` (which anonymous visitors read). Recipes inside a folder load by
name and by path, and their errors keep file:line:col (they are the engineer's own files).

The bench is the command-path rig (``commandrig``: its recipe folder is the test's own
temporary folder); the secrets are in another temporary folder, outside it.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import yaml
from asyncua import ua
from commandrig import DISCHARGE, io_map, recipe
from opcuarig import Rig, call, opcua_rig, text

from supervisor.app import Bench, build_bench
from supervisor.commands import Command, ResultKind, Verb
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigErrors
from supervisor.devices.registry import load_bench
from supervisor.hmi import HttpApi
from supervisor.hmi.recipes_api import RecipesConfig
from supervisor.testing import run_scans

pytestmark = pytest.mark.integration

SECRET = "INFLUX_TOKEN: s3cr3t-7f9a2c"
"""Shaped as a recipe's unknown key: the refusal of old quoted it (``unknown key ...``)."""
SECRET_BYTES = ("s3cr3t", "7f9a2c", "INFLUX_TOKEN")
EPOCH = 1_767_225_600.0  # the virtual clock's 2026-01-01T00:00:00Z


@pytest.fixture
def elsewhere(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder outside the bench's recipe folder, with a secret in it."""
    folder = tmp_path_factory.mktemp("elsewhere")
    (folder / ".env").write_text(SECRET + "\nPASSWORD: hunter2-b8e1\n", encoding="utf-8")
    (folder / "secret.yaml").write_text(SECRET + "\n", encoding="utf-8")
    return folder


@dataclass
class Client:
    bench: Bench
    api: HttpApi
    session: aiohttp.ClientSession

    async def call(self, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        kw: dict[str, Any] = {} if body is None else {"json": body}
        async with self.session.request(method, self.api.url + path, **kw) as resp:
            return resp.status, await resp.json()

    async def load(self, file: str) -> tuple[int, Any]:
        return await self.call("PUT", "/channels/ch0/recipe", {"file": file})

    async def everything_kept(self) -> str:
        """What a visitor can read of the refusals: the events, the channel's last event,
        the command log (as text, to look for the secret in)."""
        await run_scans(self.bench.engine, 3)
        assert self.bench.historian is not None
        assert self.bench.historian.writer.flush()
        end = self.bench.clock.wall() + 1
        async with self.session.get(
            self.api.url + "/events", params={"start": str(EPOCH), "end": str(end)}
        ) as resp:
            assert resp.status == 200
            events = await resp.text()
        last = str(self.bench.db["ch0.chain.last_event"].value)
        log = json.dumps([e.as_json() for e in self.bench.commands.log])
        return "\n".join([events, last, log])


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[Client]:
    bench = build_bench(load_bench(io_map(tmp_path)), VirtualClock(), in_process=True)
    bench.record_history()
    await bench.start()
    await run_scans(bench.engine, 10)
    assert bench.historian is not None
    api = HttpApi(
        bench.db,
        bench.clock,
        "127.0.0.1",
        0,
        commands=bench.commands,
        history=bench.historian.query,
        recipes=RecipesConfig(tmp_path, folders=bench.commands.recipe_folders),
    )
    await api.start()
    try:
        async with aiohttp.ClientSession() as session:
            yield Client(bench, api, session)
    finally:
        await api.stop()
        await bench.shutdown()


def assert_no_secret(text: str) -> None:
    for part in SECRET_BYTES:
        assert part not in text
    assert "hunter2" not in text
    assert "root:" not in text  # /etc/passwd's and /etc/shadow's lines


async def test_a_recipe_outside_the_folders_is_forbidden_and_none_of_it_is_shown(
    client: Client, tmp_path: Path, elsewhere: Path
) -> None:
    relative_way_out = Path("../" * len(tmp_path.parts)) / str(elsewhere / ".env").lstrip("/")
    for file in (
        "/etc/passwd",
        "/etc/shadow",
        "../../../../etc/passwd",
        str(elsewhere / ".env"),
        str(elsewhere / "secret.yaml"),
        str(tmp_path / ".." / elsewhere.name / "secret.yaml"),  # ``..`` out of the folder
        str(relative_way_out),
        str(elsewhere / "not-there.yaml"),  # outside and missing: the same refusal
    ):
        status, body = await client.load(file)
        assert status == 403, (file, body)
        assert body["accepted"] is False and body["kind"] == "forbidden"
        assert "is outside the recipe folders: recipes load only from" in body["reason"]
        assert f"{tmp_path}/" in body["reason"]  # the allowed folder is named
        assert_no_secret(json.dumps(body))
    # Started with a recipe: the same refusal, nothing started.
    status, body = await client.call(
        "POST", "/channels/ch0/commands/start", {"recipe": str(elsewhere / ".env")}
    )
    assert status == 403 and body["kind"] == "forbidden", body
    assert client.bench.runners["ch0"].program is None
    # A client cannot claim to be the local shell: "local" is an unknown argument.
    status, body = await client.call(
        "PUT", "/channels/ch0/recipe", {"file": str(elsewhere / ".env"), "local": True}
    )
    assert status in (400, 403) and body["accepted"] is False, body
    assert_no_secret(json.dumps(body))
    assert_no_secret(await client.everything_kept())


async def test_a_symbolic_link_in_the_folder_to_a_file_elsewhere_is_forbidden(
    client: Client, tmp_path: Path, elsewhere: Path
) -> None:
    (tmp_path / "innocent.yaml").symlink_to(elsewhere / "secret.yaml")
    (tmp_path / "sub").symlink_to(elsewhere, target_is_directory=True)
    for file in (str(tmp_path / "innocent.yaml"), "innocent", str(tmp_path / "sub" / ".env")):
        status, body = await client.load(file)
        assert status == 403, (file, body)
        assert "outside the recipe folders" in body["reason"]
        assert_no_secret(json.dumps(body))
    # The recipe editor neither lists nor serves it.
    status, listing = await client.call("GET", "/recipes")
    assert status == 200 and "innocent" not in [r["name"] for r in listing["recipes"]]
    status, body = await client.call("GET", "/recipes/innocent")
    assert status == 403, body
    assert_no_secret(json.dumps(body))
    assert_no_secret(await client.everything_kept())


async def test_a_recipe_in_the_folder_loads_by_name_and_by_path(
    client: Client, tmp_path: Path
) -> None:
    recipe(tmp_path, DISCHARGE, "discharge.yaml")
    status, body = await client.load("discharge")  # a name: <folder>/discharge.yaml
    assert status == 200 and body["recipe"] == "d", body
    status, body = await client.load(str(tmp_path / "discharge.yaml"))
    assert status == 200 and body["recipe"] == "d", body
    # A link inside the folder to another file inside it is the same recipe.
    (tmp_path / "alias.yaml").symlink_to(tmp_path / "discharge.yaml")
    status, body = await client.load("alias")
    assert status == 200 and body["recipe"] == "d", body
    status, body = await client.load("missing")
    assert status == 404 and "no such recipe in" in body["reason"], body


async def test_a_refused_recipe_in_the_folder_still_says_file_line_and_column(
    client: Client, tmp_path: Path
) -> None:
    file = recipe(tmp_path, "recipe: x\nsteps:\n  - {id: a, rest: 1 h, colour: red}\n", "bad.yaml")
    status, body = await client.load(file)
    assert status == 422, body
    assert body["details"][0].startswith(f"{file}:3:"), body
    assert "colour" in body["details"][0]


async def test_a_recipe_given_in_the_shell_is_read_wherever_it_is(
    client: Client, elsewhere: Path
) -> None:
    # `supervisor run --recipe ch0=FILE` (Command.local): the shell user's own files.
    recipe(elsewhere, DISCHARGE, "mine.yaml")
    command = Command.channel("ch0", Verb.LOAD, "command line", recipe=str(elsewhere / "mine.yaml"))
    refused = await client.bench.commands.execute_async(command)
    assert refused.kind is ResultKind.FORBIDDEN  # the same command over the network
    local = await client.bench.commands.execute_async(dataclasses.replace(command, local=True))
    assert local.accepted, local.reason


# --- OPC UA -------------------------------------------------------------------------------
@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path) as r:
        yield r


async def test_opc_ua_start_outside_the_folders_is_access_denied_without_its_content(
    rig: Rig, tmp_path: Path, elsewhere: Path
) -> None:
    async with rig.client("alice") as c:
        ns = await rig.ns(c)
        node = ua.NodeId("/Bench/Channels/ch1", ns)
        start = ua.NodeId("/Bench/Channels/ch1/Start", ns)
        for file in ("/etc/passwd", str(elsewhere / ".env"), "../../../../etc/shadow"):
            res = await call(
                c,
                node,
                start,
                ua.Variant(file, ua.VariantType.String),
                ua.Variant("", ua.VariantType.String),
            )
            assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied, text(res)
            assert "outside the recipe folders" in text(res)
            assert f"{tmp_path}/" in text(res)
            assert_no_secret(text(res))
        # A recipe of the folder, by name, starts.
        recipe(tmp_path, DISCHARGE, "discharge.yaml")
        res = await call(
            c,
            node,
            start,
            ua.Variant("discharge", ua.VariantType.String),
            ua.Variant("", ua.VariantType.String),
        )
        assert res.StatusCode.is_good(), text(res)
    assert_no_secret(json.dumps([e.as_json() for e in rig.bench.commands.log]))
    assert_no_secret(str(rig.bench.db["ch1.chain.last_event"].value))


def profile_recipe(csv: Path | str) -> str:
    return f"recipe: p\nsteps:\n  - id: a\n    profile: {{file: {csv}}}\n"


async def test_a_load_profile_outside_the_folders_is_never_read(
    client: Client, tmp_path: Path, elsewhere: Path
) -> None:
    # A CSV whose second row the profile reader of old quoted ("time '...' is not a number").
    (elsewhere / "leak.csv").write_text(f"t,i\n{SECRET},1\n", encoding="utf-8")
    for csv in (elsewhere / "leak.csv", "/etc/passwd", f"../{elsewhere.name}/leak.csv"):
        # Loaded from a recipe in the folder that names it.
        file = recipe(tmp_path, profile_recipe(csv), "profile.yaml")
        status, body = await client.load(file)
        assert status == 422, body
        assert "is outside the recipe folders: a recipe reads files only from" in body["reason"]
        assert body["details"][0].startswith(f"{file}:4:"), body  # where the recipe names it
        assert_no_secret(json.dumps(body))
        # Validated by the recipe editor (any logged-in user may validate).
        status, body = await client.call(
            "POST", "/recipes/validate", {"text": profile_recipe(csv), "name": "p"}
        )
        assert status == 422, body
        assert "outside the recipe folders" in body["errors"][0]["message"]
        assert_no_secret(json.dumps(body))
    assert_no_secret(await client.everything_kept())
    # A profile beside the recipe, in the folder, is read.
    (tmp_path / "ok.csv").write_text("t,i\n0,0.1\n10,0.2\n", encoding="utf-8")
    status, body = await client.load(recipe(tmp_path, profile_recipe("ok.csv"), "ok.yaml"))
    assert status == 200, body


def test_the_recipe_folders_are_one_setting_of_the_map_and_the_old_key_its_alias(
    tmp_path: Path,
) -> None:
    path = Path(io_map(tmp_path))
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    del data["recipes"]
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    assert load_bench(path).recipe_folders == ["recipes"]  # beside the working directory
    data["opcua"]["recipes_dir"] = "old"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    assert load_bench(path).recipe_folders == ["old"]
    data["recipes"] = {"folders": ["new"]}
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ConfigErrors, match="disagree"):
        load_bench(path)
