"""Cross-site request forgery (issue 27, finding 2), at the API: a command needs a JSON
body and comes from the HMI's own origin (or ``hmi.allowed_origins``); the WebSocket's
handshake checks ``Origin`` too. Each refusal is made before the command path: nothing is
recorded, nothing changes. The browser's side: tests/browser/test_csrf_browser.py."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import aiohttp
import pytest
from hmirig import JSON, Hmi, hmi_bench, password
from pydantic import ValidationError

from supervisor.config.models import HmiConfig

pytestmark = pytest.mark.integration

ATTACKER = "http://127.0.0.1:1"
"""A page of another origin: the same host, another port (SameSite does not tell them apart)."""


async def send(
    hmi: Hmi,
    s: aiohttp.ClientSession,
    method: str,
    path: str,
    data: bytes | None = None,
    **headers: str,
) -> tuple[int, Any]:
    async with s.request(method, hmi.base + path, data=data, headers=headers) as resp:
        return resp.status, await resp.json()


def own(hmi: Hmi) -> str:
    return f"http://127.0.0.1:{hmi.api.port}"


def manual_current_unchanged(hmi: Hmi) -> None:
    assert not hmi.bench.commands.log, "a refused request reached the command path"
    assert hmi.bench.db["ch0.manual_current"].value == 0.0


JSON_BODY = b'{"value": 0.3}'
FORM = {"Content-Type": "application/x-www-form-urlencoded"}
TEXT = {"Content-Type": "text/plain"}


@pytest.mark.parametrize("login", [False, True], ids=["login-off", "login-on"])
@pytest.mark.parametrize(
    ("data", "headers", "received"),
    [
        (b'{"value": 0.3}=', FORM, "application/x-www-form-urlencoded"),
        (JSON_BODY, TEXT, "text/plain"),
        (JSON_BODY, {"Content-Type": "text/plain; charset=utf-8"}, "text/plain; charset=utf-8"),
        (JSON_BODY, {"Content-Type": "multipart/form-data; boundary=x"}, "multipart/form-data"),
    ],
    ids=["form", "text-plain", "text-plain-charset", "multipart"],
)
async def test_a_command_whose_body_is_not_declared_json_is_refused_415(
    tmp_path: Path, login: bool, data: bytes, headers: dict[str, str], received: str
) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=login)) as hmi:
        s = await hmi.login("otto") if login else await hmi.client()
        status, body = await send(hmi, s, "PUT", "/api/tags/ch0.manual_current", data, **headers)
        assert status == 415, body
        assert body["accepted"] is False
        assert "needs Content-Type: application/json" in body["reason"]
        assert received in body["reason"]
        manual_current_unchanged(hmi)


async def test_a_command_without_a_body_still_declares_json(tmp_path: Path) -> None:
    # A bodyless POST is what a page sends to another origin without asking (no preflight).
    async with hmi_bench(tmp_path, HmiConfig(login=False)) as hmi:
        s = await hmi.client()
        status, body = await send(hmi, s, "POST", "/api/channels/ch0/commands/abort")
        assert status == 415, body
        assert "needs Content-Type: application/json, a body or not" in body["reason"]
        status, body = await send(hmi, s, "DELETE", "/api/tags/ch0.manual_current/force")
        assert status == 415, body
        assert not hmi.bench.commands.log


@pytest.mark.parametrize("login", [False, True], ids=["login-off", "login-on"])
@pytest.mark.parametrize("header", ["Origin", "Referer"], ids=["origin", "referer-without-origin"])
async def test_a_command_from_a_page_of_another_origin_is_refused_403_naming_it(
    tmp_path: Path, login: bool, header: str
) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=login)) as hmi:
        s = await hmi.login("otto") if login else await hmi.client()
        sent = ATTACKER if header == "Origin" else ATTACKER + "/attack.html"
        status, body = await send(
            hmi, s, "PUT", "/api/tags/ch0.manual_current", JSON_BODY, **JSON, **{header: sent}
        )
        assert status == 403, body
        assert body["accepted"] is False
        assert f"{header} {sent!r}" in body["reason"]
        assert own(hmi) in body["reason"]  # what is allowed
        manual_current_unchanged(hmi)


@pytest.mark.parametrize(
    "origin",
    ["null", "http://127.0.0.1", "https://127.0.0.1:{port}", "http://localhost:{port}"],
    ids=["null", "no-port", "https", "another-host-name"],
)
async def test_an_origin_that_is_not_exactly_the_hmi_s_own_is_foreign(
    tmp_path: Path, origin: str
) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=False)) as hmi:
        s = await hmi.client()
        sent = origin.format(port=hmi.api.port)
        status, body = await send(
            hmi, s, "PUT", "/api/tags/ch0.manual_current", JSON_BODY, **JSON, Origin=sent
        )
        assert status == 403, body
        manual_current_unchanged(hmi)


async def test_a_command_of_the_hmi_s_own_page_is_taken(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=True)) as hmi:
        s = await hmi.login("otto")
        path = "/api/channels/ch0/commands/mode"
        status, body = await send(
            hmi, s, "POST", path, b'{"value": "manual"}', **JSON, Origin=own(hmi)
        )
        assert status == 200 and body["accepted"] is True, body
        status, body = await send(
            hmi,
            s,
            "PUT",
            "/api/tags/ch0.manual_current",
            JSON_BODY,
            **{"Content-Type": "application/json; charset=utf-8"},
            Referer=own(hmi) + "/#/channel/ch0",
        )
        assert status == 200 and body["accepted"] is True, body
        assert [e.actor for e in hmi.bench.commands.log] == ["hmi:otto", "hmi:otto"]


async def test_a_client_that_is_no_page_commands_with_json_and_no_origin(tmp_path: Path) -> None:
    # curl, scripts: neither Origin nor Referer; browsers send Origin with any such request.
    async with hmi_bench(tmp_path, HmiConfig(login=False)) as hmi:
        s = await hmi.client()
        path = "/api/channels/ch0/commands/mode"
        status, body = await send(hmi, s, "POST", path, b'{"value": "manual"}', **JSON)
        assert status == 200 and body["accepted"] is True, body
        status, body = await send(hmi, s, "POST", "/api/channels/ch0/commands/reset", None, **JSON)
        assert status in (200, 409), body  # taken by the command path: its own answer
        assert len(hmi.bench.commands.log) == 2


async def test_a_page_of_an_allowed_origin_commands(tmp_path: Path) -> None:
    proxy = "https://bench.lab.example:8443"
    cfg = HmiConfig(login=True, allowed_origins=[proxy + "/"])
    async with hmi_bench(tmp_path, cfg) as hmi:
        s = await hmi.login("otto")
        path = "/api/channels/ch0/commands/mode"
        status, body = await send(
            hmi, s, "POST", path, b'{"value": "manual"}', **JSON, Origin=proxy
        )
        assert status == 200 and body["accepted"] is True, body
        status, body = await send(
            hmi, s, "POST", path, b'{"value": "auto"}', **JSON, Origin=ATTACKER
        )
        assert status == 403 and proxy in body["reason"], body


async def test_a_login_from_another_origin_or_not_json_is_refused(tmp_path: Path) -> None:
    # Login CSRF: a page logging the operator's browser in as someone else.
    async with hmi_bench(tmp_path, HmiConfig(login=True)) as hmi:
        s = await hmi.client()
        credentials = f'{{"user": "otto", "password": "{password("otto")}"}}'.encode()
        status, body = await send(hmi, s, "POST", "/api/login", credentials, **TEXT)
        assert status == 415, body
        status, body = await send(
            hmi, s, "POST", "/api/login", credentials, **JSON, Origin=ATTACKER
        )
        assert status == 403, body
        assert not len(hmi.screens.sessions), "no session was opened"
        assert "bench_session" not in {c.key for c in s.cookie_jar}
        status, body = await send(
            hmi, s, "POST", "/api/login", credentials, **JSON, Origin=own(hmi)
        )
        assert status == 200, body


@pytest.mark.parametrize("login", [False, True], ids=["login-off", "login-on"])
async def test_the_live_feed_refuses_a_page_of_another_origin(tmp_path: Path, login: bool) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=login)) as hmi:
        s = await hmi.login("otto") if login else await hmi.client()
        url = f"ws://127.0.0.1:{hmi.api.port}/api/ws"
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await s.ws_connect(url, origin=ATTACKER)
        assert refused.value.status == 403
        ws = await s.ws_connect(url, origin=own(hmi))  # the HMI's own page
        first = await ws.receive_json(timeout=10)
        assert first["type"] == "snapshot"
        await ws.close()
        ws = await s.ws_connect(url)  # no Origin: not a browser's page
        await ws.close()


@pytest.mark.parametrize(
    "origin",
    ["bench.lab:8443", "https://bench.lab/hmi", "ftp://bench.lab", "https://u@bench.lab", "null"],
)
def test_an_allowed_origin_that_is_not_an_origin_is_refused_with_the_text(origin: str) -> None:
    with pytest.raises(ValidationError) as refused:
        HmiConfig(allowed_origins=[origin])
    assert f"allowed origin {origin!r} is not an origin" in str(refused.value)


def test_allowed_origins_are_kept_as_browsers_send_them() -> None:
    cfg = HmiConfig(allowed_origins=["HTTPS://Bench.Lab:443/", "http://[::1]:8080"])
    assert cfg.allowed_origins == ["https://bench.lab", "http://[::1]:8080"]


async def test_a_method_a_route_does_not_have_answers_405_not_415(tmp_path: Path) -> None:
    # Found by schemathesis (unsupported_method): the check answered before the router's
    # 405 for a PUT on a read-only route. No route runs, nothing can change: the router's.
    async with hmi_bench(tmp_path, HmiConfig(login=False)) as hmi:
        s = await hmi.client()
        async with s.put(hmi.base + "/api/alarms") as resp:
            assert resp.status == 405
            assert "GET" in resp.headers["Allow"]
        async with s.delete(hmi.base + "/api/no-such-route") as resp:
            assert resp.status == 404
