"""Issue 34, "What to build": the Alarms screen's journal and its alarm performance panel,
in Debian's Chromium against a real ``supervisor run`` of the simulated bench. After a
scripted e-stop that an operator acknowledges, a search by alarm and actor finds that
acknowledgement (and only it), the "Export CSV" link downloads the same search as a CSV
file that holds the journal API's rows, and the panel shows the ``alarms.*`` figures the
supervisor publishes (as ``GET /api/tags`` gives them) beside their ISA-18.2 targets. At a
tablet's 800 px nothing is wider than the screen."""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

import pytest
from browserrig import Supervisor, login, screenshot, wait_for

TABLET = {"width": 800, "height": 1180}
ACTOR = "hmi:operator"  # the operator's acknowledgement, as the alarm model records it


def _journal(bench: Supervisor, **query: str) -> list[dict[str, Any]]:
    status, body = bench.call("GET", f"/api/alarms/journal?{urlencode(query)}")
    assert status == 200, body
    return list(body["entries"])


@pytest.fixture(scope="module")
def acknowledged(bench: Supervisor) -> Iterator[Supervisor]:
    """The simulated e-stop pressed, its alarm acknowledged by the operator, both in the
    journal (the historian writes its events a moment later)."""
    status, body = bench.call("PUT", "/api/sim/estop", {"pressed": True})
    assert status == 200, body
    wait_for("the e-stop alarm", lambda: bench.tag("estop.ok") is False)
    wait_for("the e-stop alarm active", lambda: _journal(bench, alarm="estop"))
    status, body = bench.call("POST", "/api/alarms/estop/acknowledge", {})
    assert status == 200, body
    wait_for(
        "the acknowledgement in the journal",
        lambda: _journal(bench, alarm="estop", actor=ACTOR, transition="acknowledged"),
    )
    yield bench


def _search(page: Any, **fields: str) -> list[tuple[str, str, str]]:
    """Fill the journal's filters (``alarm``, ``actor``, ``transition``), search, and give
    the rows shown: (alarm, transition, actor)."""
    page.wait_for_selector("#alarm-journal[data-searched]")
    before = page.get_attribute("#alarm-journal", "data-searched")
    for name in ("alarm", "actor"):
        page.fill(f"#journal-{name}", fields.get(name, ""))
    page.select_option("#journal-transition", fields.get("transition", ""))
    page.click("#journal-search")
    page.wait_for_function(
        "(n) => document.querySelector('#alarm-journal').dataset.searched !== n", arg=before
    )
    return [
        tuple(r)
        for r in page.eval_on_selector_all(
            "#journal-table tbody tr",
            "rows => rows.map(r => [r.dataset.alarmId, r.dataset.transition,"
            " r.cells[5].textContent])",
        )
    ]


def test_a_search_by_alarm_and_actor_finds_the_operators_acknowledgement(
    page: Any, acknowledged: Supervisor
) -> None:
    login(page, acknowledged, "operator", "#/alarms")
    rows = _search(page, alarm="estop", actor=ACTOR)
    assert rows == [("estop", "acknowledged", ACTOR)]
    # The alarm alone: its activation by the safety checks too, newest first, and the
    # same rows as the journal API gives (oldest first).
    rows = _search(page, alarm="estop")
    expected = _journal(acknowledged, alarm="estop")
    assert rows == [(e["alarm"], e["transition"], e["actor"]) for e in reversed(expected)]
    assert ("estop", "activated", "safety") in rows
    assert page.text_content("#journal-count") == f"{len(rows)} entries, newest first."
    # A transition chosen: only those.
    rows = _search(page, alarm="estop", transition="activated")
    assert rows and {r[1] for r in rows} == {"activated"}
    # Its priority by shape, number and word, as the active alarms' table shows it.
    cell = "#journal-table tbody tr[data-priority='critical'] td.prio-cell"
    assert page.get_attribute(f"{cell} svg", "class") == "prio prio-critical"
    assert page.text_content(f"{cell} .prio-name") == "critical"
    screenshot(page, "alarm-journal")


