"""Issue 33, finding 9: the screens in French and English, and the dates and times of
finding 6. The browser's language chooses (navigator.languages: fr* → French, else English),
a switch in the header changes it and the browser remembers it; every label and message
comes from one catalogue per language (hmi/js/i18n/en.js, fr.js), so a French screen shows
no English text of the catalogue; numbers are written in the locale's format ("3,300 V"),
a value that rounds to zero unsigned; dates and times are 24 h in the locale's order, the
same in the tables and on the trend's time axis (it said "3:14pm")."""

from __future__ import annotations

import re
from collections.abc import Iterator
from datetime import datetime
from typing import Any

import pytest
from browserrig import VIEWPORT, Supervisor, login, supervisor_fixture, wait_for
from test_accessibility import SCREENS, THEN, _busy, _test_id

TABLET = {"width": 800, "height": 1180}


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Supervisor]:
    """The bench of the accessibility checks: a recipe on ch0, an aborted test of ch1, the
    simulated e-stop pressed (an alarm in the table): the most text on each screen."""
    for sup in supervisor_fixture(tmp_path_factory.mktemp("hmi-i18n")):
        _busy(sup)
        yield sup


def _page(
    browser: Any, locale: str, viewport: dict[str, int] = VIEWPORT
) -> tuple[Any, Any, list[str]]:
    """A fresh context in ``locale`` (navigator.languages) and its page, its errors listed."""
    ctx = browser.new_context(viewport=viewport, locale=locale)
    ctx.set_default_timeout(15_000)
    page = ctx.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    return ctx, page, errors


@pytest.fixture
def french(browser: Any) -> Iterator[Any]:
    ctx, page, errors = _page(browser, "fr-FR")
    try:
        yield page
    finally:
        ctx.close()
    assert not errors, errors


@pytest.fixture
def english(browser: Any) -> Iterator[Any]:
    ctx, page, errors = _page(browser, "en-US")
    try:
        yield page
    finally:
        ctx.close()
    assert not errors, errors


def _catalogues(page: Any) -> tuple[dict[str, str], dict[str, str]]:
    cats = page.evaluate("() => window.hmi.i18n.catalogues()")
    return cats["en"], cats["fr"]


def test_a_french_browser_shows_the_screens_in_french(french: Any, bench: Supervisor) -> None:
    login(french, bench, "operator")
    french.wait_for_selector("#tile-ch0")
    assert french.evaluate("() => document.documentElement.lang") == "fr"
    assert french.text_content("[data-nav='overview']") == "Vue d'ensemble"
    labels = french.eval_on_selector_all(
        "#tile-ch0 .nums > div > small", "els => els.map(e => e.textContent)"
    )
    assert labels == ["tension", "courant", "température", "charge"]
    assert french.text_content("#estop-press") == "ARRÊT D'URGENCE toutes voies"
    # The switch names the other language, in that language.
    assert french.text_content("#lang") == "EN"
    assert french.get_attribute("#lang", "title") == "English"
    assert french.title().endswith("— superviseur de banc")


def test_an_english_browser_switches_to_french_and_the_choice_is_remembered(
    english: Any, bench: Supervisor
) -> None:
    login(english, bench, "operator", "#/channel/ch0")
    english.wait_for_selector("#cmd-start")
    assert english.text_content("#cmd-start") == "Start"
    assert english.text_content("#lang") == "FR"
    english.click("#lang")
    # The screen is rendered again in French, without a reload.
    english.wait_for_function(
        "() => document.querySelector('#cmd-start')?.textContent === 'Démarrer'"
    )
    assert english.text_content("[data-nav='alarms'] [data-i18n]") == "Alarmes"
    assert english.evaluate("() => document.documentElement.lang") == "fr"
    english.reload()
    english.wait_for_selector("#cmd-start")
    assert english.text_content("#cmd-start") == "Démarrer"
    english.click("#lang")
    english.wait_for_function("() => document.querySelector('#cmd-start')?.textContent === 'Start'")


def test_both_catalogues_have_the_same_keys_and_placeholders(
    english: Any, bench: Supervisor
) -> None:
    login(english, bench, "operator")
    en, fr = _catalogues(english)
    assert set(en) == set(fr), set(en) ^ set(fr)
    placeholders = re.compile(r"\{(\w+)\}")
    for key, text in en.items():
        assert set(placeholders.findall(text)) == set(placeholders.findall(fr[key])), key


