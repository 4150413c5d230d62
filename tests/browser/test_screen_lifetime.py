"""A screen's life ends when the operator leaves it: an answer it asked for that arrives
later has nowhere to land, and what it listened to stops listening. Found by CI on a
loaded machine (the alarm history's answer landed on the next screen: "Cannot set
properties of null (setting 'innerHTML')"), and by reading why (the Alarms screen put its
click handler on the element every screen shares, once per visit). In Debian's Chromium
against a real ``supervisor run`` of the simulated bench."""

from __future__ import annotations

from typing import Any

import pytest
from browserrig import Supervisor, login, wait_for

BURST_TRIES = 20  # supervisor.core.logins.BURST_TRIES

# Every screen that asks the supervisor for something after it is drawn.
# (The overview is drawn from the live data alone.)
SCREENS = ["#/alarms", "#/tests", "#/recipes", "#/channel/ch0", "#/diagnostics"]


def pumped(page: Any, value: Any) -> Any:
    """``value``, after a call into the page: Playwright delivers its events (a request to
    hold, a finished one) only while the test talks to it."""
    page.evaluate("() => 0")
    return value


def settle(page: Any) -> None:
    """Two turns of the page's event loop: the continuations of answers already received
    (fetch, then its JSON, then the screen's code) have run."""
    for _ in range(2):
        page.evaluate("() => new Promise((r) => setTimeout(r, 0))")


@pytest.mark.parametrize("screen", SCREENS)
def test_an_answer_that_arrives_after_the_screen_was_left_writes_nothing(
    page: Any, bench: Supervisor, screen: str
) -> None:
    login(page, bench, "engineer")
    held: list[Any] = []
    holding = {"on": True}

    def hold(route: Any) -> None:
        if holding["on"] and route.request.method == "GET":
            held.append(route)
        else:
            route.continue_()

    finished: list[Any] = []
    page.on("requestfinished", lambda request: finished.append(request))
    page.route("**/api/**", hold)
    page.evaluate("(h) => { location.hash = h; }", screen)
    wait_for(f"{screen} asked the supervisor", lambda: pumped(page, held))
    # The operator leaves before the answers come (the overview is drawn from live data).
    other = "#/recipes" if screen != "#/recipes" else "#/alarms"
    holding["on"] = False
    page.evaluate("(h) => { location.hash = h; }", other)
    page.wait_for_function("(h) => location.hash === h", arg=other)
    released = list(held)
    for route in released:
        route.continue_()
    wait_for(
        "the held answers received",
        lambda: pumped(page, all(any(f is r.request for f in finished) for r in released)),
    )
    settle(page)
    # The page fixture fails the test on any error the page raised.


def test_leaving_and_returning_to_the_alarms_screen_acknowledges_once_per_click(
    page: Any, bench: Supervisor
) -> None:
    for _ in range(BURST_TRIES + 2):
        bench.call("POST", "/api/login", {"user": "nobody", "password": "wrong"}, user=None)
    login(page, bench, "operator", "#/alarms")
    acks: list[str] = []
    page.on(
        "request",
        lambda r: acks.append(r.url) if r.method == "POST" and "/api/alarms/" in r.url else None,
    )
    for where in ("#/", "#/alarms", "#/tests", "#/alarms"):
        page.evaluate("(h) => { location.hash = h; }", where)
        page.wait_for_function("(h) => location.hash === h", arg=where)
    button = "#alarm-table tr[data-alarm='security.login_burst'] button[data-act='acknowledge']"
    page.wait_for_selector(button)
    page.click(button)
    page.wait_for_selector("#alarm-result:not([hidden])")
    # Every handler of that click has sent its request by now (each posts before it awaits).
    assert acks == [f"{bench.base}/api/alarms/security.login_burst/acknowledge"], acks
