"""Issue 34's Must show for notifications, on a real ``supervisor run`` of the simulated
seed 002 bench with a real SMTP server (aiosmtpd: STARTTLS, AUTH LOGIN) and a real HTTP
receiver on loopback (tests/notifyrig.py):

(a) an e-stop (``PUT /api/sim/estop``) produces ONE summary message per route within 5 s,
    listing the alarms;
(b) the receivers stopped for ``DOWN_S`` (60 s, the issue's figure) while alarms are
    raised, the supervisor SIGKILLed meanwhile and started again: once the receivers are
    back, every queued message is delivered, none twice (each receiver counts its
    deliveries by idempotency key: 0 duplicates). The counts are printed (``pytest -s``).

Every process is stopped by its pid (bench/killrestart.py's helpers).
"""

from __future__ import annotations

import sqlite3
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import pytest
import yaml
from notifyrig import PASSWORD, SmtpReceiver, WebhookReceiver, routes

from supervisor.bench.killrestart import (
    _connected,
    _http,
    _in_state,
    _Process,
    _wait,
    kill_restart_map,
)
from supervisor.notify import NOTIFY_NAME

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration

DOWN_S = 60.0
"""How long the receivers are down (the issue's figure)."""
SUMMARY_WITHIN_S = 5.0
"""The issue's bound for the e-stop's summary (the flood window is 2 s)."""
RECIPE = "recipe: rest\nsteps:\n  - {id: rest, rest: 10 min}\n"
"""A test for the e-stop to abort (its end is one more event of the summary)."""
SETTLE_S = 3.0
"""After the summary: long enough for a second message to show up if there were one."""


