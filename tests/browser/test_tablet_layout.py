"""Issue 33, finding 3: the screens at a tablet's 800 px, in Debian's Chromium against a real
``supervisor run`` of the simulated bench, with two active alarms (the e-stop, critical, and
a burst of failed logins, medium): nothing wider than the screen, every alarm action in
reach, messages broken between words only, the header's "Log out" beside the user it logs
out, and the mimic's boxes joined by their wires on one line."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from axe import audit, blocking
from browserrig import Supervisor, login, screenshot, wait_for

TABLET = {"width": 800, "height": 1180}
BURST_TRIES = 20  # supervisor.core.logins.BURST_TRIES: failed logins that raise the alarm


def active_alarms(bench: Supervisor) -> set[str]:
    status, body = bench.call("GET", "/api/alarms")
    assert status == 200, body
    return {a["id"] for a in body["active"] if a["state"] != "normal"}


@pytest.fixture(scope="module")
def two_alarms(bench: Supervisor) -> Iterator[Supervisor]:
    """The e-stop pressed (critical, first out) and a burst of failed logins (medium)."""
    status, body = bench.call("PUT", "/api/sim/estop", {"pressed": True})
    assert status == 200, body
    for _ in range(BURST_TRIES + 2):
        bench.call("POST", "/api/login", {"user": "nobody", "password": "wrong"}, user=None)
    wait_for(
        "two active alarms",
        lambda: {"estop", "security.login_burst"} <= active_alarms(bench),
        timeout_s=30,
    )
    yield bench


def overflow(page: Any) -> int:
    """How far the page is wider than the viewport (px): 0 when nothing sticks out."""
    return int(
        page.evaluate(
            "() => document.documentElement.scrollWidth - document.documentElement.clientWidth"
        )
    )


# Each word of each message cell on one line: a word broken across two lines has two
# client rectangles.
BROKEN_WORDS = """(cells) => {
  const broken = [];
  for (const cell of cells) {
    const text = cell.firstChild;
    if (!text || text.nodeType !== Node.TEXT_NODE) continue;
    const re = /\\S+/g;
    let m;
    while ((m = re.exec(text.data))) {
      const r = document.createRange();
      r.setStart(text, m.index);
      r.setEnd(text, m.index + m[0].length);
      const tops = new Set(Array.from(r.getClientRects()).map((x) => Math.round(x.top)));
      if (tops.size > 1) broken.push(m[0]);
    }
  }
  return broken;
}"""


def test_the_alarm_table_fits_an_800_px_tablet_with_its_actions_and_whole_words(
    page: Any, two_alarms: Supervisor
) -> None:
    page.set_viewport_size(TABLET)
    login(page, two_alarms, "operator", "#/alarms")
    page.wait_for_selector("#alarm-table tr[data-alarm='security.login_burst']")
    page.wait_for_selector("#alarm-table tr[data-alarm='estop']")
    page.wait_for_selector("#alarm-history-table")
    screenshot(page, "alarms-tablet")
    assert overflow(page) == 0
    table = page.locator("#alarm-table").bounding_box()
    assert table["x"] >= 0 and table["x"] + table["width"] <= TABLET["width"], table
    controls = "#alarm-table td.actions button, #alarm-table td.actions select"
    for control in page.locator(controls).all():
        box = control.bounding_box()
        label = control.text_content() or control.get_attribute("aria-label")
        assert box["x"] >= 0 and box["x"] + box["width"] <= TABLET["width"], (label, box)
        # The whole label shows: the control is as wide as its text needs.
        assert control.evaluate("b => b.scrollWidth <= b.clientWidth"), label
    cells = page.locator("#alarm-table td.wrap, #alarm-history-table td.wrap")
    assert cells.count() >= 2
    assert cells.evaluate_all(BROKEN_WORDS) == []
    # The priorities' icons, the wrapped actions: nothing serious for axe-core either.
    assert [str(v) for v in blocking(audit(page))] == []


def test_the_header_keeps_its_session_controls_together_at_800_px(
    page: Any, bench: Supervisor
) -> None:
    page.set_viewport_size(TABLET)
    login(page, bench, "engineer")  # the longest user label of the demo users
    page.wait_for_selector("#tile-ch0")
    screenshot(page, "header-tablet")
    assert overflow(page) == 0
    # The link's state, the sound switch, the user and "Log out": one line, so "Log out"
    # never ends up alone on a line, away from the user it logs out.
    centres = [
        box["y"] + box["height"] / 2
        for box in (
            page.locator(sel).bounding_box() for sel in ("#link", "#sound", "#who", "#logout")
        )
    ]
    assert max(centres) - min(centres) < 8, centres
    right = page.locator("#logout").bounding_box()
    assert right["x"] + right["width"] <= TABLET["width"]


def test_the_mimic_keeps_its_boxes_and_wires_on_one_line_at_800_px(
    page: Any, two_alarms: Supervisor
) -> None:
    page.set_viewport_size(TABLET)
    login(page, two_alarms, "operator")
    page.wait_for_selector("#mimic-bms")
    page.wait_for_function(
        "() => document.querySelector('#mimic-estop').textContent.includes('PRESSED')"
    )
    screenshot(page, "overview-tablet-alarms")
    assert overflow(page) == 0
    boxes = page.eval_on_selector_all(
        ".mimic > .mimic-box, .mimic > .wire",
        "els => els.map(e => { const r = e.getBoundingClientRect();"
        " return {wire: e.classList.contains('wire'), left: r.left, right: r.right,"
        " top: r.top, bottom: r.bottom}; })",
    )
    assert [b["wire"] for b in boxes] == [False, True, False, True, False, True, False]
    for i in range(1, len(boxes), 2):
        before, wire, after = boxes[i - 1], boxes[i], boxes[i + 1]
        # Each wire joins the box before it to the box after it: between them, at a height
        # both boxes have (not dangling at the end of a line).
        assert before["right"] <= wire["left"] + 1 and wire["right"] <= after["left"] + 1
        for box in (before, after):
            assert box["top"] <= wire["top"] <= box["bottom"], (box, wire)
    assert max(b["right"] for b in boxes) <= TABLET["width"]


@pytest.mark.parametrize(
    "where", ["#/", "#/channel/ch0", "#/alarms", "#/recipes", "#/tests", "#/diagnostics"]
)
def test_no_screen_is_wider_than_an_800_px_tablet(
    page: Any, two_alarms: Supervisor, where: str
) -> None:
    page.set_viewport_size(TABLET)
    login(page, two_alarms, "operator", where)
    page.wait_for_selector("#main > *")
    page.wait_for_load_state("networkidle")
    assert overflow(page) == 0
