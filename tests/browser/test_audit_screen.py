"""Issue 34, "What to build": the audit trail in the screens, an engineer's. An operator has
no link to it, and reaching it by its address reads the supervisor's refusal in words (no
empty form); an engineer has the link, sees the chain checked whole (with the number of
entries ``GET /api/audit/verify`` gives), finds the operator's acknowledgement of a
scripted e-stop with the filters, downloads the same selection as CSV (the entries of
``GET /api/audit``), and the screen fits a tablet's 800 px; an entry edited in the file
afterwards is named as the chain's first broken one."""

from __future__ import annotations

import csv
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from browserrig import Supervisor, login, screenshot, wait_for

from supervisor.audit import audit_path

TABLET = {"width": 800, "height": 1180}


def _api(bench: Supervisor, path: str) -> Any:
    status, body = bench.call("GET", path, user="engineer")
    assert status == 200, body
    return body


@pytest.fixture(scope="module")
def audited(bench: Supervisor) -> Iterator[Supervisor]:
    """The e-stop pressed and its alarm acknowledged by the operator (a command, audited);
    the engineer's API client logged in first (a login is an entry too)."""
    _api(bench, "/api/audit/verify")
    status, body = bench.call("PUT", "/api/sim/estop", {"pressed": True})
    assert status == 200, body
    wait_for("the e-stop alarm", lambda: bench.tag("estop.ok") is False)
    status, body = bench.call("POST", "/api/alarms/estop/acknowledge", {})
    assert status == 200, body
    wait_for(
        "the acknowledgement audited",
        lambda: _api(bench, "/api/audit?kind=command.acknowledge")["entries"],
    )
    yield bench


def test_an_operator_has_no_audit_link_and_reads_the_refusal_in_words(
    page: Any, audited: Supervisor
) -> None:
    login(page, audited, "operator")
    page.wait_for_selector("#tile-ch0")
    assert page.locator("#nav-audit").is_hidden()
    page.evaluate("() => { location.hash = '#/audit'; }")
    page.wait_for_selector("#audit-refused", state="visible")
    text = page.text_content("#audit-refused") or ""
    assert text.startswith("The audit trail is for engineers only: log in as an engineer")
    # The server's own reason, quoted.
    assert "operator may not read the audit log: log in as an engineer" in text
    assert page.locator("#audit-body").is_hidden()
    assert page.title().startswith("Audit")


def test_an_engineer_reads_the_trail_with_its_chain_verified(
    page: Any, audited: Supervisor
) -> None:
    login(page, audited, "engineer")
    page.click("#nav-audit")
    page.wait_for_selector("#audit-verify.accepted")
    page.wait_for_selector("#audit-table tbody tr")
    # The page's check, then the API's: nothing acted in between (reads are no entries).
    verify = _api(audited, "/api/audit/verify")
    assert verify["ok"] is True
    assert page.text_content("#audit-verify") == (
        f"Chain OK: {verify['entries']} entries verified,"
        f" head {verify['head'][:8]}…{verify['head'][-8:]}."
    )
    assert page.get_attribute("[data-nav='audit']", "aria-current") == "page"
    # The newest first: the engineer's own login at the top.
    first = page.locator("#audit-table tbody tr").first
    assert first.get_attribute("data-kind") == "login"
    assert "hmi:engineer" in (first.text_content() or "")
    # The operator's acknowledgement, by actor and kind (a family: every command.*).
    page.fill("#audit-actor", "hmi:operator")
    page.fill("#audit-kind", "command")
    page.click("#audit-search")
    page.wait_for_function(
        "() => [...document.querySelectorAll('#audit-table tbody tr')]"
        ".every(r => r.dataset.kind.startsWith('command.'))"
    )
    kinds = page.eval_on_selector_all(
        "#audit-table tbody tr", "rows => rows.map(r => r.dataset.kind)"
    )
    entries = _api(audited, "/api/audit?actor=hmi:operator&kind=command")["entries"]
    assert kinds == [e["kind"] for e in entries]
    assert "command.acknowledge" in kinds
    screenshot(page, "audit-engineer")


