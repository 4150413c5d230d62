"""Issue 28, finding 6, against the real aiohttp server on loopback: every body the API
cannot take is refused with a JSON 400/415 naming what was received, never a 500
text/plain (``supervisor.hmi.body``, the one reader of every route's JSON body). And
finding 1's edge: a lone surrogate in a value, a command's argument or a password is
refused, 400, naming the member.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from hmirig import Hmi, hmi_bench, password

from supervisor.commands import Command, Verb
from supervisor.config.models import HmiConfig

pytestmark = pytest.mark.integration

JSON_ROUTES = (
    ("PUT", "/api/tags/ch0.manual_current"),
    ("PUT", "/api/tags/ch0.manual_current/force"),
    ("PUT", "/api/channels/ch0/recipe"),
    ("POST", "/api/channels/ch0/commands/mode"),
    ("POST", "/api/alarms/estop/shelve"),
    ("POST", "/api/login"),
)


@pytest.fixture
async def hmi(tmp_path: Path) -> AsyncIterator[Hmi]:
    async with hmi_bench(tmp_path, HmiConfig(login=True)) as h:
        yield h


async def send(
    s: aiohttp.ClientSession,
    hmi: Hmi,
    method: str,
    path: str,
    data: bytes,
    headers: dict[str, str] | None = None,
) -> tuple[int, str, Any]:
    h = {"Content-Type": "application/json", **(headers or {})}
    async with s.request(method, hmi.base + path, data=data, headers=h) as resp:
        kind = resp.headers.get("Content-Type", "")
        body = await resp.json() if "json" in kind else await resp.text()
        return resp.status, kind, body


def reason(body: Any) -> str:
    assert isinstance(body, dict), body
    return str(body.get("reason", ""))


async def test_a_body_nested_100000_deep_is_a_json_400_on_every_json_route(hmi: Hmi) -> None:
    s = await hmi.login("erin")
    for method, path in JSON_ROUTES:
        status, kind, body = await send(s, hmi, method, path, b"[" * 100_000)
        assert status == 400 and "json" in kind, (path, status, body)
        assert "nested deeper than" in reason(body), path


async def test_a_command_argument_named_like_a_parameter_is_refused_by_name(hmi: Hmi) -> None:
    s = await hmi.login("otto")
    for member in ("actor", "verb", "name", "cls"):
        status, body = await hmi.call(
            s, "POST", "/api/channels/ch0/commands/mode", {"value": "manual", member: "x"}
        )
        assert status == 400, (member, body)
        assert f"unknown argument {member}" in body["reason"], body
    for member in ("alarm_id", "verb", "actor", "cls"):
        status, body = await hmi.call(
            s, "POST", "/api/alarms/estop/shelve", {"duration_s": 60, member: "x"}
        )
        assert status == 400, (member, body)
        assert f"unknown argument {member}" in body["reason"], body
    status, body = await hmi.call(
        s, "PUT", "/api/channels/ch0/recipe", {"file": "x.yaml", "actor": "mallory"}
    )
    assert status in (400, 404), body
    assert body["kind"] != "internal error", body


async def test_an_unknown_charset_is_a_json_415_naming_it(hmi: Hmi) -> None:
    s = await hmi.login("otto")
    for method, path in JSON_ROUTES:
        status, kind, body = await send(
            s,
            hmi,
            method,
            path,
            b'{"value": 1}',
            {"Content-Type": "application/json; charset=nonexistent"},
        )
        assert status == 415 and "json" in kind, (path, status, body)
        assert "charset 'nonexistent'" in reason(body), path


async def test_a_content_encoding_on_a_plain_body_is_a_json_415(hmi: Hmi) -> None:
    s = await hmi.login("otto")
    for method, path in JSON_ROUTES:
        status, kind, body = await send(
            s, hmi, method, path, b'{"value": 1}', {"Content-Encoding": "gzip"}
        )
        assert status == 415 and "json" in kind, (path, status, body)
        assert "Content-Encoding 'gzip'" in reason(body), path


async def test_a_nul_byte_in_a_static_path_is_a_404(tmp_path: Path) -> None:
    root = tmp_path / "hmi"
    dist = root / "node_modules" / "uplot" / "dist"
    dist.mkdir(parents=True)
    (root / "index.html").write_text("<!doctype html><title>x</title>", encoding="utf-8")
    (dist / "uPlot.iife.min.js").write_text("var uPlot;", encoding="utf-8")
    async with hmi_bench(tmp_path, root=root) as hmi:
        s = await hmi.client()
        for path in ("/vendor/uplot/%00", "/static/%00", "/vendor/uplot/a%00b.js"):
            async with s.get(hmi.base + path) as resp:
                assert resp.status == 404, path


async def test_an_unknown_member_of_a_tag_write_is_refused_by_name(hmi: Hmi) -> None:
    s = await hmi.login("erin")
    for path in ("/api/tags/ch0.manual_current", "/api/tags/ch0.manual_current/force"):
        status, body = await hmi.call(s, "PUT", path, {"value": 0.1, "valeu": 0.2})
        assert status == 400, (path, body)
        assert "unknown member 'valeu'" in body["reason"], body
        assert hmi.bench.db["ch0.manual_current"].forced is False


async def test_a_lone_surrogate_is_refused_at_the_edge_naming_the_member(hmi: Hmi) -> None:
    s = await hmi.login("otto")
    for method, path, data in (
        ("PUT", "/api/tags/ch1.command", b'{"value": "\\ud800"}'),
        ("POST", "/api/channels/ch1/commands/mode", b'{"value": "\\ud800"}'),
        ("PUT", "/api/channels/ch1/recipe", b'{"file": "a\\udfffb.yaml"}'),
    ):
        status, kind, body = await send(s, hmi, method, path, data)
        assert status == 400 and "json" in kind, (path, status, body)
        assert "lone surrogate (U+D" in reason(body), body
    status, _, body = await send(
        s, hmi, "POST", "/api/channels/ch1/commands/mode", b'{"value": "\\ud800"}'
    )
    assert reason(body).startswith("value:"), body


async def test_a_password_with_a_lone_surrogate_is_a_json_refusal_not_a_500(hmi: Hmi) -> None:
    s = await hmi.client()
    for user in ("otto", "nobody"):
        data = f'{{"user": "{user}", "password": "{password(user)}\\ud800"}}'.encode()
        status, kind, body = await send(s, hmi, "POST", "/api/login", data)
        assert status == 400 and "json" in kind, (user, status, body)
        assert reason(body).startswith("password:"), body


async def test_a_refusal_quoting_a_lone_surrogate_is_stored_escaped_and_history_goes_on(
    hmi: Hmi,
) -> None:
    """Past the edge (a value from elsewhere than a JSON body): the command path's refusal
    quotes the value in its event, which the real historian stores escaped."""
    bench = hmi.bench
    historian = bench.record_history()  # the rig's bench records none by itself
    assert historian is not None
    await historian.start()
    for command in (
        Command.write("ch1.command", "\ud800", "hmi:vera"),
        Command.channel("ch1", Verb.MODE, "hmi:otto", value="\ud800"),
    ):
        result = bench.commands.execute(command)
        assert result.http_status == 400, result
    await hmi.scans(3)
    assert await asyncio.to_thread(historian.writer.flush)
    written = historian.writer.rows_written
    await hmi.scans(3)
    assert await asyncio.to_thread(historian.writer.flush)
    assert historian.writer.rows_written > written
    assert (historian.writer.crashes, historian.writer.write_errors) == (0, 0)
    texts = [e.text for e in historian.query.events(0, 4e9, kind="command")]
    assert any("'\\ud800'" in t and "ch1.command" in t for t in texts), texts
    assert any("mode \\ud800" in t for t in texts), texts
