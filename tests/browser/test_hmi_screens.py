"""Issue 12 "Must show", in Debian's Chromium against a real ``supervisor run`` of the
simulated bench (io_maps/sim.yaml on free ports). Every screen is saved as a screenshot
under tests/artifacts/screens/; the update latency and the page's weight are measured
here, printed (``-s``) and written to tests/artifacts/hmi-figures.json, never asserted.

The simulated bench runs on the wall clock (it is a real supervisor process, the page a
real browser): these tests wait for what they expect with timeouts, and the recipe they
run lasts seconds (tests/browser/short-cycle.yaml). They share one supervisor and use a
different channel each where they can: ch0 runs the recipe, ch1 the stale command, ch2 the
viewer, ch3 the latency; the e-stop (the whole bench) comes last."""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from browserrig import (
    ARTIFACTS,
    SHORT_RECIPE,
    USERS,
    VIEWPORT,
    Supervisor,
    free_port,
    hmi_options,
    login,
    result_text,
    save_figures,
    screenshot,
    start_supervisor,
    stop_supervisor,
    supervisor_fixture,
    wait_for,
)

LATENCY_CHANGES = 60
TABLET = {"width": 800, "height": 1180}


def test_an_operator_logs_in_and_sees_the_bench_mimic_and_a_tile_per_channel(
    browser: Any, bench: Supervisor
) -> None:
    # A fresh context: nothing cached, so what is transferred is the first load's weight.
    ctx = browser.new_context(viewport=VIEWPORT)
    page = ctx.new_page()
    transferred: list[tuple[str, int]] = []

    def finished(req: Any) -> None:
        sizes = req.sizes()
        transferred.append((req.url, sizes["responseBodySize"] + sizes["responseHeadersSize"]))

    page.on("requestfinished", finished)
    problems: list[str] = []
    page.on("pageerror", lambda exc: problems.append(f"page error: {exc}"))
    page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}"))
    page.on("response", lambda r: r.status >= 400 and problems.append(f"{r.status} {r.url}"))
    try:
        page.goto(f"{bench.base}/")
        try:
            if bench.login:
                page.wait_for_function("() => location.hash.startsWith('#/login')")
                page.wait_for_selector("#login-form")
                screenshot(page, "login")
                page.fill("#login-user", "operator")
                page.fill("#login-password", USERS["operator"])
                page.click("#login-submit")
            page.wait_for_selector("#top:not([hidden])")
        except Exception:
            print("\n".join(problems))
            raise
        page.wait_for_selector("#tile-ch4")
        wait_for("live values", lambda: page.text_content("#tile-ch0 .big") not in ("", "—"))
        page.wait_for_load_state("networkidle")
        assert page.text_content("#mimic-estop") and "closed" in page.text_content("#mimic-estop")
        # The supply's and the BMS's lines, as /api/bench describes them (their kinds').
        supply_box, bms_box = page.text_content("#mimic-supply"), page.text_content("#mimic-bms")
        assert all(w in supply_box for w in ("output", "voltage", "link")), supply_box
        assert all(w in bms_box for w in ("link", "pack", "cell min", "temp max")), bms_box
        for ch in ("ch0", "ch1", "ch2", "ch3", "ch4"):
            tile = page.locator(f"#tile-{ch}")
            assert tile.is_visible()
            assert "Idle" in tile.text_content() or "Complete" in tile.text_content()
        # Grey when normal: a bench at rest shows no fault colour anywhere. A Chadèche board
        # has no thermometer: n/a, not a bad value.
        temperature = page.locator('#tile-ch0 [data-tag="ch0.temperature"]')
        assert temperature.text_content() == "n/a"
        assert page.locator(".tiles .q-bad, .tiles .abn, .mimic .q-bad, .mimic .abn").count() == 0
        screenshot(page, "overview")
        page.set_viewport_size(TABLET)
        screenshot(page, "overview-tablet")
    finally:
        ctx.close()
    total_b = sum(b for _, b in transferred)
    biggest = sorted(transferred, key=lambda x: -x[1])[:5]
    print(
        f"page weight, first load (login + overview): {total_b / 1024:.1f} KB"
        f" in {len(transferred)} requests"
    )
    for url, b in biggest:
        print(f"  {b / 1024:7.1f} KB  {url.removeprefix(bench.base)}")
    save_figures(
        {
            "page_weight_kb": round(total_b / 1024, 1),
            "page_requests": len(transferred),
            "page_weight_largest": [
                {"url": u.removeprefix(bench.base), "kb": round(b / 1024, 1)} for u, b in biggest
            ],
        }
    )


