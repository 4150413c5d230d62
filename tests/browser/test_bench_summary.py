"""Issue 33, finding 8: a bench summary on every screen (channels running, held, faulted;
alarms by priority) and ISA-101 priority indication by shape and colour, not colour
alone. In Debian's Chromium against a real ``supervisor run`` of the simulated bench."""

from __future__ import annotations

import json
from typing import Any

import pytest
from axe import audit, blocking
from browserrig import SHORT_RECIPE, Supervisor, login, screenshot, wait_for

from supervisor.safety.alarms import Severity

SCREENS = ["#/", "#/channel/ch2", "#/alarms", "#/recipes", "#/tests", "#/diagnostics"]
BURST_TRIES = 20  # supervisor.core.logins.BURST_TRIES


def summary(page: Any) -> dict[str, str]:
    """The summary bar's counts by their data-count names."""
    return dict(
        page.eval_on_selector_all(
            "#summary [data-count]", "els => els.map(e => [e.dataset.count, e.dataset.value])"
        )
    )


def wait_summary(page: Any, **want: int) -> None:
    seen: dict[str, str] = {}

    def matches() -> bool:
        seen.update(summary(page))
        return all(seen.get(k) == str(v) for k, v in want.items())

    try:
        wait_for(f"the summary {want}", matches, timeout_s=20)
    except AssertionError as err:
        raise AssertionError(f"{err}; the summary showed {seen}") from None


def alarm_counts(bench: Supervisor) -> dict[str, int]:
    """The active alarms by the server: in all, unacknowledged, and by priority name (a
    loaded machine may add a scan stall of its own at any time: compared, not assumed)."""
    status, body = bench.call("GET", "/api/alarms")
    assert status == 200, body
    active = [a for a in body["active"] if a["state"] != "normal" and not a["shelved"]]
    counts = {s.name.lower(): 0 for s in Severity}
    for a in active:
        counts[a["severity_name"]] += 1
    counts["alarms"] = len(active)
    counts["unacknowledged"] = sum("unacknowledged" in a["state"] for a in active)
    return counts


def wait_alarms_as_the_server(page: Any, bench: Supervisor) -> dict[str, int]:
    """The summary's alarm counts equal the server's (a count of 0 shown by its absence)."""
    seen: dict[str, Any] = {}

    def same() -> bool:
        want = alarm_counts(bench)
        shown = summary(page)
        seen.update(want=want, shown=shown)
        return all(shown.get(k, "0") == str(v) for k, v in want.items())

    try:
        wait_for("the summary's alarms as the server's", same, timeout_s=20)
    except AssertionError as err:
        raise AssertionError(f"{err}; {seen}") from None
    return dict(seen["want"])


def start(bench: Supervisor, channel: str) -> None:
    status, body = bench.call(
        "PUT", f"/api/channels/{channel}/recipe", {"file": SHORT_RECIPE.stem, "parameters": {}}
    )
    assert status == 200, body
    status, body = bench.call("POST", f"/api/channels/{channel}/commands/start")
    assert status == 200, body


def test_every_priority_has_its_own_shape_colour_and_number(
    as_operator: Any, bench: Supervisor
) -> None:
    page = as_operator
    page.wait_for_selector("#summary")
    icons = page.evaluate(
        """async (severities) => {
          const m = await import('/static/js/priority.js');
          return severities.map(([name, number]) => {
            const box = document.createElement('span');
            box.innerHTML = m.priorityIcon(number);
            document.body.append(box);
            const svg = box.querySelector('svg');
            const shape = svg.querySelector('[data-shape]');
            const out = {name, number, label: svg.getAttribute('aria-label'),
                         shape: shape.dataset.shape, fill: getComputedStyle(shape).fill,
                         text: svg.textContent.trim(), priority: m.priorityOf(number).name};
            box.remove();
            return out;
          });
        }""",
        [[s.name.lower(), int(s)] for s in Severity],
    )
    assert len(icons) == len(Severity)
    for icon in icons:
        assert icon["priority"] == icon["name"], icon  # as the server names it
        assert icon["name"] in icon["label"], icon
    # Shape, colour and number each tell every priority apart (not colour alone).
    for key in ("shape", "fill", "text"):
        assert len({i[key] for i in icons}) == len(Severity), (key, icons)


