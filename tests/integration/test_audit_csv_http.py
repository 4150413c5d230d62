"""The audit trail's export over HTTP (issue 34, the Audit screen's "Export CSV" link):
``GET /api/audit?…&format=csv`` answers every entry the filters select, oldest first, as a
CSV download with the columns of ``supervisor audit export``, a formula-like text escaped;
an engineer's only, as the JSON."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import pytest
from hmirig import Hmi, hmi_bench

from supervisor.audit import AuditLog, audit_path
from supervisor.hmi.audit_api import CSV_COLUMNS

pytestmark = pytest.mark.integration


def _log(hmi: Hmi) -> None:
    with AuditLog(audit_path(hmi.bench.cfg.state_dir)) as audit:
        audit.append("hmi:erin", "login", "erin", {"role": "engineer"})
        audit.append("hmi:otto", "command.start", "ch0", {"channel": "ch0", "accepted": True})
        audit.append("hmi:=cmd", "login.failed", "=cmd", {"address": "127.0.0.1"})
        audit.append("hmi:otto", "command.stop", "ch1", {"channel": "ch1", "accepted": True})


async def test_the_audit_csv_holds_every_selected_entry_oldest_first(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        _log(hmi)
        erin = await hmi.login("erin")
        # limit and before page the JSON; the export ignores them (the whole selection).
        async with erin.get(hmi.base + "/api/audit?kind=command&limit=1&format=csv") as resp:
            assert resp.status == 200
            assert resp.content_type == "text/csv"
            assert "attachment" in resp.headers["Content-Disposition"]
            rows = list(csv.DictReader(io.StringIO(await resp.text())))
        assert [(r["seq"], r["kind"], r["target"]) for r in rows] == [
            ("2", "command.start", "ch0"),
            ("4", "command.stop", "ch1"),
        ]
        assert tuple(rows[0]) == CSV_COLUMNS
        assert json.loads(rows[0]["details"])["channel"] == "ch0"
        async with erin.get(hmi.base + "/api/audit?format=csv") as resp:
            every = list(csv.DictReader(io.StringIO(await resp.text())))
        status, body = await hmi.call(erin, "GET", "/api/audit?limit=1000")
        assert status == 200, body
        assert [r["hash"] for r in every] == [e["hash"] for e in reversed(body["entries"])]
        # A name a spreadsheet would run as a formula is written with a leading '.
        assert every[2]["target"] == "'=cmd"


async def test_an_operator_cannot_export_the_audit_trail_and_a_bad_format_is_named(
    tmp_path: Path,
) -> None:
    async with hmi_bench(tmp_path) as hmi:
        _log(hmi)
        otto = await hmi.login("otto")
        status, body = await hmi.call(otto, "GET", "/api/audit?format=csv")
        assert status == 403 and "log in as an engineer" in body["reason"]
        erin = await hmi.login("erin")
        status, body = await hmi.call(erin, "GET", "/api/audit?format=xml")
        assert status == 400 and body["reason"] == "format: json or csv"
