"""The channel's command bar (issue 33, findings 2 and 5), in Debian's Chromium against a
real ``supervisor run`` of the simulated bench (io_maps/sim.yaml on free ports).

Finding 2: the buttons follow the state table — a button is enabled only when the command
path would accept its command now (``GET /api/channels/{ch}/commands``), otherwise
aria-disabled with the reason as its tooltip, and a tap on it shows the refusal and sends
nothing; Stop, Abort, Reset of a finished test and forcing ask first, in a dialog naming
the channel and the test; Cancel sends nothing. Finding 5: "last transition" keeps the
chain's own transition and its cause, "last command" shows the commands (a refused Start,
a refused manual setpoint) beside it.

Each test uses its own channel of the module's supervisor: ch0 the state-following buttons,
ch1 the confirmations, ch3 the last transition and command, ch2 (whose AAA cell the short
recipe's currents exceed) forcing and the viewer.
"""

from __future__ import annotations

from typing import Any

from browserrig import SHORT_RECIPE, Supervisor, login, result_text, screenshot, wait_for


def refused_ahead(page: Any, button: str) -> str:
    """The button's refusal ahead (its tooltip), waiting until the bar says no."""
    page.wait_for_selector(f"#{button}[aria-disabled='true'][title]")
    return str(page.get_attribute(f"#{button}", "title"))


def allowed(page: Any, button: str) -> None:
    page.wait_for_selector(f"#{button}[aria-disabled='false']")
    assert page.get_attribute(f"#{button}", "title") is None


LONG_RECIPE = "nimh-ds2710"
"""A test of hours: still Running however slow the machine is while the page asks (the
short cycle ends by itself after 26 s)."""


def started(bench: Supervisor, channel: str, recipe: str = SHORT_RECIPE.stem) -> str:
    """``channel`` running ``recipe`` (loaded and started over the API); its test id."""
    status, body = bench.call("PUT", f"/api/channels/{channel}/recipe", {"file": recipe})
    assert status == 200, body
    status, body = bench.call("POST", f"/api/channels/{channel}/commands/start")
    assert status == 200, body
    wait_for(f"{channel} running", lambda: bench.tag(f"{channel}.chain.state") == "Running")
    return str(bench.tag(f"{channel}.chain.test_id"))


def shows_state(page: Any, state: str) -> None:
    """Until the channel screen shows ``state`` (its live feed has caught up)."""
    page.wait_for_function(
        "(s) => document.querySelector('#ch-state').textContent === s", arg=state
    )


def answer(page: Any, text: str) -> None:
    """Until the result line holds ``text``: the answer to the command just given, not the
    one before it still shown."""
    page.wait_for_function(
        "(t) => (document.querySelector('#cmd-result').textContent || '').includes(t)",
        arg=text,
    )


def confirm(page: Any, button: str) -> str:
    """Click ``button``; the dialog it opens: its title and text."""
    page.click(f"#{button}")
    page.wait_for_selector("#cmd-confirm[open]")
    return f"{page.text_content('#cmd-confirm-title')} {page.text_content('#cmd-confirm-what')}"


def test_the_chain_buttons_follow_the_state_with_the_reason_as_tooltip(
    page: Any, bench: Supervisor
) -> None:
    login(page, bench, "operator", "#/channel/ch0")
    page.wait_for_selector("#load-form")
    # Idle, nothing loaded: Start says why not; everything that needs a test too.
    assert refused_ahead(page, "cmd-start") == "ch0: no recipe loaded"
    assert refused_ahead(page, "cmd-hold") == "ch0: hold is not allowed while Idle (allowed: start)"
    assert refused_ahead(page, "cmd-abort").startswith("ch0: abort is not allowed while Idle")
    # Enable off in manual: setting a setpoint is allowed, auto is allowed.
    allowed(page, "cmd-manual-current")
    allowed(page, "cmd-load")
    page.fill("#load-recipe", SHORT_RECIPE.stem)
    page.click("#cmd-load")
    assert "loaded" in result_text(page)
    allowed(page, "cmd-start")
    page.click("#cmd-start")
    assert "started" in result_text(page)
    # Running: Start and Resume are refused ahead with the state table's words; Hold,
    # Advance, Stop and Abort are the ones allowed.
    running = "ch0: start is not allowed while Running (allowed: hold, advance, stop, abort)"
    assert refused_ahead(page, "cmd-start") == running
    assert refused_ahead(page, "cmd-resume").startswith("ch0: resume is not allowed while Running")
    assert refused_ahead(page, "cmd-reset").startswith("ch0: reset is not allowed while Running")
    assert refused_ahead(page, "cmd-load").startswith(
        "ch0: cannot load a recipe while Running: a test is under way"
    )
    assert refused_ahead(page, "cmd-manual-current").startswith("channel ch0 is in auto")
    for button in ("cmd-hold", "cmd-advance", "cmd-stop", "cmd-abort"):
        allowed(page, button)
    enabled = page.eval_on_selector_all(
        "#main [data-verb]",
        "bs => bs.filter(b => b.getAttribute('aria-disabled') === 'false').map(b => b.id)",
    )
    assert enabled == ["cmd-hold", "cmd-advance", "cmd-stop", "cmd-abort", "cmd-acknowledge"]
    screenshot(page, "channel-command-bar-running")
    # A tap on Start shows the refusal, worded as a sent one, and sends nothing (force:
    # Playwright, as a user would, takes an aria-disabled button for a disabled one).
    before = bench.tag("ch0.chain.last_command")
    page.click("#cmd-start", force=True)
    assert result_text(page) == f"Refused (409): {running}"
    assert bench.tag("ch0.chain.last_command") == before
    assert bench.tag("ch0.chain.state") == "Running"
    # Held (by the operator): Resume comes back, Hold goes.
    page.click("#cmd-hold")
    assert "Running → Holding" in result_text(page)
    allowed(page, "cmd-resume")
    assert refused_ahead(page, "cmd-hold").startswith("ch0: hold is not allowed while Held")
    screenshot(page, "channel-command-bar-held")


