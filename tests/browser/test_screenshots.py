"""Issue 33, "What to build": screenshots of every screen at both sizes in both languages,
in tests/artifacts/screens/ as SCREEN-LANG-WxH.png (git-ignored): Login, Overview and its
e-stop confirmation, a channel and its command confirmation, Alarms with an alarm, Recipes
(the list, a recipe, its dry run), Tests (the list, a test), Diagnostics, the Alarms
screen's journal and performance panel, Audit (issue 34). Each page must have
rendered: no error on the page, its title set for the screen, its root not empty; the
French ones are also checked by axe-core (the English ones are, by test_accessibility.py):
no serious or critical violation.

The bench is the accessibility checks' (a recipe on ch0, an aborted test of ch1, the
simulated e-stop pressed). One browser context per language and size, logged in once, the
screens opened by their hash: four logins for the 48 screenshots."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from axe import audit, blocking
from browserrig import SCREENS as SCREENS_DIR
from browserrig import SHORT_RECIPE, VIEWPORT, Supervisor, login, supervisor_fixture, wait_for
from test_accessibility import _busy, _test_id

SIZES = {"1366x768": VIEWPORT, "800x1180": {"width": 800, "height": 1180}}
LOCALES = {"en": "en-GB", "fr": "fr-FR"}
TITLE_END = {"en": "— bench supervisor", "fr": "— superviseur de banc"}

# Each shot: its hash, what shows it is ready, then (optionally) a button to click and
# what shows the result (a dialog open: never confirmed, the bench stays as it is).
SHOTS: dict[str, tuple[str, str, tuple[str, str] | None]] = {
    "overview": ("#/", "#tile-ch4", None),
    "estop-confirm": ("#/", "#estop-press", ("#estop-press", "#estop-confirm")),
    "channel": ("#/channel/ch0", "#chain li[data-step]", None),
    "reset-confirm": (
        "#/channel/ch1",
        "section.commands[data-asked]",
        ("#cmd-reset", "#cmd-confirm"),
    ),
    "alarms": ("#/alarms", "#alarm-table tr[data-alarm='estop']", None),
    "recipes": ("#/recipes", "#recipe-items", None),
    "recipe": (f"#/recipes/{SHORT_RECIPE.stem}", "#recipe-text", None),
    "recipe-dry-run": (
        f"#/recipes/{SHORT_RECIPE.stem}",
        "#recipe-text",
        ("#recipe-dryrun", "#preview:not([hidden]) #dry-cycles .uplot"),
    ),
    "tests": ("#/tests", "#test-table a", None),
    "test": ("#/tests/{test}", "#test-files a", None),
    "diagnostics": ("#/diagnostics", "#diag-devices-table", None),
    # issue 34: the Alarms screen's journal and performance panel; the audit trail.
    "alarm-journal": ("#/alarms", "#journal-table tr[data-alarm-id='estop']", None),
    "audit": ("#/audit", "#audit-table tbody tr", None),
}


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Supervisor]:
    for sup in supervisor_fixture(tmp_path_factory.mktemp("hmi-shots")):
        _busy(sup)
        yield sup


def _shoot(page: Any, name: str, full_page: bool = True) -> None:
    """The whole page, or (a dialog open: its backdrop covers the window only) the window."""
    SCREENS_DIR.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SCREENS_DIR / f"{name}.png"), full_page=full_page)


def _rendered(page: Any, lang: str, shot: str) -> None:
    title = page.title()
    assert title.endswith(TITLE_END[lang]) and not title.startswith(TITLE_END[lang]), (shot, title)
    assert page.evaluate("() => document.documentElement.lang") == lang, shot
    assert page.evaluate("() => document.querySelector('#main').children.length") > 0, shot


@pytest.mark.parametrize("size", list(SIZES))
@pytest.mark.parametrize("lang", list(LOCALES))
def test_every_screen_renders_and_is_saved_as_a_screenshot(
    browser: Any, bench: Supervisor, lang: str, size: str
) -> None:
    ctx = browser.new_context(viewport=SIZES[size], locale=LOCALES[lang])
    ctx.set_default_timeout(15_000)
    page = ctx.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        page.goto(f"{bench.base}/#/")
        page.wait_for_selector("#login-form")
        _rendered(page, lang, "login")
        _shoot(page, f"login-{lang}-{size}")
        login(page, bench, "engineer")
        test_id = _test_id(bench)
        for shot, (where, ready, then) in SHOTS.items():
            # By the hash, as an operator goes: the screen is rendered anew (a dialog of the
            # previous one is gone with it); the same hash again keeps the screen.
            page.evaluate("(h) => { location.hash = h; }", where.format(test=test_id))
            page.wait_for_selector(ready)
            if then:
                button, shown = then
                page.click(button)
                page.wait_for_selector(shown, state="visible")
            wait_for(f"{shot} titled", lambda: page.title().endswith(TITLE_END[lang]))
            page.wait_for_load_state("networkidle")
            _rendered(page, lang, shot)
            _shoot(page, f"{shot}-{lang}-{size}", full_page=not shot.endswith("-confirm"))
            if lang != "en":
                bad = blocking(audit(page))
                assert not bad, (shot, [str(v) for v in bad])
    finally:
        ctx.close()
    assert not errors, errors