def test_the_screens_are_reachable_with_the_keyboard_and_show_the_focus(
    as_operator: Any, bench: Supervisor
) -> None:
    page = as_operator
    page.wait_for_selector("#tile-ch0")
    page.locator("body").focus()
    focused = ""
    for _ in range(40):  # skip link, screens, header controls, then the tiles
        page.keyboard.press("Tab")
        focused = page.evaluate("() => document.activeElement.id")
        if focused == "tile-ch0":
            break
    assert focused == "tile-ch0"
    outline = page.evaluate("() => getComputedStyle(document.activeElement).outlineStyle")
    assert outline not in ("", "none"), outline
    page.keyboard.press("Enter")
    page.wait_for_selector("#load-form")
    assert page.url.endswith("#/channel/ch0")


def test_an_operator_loads_and_starts_a_recipe_and_sees_the_step_advance_and_the_trend_grow(
    as_operator: Any, bench: Supervisor
) -> None:
    page = as_operator
    page.click("#tile-ch0")
    page.wait_for_selector("#load-form")
    page.fill("#load-recipe", SHORT_RECIPE.stem)  # by name, in the recipe folder
    page.click("#cmd-load")
    assert "loaded" in result_text(page)
    # The chain drawn from the compiled program, not from the YAML.
    page.wait_for_selector("#chain li[data-step='settle']")
    steps = page.eval_on_selector_all("#chain li[data-step]", "els => els.map(e => e.dataset.step)")
    assert steps == ["settle", "charge", "pause", "discharge"]
    page.click("#cmd-start")
    assert "started" in result_text(page)
    page.wait_for_selector("#chain li.active[data-step='settle']")
    points_before = int(page.get_attribute("#trend", "data-points") or 0)
    # The step advances by itself (3 s rest), with its cause shown.
    page.wait_for_selector("#chain li.active[data-step='charge']", timeout=20_000)
    assert page.text_content("#ch-step") == "charge"
    assert "duration elapsed" in (page.text_content("#ch-last-transition") or "")
    wait_for(
        "the trend to grow",
        lambda: int(page.get_attribute("#trend", "data-points") or 0) > points_before + 3,
    )
    screenshot(page, "channel")
    page.set_viewport_size(TABLET)
    screenshot(page, "channel-tablet")


def test_a_command_from_a_stale_page_is_refused_with_the_reason(
    page: Any, bench: Supervisor
) -> None:
    held = {"paused": False}

    def relay(ws: Any) -> None:
        server = ws.connect_to_server()
        server.on_message(lambda msg: None if held["paused"] else ws.send(msg))

    # Between the supervisor and the page, a relay this test can hold (before the page
    # opens its WebSocket).
    page.route_web_socket("**/api/ws", relay)
    login(page, bench, "operator", "#/channel/ch1")
    page.wait_for_selector("#load-form")
    page.fill("#load-recipe", SHORT_RECIPE.stem)  # by name, in the recipe folder
    page.click("#cmd-load")
    assert "loaded" in result_text(page)
    page.click("#cmd-start")
    assert "started" in result_text(page)
    page.wait_for_function("() => document.querySelector('#ch-state').textContent === 'Running'")
    # The command bar's answer for Running is in (Start refused ahead, Hold accepted): asked
    # after the start, it must not land after the abort below, or the page would not be
    # stale (it would refuse Hold itself, ahead).
    page.wait_for_function(
        "() => document.querySelector('#cmd-start').getAttribute('aria-disabled') === 'true'"
        " && document.querySelector('#cmd-hold').getAttribute('aria-disabled') !== 'true'"
    )
    # The page stops hearing from the supervisor; meanwhile someone else aborts the test.
    held["paused"] = True
    status, body = bench.call("POST", "/api/channels/ch1/commands/abort")
    assert status == 200, body
    wait_for("ch1 aborted", lambda: bench.tag("ch1.chain.state") == "Aborted")
    assert page.text_content("#ch-state") == "Running"  # what the stale page still shows
    page.click("#cmd-hold")
    text = result_text(page)
    assert text.startswith("Refused (409)"), text
    assert "hold is not allowed while Aborted" in text
    screenshot(page, "channel-stale-command-refused")


