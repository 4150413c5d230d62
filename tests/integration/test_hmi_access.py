"""HMI access (issue 12 "Access"): log in with the OPC UA users, sessions that expire,
viewers see, operators command, every command recorded as ``hmi:<user>``. Real aiohttp
server on loopback, bench on the virtual clock (a session's age is the clock's time)."""

from __future__ import annotations

from pathlib import Path

import pytest
from commandrig import DISCHARGE, recipe
from hmirig import hmi_bench, password

from supervisor.config.models import HmiConfig
from supervisor.tags import Access, TagSpec

pytestmark = pytest.mark.integration


async def test_a_user_logs_in_and_gets_an_http_only_strict_cookie(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.client()
        async with s.post(
            hmi.base + "/api/login", json={"user": "otto", "password": password("otto")}
        ) as resp:
            assert resp.status == 200
            body = await resp.json()
            cookie = resp.headers["Set-Cookie"]
        assert body == {
            "user": "otto",
            "role": "operator",
            "expires_s": 8 * 3600.0,
            "login": True,
            "alarm_sound_repeat_s": 10.0,  # hmi.alarm_sound_repeat_s (ADR 0043)
        }
        assert cookie.startswith("bench_session=")
        assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and "Path=/" in cookie
        status, session = await hmi.call(s, "GET", "/api/session")
        assert status == 200
        assert (session["user"], session["role"]) == ("otto", "operator")


async def test_a_wrong_password_and_an_unknown_user_get_the_same_401(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.client()
        wrong_password = await hmi.call(
            s, "POST", "/api/login", {"user": "otto", "password": "nope"}
        )
        unknown_user = await hmi.call(
            s, "POST", "/api/login", {"user": "nobody", "password": password("otto")}
        )
        assert wrong_password == unknown_user  # no hint which part was wrong
        assert wrong_password == (
            401,
            {"error": "login failed", "reason": "wrong user name or password"},
        )
        assert not s.cookie_jar.filter_cookies(hmi.base)  # type: ignore[arg-type]
        status, _ = await hmi.call(s, "GET", "/api/session")
        assert status == 401


async def test_a_login_without_user_or_password_is_a_bad_request(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.client()
        status, body = await hmi.call(s, "POST", "/api/login", {"user": "otto"})
        assert status == 400 and "password" in body["reason"]


async def test_a_session_unused_for_the_timeout_expires(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=True, session_timeout_s=5.0)) as hmi:
        s = await hmi.login("otto")
        await hmi.scans(30)  # 3 s of the bench's clock
        status, body = await hmi.call(s, "GET", "/api/session")
        assert status == 200 and body["expires_s"] == pytest.approx(5.0)  # used: renewed
        await hmi.scans(30)
        status, body = await hmi.call(s, "GET", "/api/session")
        assert status == 200  # 3 s after its last use: still open
        await hmi.scans(51)  # 5.1 s unused
        status, body = await hmi.call(s, "GET", "/api/session")
        assert status == 401
        assert body["reason"] == "not logged in, or the session expired"
        status, body = await hmi.call(s, "POST", "/api/channels/ch0/commands/reset", {})
        assert status == 401 and body["accepted"] is False


async def test_logout_ends_the_session(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.login("otto")
        status, _ = await hmi.call(s, "POST", "/api/logout")
        assert status == 200
        status, _ = await hmi.call(s, "GET", "/api/session")
        assert status == 401
        status, _ = await hmi.call(s, "POST", "/api/channels/ch0/commands/reset", {})
        assert status == 401


async def test_a_viewer_is_refused_a_command_with_403_and_the_reason(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.login("vera")
        status, body = await hmi.call(
            s, "POST", "/api/channels/ch0/commands/start", {"recipe": recipe(tmp_path, DISCHARGE)}
        )
        assert status == 403
        assert body["accepted"] is False
        assert body["reason"] == (
            "viewer may not start ch0 (hmi:vera is a viewer): log in as an operator"
        )
        status, body = await hmi.call(s, "PUT", "/api/tags/ch0.manual_current", {"value": 0.1})
        assert status == 403
        assert body["reason"] == (
            "viewer may not manual_current ch0 (hmi:vera is a viewer): log in as an operator"
        )
        last = hmi.bench.commands.log[-1]
        assert (last.actor, last.accepted) == ("hmi:vera", False)
        await hmi.scans(5)
        assert hmi.bench.db["ch0.chain.state"].value == "Idle"


async def test_an_operator_command_is_recorded_with_the_actor_hmi_user(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.login("otto")
        status, body = await hmi.call(
            s, "POST", "/api/channels/ch0/commands/start", {"recipe": recipe(tmp_path, DISCHARGE)}
        )
        assert status == 200 and body["accepted"] is True, body
        await hmi.scans(20)
        assert hmi.bench.db["ch0.chain.state"].value == "Running"
        started = [e for e in hmi.bench.commands.log if e.command.startswith("start")]
        assert [e.actor for e in started] == ["hmi:otto"]


async def test_an_engineer_tag_needs_an_engineer(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        hmi.bench.db.add(TagSpec("lab.limit_a", access=Access.ENGINEER, initial=1.0))
        operator = await hmi.login("otto")
        status, body = await hmi.call(operator, "PUT", "/api/tags/lab.limit_a", {"value": 2.0})
        assert (status, body["reason"]) == (403, "lab.limit_a needs engineer access")
        engineer = await hmi.login("erin")
        status, body = await hmi.call(engineer, "PUT", "/api/tags/lab.limit_a", {"value": 2.0})
        assert status == 200, body
        assert hmi.bench.commands.log[-1].actor == "hmi:erin"


async def test_anonymous_read_on_answers_gets_and_refuses_commands(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=True, anonymous_read=True)) as hmi:
        s = await hmi.client()
        status, tag = await hmi.call(s, "GET", "/api/tags/ch0.voltage")
        assert status == 200 and tag["name"] == "ch0.voltage"
        status, body = await hmi.call(s, "GET", "/api/session")
        assert status == 401 and body["anonymous_read"] is True
        status, body = await hmi.call(s, "POST", "/api/channels/ch0/commands/reset", {})
        assert status == 401 and body["accepted"] is False
        status, body = await hmi.call(s, "PUT", "/api/tags/ch0.manual_current", {"value": 0.1})
        assert status == 401


async def test_anonymous_read_off_answers_401_to_every_api_read(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=True, anonymous_read=False)) as hmi:
        s = await hmi.client()
        for path in ("/api/tags", "/api/alarms", "/api/bench", "/api/diagnostics", "/api/ws"):
            status, body = await hmi.call(s, "GET", path)
            assert status == 401, path
            assert body["reason"] == "log in first (no session, or it expired)"
        viewer = await hmi.login("vera")
        status, _ = await hmi.call(viewer, "GET", "/api/tags/ch0.voltage")
        assert status == 200


async def test_with_login_off_everyone_operates_as_before(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path, HmiConfig(login=False)) as hmi:
        s = await hmi.client()
        status, body = await hmi.call(s, "GET", "/api/session")
        assert (status, body) == (
            200,
            {"user": "anonymous", "role": "operator", "login": False, "alarm_sound_repeat_s": 10.0},
        )
        status, body = await hmi.call(
            s, "POST", "/api/channels/ch0/commands/start", {"recipe": recipe(tmp_path, DISCHARGE)}
        )
        assert status == 200, body
        assert hmi.bench.commands.log[-1].actor == "operator"
        status, body = await hmi.call(s, "POST", "/api/login", {"user": "otto", "password": "x"})
        assert status == 409