# Every visible text node, and the texts a screen reader or a tooltip gives; not what the
# page marks translate="no" (a recipe's step names, the supervisor's field names).
VISIBLE_TEXTS = """() => {
  const out = [];
  const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  for (let n = walker.nextNode(); n; n = walker.nextNode()) {
    const el = n.parentElement;
    const text = n.textContent.trim();
    const skip = 'script, style, datalist, [translate="no"]';
    if (text && el && el.checkVisibility() && !el.closest(skip)) out.push(text);
  }
  for (const el of document.querySelectorAll('[title], [aria-label], [placeholder]')) {
    if (!el.checkVisibility()) continue;
    for (const a of ['title', 'aria-label', 'placeholder'])
      if (el.getAttribute(a)) out.push(el.getAttribute(a).trim());
  }
  return out;
}"""

MIN_LITERAL_LETTERS = 4  # a text with placeholders is matched when it has this many letters


def _english_only(en: dict[str, str], fr: dict[str, str]) -> list[tuple[str, re.Pattern[str]]]:
    """The English texts that are not French (a word that is the same in both, "message",
    "cycle", is not English only), each as a pattern: a placeholder matches anything. Not
    the alarms' texts by code: without its code an alarm shows the supervisor's message."""
    french_texts = set(fr.values())
    out = []
    for key, text in en.items():
        # (an alarm's text without a code is the supervisor's, shown as it came)
        if text == fr[key] or text in french_texts or key.startswith("alarm."):
            continue
        literal = re.sub(r"\{\w+\}", "", text)
        if "{" in text and len(re.findall(r"[A-Za-z]", literal)) < MIN_LITERAL_LETTERS:
            continue
        parts = re.split(r"\{\w+\}", text)
        out.append((key, re.compile("^" + ".+?".join(re.escape(p) for p in parts) + "$", re.S)))
    return out


def _open(page: Any, bench: Supervisor, screen: str) -> None:
    where, ready = SCREENS[screen]
    page.goto(f"{bench.base}/{where.format(test=_test_id(bench))}")
    page.wait_for_selector(ready)
    if screen in THEN:
        button, shown = THEN[screen]
        page.click(button)
        page.wait_for_selector(shown, state="visible")
    page.wait_for_load_state("networkidle")


def test_no_french_screen_shows_an_english_text_of_the_catalogue(
    french: Any, bench: Supervisor
) -> None:
    # The login screen first, then every screen and dialog of the accessibility checks.
    french.goto(f"{bench.base}/#/")
    french.wait_for_selector("#login-form")
    en, fr = _catalogues(french)
    patterns = _english_only(en, fr)
    assert len(patterns) > 200, len(patterns)
    found: dict[str, set[str]] = {}

    def check(screen: str) -> None:
        for text in french.evaluate(VISIBLE_TEXTS):
            for key, pattern in patterns:
                if pattern.match(text):
                    found.setdefault(screen, set()).add(f"{text!r} ({key})")

    check("login")
    login(french, bench, "engineer")
    for screen in SCREENS:
        _open(french, bench, screen)
        check(screen)
    # The command bar's confirmation (Reset of ch1's finished test), never confirmed.
    french.goto(f"{bench.base}/#/channel/ch1")
    french.wait_for_selector("#cmd-reset")
    wait_for("ch1's commands asked", lambda: french.get_attribute("section.commands", "data-asked"))
    french.click("#cmd-reset")
    french.wait_for_selector("#cmd-confirm", state="visible")
    check("reset-confirm")
    assert not found, found


def test_numbers_are_written_in_the_locale_and_zero_is_unsigned(
    french: Any, bench: Supervisor
) -> None:
    login(french, bench, "operator", "#/channel/ch0")
    french.wait_for_selector("#cmd-start")
    wait_for("a voltage", lambda: re.search(r"\d", french.text_content(".values .big") or ""))
    # "3,300 V": a comma, three decimals, the unit after a space.
    assert re.fullmatch(r"-?\d+,\d{3} V", french.text_content(".values .big") or ""), (
        french.text_content(".values .big")
    )
    fmt = "([v, d]) => window.hmi.i18n.fmtNumber(v, d)"
    assert french.evaluate(fmt, [1.5, 1]) == "1,5"
    assert french.evaluate(fmt, [-0.0004, 3]) == "0,000"
    assert french.evaluate(fmt, [-0.0, 3]) == "0,000"
    assert french.evaluate(fmt, [-0.2, 3]) == "-0,200"
    assert french.evaluate(fmt, [1234.5, 1]) == "1234,5"
    french.click("#lang")
    french.wait_for_function("() => window.hmi.i18n.lang() === 'en'")
    assert french.evaluate(fmt, [1.5, 1]) == "1.5"
    assert french.evaluate(fmt, [-0.0004, 3]) == "0.000"