def test_a_viewer_is_refused_a_command_and_sees_why(page: Any, bench: Supervisor) -> None:
    if not bench.login:
        pytest.skip("this supervisor has no login (hmi.login): everyone operates")
    login(page, bench, "viewer", "#/channel/ch2")
    page.wait_for_selector("#cmd-start")
    assert "(viewer)" in (page.text_content("#who") or "")
    page.click("#cmd-start", force=True)  # refused ahead (aria-disabled): the reason shows
    text = result_text(page)
    assert text.startswith("Refused (403)"), text
    assert "viewer" in text
    assert bench.tag("ch2.chain.state") == "Idle"
    screenshot(page, "channel-viewer-refused")


def test_a_broken_recipe_upload_shows_the_error_at_its_line_and_saves_nothing(
    page: Any, bench: Supervisor, tmp_path: Path
) -> None:
    broken = (
        SHORT_RECIPE.read_text(encoding="utf-8")
        .replace("recipe: browser-short-cycle", "recipe: browser-broken")
        .replace("duration: 4 s}", "duraton: 4 s}", 1)
    )
    bad_line = next(i for i, line in enumerate(broken.splitlines(), 1) if "duraton" in line)
    path = tmp_path / "browser-broken.yaml"
    path.write_text(broken, encoding="utf-8")
    login(page, bench, "engineer", "#/recipes")
    page.wait_for_selector("#recipe-items")
    page.set_input_files("#recipe-file", str(path))
    page.wait_for_selector(f"#gutter .err[data-line='{bad_line}']")
    errors = page.locator("#recipe-errors li").all_text_contents()
    assert any(e.startswith(f"line {bad_line}") and "duraton" in e for e in errors), errors
    page.click("#recipe-save")
    page.wait_for_function(
        "() => document.querySelector('#recipe-result').textContent.includes('not saved')"
    )
    status, listing = bench.call("GET", "/api/recipes")
    assert status == 200, listing
    assert "browser-broken" not in [r["name"] for r in listing["recipes"]]
    screenshot(page, "recipes-broken-upload")
    # The good one: valid, and its dry run previews timeline and capacity per cycle.
    page.fill("#recipe-text", SHORT_RECIPE.read_text(encoding="utf-8"))
    page.click("#recipe-validate")
    page.wait_for_function(
        "() => document.querySelector('#recipe-result').textContent.startsWith('valid')"
    )
    page.click("#recipe-dryrun")
    page.wait_for_selector("#preview:not([hidden]) #dry-cycles .uplot")
    assert "2 cycle(s)" in (page.text_content("#dry-summary") or "")
    screenshot(page, "recipes-dry-run")


def test_a_result_csv_is_downloaded_from_the_tests_screen(
    as_operator: Any, bench: Supervisor
) -> None:
    page = as_operator
    # ch0's test (started above) lasts 26 s.
    wait_for("ch0's test to complete", lambda: bench.tag("ch0.chain.state") == "Complete", 60)
    test_id = bench.tag("ch0.chain.test_id")
    page.goto(f"{bench.base}/#/tests/{test_id}")
    link = page.locator("#test-files a", has_text=".bdf.csv")
    link.wait_for()
    with page.expect_download() as info:
        link.click()
    download = info.value
    target = ARTIFACTS / "downloads" / download.suggested_filename
    target.parent.mkdir(parents=True, exist_ok=True)
    download.save_as(str(target))
    print(f"downloaded: {target}")
    header = target.read_text(encoding="utf-8").splitlines()[0]
    assert "Voltage" in header or "voltage" in header.lower(), header
    page.wait_for_selector("#test-capacity .uplot")
    screenshot(page, "tests")


