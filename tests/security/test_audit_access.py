"""The audit trail over HTTP is an engineer's, read-only (issue 34): a viewer or an
operator is refused with the reason, no session is 401, and another origin's page can
neither read it (no CORS grant) nor write it (there is no write)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hmirig import Hmi, hmi_bench

from supervisor.audit import AuditLog, audit_path

pytestmark = pytest.mark.integration

ATTACKER = "http://127.0.0.1:1"
"""A page of another origin: the same host, another port (SameSite does not tell them apart)."""
PATHS = ("/api/audit", "/api/audit/verify")


def _log(hmi: Hmi) -> None:
    with AuditLog(audit_path(hmi.bench.cfg.state_dir)) as audit:
        audit.append("hmi:erin", "login", "erin", {"role": "engineer"})


async def test_a_viewer_or_an_operator_cannot_read_the_audit_log(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        _log(hmi)
        for user, role in (("vera", "viewer"), ("otto", "operator")):
            s = await hmi.login(user)
            for path in PATHS:
                status, body = await hmi.call(s, "GET", path)
                assert status == 403, (user, path)
                assert body["reason"] == f"{role} may not read the audit log: log in as an engineer"
                assert "entries" not in body
        anonymous = await hmi.client()
        for path in PATHS:
            status, body = await hmi.call(anonymous, "GET", path)
            assert status == 401 and "entries" not in body
        erin = await hmi.login("erin")
        status, body = await hmi.call(erin, "GET", "/api/audit")
        assert status == 200 and [e["actor"] for e in body["entries"]] == ["hmi:erin"]
        # An engineer's own reads are not actions: the log is as it was.
        status, body = await hmi.call(erin, "GET", "/api/audit/verify")
        assert status == 200 and body["entries"] == 1 and body["ok"] is True


async def test_another_origin_can_neither_read_nor_write_the_audit_log(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        _log(hmi)
        s = await hmi.login("erin")
        foreign = {"Origin": ATTACKER}
        async with s.get(hmi.base + "/api/audit", headers=foreign) as resp:
            # Answered (a GET changes nothing), but with no CORS grant the browser keeps the
            # answer from the other origin's page, as for every read of this API.
            assert resp.status == 200
            assert "Access-Control-Allow-Origin" not in resp.headers
        preflight = {**foreign, "Access-Control-Request-Method": "GET"}
        async with s.options(hmi.base + "/api/audit", headers=preflight) as resp:
            assert "Access-Control-Allow-Origin" not in resp.headers
        for method in ("POST", "PUT", "DELETE"):
            async with s.request(method, hmi.base + "/api/audit", json={}, headers=foreign) as resp:
                assert resp.status == 405, method  # no route writes the log
        async with s.get(hmi.base + "/api/audit/verify") as resp:
            assert (await resp.json())["entries"] == 1


async def test_bad_filters_are_refused_with_the_parameter_named(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        _log(hmi)
        s = await hmi.login("erin")
        for query, why in (
            ("limit=0", "limit must be between 1 and 1000, not 0"),
            ("limit=x", "limit must be an integer, not 'x'"),
            ("before=-1", "before must be between 1 and"),
            ("since=monday", "since: 'monday' is not an ISO 8601 time"),
            ("actor=" + "a" * 300, "actor is longer than 256 characters"),
        ):
            status, body = await hmi.call(s, "GET", f"/api/audit?{query}")
            assert status == 400 and body["reason"].startswith(why), query


async def test_a_missing_log_is_a_503_with_the_reason(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.login("erin")
        for path in PATHS:
            status, body = await hmi.call(s, "GET", path)
            assert status == 503 and "no audit log there" in body["reason"]