def test_stop_abort_reset_ask_first_naming_the_channel_and_the_test(
    page: Any, bench: Supervisor
) -> None:
    test_id = started(bench, "ch1", LONG_RECIPE)
    login(page, bench, "operator", "#/channel/ch1")
    allowed(page, "cmd-abort")
    # Abort asks, naming ch1 and its test; Cancel sends nothing.
    asked = confirm(page, "cmd-abort")
    assert "Abort on ch1" in asked and test_id in asked and "Running" in asked, asked
    assert page.text_content("#cmd-confirm-yes") == "Abort ch1"
    screenshot(page, "channel-confirm-abort")
    page.click("#cmd-confirm-no")
    assert not page.locator("#cmd-confirm").is_visible()
    assert bench.tag("ch1.chain.state") == "Running"
    assert str(bench.tag("ch1.chain.last_command")).startswith("start by hmi:operator")
    # Confirmed, it is given.
    confirm(page, "cmd-abort")
    page.click("#cmd-confirm-yes")
    answer(page, "Running → Aborting")
    wait_for("ch1 aborted", lambda: bench.tag("ch1.chain.state") == "Aborted")
    # Reset of the finished test asks too, naming it (once the page shows it finished, as
    # an operator would see it: the live state says whether a reset ends a test).
    shows_state(page, "Aborted")
    allowed(page, "cmd-reset")
    asked = confirm(page, "cmd-reset")
    assert "Reset on ch1" in asked and test_id in asked and "Aborted" in asked, asked
    page.click("#cmd-confirm-yes")
    answer(page, "Aborted → Idle")
    # Stop asks as well.
    test_id = started(bench, "ch1", LONG_RECIPE)
    shows_state(page, "Running")
    allowed(page, "cmd-stop")
    asked = confirm(page, "cmd-stop")
    assert "Stop on ch1" in asked and test_id in asked, asked
    page.click("#cmd-confirm-yes")
    wait_for("ch1 stopped", lambda: bench.tag("ch1.chain.state") == "Stopped")
    shows_state(page, "Stopped")
    # Hold does not end a test: it asks nothing.
    page.click("#cmd-hold", force=True)
    answer(page, "Refused (409)")  # Stopped: refused
    assert not page.locator("#cmd-confirm").is_visible()


def test_last_transition_keeps_the_chain_s_cause_and_last_command_shows_the_commands(
    page: Any, bench: Supervisor
) -> None:
    started(bench, "ch3")
    login(page, bench, "operator", "#/channel/ch3")
    page.wait_for_function(
        "() => document.querySelector('#ch-last-transition').textContent"
        ".startsWith('starting step 2 charge (duration elapsed')",
        timeout=20_000,
    )
    transition = str(page.text_content("#ch-last-transition"))
    # A refused Start and a refused manual setpoint (given by another client meanwhile).
    status, body = bench.call("POST", "/api/channels/ch3/commands/start")
    assert status == 409, body
    page.wait_for_function(
        "() => document.querySelector('#ch-last-command').textContent"
        ".startsWith('start by hmi:operator: refused')"
    )
    status, body = bench.call("PUT", "/api/tags/ch3.manual_current", {"value": 500})
    assert status == 409, body
    page.wait_for_function(
        "() => document.querySelector('#ch-last-command').textContent"
        ".startsWith('manual_current 500 A by hmi:operator: refused')"
    )
    # The chain's transition is still the one shown, with its cause.
    assert page.text_content("#ch-last-transition") == transition
    screenshot(page, "channel-last-transition-and-command")


def test_forcing_is_an_engineer_s_and_asks_first(browser: Any, bench: Supervisor) -> None:
    ctx = browser.new_context(viewport={"width": 1366, "height": 768})
    try:
        page = ctx.new_page()
        login(page, bench, "operator", "#/channel/ch2")
        page.wait_for_selector("#main section.commands[data-asked]")
        assert page.locator("#force-form").is_hidden()  # an operator does not force
        ctx.clear_cookies()
        login(page, bench, "engineer", "#/channel/ch2")
        page.wait_for_selector("#force-form:not([hidden])")
        page.fill("#force-tag", "room.temp")
        page.fill("#force-value", "21.5")
        asked = confirm(page, "cmd-force")
        assert "Force on ch2" in asked and "test none" in asked, asked
        assert "force room.temp := 21.5" in asked
        screenshot(page, "channel-confirm-force")
        page.click("#cmd-confirm-no")
        assert bench.tag("room.temp") != 21.5
        confirm(page, "cmd-force")
        page.click("#cmd-confirm-yes")
        assert "room.temp forced" in result_text(page)
        assert bench.tag("room.temp") == 21.5
        page.click("#cmd-unforce")
        assert "room.temp unforced" in result_text(page)
    finally:
        ctx.close()


def test_a_viewer_sees_every_button_refused_ahead_with_the_reason(
    page: Any, bench: Supervisor
) -> None:
    if not bench.login:
        return  # without logins everyone operates
    login(page, bench, "viewer", "#/channel/ch2")
    page.wait_for_selector("#main section.commands[data-asked]")
    reasons = page.eval_on_selector_all(
        "#main [data-bar]:not(#force-form [data-bar])",
        "bs => bs.map(b => [b.getAttribute('aria-disabled'), b.title])",
    )
    assert reasons and all(d == "true" and "viewer may not" in t for d, t in reasons), reasons
    assert page.locator("#force-form").is_hidden()