def test_the_update_latency_from_a_tag_change_to_the_page(
    as_operator: Any, bench: Supervisor
) -> None:
    """Figures only: p50/p99 from an operator's write of ch3.manual_current (sent by this
    test; timestamped by the supervisor's scan as source_time) to the page showing it."""
    page = as_operator
    page.goto(f"{bench.base}/#/channel/ch3")
    page.wait_for_selector("#ch-manual-current")
    page.evaluate(
        """() => {
        window.__shown = [];
        const el = document.querySelector('#ch-manual-current');
        new MutationObserver(() => window.__shown.push({
            text: el.textContent, at_ms: performance.timeOrigin + performance.now(),
            source_time: Number(el.dataset.sourceTime || 0)})
        ).observe(el, {childList: true, characterData: true, subtree: true});
    }"""
    )
    from_write: list[float] = []
    from_source: list[float] = []
    for k in range(LATENCY_CHANGES):
        value = round(0.1 + 0.001 * (k + 1), 3)
        sent = time.time()
        status, body = bench.call("PUT", "/api/tags/ch3.manual_current", {"value": value})
        assert status == 200, body
        text = f"{value:.3f} A"
        page.wait_for_function(
            "t => window.__shown.some(s => s.text === t)", arg=text, timeout=10_000
        )
        shown = page.evaluate("t => window.__shown.find(s => s.text === t)", text)
        from_write.append(shown["at_ms"] / 1000 - sent)
        if shown["source_time"]:
            from_source.append(shown["at_ms"] / 1000 - shown["source_time"])

    def pct(xs: list[float], q: float) -> float:
        xs = sorted(xs)
        return xs[min(len(xs) - 1, round(q * (len(xs) - 1)))] * 1000

    figures = {
        "latency_changes": LATENCY_CHANGES,
        "latency_write_to_page_ms": {
            "p50": round(pct(from_write, 0.5), 1),
            "p99": round(pct(from_write, 0.99), 1),
            "mean": round(statistics.fmean(from_write) * 1000, 1),
        },
    }
    if from_source:
        figures["latency_source_time_to_page_ms"] = {
            "p50": round(pct(from_source, 0.5), 1),
            "p99": round(pct(from_source, 0.99), 1),
        }
    w = figures["latency_write_to_page_ms"]
    print(f"update latency over {LATENCY_CHANGES} changes of ch3.manual_current:")
    print(f"  write sent -> page shows it: p50 {w['p50']} ms, p99 {w['p99']} ms")
    if from_source:
        src = figures["latency_source_time_to_page_ms"]
        print(f"  server source_time -> page shows it: p50 {src['p50']} ms, p99 {src['p99']} ms")
    save_figures(figures)


def test_the_diagnostics_screen_shows_devices_scan_and_publishers(
    as_operator: Any, bench: Supervisor
) -> None:
    page = as_operator
    page.goto(f"{bench.base}/#/diagnostics")
    page.wait_for_selector("#diag-live")
    assert "scan.overruns" in (page.text_content("#diag-live") or "")
    page.wait_for_selector("#diag-devices-table")
    for dev in ("adam", "ea", "bms", "chadeche"):
        assert dev in (page.text_content("#diag-devices-table") or "")
    screenshot(page, "diagnostics")


def test_a_channel_driven_in_manual_shows_what_it_does_and_its_chain_s_state_apart(
    as_operator: Any, bench: Supervisor
) -> None:
    """Issue 26, finding 3: ch4 in Manual at 20 A with its contactor closed was shown
    "Idle manual" (its step chain's state) on its tile and its channel screen."""
    page = as_operator
    for tag, value in (("ch4.manual_current", 20.0), ("ch4.enable", True)):
        status, body = bench.call("PUT", f"/api/tags/{tag}", {"value": value})
        assert status == 200, body
    try:
        wait_for("ch4 charging", lambda: bench.tag("ch4.state") == "charging")
        wait_for("the contactor closed", lambda: bench.tag("contactor.fb") is True)
        amps = bench.tag("ch4.current_cmd")
        assert amps > 0
        label = f"charging {amps:.3f} A, manual"
        page.wait_for_function(
            "t => document.querySelector('#tile-ch4 .activity').textContent === t", arg=label
        )
        assert page.text_content("#tile-ch4 .chain-state") == "chain: Idle"
        screenshot(page, "overview-manual-charging")
        page.click("#tile-ch4")
        page.wait_for_selector("#ch-activity")
        page.wait_for_function(
            "t => document.querySelector('#ch-activity').textContent === t", arg=label
        )
        assert page.text_content("#ch-state") == "Idle"
        assert page.text_content(".channel-head .chain-state") == "chain: Idle"
        screenshot(page, "channel-manual-charging")
    finally:
        bench.call("PUT", "/api/tags/ch4.enable", {"value": False})
        bench.call("PUT", "/api/tags/ch4.manual_current", {"value": 0.0})
    wait_for("ch4 idle", lambda: bench.tag("ch4.state") == "idle")
    page.wait_for_function(
        "() => document.querySelector('#ch-activity').textContent === 'idle, manual'"
    )


