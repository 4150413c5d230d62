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
from functools import partial
from pathlib import Path

import pytest
import yaml
from notifyrig import PASSWORD, SmtpReceiver, WebhookReceiver, routes

from supervisor.bench.killrestart import _connected, _http, _Process, _wait, kill_restart_map
from supervisor.notify import NOTIFY_NAME

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration

DOWN_S = 60.0
"""How long the receivers are down (the issue's figure)."""
SUMMARY_WITHIN_S = 5.0
"""The issue's bound for the e-stop's summary (the flood window is 2 s)."""
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


@pytest.mark.timeout(600)
def test_estop_summary_per_route_and_a_kill_while_receivers_are_down_loses_none(
    tmp_path: Path,
) -> None:
    smtp, hook = SmtpReceiver(tmp_path), WebhookReceiver()
    smtp.start()
    hook.start()
    exe = [
        sys.executable,
        "-m",
        "supervisor.cli.main",
        "run",
        str(_bench_map(tmp_path, smtp, hook)),
    ]
    p: _Process | None = None
    try:
        p, url = _start(exe, tmp_path)
        # Whatever the start raised (none expected) is delivered before the e-stop.
        _wait("start-up messages sent", lambda: _tag(url, "notify.queued") == 0)
        time.sleep(SETTLE_S)
        before = _counts(smtp, hook)

        # (a) the e-stop: one summary per route, within 5 s, naming the alarms
        pressed = time.monotonic()
        _http("PUT", f"{url}/sim/estop", {"pressed": True})
        _wait(
            "one message per route",
            lambda: _counts(smtp, hook) == (before[0] + 1, before[1] + 1),
            limit_s=SUMMARY_WITHIN_S,
        )
        took_s = time.monotonic() - pressed
        _quiet(lambda: _counts(smtp, hook) == (before[0] + 1, before[1] + 1), SETTLE_S)
        mail = list(smtp.taken.bodies.values())[-1]
        posted = list(hook.taken.bodies.values())[-1]["body"]
        alarms = [e["source"] for e in posted["events"]]
        assert "estop" in alarms, posted
        body = mail.get_content()
        assert all(a in body for a in alarms), body
        _say(
            f"(a) e-stop → 1 message per route in {took_s:.2f} s (bound {SUMMARY_WITHIN_S:g} s);"
            f" {len(alarms)} alarms listed: {', '.join(alarms)}; subject {posted['subject']!r}"
        )
        _http("PUT", f"{url}/sim/estop", {"pressed": False})
        _wait("e-stop released", lambda: _tag(url, "estop.ok") is True)

        # (b) receivers down, alarms raised, the supervisor SIGKILLed and restarted
        delivered_before = _counts(smtp, hook)
        smtp.stop()
        hook.stop()
        down_at = time.monotonic()
        _http("PUT", f"{url}/sim/estop", {"pressed": True})  # the e-stop again: new activation
        _wait("a failed attempt on each route", lambda: int(_tag(url, "notify.retrying")) >= 2)
        queued_at_kill = int(_tag(url, "notify.queued"))
        failed_at_kill = int(_tag(url, "notify.failed"))
        p.kill()
        p.stop()
        p, url = _start(exe, tmp_path)
        _wait("the failing alarm", lambda: int(_tag(url, "notify.retrying")) >= 2)
        queued_after_restart = int(_tag(url, "notify.queued"))
        time.sleep(max(0.0, DOWN_S - (time.monotonic() - down_at)))
        down_s = time.monotonic() - down_at
        failing = _http("GET", f"{url}/tags/notify.last_error")["value"]
        smtp.start()
        hook.start()
        back_at = time.monotonic()
        _wait("every queued message delivered", lambda: _tag(url, "notify.queued") == 0)
        drained_s = time.monotonic() - back_at
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
    after = _counts(smtp, hook)
    _say(
        f"(b) receivers down {down_s:.1f} s, SIGKILL with {queued_at_kill} queued"
        f" ({failed_at_kill} failed attempts), {queued_after_restart} queued after the restart;"
        f" back: all delivered in {drained_s:.1f} s; delivered since the receivers stopped:"
        f" mail {after[0] - delivered_before[0]}, webhook {after[1] - delivered_before[1]};"
        f" total messages {len(rows)} (mail {after[0]}, webhook {after[1]});"
        f" duplicates by key: mail {smtp.taken.duplicates}, webhook {hook.taken.duplicates};"
        f" retried attempts {sum(a - 1 for *_, a in rows)}; last error while down: {failing}"
    )
    for posted in hook.taken.bodies.values():
        _say(f"    webhook: {posted['body']['subject']}")
