"""Password guessing over HTTP (issue 27, finding 4): wrong passwords beyond the limit get
429 with ``Retry-After`` and the reason, the right one too while the delay runs, and raise
``security.login_burst`` until a minute after the tries stop; another user, and the user
at the address they logged in from, still log in; an unknown user costs the same hash work
as a known one; a viewer logging in 1001 times keeps the operator's session. Real aiohttp
server on loopback; the attacker's "other address" is 127.0.0.2 (loopback too, another
source address); the bench's virtual clock is the throttle's time."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import aiohttp
import pytest
from hmirig import Hmi, hmi_bench, password

from supervisor.app.logins import BURST_ALARM
from supervisor.core.logins import BURST_TRIES, PAIR

pytestmark = pytest.mark.integration
ELSEWHERE = "127.0.0.2"


async def client_at(hmi: Hmi, address: str) -> aiohttp.ClientSession:
    s = aiohttp.ClientSession(
        connector=aiohttp.TCPConnector(local_addr=(address, 0)),
        cookie_jar=aiohttp.CookieJar(unsafe=True),
    )
    hmi.sessions.append(s)
    return s


async def login(
    hmi: Hmi, s: aiohttp.ClientSession, user: str, pw: str
) -> tuple[int, Any, str | None]:
    async with s.post(hmi.base + "/api/login", json={"user": user, "password": pw}) as resp:
        return resp.status, await resp.json(), resp.headers.get("Retry-After")


async def test_wrong_passwords_beyond_the_limit_get_429_with_retry_after_and_raise_the_alarm(
    tmp_path: Path,
) -> None:
    async with hmi_bench(tmp_path) as hmi:
        assert hmi.bench.alarms is not None
        alarm = hmi.bench.alarms[BURST_ALARM]
        home = await hmi.login("otto")  # the operator's panel, at 127.0.0.1
        attacker = await client_at(hmi, ELSEWHERE)
        for _ in range(PAIR.free):
            status, body, _ = await login(hmi, attacker, "otto", "guess")
            assert (status, body["reason"]) == (401, "wrong user name or password")
        status, body, retry_after = await login(hmi, attacker, "otto", "guess")
        assert status == 429
        assert retry_after == "1"
        assert body == {
            "error": "too many failed logins",
            "reason": "too many failed logins for this user from this address: try again in 1 s",
            "retry_after_s": 1,
        }
        # The right password is refused too while the delay runs (else it slows nothing).
        status, _, _ = await login(hmi, attacker, "otto", password("otto"))
        assert status == 429
        # Another user from another address, and otto from his own panel, still log in.
        status, _, _ = await login(hmi, await hmi.client(), "erin", password("erin"))
        assert status == 200
        status, _, _ = await login(hmi, await hmi.client(), "otto", password("otto"))
        assert status == 200
        status, body = await hmi.call(home, "PUT", "/api/tags/ch0.manual_current", {"value": 0.1})
        assert status == 200, body
        # A burst: the scan raises the alarm, and clears it a minute after the tries stop.
        for _ in range(BURST_TRIES):
            status, _, _ = await login(hmi, attacker, "otto", "guess")
            assert status == 429
        await hmi.scans(1)
        assert alarm.active
        assert "failed or refused logins within 60 s" in alarm.message
        await hmi.bench.engine.run_for(61.0)
        await hmi.scans(1)
        assert not alarm.active


async def test_an_unknown_user_costs_the_same_hash_work_as_a_known_one(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        users = hmi.screens.access.users
        assert users is not None
        s = await hmi.client()
        before = users.checks
        status, known, _ = await login(hmi, s, "otto", "wrong")
        after_known = users.checks
        status2, unknown, _ = await login(hmi, s, "nobody", "wrong")
        assert (status, known) == (status2, unknown)
        assert users.checks - after_known == after_known - before == 1


async def test_a_viewer_logging_in_1001_times_keeps_the_operators_session(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        operator = await hmi.login("otto")
        viewer = await hmi.client()
        for _ in range(1001):
            viewer.cookie_jar.clear()
            status, _, _ = await login(hmi, viewer, "vera", password("vera"))
            assert status == 200
        status, body = await hmi.call(
            operator, "PUT", "/api/tags/ch0.manual_current", {"value": 0.1}
        )
        assert status == 200, body
        assert hmi.bench.commands.log[-1].actor == "hmi:otto"
        status, session = await hmi.call(operator, "GET", "/api/session")
        assert (status, session["user"]) == (200, "otto")
        status, session = await hmi.call(viewer, "GET", "/api/session")  # the last one lives
        assert (status, session["user"]) == (200, "vera")