def test_the_simulated_estop_shows_the_alarm_which_is_acknowledged_then_reset(
    as_operator: Any, bench: Supervisor
) -> None:
    page = as_operator
    page.goto(f"{bench.base}/#/alarms")
    page.wait_for_selector("#alarm-active")
    page.check("#sound")  # the optional audible alert, switched on
    status, body = bench.call("PUT", "/api/sim/estop", {"pressed": True})
    assert status == 200, body
    row = page.locator("#alarm-table tr[data-alarm='estop']")
    row.wait_for()
    assert "FIRST OUT" in row.text_content()
    assert "unacknowledged" in row.text_content()
    assert page.locator("#banner").is_visible()
    played = page.evaluate("() => window.hmi.sound.played.map(p => p.kind)")
    assert "alarm" in played, played
    screenshot(page, "alarms-estop")
    page.goto(f"{bench.base}/#/")
    page.wait_for_function(
        "() => document.querySelector('#mimic-estop').textContent.includes('PRESSED')"
    )
    screenshot(page, "overview-estop")
    page.goto(f"{bench.base}/#/alarms")
    row.wait_for()
    # A reset is refused while the cause is present, with the reason.
    row.locator("button[data-act='reset']").click()
    page.wait_for_selector("#alarm-result.refused")
    assert "Refused" in (page.text_content("#alarm-result") or "")
    row.locator("button[data-act='acknowledge']").click()
    page.wait_for_function(
        "() => { const r = document.querySelector(\"#alarm-table tr[data-alarm='estop']\");"
        " const t = r ? r.textContent : '';"
        " return t.includes('acknowledged') && !t.includes('unacknowledged'); }"
    )
    status, body = bench.call("PUT", "/api/sim/estop", {"pressed": False})
    assert status == 200, body
    wait_for("the e-stop circuit closed", lambda: bench.tag("estop.ok") is True)
    page.locator("#alarm-table tr[data-alarm='estop'] button[data-act='reset']").click()
    page.wait_for_function("() => !document.querySelector(\"tr[data-alarm='estop']\")")
    history = page.text_content("#alarm-history") or ""
    assert "reset" in history and "acknowledged" in history
    screenshot(page, "alarms-after-reset")


@pytest.fixture(scope="module")
def short_sessions(tmp_path_factory: pytest.TempPathFactory) -> Any:
    if "session_timeout_s" not in hmi_options():
        pytest.skip("this supervisor has no hmi.session_timeout_s")
    yield from supervisor_fixture(tmp_path_factory.mktemp("hmi-short"), session_timeout_s=3)


def test_an_expired_session_goes_to_login_and_back_to_the_same_page(
    page: Any, short_sessions: Supervisor
) -> None:
    bench = short_sessions
    login(page, bench, "operator", "#/channel/ch1")
    page.wait_for_selector("#cmd-hold")
    # Nobody uses the page: once hmi.session_timeout_s has passed it goes to the login
    # screen by itself (the live values do not keep a session open).
    page.wait_for_selector("#login-form", timeout=15_000)
    assert "next=" in page.url and "channel%2Fch1" in page.url
    assert "session has ended" in (page.text_content("#login-form") or "")
    assert page.locator("#top").is_hidden()
    screenshot(page, "login-session-expired")
    page.fill("#login-user", "operator")
    page.fill("#login-password", "operator-pw")
    page.click("#login-submit")
    page.wait_for_selector("#cmd-hold")
    assert page.url.endswith("#/channel/ch1")


@pytest.fixture(scope="module")
def restartable(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """A supervisor on a fixed port, which the test stops and starts again."""
    workdir = tmp_path_factory.mktemp("hmi-restart")
    port = free_port()
    held = {"sup": start_supervisor(workdir, port=port), "workdir": workdir, "port": port}
    try:
        yield held
    finally:
        stop_supervisor(held["sup"])


@pytest.mark.timeout(300)  # a stop and a start of the supervisor, on a loaded machine
def test_the_page_reconnects_by_itself_after_a_supervisor_restart(
    page: Any, restartable: dict[str, Any]
) -> None:
    sup = restartable["sup"]
    login(page, sup, "operator", "#/channel/ch2")
    link = "() => document.querySelector('#link').textContent"
    page.wait_for_function(f"{link} === 'live'")
    stop_supervisor(sup)
    page.wait_for_function(f"{link} === 'disconnected'")
    assert page.evaluate("() => document.body.classList.contains('stale')")
    screenshot(page, "channel-supervisor-down")
    sup = restartable["sup"] = start_supervisor(restartable["workdir"], port=restartable["port"])
    if sup.login:
        # A restart forgets every session: the page reconnects by itself, finds its
        # session gone and asks for a login, keeping its place.
        page.wait_for_selector("#login-form", timeout=60_000)
        assert "channel%2Fch2" in page.url
        page.fill("#login-user", "operator")
        page.fill("#login-password", USERS["operator"])
        page.click("#login-submit")
    page.wait_for_function("() => location.hash === '#/channel/ch2'")
    page.wait_for_function(f"{link} === 'live'", timeout=60_000)
    assert not page.evaluate("() => document.body.classList.contains('stale')")