def test_export_csv_downloads_the_search_on_screen(
    page: Any, acknowledged: Supervisor, tmp_path: Path
) -> None:
    login(page, acknowledged, "operator", "#/alarms")
    rows = _search(page, alarm="estop")
    with page.expect_download() as info:
        page.click("#journal-export")
    download = info.value
    assert download.suggested_filename == "alarm-journal.csv"
    path = tmp_path / "journal.csv"
    download.save_as(path)
    with path.open(encoding="utf-8", newline="") as f:
        exported = list(csv.DictReader(f))
    assert [(r["alarm"], r["transition"], r["actor"]) for r in reversed(exported)] == rows
    expected = _journal(acknowledged, alarm="estop")
    assert [r["time_iso"] for r in exported] == [e["time_iso"] for e in expected]
    assert {r["priority"] for r in exported} == {"critical"}


KPI_TAGS = (
    "alarms.per_10min",
    "alarms.per_10min_last",
    "alarms.per_day",
    "alarms.in_flood",
    "alarms.flood_s",
    "alarms.flood_pct",
    "alarms.stale",
    "alarms.chattering",
    "alarms.kpi_dropped",
    *(f"alarms.priority.{p}" for p in ("critical", "high", "medium", "low")),
    *(f"alarms.priority.{p}_pct" for p in ("critical", "high", "medium", "low")),
)


def _shown(page: Any) -> dict[str, str]:
    return dict(
        page.eval_on_selector_all(
            "#alarm-kpi [data-kpi]", "els => els.map(e => [e.dataset.kpi, e.dataset.value])"
        )
    )


def _same(shown: str, value: Any) -> bool:
    if isinstance(value, bool):
        return shown == str(value).lower()
    return shown != "" and float(shown) == float(value)


def test_the_performance_panel_shows_the_supervisors_figures_beside_their_targets(
    page: Any, acknowledged: Supervisor
) -> None:
    login(page, acknowledged, "operator", "#/alarms")
    page.wait_for_selector("#alarm-kpi")
    # The figures move only when an alarm does (or with time): read them once settled.
    server = wait_for(
        "the panel showing the server's figures",
        lambda: (
            (figures := {t: acknowledged.tag(t) for t in KPI_TAGS})
            and all(_same(_shown(page).get(t, ""), v) for t, v in figures.items())
            and figures
        ),
    )
    assert server["alarms.per_day"] >= 1 and server["alarms.priority.critical"] >= 1
    # Each figure's text is its value (with its unit), its target beside it.
    per_day = page.locator("#kpi-figures tr[data-row='alarms.per_day']")
    assert per_day.locator("td.num").text_content() == str(server["alarms.per_day"])
    assert per_day.locator("td.target").text_content() == "~150 acceptable, ≤ 300 manageable"
    assert per_day.locator("td.verdict").text_content() in ("within target", "over target")
    flood = page.locator("#kpi-figures tr[data-row='alarms.flood_pct'] td.num").text_content()
    assert flood == f"{server['alarms.flood_pct']:.1f} %"
    target = "#kpi-figures tr[data-row='alarms.in_flood'] td.target"
    assert page.text_content(target) == "no (flood: over 10 in 10 min)"
    # The ten most frequent: the e-stop with the count the tag gives.
    top = json.loads(acknowledged.tag("alarms.top"))
    estop = next(e for e in top if e["id"] == "estop")
    assert page.text_content("#kpi-top-table [data-top='estop']") == str(estop["count"])


def test_the_journal_and_the_panel_fit_an_800_px_tablet(
    page: Any, acknowledged: Supervisor
) -> None:
    page.set_viewport_size(TABLET)
    login(page, acknowledged, "operator", "#/alarms")
    page.wait_for_selector("#journal-table tbody tr")
    page.wait_for_selector("#kpi-top-table")
    page.wait_for_load_state("networkidle")
    screenshot(page, "alarm-journal-tablet")
    width = page.evaluate(
        "() => document.documentElement.scrollWidth - document.documentElement.clientWidth"
    )
    assert width == 0
    for sel in ("#journal-form", "#journal-table", "#kpi-figures", "#kpi-top-table"):
        box = page.locator(sel).bounding_box()
        assert box["x"] >= 0 and box["x"] + box["width"] <= TABLET["width"], (sel, box)