def test_the_export_downloads_the_selection_as_csv(
    page: Any, audited: Supervisor, tmp_path: Path
) -> None:
    login(page, audited, "engineer", "#/audit")
    page.wait_for_selector("#audit-table tbody tr")
    page.fill("#audit-kind", "command")
    page.click("#audit-search")
    page.wait_for_function(
        "() => document.querySelector('#audit-export').href.includes('kind=command')"
    )
    with page.expect_download() as info:
        page.click("#audit-export")
    assert info.value.suggested_filename == "audit-trail.csv"
    path = tmp_path / "audit.csv"
    info.value.save_as(path)
    with path.open(encoding="utf-8", newline="") as f:
        exported = list(csv.DictReader(f))
    entries = _api(audited, "/api/audit?kind=command&limit=1000")["entries"]
    # Oldest first in the file, as `supervisor audit export` writes it.
    assert [r["hash"] for r in exported] == [e["hash"] for e in reversed(entries)]
    assert any(r["kind"] == "command.acknowledge" for r in exported)


def test_the_audit_screen_fits_an_800_px_tablet(page: Any, audited: Supervisor) -> None:
    page.set_viewport_size(TABLET)
    login(page, audited, "engineer", "#/audit")
    page.wait_for_selector("#audit-verify.accepted")
    page.wait_for_selector("#audit-table tbody tr")
    page.wait_for_load_state("networkidle")
    screenshot(page, "audit-tablet")
    width = page.evaluate(
        "() => document.documentElement.scrollWidth - document.documentElement.clientWidth"
    )
    assert width == 0
    box = page.locator("#audit-table").bounding_box()
    assert box["x"] >= 0 and box["x"] + box["width"] <= TABLET["width"], box


def test_older_entries_come_a_page_at_a_time(page: Any, audited: Supervisor) -> None:
    # The screen's pages of 100 made pages of 3 on their way (the server pages them).
    page.route(
        "**/api/audit?*",
        lambda route: route.continue_(url=route.request.url.replace("limit=100", "limit=3")),
    )
    login(page, audited, "engineer", "#/audit")
    page.wait_for_selector("#audit-table tbody tr")
    every = [e["seq"] for e in _api(audited, "/api/audit?limit=1000")["entries"]]
    assert len(every) > 3 and page.locator("#audit-table tbody tr").count() == 3
    while page.locator("#audit-older").is_visible():
        shown = page.locator("#audit-table tbody tr").count()
        page.click("#audit-older")
        page.wait_for_function(
            "(n) => document.querySelectorAll('#audit-table tbody tr').length > n", arg=shown
        )
    seqs = page.eval_on_selector_all(
        "#audit-table tbody tr", "rows => rows.map(r => Number(r.dataset.seq))"
    )
    # Every entry (reads add none), newest first, each once, down to the first.
    assert seqs == every and seqs == sorted(set(seqs), reverse=True) and seqs[-1] == 1
    assert page.text_content("#audit-count") == f"{len(seqs)} entries shown, newest first."


def test_an_entry_edited_afterwards_is_named_as_the_first_broken_one(
    page: Any, audited: Supervisor
) -> None:
    """(last: it breaks the module's chain) As someone who can write the state folder
    would: the guard trigger dropped, entry 2's target rewritten."""
    with sqlite3.connect(audit_path(audited.state_dir)) as db:
        db.execute("DROP TRIGGER entries_no_update")
        db.execute("UPDATE entries SET target = 'someone else' WHERE seq = 2")
    db.close()
    login(page, audited, "engineer", "#/audit")
    page.wait_for_selector("#audit-verify[data-ok='false']")
    broken = _api(audited, "/api/audit/verify")["first_broken"]
    assert broken["seq"] == 2, broken
    text = page.text_content("#audit-verify") or ""
    assert text.startswith("Chain BROKEN at entry 2 (") and text.endswith(broken["problem"])
    assert "refused" in (page.get_attribute("#audit-verify", "class") or "")
    # The entry itself, in the table: marked in words and colour.
    row = page.locator("#audit-table tbody tr[data-seq='2']")
    assert row.locator(".broken-mark").text_content() == "broken here"
    assert "abn" in (row.get_attribute("class") or "")
    assert page.locator("#audit-table .broken-mark").count() == 1
    screenshot(page, "audit-broken")
