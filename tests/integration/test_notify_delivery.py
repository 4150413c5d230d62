"""Notifications against real servers on loopback (issue 34): aiosmtpd requiring STARTTLS
(a self-signed certificate made by the test, given as the route's ``ca_file``) and AUTH
LOGIN, and an aiohttp receiver. ``supervisor notify test`` says OK per route and exits 0;
a wrong password is FAILED with why, exit 1; a bad section is exit 2 with file:line:col.
The notifier itself, with real senders, keeps a message while its server is down and
delivers it once when it is back (the receiver counts by idempotency key)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from commandrig import io_map as command_map
from notifyrig import PASSWORD, USER, SmtpReceiver, WebhookReceiver, routes

from supervisor.audit import audit_path, read_entries
from supervisor.cli.main import main
from supervisor.config.notifications import NotificationsConfig
from supervisor.core.clock import RealClock
from supervisor.notify import Notice, Notifier

pytestmark = pytest.mark.integration


@pytest.fixture
def receivers(tmp_path: Path) -> Iterator[tuple[SmtpReceiver, WebhookReceiver]]:
    smtp, hook = SmtpReceiver(tmp_path), WebhookReceiver()
    smtp.start()
    hook.start()
    try:
        yield smtp, hook
    finally:
        smtp.stop()
        hook.close()


def password_file(tmp: Path, text: str = PASSWORD) -> Path:
    path = tmp / "smtp-password"
    path.write_text(text + "\n", encoding="utf-8")
    return path


def bench_map(tmp: Path, route_list: list[dict[str, Any]]) -> Path:
    path = command_map(tmp)
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data["notifications"] = {"routes": route_list}
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def test_notify_test_reaches_both_routes_over_starttls_with_auth_login(
    tmp_path: Path,
    receivers: tuple[SmtpReceiver, WebhookReceiver],
    capsys: pytest.CaptureFixture[str],
) -> None:
    smtp, hook = receivers
    path = bench_map(tmp_path, routes(smtp, hook, password_file(tmp_path)))
    code = main(["notify", "test", "--io-map", str(path)])
    out = capsys.readouterr()
    assert code == 0, out
    assert out.out.splitlines() == ["mail: OK", "hook: OK"]
    assert smtp.logins == [("LOGIN", USER, True)]  # AUTH LOGIN, after STARTTLS
    (mail,) = smtp.taken.bodies.values()
    assert "test message of route mail" in str(mail["Subject"])
    assert mail["To"] == "oncall@lab.test"
    ((key, posted),) = hook.taken.bodies.items()
    assert posted["body"]["kind"] == "test" and posted["body"]["key"] == key
    (entry,) = [e for e in read_entries(audit_path(tmp_path / "state")) if e.kind == "notify.test"]
    assert '"hook":"ok"' in entry.details and '"mail":"ok"' in entry.details


def test_notify_test_names_a_wrong_password_and_exits_1(
    tmp_path: Path,
    receivers: tuple[SmtpReceiver, WebhookReceiver],
    capsys: pytest.CaptureFixture[str],
) -> None:
    smtp, hook = receivers
    path = bench_map(tmp_path, routes(smtp, hook, password_file(tmp_path, "wrong")))
    code = main(["notify", "test", "--io-map", str(path)])
    lines = capsys.readouterr().out.splitlines()
    assert code == 1
    assert lines[0].startswith("mail: FAILED login refused for bench: 535"), lines
    assert lines[1] == "hook: OK"
    assert smtp.taken.unique == 0


def test_notify_test_on_a_stopped_server_fails_and_a_bad_section_is_a_config_error(
    tmp_path: Path,
    receivers: tuple[SmtpReceiver, WebhookReceiver],
    capsys: pytest.CaptureFixture[str],
) -> None:
    smtp, hook = receivers
    hook.stop()
    path = bench_map(tmp_path, routes(smtp, hook, password_file(tmp_path)))
    assert main(["notify", "test", "--io-map", str(path)]) == 1
    assert "hook: FAILED" in capsys.readouterr().out
    bad = routes(smtp, hook, password_file(tmp_path))
    bad[1]["url"] = "http//127.0.0.1/hook"
    path = bench_map(tmp_path, bad)
    assert main(["notify", "test", "--io-map", str(path)]) == 2
    assert f"{path}:" in capsys.readouterr().err


async def test_a_message_kept_while_the_servers_are_down_is_delivered_once_they_are_back(
    tmp_path: Path, receivers: tuple[SmtpReceiver, WebhookReceiver]
) -> None:
    smtp, hook = receivers
    cfg = NotificationsConfig.model_validate(
        {
            "routes": routes(smtp, hook, password_file(tmp_path)),
            "retry_min_s": 0.2,
            "retry_max_s": 0.5,
        }
    )
    clock = RealClock()
    n = Notifier(cfg, "sim", clock, tmp_path)
    smtp.stop()
    hook.stop()
    await n.start()
    try:
        wall = clock.wall()
        for i in range(3):  # inside one window: one summary per route
            n.inbox.append(Notice(wall + i * 0.1, "alarm", f"ch{i}.trip", f"ch{i}", "high", "x"))
        await _until(lambda: n.status.counts.retrying == 2)
        assert n.status.failed >= 2
        smtp.start()
        hook.start()
        await _until(lambda: n.status.counts.sent == 2)
    finally:
        await n.stop()
    assert smtp.taken.unique == hook.taken.unique == 1
    assert smtp.taken.duplicates == hook.taken.duplicates == 0
    (posted,) = hook.taken.bodies.values()
    assert [e["source"] for e in posted["body"]["events"]] == ["ch0.trip", "ch1.trip", "ch2.trip"]


async def _until(pred: Any, limit_s: float = 30.0) -> None:
    """Wait for ``pred`` (an upper bound for a loaded machine, not a timing claim)."""
    for _ in range(int(limit_s / 0.05)):
        if pred():
            return
        await asyncio.sleep(0.05)
    raise TimeoutError(f"gave up after {limit_s:g} s")
