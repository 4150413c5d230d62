"""Issue 33, finding 4: a page that lost its supervisor must not look live (ISA-101: stale
values unmistakable). In Debian's Chromium against a real ``supervisor run`` stopped by
SIGTERM while ch0 runs a recipe: a banner says the values are frozen and since when (the
time they were last fresh, which stays put while the page retries), every value and
state shown is marked stale, and the page's title says so. The same when the connection
stays open but nothing comes (a hung supervisor), and all of it goes when data comes
back."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest
from axe import audit, blocking
from browserrig import (
    SHORT_RECIPE,
    Supervisor,
    login,
    screenshot,
    start_supervisor,
    stop_supervisor,
    wait_for,
)


@pytest.fixture(scope="module")
def doomed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Supervisor]:
    """A supervisor of its own, which the test stops with SIGTERM."""
    sup = start_supervisor(tmp_path_factory.mktemp("hmi-stale"))
    try:
        yield sup
    finally:
        stop_supervisor(sup)


# What a stale value looks like, element by element, in the page (computed styles).
STALE_MARKS = """(els) => els.filter((e) => e.checkVisibility()).map((e) => {
  const s = getComputedStyle(e);
  const stale = s.backgroundImage.includes('repeating-linear-gradient');
  return {tag: e.dataset.tag || e.id, stale, color: s.color};
})"""


@pytest.mark.timeout(120)
def test_a_page_that_lost_its_supervisor_marks_every_value_stale_with_the_time(
    page: Any, doomed: Supervisor
) -> None:
    status, body = doomed.call(
        "PUT", "/api/channels/ch0/recipe", {"file": SHORT_RECIPE.stem, "parameters": {}}
    )
    assert status == 200, body
    status, body = doomed.call("POST", "/api/channels/ch0/commands/start")
    assert status == 200, body
    login(page, doomed, "operator", "#/channel/ch0")
    page.wait_for_function("() => document.querySelector('#ch-state').textContent === 'Running'")
    link = "() => document.querySelector('#link').textContent"
    page.wait_for_function(f"{link} === 'live'")
    assert page.locator("#stale").is_hidden()
    before_s = page.evaluate("() => Date.now() / 1000")
    stop_supervisor(doomed)  # SIGTERM
    after_s = page.evaluate("() => Date.now() / 1000")
    page.wait_for_function(f"{link} === 'disconnected'")
    page.wait_for_selector("#stale:not([hidden])")
    banner = page.locator("#stale")
    # The time the values were last fresh: when the connection was lost, to the second.
    since_s = float(banner.get_attribute("data-since") or 0)
    assert before_s - 1 <= since_s <= after_s + 1, (before_s, since_s, after_s)
    shown = page.evaluate(
        "(s) => new Date(s * 1000).toLocaleTimeString(undefined, {hour12: false})", since_s
    )
    assert "stale since" in (banner.text_content() or "").lower()
    assert shown in (banner.text_content() or ""), (shown, banner.text_content())
    # The page keeps retrying (polls fail): the time stays the one it was last fresh.
    time.sleep(2.5)
    assert float(banner.get_attribute("data-since") or 0) == since_s
    assert page.title().startswith("STALE")
    marks = page.eval_on_selector_all("main [data-tag], #ch-activity, #summary a", STALE_MARKS)
    assert len(marks) > 10
    assert [m["tag"] for m in marks if not m["stale"]] == [], marks
    # The last value stays readable (an operator wants to know what it was), in grey.
    assert page.text_content("#ch-state") == "Running"
    red = "rgb(200, 16, 46)"
    assert [m["tag"] for m in marks if m["color"] == red] == []
    # Grey on hatching, the banner's white on its dark grey: still 4.5:1 (axe-core).
    assert [str(v) for v in blocking(audit(page))] == []
    screenshot(page, "channel-stale")
    wait_for("the supervisor gone", lambda: doomed.proc.poll() is not None)


def test_an_open_but_silent_connection_turns_the_page_stale_until_data_comes_back(
    page: Any, bench: Supervisor
) -> None:
    held = {"paused": False}

    def relay(ws: Any) -> None:
        server = ws.connect_to_server()
        server.on_message(lambda msg: None if held["paused"] else ws.send(msg))

    # Between the supervisor and the page, a relay this test can hold: the connection
    # stays open, nothing reaches the page (as from a supervisor whose loop hangs).
    page.route_web_socket("**/api/ws", relay)
    login(page, bench, "operator", "#/channel/ch3")
    link = "() => document.querySelector('#link').textContent"
    page.wait_for_function(f"{link} === 'live'")
    page.evaluate("() => { window.hmi.stale.silenceS = 2; }")  # 15 s in service
    held["paused"] = True
    paused_s = page.evaluate("() => Date.now() / 1000")
    page.wait_for_selector("#stale:not([hidden])", timeout=20_000)
    since_s = float(page.get_attribute("#stale", "data-since") or 0)
    # The last data came at most a publish period (0.2 s here) before the hold.
    assert paused_s - 1 <= since_s <= paused_s + 0.5, (paused_s, since_s)
    assert "sent nothing" in (page.text_content("#stale") or "")
    assert page.text_content("#link") == "no data"
    assert page.evaluate("() => document.body.classList.contains('stale')")
    screenshot(page, "channel-silent")
    held["paused"] = False
    page.wait_for_selector("#stale", state="hidden")
    page.wait_for_function(f"{link} === 'live'")
    assert not page.evaluate("() => document.body.classList.contains('stale')")
    assert not page.title().startswith("STALE")