def _say(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def _bench_map(tmp: Path, smtp: SmtpReceiver, hook: WebhookReceiver) -> Path:
    path = kill_restart_map(tmp, str(ROOT / "io_maps" / "sim.yaml"))
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    password = tmp / "smtp-password"
    password.write_text(PASSWORD + "\n", encoding="utf-8")
    data["notifications"] = {
        "routes": routes(smtp, hook, password),
        "retry_min_s": 1.0,
        "retry_max_s": 5.0,  # back within 5 s of the receivers' return
    }
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def _start(exe: list[str], tmp: Path) -> tuple[_Process, str]:
    p = _Process([*exe, "--log-level", "info"], tmp, tmp / "logs.txt")
    url = ""
    for line in p.banner("Ctrl-C"):
        if line.startswith("HTTP API listening on "):
            url = line.split()[-1].removesuffix("/tags")
    _wait("devices connected", partial(_connected, url))
    return p, url


def _tag(url: str, name: str) -> object:
    return _http("GET", f"{url}/tags/{name}")["value"]


def _counts(smtp: SmtpReceiver, hook: WebhookReceiver) -> tuple[int, int]:
    return smtp.taken.unique, hook.taken.unique


def _quiet(pred: Callable[[], bool], seconds: float) -> None:
    """Wait ``seconds``, failing as soon as ``pred`` stops holding."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        assert pred()
        time.sleep(0.1)


@dataclass
class Outage:
    """What part (b) saw."""

    down_s: float = 0.0
    queued_at_kill: int = 0
    failed_at_kill: int = 0
    queued_after_restart: int = 0
    drained_s: float = 0.0
    last_error: str = ""


def _estop_is_one_message_per_route(
    url: str, tmp: Path, smtp: SmtpReceiver, hook: WebhookReceiver
) -> None:
    """(a): a test running on ch4, the e-stop pressed: it trips and aborts the test; one
    summary per route within 5 s, naming the alarm and the test's end; printed."""
    recipe = tmp / "rest.yaml"
    recipe.write_text(RECIPE, encoding="utf-8")
    _http("PUT", f"{url}/channels/ch4/recipe", {"file": str(recipe)})
    _http("PUT", f"{url}/tags/ch4.command", {"value": "start"})
    _wait("Running", partial(_in_state, url, ("Running",)))
    _wait("start-up messages sent", lambda: _tag(url, "notify.queued") == 0)
    time.sleep(SETTLE_S)  # whatever the start raised (none expected) delivered first
    before = _counts(smtp, hook)
    one_more = (before[0] + 1, before[1] + 1)
    pressed = time.monotonic()
    _http("PUT", f"{url}/sim/estop", {"pressed": True})
    _wait("one message per route", lambda: _counts(smtp, hook) == one_more, SUMMARY_WITHIN_S)
    took_s = time.monotonic() - pressed
    _quiet(lambda: _counts(smtp, hook) == one_more, SETTLE_S)
    mail = list(smtp.taken.bodies.values())[-1]
    posted = list(hook.taken.bodies.values())[-1]["body"]
    events = [f"{e['kind']} {e['source']}" for e in posted["events"]]
    assert posted["kind"] == "summary" and "alarm estop" in events, posted
    assert "test_end ch4" in events, posted  # the e-stop aborted the test
    body = mail.get_content()
    assert all(e["text"] in body for e in posted["events"]), body
    _say(
        f"(a) e-stop → 1 message per route in {took_s:.2f} s (bound {SUMMARY_WITHIN_S:g} s);"
        f" {len(events)} events listed: {', '.join(events)}; subject {posted['subject']!r}"
    )
    _http("PUT", f"{url}/sim/estop", {"pressed": False})
    _wait("e-stop released", lambda: _tag(url, "estop.ok") is True)


def _outage_with_a_kill(
    p: _Process, url: str, exe: list[str], tmp: Path, smtp: SmtpReceiver, hook: WebhookReceiver
) -> tuple[_Process, Outage]:
    """(b): receivers down DOWN_S, the e-stop again, SIGKILL, restart, receivers back,
    everything drained. Returns the running process (restarted) and what it saw."""
    seen = Outage()
    smtp.stop()
    hook.stop()
    down_at = time.monotonic()
    _http("PUT", f"{url}/sim/estop", {"pressed": True})  # a new activation while down
    _wait("a failed attempt on each route", lambda: int(_tag(url, "notify.retrying")) >= 2)
    seen.queued_at_kill = int(_tag(url, "notify.queued"))
    seen.failed_at_kill = int(_tag(url, "notify.failed"))
    p.kill()
    p.stop()
    p, url = _start(exe, tmp)
    _wait("the queue retried", lambda: int(_tag(url, "notify.retrying")) >= 2)
    seen.queued_after_restart = int(_tag(url, "notify.queued"))
    time.sleep(max(0.0, DOWN_S - (time.monotonic() - down_at)))
    seen.down_s = time.monotonic() - down_at
    seen.last_error = str(_tag(url, "notify.last_error"))
    smtp.start()
    hook.start()
    back_at = time.monotonic()
    _wait("every queued message delivered", lambda: _tag(url, "notify.queued") == 0)
    seen.drained_s = time.monotonic() - back_at
    return p, seen


@pytest.mark.timeout(600)
def test_estop_summary_per_route_and_a_kill_while_receivers_are_down_loses_none(
    tmp_path: Path,
) -> None:
    smtp, hook = SmtpReceiver(tmp_path), WebhookReceiver()
    smtp.start()
    hook.start()
    bench_map = _bench_map(tmp_path, smtp, hook)
    exe = [sys.executable, "-m", "supervisor.cli.main", "run", str(bench_map)]
    p: _Process | None = None
    try:
        p, url = _start(exe, tmp_path)
        _estop_is_one_message_per_route(url, tmp_path, smtp, hook)
        p, seen = _outage_with_a_kill(p, url, exe, tmp_path, smtp, hook)
        p.stop()
        p = None
    finally:
        if p is not None:
            p.stop()
        smtp.stop()
        hook.close()

    with sqlite3.connect(tmp_path / "var" / NOTIFY_NAME) as db:
        rows = db.execute("SELECT key, route, state, attempts FROM messages").fetchall()
    assert rows and all(state == "sent" for _, _, state, _ in rows), rows
    stored = {route: {k for k, r, _, _ in rows if r == route} for route in ("mail", "hook")}
    assert set(smtp.taken.counts) == stored["mail"]  # every message delivered …
    assert set(hook.taken.counts) == stored["hook"]
    assert smtp.taken.duplicates == 0 and hook.taken.duplicates == 0  # … none twice
    _say(
        f"(b) receivers down {seen.down_s:.1f} s; SIGKILL with {seen.queued_at_kill} queued"
        f" ({seen.failed_at_kill} failed attempts); {seen.queued_after_restart} queued after"
        f" the restart; receivers back: all delivered in {seen.drained_s:.1f} s;"
        f" messages in all {len(rows)} (mail {smtp.taken.unique}, webhook {hook.taken.unique}),"
        f" all sent; duplicates by key: mail {smtp.taken.duplicates}, webhook"
        f" {hook.taken.duplicates}; failed attempts retried {sum(a - 1 for *_, a in rows)};"
        f" last error while down: {seen.last_error}"
    )
    for posted in hook.taken.bodies.values():
        _say(f"    webhook: {posted['body']['subject']}")