CLOCK = re.compile(r"^\d{2}:\d{2}(:\d{2})?$")


def _axis_and_table_times(page: Any, bench: Supervisor) -> tuple[str, list[str], str]:
    """The time the trend's legend gives under the cursor and its time axis's labels (ch0),
    and the Alarms table's "since" date and time of the e-stop alarm."""
    page.goto(f"{bench.base}/#/channel/ch0")
    page.wait_for_selector("#trend .uplot")
    wait_for("points on the trend", lambda: int(page.get_attribute("#trend", "data-points") or 0))
    # The cursor on the plot, as an operator reads a time.
    page.hover("#trend .u-over")
    legend = page.text_content("#trend .u-legend .u-series .u-value") or ""
    ticks = page.evaluate(
        "() => (hmi.screen.trendChart?.()?.axes[0]._values || []).filter(Boolean)"
    )
    page.goto(f"{bench.base}/#/alarms")
    page.wait_for_selector("#alarm-table tr[data-alarm='estop']")
    since = page.text_content("#alarm-table tr[data-alarm='estop'] .alarm-state .muted") or ""
    return legend, ticks, since


@pytest.mark.parametrize(
    ("locale", "date"),
    [
        # day/month in French, month/day where the browser is American; 24 h in both
        ("fr-FR", r"(\d{2})/(\d{2})/\d{4} (\d{2}:\d{2}:\d{2})"),
        ("en-US", r"(\d{2})/(\d{2})/\d{4}, (\d{2}:\d{2}:\d{2})"),
    ],
)
def test_the_trend_axis_and_the_tables_write_times_alike(
    browser: Any, bench: Supervisor, locale: str, date: str
) -> None:
    ctx, page, errors = _page(browser, locale)
    try:
        login(page, bench, "operator")
        legend, ticks, since = _axis_and_table_times(page, bench)
    finally:
        ctx.close()
    assert not errors, errors
    # The time under the cursor as the table writes a time: the same pattern, 24 h.
    assert re.fullmatch(date, legend), legend
    m = re.search(date, since)
    assert m, since
    # (the alarm was raised today: its day and month, in the locale's order)
    today = datetime.now()
    order = (today.day, today.month) if locale.startswith("fr") else (today.month, today.day)
    assert (int(m.group(1)), int(m.group(2))) == order, since
    # The axis: hours and minutes (and seconds), 24 h, never "3:14pm".
    assert ticks and all(CLOCK.match(t.split("\n")[-1]) for t in ticks), ticks
    assert not any(re.search(r"[ap]m", t, re.I) for t in ticks), ticks


def test_an_alarm_with_a_code_reads_in_french_with_its_figures(
    french: Any, bench: Supervisor
) -> None:
    # The e-stop pressed (the module's bench): its alarm carries a code and params.
    status, body = bench.call("GET", "/api/alarms")
    assert status == 200, body
    estop = next(a for a in body["active"] if a["id"] == "estop")
    assert estop.get("code") == "estop.pressed", estop
    login(french, bench, "operator", "#/alarms")
    cell = "#alarm-table tr[data-alarm='estop'] td.wrap"
    french.wait_for_selector(cell)
    text = french.text_content(cell) or ""
    assert text.startswith("Arrêt d'urgence enfoncé (circuit ouvert)"), text
    assert estop["message"] not in text  # the English words are not there
    # The tags behind it (the detail) stay as they are, marked as not to translate.
    assert french.get_attribute(f"{cell} small", "translate") == "no"
    # The journal's entry of that activation carries the same code: French too.
    (activated,) = [
        e for e in body["history"] if e["alarm"] == "estop" and e["transition"] == "activated"
    ][-1:]
    assert activated["code"] == "estop.pressed", activated
    row = "#alarm-history-table tbody tr"
    french.wait_for_selector(row)
    journal = french.locator(row, has_text="estop").filter(has_text="Arrêt d'urgence enfoncé")
    assert journal.count() >= 1, french.text_content("#alarm-history-table")
    assert estop["message"] not in (french.text_content("#alarm-history-table") or "")