def test_a_french_journal_says_the_alarms_text_in_french(
    browser: Any, acknowledged: Supervisor
) -> None:
    ctx = browser.new_context(locale="fr-FR")
    ctx.set_default_timeout(15_000)
    try:
        page = ctx.new_page()
        login(page, acknowledged, "operator", "#/alarms")
        page.wait_for_selector("#journal-table tr[data-alarm-id='estop']")
        assert page.text_content("#alarm-journal h2") == "Journal"
        assert page.text_content("#journal-export") == "Exporter en CSV"
        cell = "#journal-table tr[data-alarm-id='estop'][data-transition='acknowledged'] td.wrap"
        # The journal carries the supervisor's English text; the alarm the page knows by
        # its code says it in French.
        assert (page.text_content(cell) or "").startswith("Arrêt d'urgence enfoncé")
        transition = "#journal-table tr[data-transition='acknowledged'] td:nth-child(4)"
        assert page.text_content(transition) == "acquittement"
    finally:
        ctx.close()


def _search_form(page: Any, channel: str, **times: str) -> list[str]:
    """Search by the channel's choice (and ``since``/``until`` if given, as the inputs hold
    them): the alarms shown."""
    page.wait_for_selector("#alarm-journal[data-searched]")
    before = page.get_attribute("#alarm-journal", "data-searched")
    page.select_option("#journal-channel", channel)
    for name, value in times.items():
        page.fill(f"#journal-{name}", value)
    page.click("#journal-search")
    page.wait_for_function(
        "(n) => document.querySelector('#alarm-journal').dataset.searched !== n", arg=before
    )
    return list(
        page.eval_on_selector_all(
            "#journal-table tbody tr", "rows => rows.map(r => r.dataset.alarmId)"
        )
    )


def test_a_search_by_channel_and_time_keeps_to_them(page: Any, acknowledged: Supervisor) -> None:
    login(page, acknowledged, "operator", "#/alarms")
    # The e-stop is the bench's own alarm (channel=), no channel's.
    assert "estop" in _search_form(page, "-")
    assert "estop" not in _search_form(page, "ch0")
    assert page.get_attribute("#journal-export", "href").endswith("channel=ch0&format=csv")
    # Up to an hour ago (the browser's local time): before the e-stop, nothing.
    earlier = page.evaluate(
        "() => { const d = new Date(Date.now() - 3600000), p = (n) => String(n).padStart(2, '0');"
        " return `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())}T"
        "${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}`; }"
    )
    assert _search_form(page, "", until=earlier) == []
    assert page.text_content("#journal-none") == "No journal entry matches the search."
    # A period the supervisor refuses (from after to): its reason, in words.
    assert _search_form(page, "", since=earlier, until="2000-01-01T00:00:00") == []
    assert page.text_content("#journal-count") == (
        "The journal could not be read: since is after until"
    )


def test_a_search_with_more_matches_than_shown_says_older_ones_were_left_out(
    page: Any, acknowledged: Supervisor
) -> None:
    # The journal's limit (1000 on the screen's searches) made 1 on the way.
    page.route(
        "**/api/alarms/journal?*",
        lambda route: route.continue_(url=route.request.url + "&limit=1"),
    )
    login(page, acknowledged, "operator", "#/alarms")
    rows = _search(page, alarm="estop")
    newest = _journal(acknowledged, alarm="estop")[-1]
    assert rows == [(newest["alarm"], newest["transition"], newest["actor"])]
    assert page.text_content("#journal-count") == (
        "1 entry, newest first. Older entries were left out: search an earlier period."
    )


def test_the_performance_panel_follows_a_new_alarm_live(
    page: Any, acknowledged: Supervisor
) -> None:
    """(last: it raises the e-stop again) The figures move on the open page, no reload."""
    login(page, acknowledged, "operator", "#/alarms")
    cell = "#kpi-figures [data-kpi='alarms.per_day']"
    page.wait_for_function("(sel) => document.querySelector(sel).dataset.value !== ''", arg=cell)
    before = int(page.get_attribute(cell, "data-value") or 0)
    bench = acknowledged
    status, body = bench.call("PUT", "/api/sim/estop", {"pressed": False})
    assert status == 200, body
    wait_for("the e-stop circuit closed", lambda: bench.tag("estop.ok") is True)
    status, body = bench.call("POST", "/api/alarms/estop/reset", {})
    assert status == 200, body
    status, body = bench.call("PUT", "/api/sim/estop", {"pressed": True})
    assert status == 200, body
    page.wait_for_function(
        "([sel, n]) => Number(document.querySelector(sel).dataset.value) > n",
        arg=[cell, before],
    )
    assert int(page.get_attribute(cell, "data-value") or 0) == bench.tag("alarms.per_day")
