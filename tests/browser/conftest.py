"""Fixtures of the HMI's browser tests (browserrig.py): one supervisor and one Chromium per
module, a fresh browser context (cookies, storage) per test.

Playwright's sync API runs its own event loop in this thread while the browser is open: the
browser is module-scoped so that it is closed before the asyncio tests of other modules
run, and the project's async autouse check for leftover tasks is replaced here by a no-op
(these tests start no asyncio task in this process; the supervisor is another process)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from browserrig import (
    CHROMIUM,
    CHROMIUM_ARGS,
    ROOT,
    VIEWPORT,
    Supervisor,
    login,
    supervisor_fixture,
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    here = Path(__file__).parent
    for item in items:
        if here in Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.browser)


@pytest.fixture(autouse=True)
def _no_leftover_tasks() -> None:
    """No asyncio here (see the module's docstring)."""


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is missing: `make chromium` installs Debian's chromium")
    if not (ROOT / "hmi" / "node_modules" / "uplot" / "dist" / "uPlot.iife.min.js").exists():
        pytest.fail("hmi/node_modules/uplot is missing: `make hmi` installs it (npm ci)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Supervisor]:
    """The simulated bench of io_maps/sim.yaml, run by a real ``supervisor run``."""
    yield from supervisor_fixture(tmp_path_factory.mktemp("hmi-bench"))


@pytest.fixture
def context(browser: Any) -> Iterator[Any]:
    ctx = browser.new_context(viewport=VIEWPORT, accept_downloads=True)
    ctx.set_default_timeout(15_000)
    try:
        yield ctx
    finally:
        ctx.close()


@pytest.fixture
def page(context: Any, request: pytest.FixtureRequest) -> Iterator[Any]:
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    # Anything the Content-Security-Policy blocked (issue 27): a script, a style, the
    # WebSocket — the screens must work under it. A test whose page is *meant* to be
    # refused by a directive (another origin framing the HMI) names it with
    # ``@pytest.mark.csp_refusal("frame-ancestors")``: Chromium reports that refusal on
    # the console whenever the framed answer arrives, before or after the test ends.
    marker = request.node.get_closest_marker("csp_refusal")
    expected = tuple(marker.args) if marker else ()

    def on_console(msg: Any) -> None:
        text = msg.text
        if "Content Security Policy" in text and not any(
            f'directive: "{d}' in text for d in expected
        ):
            errors.append(text)

    pg.on("console", on_console)
    yield pg
    assert not errors, f"the page raised: {errors}"


@pytest.fixture
def as_operator(page: Any, bench: Supervisor) -> Any:
    login(page, bench, "operator")
    return page