@pytest.mark.timeout(180)
def test_the_summary_bar_counts_channels_and_alarms_on_every_screen(
    as_operator: Any, bench: Supervisor
) -> None:
    page = as_operator
    page.wait_for_selector("#summary")
    wait_summary(page, channels=5, running=0, held=0, faulted=0)
    before = wait_alarms_as_the_server(page, bench)
    start(bench, "ch0")
    start(bench, "ch1")
    status, body = bench.call("POST", "/api/channels/ch1/commands/hold")
    assert status == 200, body
    wait_summary(page, running=1, held=1, faulted=0)
    for where in SCREENS:
        page.goto(f"{bench.base}/{where}")
        page.wait_for_selector("#summary [data-count='running']")
        assert page.locator("#summary").is_visible(), where
        wait_summary(page, channels=5, held=1)
    screenshot(page, "summary-bar")
    # Two alarms of two priorities: a burst of failed logins (medium), the e-stop (critical).
    for _ in range(BURST_TRIES + 2):
        bench.call("POST", "/api/login", {"user": "nobody", "password": "wrong"}, user=None)
    status, body = bench.call("PUT", "/api/sim/estop", {"pressed": True})
    assert status == 200, body
    try:
        wait_summary(page, faulted=5)
        screenshot(page, "summary-bar-alarms")
        after = wait_alarms_as_the_server(page, bench)
        assert after["critical"] == before["critical"] + 1, (before, after)
        assert after["medium"] >= before["medium"] + 1, (before, after)
        # At 1366 px the summary shares the header's one line (no height taken from the
        # screens: the channel's trend must stay above the fold).
        centres = [
            box["y"] + box["height"] / 2
            for box in (page.locator(s).bounding_box() for s in ("#summary", "#logout"))
        ]
        assert abs(centres[0] - centres[1]) < 8, centres
        page.goto(f"{bench.base}/#/alarms")
        page.wait_for_selector("#alarm-table tr[data-alarm='security.login_burst']")
        shapes = page.eval_on_selector_all(
            "#alarm-table tr[data-alarm]",
            "rs => rs.map(r => [r.dataset.alarm,"
            " r.querySelector('svg.prio [data-shape]').dataset.shape])",
        )
        by_alarm = dict(shapes)
        assert by_alarm["estop"] != by_alarm["security.login_burst"], shapes
        # The banner of the newest unacknowledged alarm carries its priority's shape too.
        assert page.locator("#banner svg.prio").count() == 1
        screenshot(page, "alarms-priorities")
        assert [str(v) for v in blocking(audit(page))] == []
    finally:
        bench.call("PUT", "/api/sim/estop", {"pressed": False})


def made_up_alarms(per_priority: int) -> list[dict[str, Any]]:
    """Unacknowledged alarms of every priority, as the supervisor sends them."""
    return [
        {
            "id": f"made_up.{s.name.lower()}{i}",
            "group": "",
            "state": "active_unacknowledged",
            "severity": int(s),
            "severity_name": s.name.lower(),
            "shelved": False,
            "first_out": False,
            "message": f"made up {s.name.lower()} alarm {i}",
            "activated_time": 0,
        }
        for s in Severity
        for i in range(per_priority)
    ]


def header_line(page: Any) -> list[float]:
    """The vertical centres of the header's parts, left to right."""
    return [
        box["y"] + box["height"] / 2
        for box in (
            page.locator(s).bounding_box() for s in ("#bench-name", "#summary", "#link", "#logout")
        )
    ]


@pytest.mark.parametrize("language", ["en", "fr"])
def test_the_header_keeps_one_line_at_1366_px_in_its_widest_state(
    page: Any, bench: Supervisor, language: str
) -> None:
    """Found by CI: on a loaded machine a scan stall (high) joined the e-stop (critical) and
    the failed logins (medium), and "Log out" went onto a second line. Whatever the header
    holds — every priority with two-digit counts, French, an engineer on a channel's screen
    — it keeps one line, its counts all shown; the words give way first, and only then."""
    phase = {"alarms": [], "ws": None}

    def relay(ws: Any) -> None:
        # Between the supervisor and the page: its alarm lists replaced by this test's.
        phase["ws"] = ws
        server = ws.connect_to_server()

        def from_server(message: Any) -> None:
            data = json.loads(message)
            if data.get("type") == "alarms":
                data["alarms"] = phase["alarms"]
            ws.send(json.dumps(data))

        server.on_message(from_server)

    page.route_web_socket("**/api/ws", relay)
    login(page, bench, "engineer", "#/channel/ch2")
    page.wait_for_selector("#summary [data-count='running']")
    if language == "fr":
        page.click("#lang")
        page.wait_for_function("() => document.documentElement.lang === 'fr'")
        page.wait_for_selector("#summary [data-count='running']")
    running = {"en": "running", "fr": "en cours"}[language]
    if language == "en":
        # Room enough in English without alarms: the counts with their words.
        page.wait_for_function(
            "(w) => document.querySelector(\"#summary [data-count='running']\")"
            ".textContent.includes(w)",
            arg=running,
        )
    centres = header_line(page)
    assert max(centres) - min(centres) < 8, centres
    phase["alarms"] = made_up_alarms(per_priority=3)
    phase["ws"].send(json.dumps({"type": "alarms", "alarms": phase["alarms"]}))
    wait_summary(page, alarms=12, critical=3, high=3, medium=3, low=3)
    screenshot(page, f"header-widest-{language}")
    centres = header_line(page)
    assert max(centres) - min(centres) < 8, centres
    for name in ("running", "held", "faulted", "alarms", "critical", "high", "medium", "low"):
        item = page.locator(f"#summary [data-count='{name}']")
        assert item.is_visible(), name
        # (the alarms' count may give way to the unacknowledged one: 12 of 12 here)
        assert item.get_attribute("data-value") in (item.text_content() or ""), name
    # What gave way is still said, in the tooltips.
    title = page.get_attribute("#summary [data-count='running']", "title") or ""
    assert running in title, title
    assert "(" in (page.get_attribute("#who", "title") or "")  # the role
