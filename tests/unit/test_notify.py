"""Notifications (issue 34, docs/notifications.md): what `check` refuses in the
``notifications:`` section, how notices become messages (filters, flood window, quiet hours,
escalation), the queue's idempotency keys across a restart, retries with backoff, the
counts and the ``notify.failing`` alarm — all on the virtual clock, with fake senders (the
real SMTP and HTTP servers are in tests/integration/test_notify_delivery.py)."""

from __future__ import annotations

import datetime
import itertools
import json
import sqlite3
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from commandrig import io_map as command_map
from commandrig import recipe

from supervisor.app import build_bench
from supervisor.app.notify import build_notifier
from supervisor.cli.main import main
from supervisor.commands import Command, Verb
from supervisor.config.notifications import NotificationsConfig
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.notify import (
    ALARM_FAILING,
    DeliveryError,
    Notice,
    Notifier,
    NotifyStore,
    Outgoing,
    Router,
    email_message,
    message_key,
    notify_path,
    payload,
    webhook_request,
)
from supervisor.safety import AlarmManager, Severity
from supervisor.tags import TagDB
from supervisor.testing import run_scans

T0 = 1_767_225_600.0  # 2026-01-01 00:00:00 UTC (the virtual clock's wall epoch)


def routes_cfg(*routes: dict[str, Any], **top: Any) -> NotificationsConfig:
    return NotificationsConfig.model_validate({"routes": list(routes), **top})


def hook(name: str = "hook", **kw: Any) -> dict[str, Any]:
    return {"name": name, "type": "webhook", "url": "http://127.0.0.1:9/in", **kw}


def alarm(t: float, source: str, priority: str = "high", channel: str = "") -> Notice:
    return Notice(T0 + t, "alarm", source, channel, priority, f"{source} tripped")


# --- check: what the section refuses, and where -------------------------------------------
def bench_with(tmp: Path, section: str) -> Path:
    """The command rig's bench with ``section`` (YAML text) appended: errors at known lines."""
    path = command_map(tmp)
    text = path.read_text(encoding="utf-8")
    path.write_text(text + section, encoding="utf-8")
    return path


def first_line_of(path: Path, needle: str) -> int:
    lines = path.read_text(encoding="utf-8").splitlines()
    return next(i for i, line in enumerate(lines, 1) if needle in line)


def check_errors(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(["check", str(path)])
    return code, capsys.readouterr().err


@pytest.mark.parametrize(
    ("route", "needle", "says"),
    [
        ("url: 'htp:/nowhere'", "htp:/nowhere", "expected http://host"),
        ("url: 'http://127.0.0.1:99999/x'", "99999", "port must be a number"),
        ("url: http://127.0.0.1/x\n    colour: red", "colour", "colour"),
        (
            "url: http://127.0.0.1/x\n    headers: {Authorization: Bearer abc}",
            "Authorization",
            "never written here",
        ),
        ("url_env: NOTIFY_TEST_UNSET_VARIABLE", "NOTIFY_TEST_UNSET", "is not set"),
    ],
    ids=["malformed-url", "bad-port", "unknown-key", "plain-secret-header", "missing-env"],
)
def test_check_refuses_a_bad_webhook_route_with_its_line_and_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], route: str, needle: str, says: str
) -> None:
    path = bench_with(
        tmp_path, f"notifications:\n  routes:\n  - name: hook\n    type: webhook\n    {route}\n"
    )
    code, err = check_errors(path, capsys)
    assert code == 2, err
    line = first_line_of(path, needle)
    assert f"{path}:{line}:" in err, err
    assert says in err, err


def test_check_refuses_a_missing_password_file_and_a_password_without_file_or_env(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = bench_with(
        tmp_path,
        "notifications:\n  routes:\n"
        "  - {name: mail, type: email, host: 127.0.0.1, user: bench, from: b@lab.test,\n"
        "     to: [o@lab.test], password_file: /nonexistent/notify-password}\n"
        "  - {name: mail2, type: email, host: 127.0.0.1, user: bench, from: b@lab.test,\n"
        "     to: [o@lab.test]}\n",
    )
    code, err = check_errors(path, capsys)
    assert code == 2
    assert "password file '/nonexistent/notify-password' not found" in err
    assert "a user needs exactly one of password_file or password_env" in err
    assert f"{path}:{first_line_of(path, 'password_file:')}:39: " in err


def test_check_refuses_a_route_for_a_channel_the_bench_does_not_have(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = bench_with(
        tmp_path,
        "notifications:\n  routes:\n  - {name: h, type: webhook, url: http://a/b,"
        " channels: [ch9]}\n",
    )
    code, err = check_errors(path, capsys)
    assert code == 2 and "notifications route h: no channel named ch9" in err


def test_a_valid_section_loads_with_every_format_and_its_secrets_from_files_and_env(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    secret = tmp_path / "pw"
    secret.write_text("s3cret\n", encoding="utf-8")
    monkeypatch.setenv("NOTIFY_TEST_TOKEN", "tok")
    path = bench_with(
        tmp_path,
        "notifications:\n  timezone: Europe/Paris\n  routes:\n"
        f"  - {{name: mail, type: email, host: smtp.lab.test, user: bench,\n"
        f"     password_file: {secret},\n"
        "     from: bench@lab.test, to: [oncall@lab.test], escalate_to: [boss@lab.test],\n"
        "     escalate_after_s: 900, min_priority: medium,\n"
        "     quiet_hours: {start: '22:00', end: '07:00', below: high}}\n"
        "  - {name: phone, type: webhook, url: 'https://ntfy.lab.test/bench', format: ntfy}\n"
        "  - {name: chat, type: webhook, url_env: NOTIFY_TEST_TOKEN_URL, format: slack}\n"
        "  - {name: team, type: webhook, url: 'https://teams.lab.test/hook', format: teams,\n"
        "     headers: {Authorization: {env: NOTIFY_TEST_TOKEN}, X-Bench: sim}}\n",
    )
    monkeypatch.setenv("NOTIFY_TEST_TOKEN_URL", "https://chat.lab.test/services/T0/B0/x")
    cfg = load_bench(path)
    assert cfg.notifications is not None
    names = [r.name for r in cfg.notifications.routes]
    assert names == ["mail", "phone", "chat", "team"]
    mail = cfg.notifications.routes[0]
    assert mail.type == "email" and mail.password() == "s3cret" and mail.starttls is True


# --- routing ---------------------------------------------------------------------------
def test_a_route_takes_only_the_kinds_priorities_and_channels_it_asks_for() -> None:
    cfg = routes_cfg(
        hook("all"),
        hook("high_ch1", min_priority="high", channels=["ch1"]),
        hook("ends", kinds=["test_end"]),
    )
    r = Router("sim", cfg.routes)
    r.offer(alarm(0, "ch1.overvoltage", "critical", "ch1"))
    r.offer(alarm(0.1, "ch2.overvoltage", "critical", "ch2"))
    r.offer(alarm(0.2, "room.temp.h", "low"))
    r.offer(Notice(T0 + 0.3, "test_end", "ch1", "ch1", "low", "Running → Complete (end)"))
    out = {m.route: m for m in r.due(T0 + 10)}
    assert [n.source for n in out["all"].notices] == [
        "ch1.overvoltage",
        "ch2.overvoltage",
        "room.temp.h",
        "ch1",
    ]
    # min_priority is the alarms' filter; test ends pass by their kind
    assert [n.source for n in out["high_ch1"].notices] == ["ch1.overvoltage", "ch1"]
    assert [n.kind for n in out["ends"].notices] == ["test_end"]


def test_fifty_alarms_inside_the_flood_window_are_one_summary_per_route() -> None:
    r = Router("sim", routes_cfg(hook("a"), hook("b", summary_window_s=5.0)).routes)
    for i in range(50):
        r.offer(alarm(i * 0.01, f"ch{i}.estop", "critical", f"ch{i}"))
    assert r.due(T0 + 1.9) == []  # the 2 s window is still open
    first = r.due(T0 + 2.0)
    assert [m.route for m in first] == ["a"]
    (summary,) = first
    assert summary.kind == "summary" and len(summary.notices) == 50
    assert summary.subject == "[sim] 50 alarms" and summary.priority == "critical"
    assert all(f"ch{i}.estop" in summary.text for i in range(50))
    (later,) = r.due(T0 + 5.0)
    assert later.route == "b" and len(later.notices) == 50
    assert r.due(T0 + 100) == []  # each once


def test_low_priorities_wait_out_the_quiet_hours_then_go_as_one_summary() -> None:
    quiet = {"start": "22:00", "end": "07:00", "below": "high"}
    r = Router("sim", routes_cfg(hook(quiet_hours=quiet), timezone="UTC").routes)
    night = datetime.datetime(2026, 1, 1, 23, 0, tzinfo=datetime.UTC).timestamp() - T0
    r.offer(alarm(night, "room.temp.h", "low"))
    r.offer(alarm(night + 60, "ch1.temp.h", "medium"))
    r.offer(alarm(night + 120, "ch1.overvoltage", "critical"))  # at once, quiet or not
    (loud,) = r.due(T0 + night + 200)
    assert [n.source for n in loud.notices] == ["ch1.overvoltage"]
    assert r.due(T0 + night + 7 * 3600) == []  # 06:00: still quiet
    (morning,) = r.due(T0 + night + 8 * 3600)  # 07:00
    assert [n.source for n in morning.notices] == ["room.temp.h", "ch1.temp.h"]


def test_an_alarm_unacknowledged_past_escalate_after_s_escalates_once_per_activation() -> None:
    r = Router("sim", routes_cfg(hook(escalate_after_s=600)).routes)
    r.offer(alarm(0, "ch1.overvoltage"))
    r.offer(alarm(1, "ch2.overvoltage"))
    r.due(T0 + 10)  # the first message
    r.offer(Notice(T0 + 100, "ack", "ch2.overvoltage", "", "high", ""))
    assert r.due(T0 + 599) == []
    (esc,) = r.due(T0 + 600)
    assert esc.escalation and esc.kind == "escalation"
    assert [n.source for n in esc.notices] == ["ch1.overvoltage"]
    assert "unacknowledged for 600 s" in esc.subject
    assert r.due(T0 + 10_000) == []  # once per activation
    r.offer(alarm(20_000, "ch1.overvoltage"))  # a new activation: escalated again
    r.due(T0 + 20_010)
    (again,) = r.due(T0 + 20_600)
    assert again.escalation and again.key != esc.key


# --- the queue: keys, restart, idempotency ---------------------------------------------
def test_a_message_s_key_is_the_same_in_any_process_and_a_restart_keeps_it(
    tmp_path: Path,
) -> None:
    notices = [alarm(0, "ch1.overvoltage"), alarm(0.5, "ch2.overvoltage")]
    key = message_key("sim", "hook", "summary", notices)
    assert key == message_key("sim", "hook", "summary", list(notices))
    assert key != message_key("sim", "other", "summary", notices)
    m = Outgoing("hook", key, "summary", "high", "s", "t", tuple(notices))
    store = NotifyStore(tmp_path / "notify.sqlite").open()
    assert store.enqueue([m], T0) == 1
    assert store.enqueue([m], T0 + 1) == 0  # the same message again: stored once
    store.close()
    again = NotifyStore(tmp_path / "notify.sqlite").open()  # a restart
    (queued,) = again.due(T0 + 2)
    assert queued.message == m
    again.sent(key, T0 + 3)
    assert again.due(T0 + 4) == [] and again.counts().sent == 1


# --- the notifier: backoff, counts, the alarm; nothing dropped ---------------------------
class FakeReceiver:
    """A sender that fails while ``down``; records the keys it took."""

    def __init__(self) -> None:
        self.down = False
        self.keys: list[str] = []
        self.attempts = 0

    async def __call__(self, m: Outgoing) -> None:
        self.attempts += 1
        if self.down:
            raise DeliveryError("connection refused")
        self.keys.append(m.key)


def notifier(
    tmp: Path, clock: VirtualClock, receiver: FakeReceiver, **top: Any
) -> tuple[Notifier, TagDB, AlarmManager]:
    db, alarms = TagDB(), AlarmManager(clock)
    n = Notifier(
        routes_cfg(hook(), **top),
        "sim",
        clock,
        tmp,
        db=db,
        alarms=alarms,
        senders={"hook": receiver},
    )
    alarms.listeners.append(n.on_alarm)
    return n, db, alarms


async def steps(
    n: Notifier, clock: VirtualClock, db: TagDB, seconds: float, dt: float = 0.5
) -> None:
    for _ in range(round(seconds / dt)):
        clock.advance(dt)
        await n.pump(clock.wall())
        n.on_scan(db, clock.now())


async def test_failed_deliveries_back_off_are_counted_alarmed_and_delivered_once_up(
    tmp_path: Path,
) -> None:
    clock, rx = VirtualClock(), FakeReceiver()
    n, db, alarms = notifier(tmp_path, clock, rx, retry_min_s=1.0, retry_max_s=8.0)
    await n.start()
    rx.down = True
    fire = alarms.declare("ch1.overvoltage", severity=Severity.HIGH)
    alarms.set(fire, True, "ch1 over voltage")
    await steps(n, clock, db, 2.5)  # the window closes at 2 s: queued, first attempt fails
    row = n.store.rows()[0]
    assert row["state"] == "queued" and row["attempts"] == 1
    assert db["notify.queued"].value == 1 and db["notify.retrying"].value == 1
    assert db["notify.route.hook.queued"].value == 1
    assert db["notify.route.hook.failing"].value is False  # one attempt only
    attempt_times: list[float] = []
    while rx.attempts < 6:
        before = rx.attempts
        await steps(n, clock, db, 0.5)
        if rx.attempts > before:
            attempt_times.append(clock.wall() - T0)
    assert attempt_times[0] == 3.0  # the first attempt at 2 s (the window closed), +1 s
    gaps = [round(b - a, 1) for a, b in itertools.pairwise(attempt_times)]
    assert gaps == [2.0, 4.0, 8.0, 8.0]  # doubled each time, capped at retry_max_s
    assert alarms[ALARM_FAILING].active  # 3 attempts
    assert db["notify.route.hook.failing"].value is True
    assert "hook (" in alarms[ALARM_FAILING].message
    assert db["notify.failed"].value == 6
    assert "connection refused" in str(db["notify.last_error"].value)
    rx.down = False
    await steps(n, clock, db, 10)
    assert len(rx.keys) >= 1 and len(rx.keys) == len(set(rx.keys))  # none twice
    assert db["notify.queued"].value == 0 and db["notify.sent"].value == len(rx.keys)
    assert db["notify.route.hook.queued"].value == 0
    assert db["notify.route.hook.failing"].value is False
    assert not alarms[ALARM_FAILING].active
    await n.stop()


async def test_a_route_failing_for_60_s_is_alarmed_before_its_third_attempt(
    tmp_path: Path,
) -> None:
    clock, rx = VirtualClock(), FakeReceiver()
    n, db, alarms = notifier(
        tmp_path, clock, rx, retry_min_s=100.0, retry_max_s=200.0, failing_after_s=60.0
    )
    await n.start()
    rx.down = True
    alarms.set(alarms.declare("x", severity=Severity.LOW), True, "x")
    await steps(n, clock, db, 55, dt=5)
    assert rx.attempts == 1 and not alarms[ALARM_FAILING].active
    await steps(n, clock, db, 10, dt=5)
    assert rx.attempts == 1 and alarms[ALARM_FAILING].active
    await n.stop()


async def test_a_stop_queues_the_open_window_and_the_next_run_delivers_it(
    tmp_path: Path,
) -> None:
    clock, rx = VirtualClock(), FakeReceiver()
    n, db, alarms = notifier(tmp_path, clock, rx)
    await n.start()
    rx.down = True
    alarms.set(alarms.declare("ch1.overvoltage"), True, "over")
    await steps(n, clock, db, 0.5)  # inside the window: nothing queued yet
    assert n.store.rows() == []
    await n.stop()  # closes the window into the queue; the send fails: kept
    (kept,) = NotifyStore(notify_path(tmp_path)).open().rows()
    assert kept["state"] == "queued"
    rx.down = False
    n2, db2, _ = notifier(tmp_path, clock, rx)
    await n2.start()
    await steps(n2, clock, db2, 1)
    assert rx.keys == [kept["key"]]
    await n2.stop()


async def test_on_a_bench_a_test_end_is_one_message_and_an_estop_one_more(
    tmp_path: Path,
) -> None:
    path = command_map(tmp_path)
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data["notifications"] = {"routes": [hook()]}
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    bench = build_bench(load_bench(path), VirtualClock(), in_process=True)
    n = build_notifier(bench)
    assert n is not None
    seen: list[Outgoing] = []

    async def record(m: Outgoing) -> None:
        seen.append(m)

    n.senders["hook"] = record
    await bench.start()
    await n.start()
    try:
        await run_scans(bench.engine, 30)
        await n.pump(bench.clock.wall())
        assert [m.notices[0].source for m in seen] == ["room.temp.H"]  # the rig's own alarm
        seen.clear()
        text = "recipe: short\nsteps:\n  - {id: r, rest: 1 s}\n"
        start = Command.channel("ch0", Verb.START, "otto", recipe=recipe(tmp_path, text))
        assert bench.commands.execute(start).accepted
        for _ in range(5):  # the test ends after 1 s; the window closes 2 s later
            await run_scans(bench.engine, 10)
            await n.pump(bench.clock.wall())
        assert [m.kind for m in seen] == ["test_end"]
        assert "Complete" in seen[0].text and seen[0].notices[0].channel == "ch0"
        assert bench.sim is not None
        bench.sim.press_estop(True)  # trips every channel
        for _ in range(5):
            await run_scans(bench.engine, 10)
            await n.pump(bench.clock.wall())
        assert len(seen) == 2, [m.subject for m in seen]  # one message for the e-stop
        tripped = {n.source for n in seen[1].notices}
        assert "estop" in tripped and "Emergency stop" in seen[1].text, seen[1]
        bench.engine.scan_once()
        assert bench.db["notify.sent"].value == 3 and bench.db["notify.queued"].value == 0
    finally:
        await n.stop()
        await bench.shutdown()


async def test_a_kill_inside_the_flood_window_loses_no_event_nor_a_pending_escalation(
    tmp_path: Path,
) -> None:
    clock, rx = VirtualClock(), FakeReceiver()
    cfg = routes_cfg(hook(escalate_after_s=60))
    n = Notifier(cfg, "sim", clock, tmp_path, senders={"hook": rx})
    await n.start()
    n.inbox.append(alarm(clock.wall() - T0, "ch1.overvoltage"))
    n.inbox.append(alarm(clock.wall() - T0 + 0.5, "ch2.overvoltage"))
    await n.pump(clock.wall())  # inside the 2 s window: nothing sent yet
    assert rx.keys == [] and n.store.rows() == []
    n.store.close()  # a SIGKILL: no stop, the window never closed in this process
    clock.advance(3.0)
    again = Notifier(cfg, "sim", clock, tmp_path, senders={"hook": rx})
    await again.start()
    await again.pump(clock.wall())
    (summary,) = again.store.rows()
    assert rx.keys == [summary["key"]]
    events = [alarm(0, "ch1.overvoltage"), alarm(0.5, "ch2.overvoltage")]
    assert summary["key"] == message_key("sim", "hook", "summary", events)  # as unkilled
    clock.advance(60.0)
    await again.pump(clock.wall())  # the escalations waited across the kill
    assert len(rx.keys) == 3
    assert NotifyStore(notify_path(tmp_path)).open().kept() == []  # nothing left waiting
    await again.stop()


async def test_a_queue_that_cannot_be_written_keeps_the_message_alarms_and_catches_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock, rx = VirtualClock(), FakeReceiver()
    n, db, alarms = notifier(tmp_path, clock, rx)
    await n.start()
    real_enqueue = n.store.enqueue

    def disk_full(*args: object) -> int:
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(n.store, "enqueue", disk_full)
    alarms.set(alarms.declare("ch1.overvoltage"), True, "over")
    await steps(n, clock, db, 5)
    assert rx.keys == [] and alarms[ALARM_FAILING].active
    assert "disk is full" in alarms[ALARM_FAILING].message
    monkeypatch.setattr(n.store, "enqueue", real_enqueue)
    await steps(n, clock, db, 1)
    # Both kept in memory meanwhile: the alarm's message, and notify.failing's own
    assert len(rx.keys) == 2 and not alarms[ALARM_FAILING].active
    stored = {r["key"] for r in n.store.rows() if r["state"] == "sent"}
    assert stored == set(rx.keys)
    await n.stop()


# --- what goes on the wire -----------------------------------------------------------------
def one_message() -> Outgoing:
    notices = (alarm(0, "ch1.overvoltage", "critical", "ch1"), alarm(0.2, "estop", "critical"))
    return Outgoing(
        "hook",
        message_key("sim", "hook", "summary", notices),
        "summary",
        "critical",
        "[sim] 2 alarms",
        'line one\nline "two"',
        notices,
    )


def test_the_json_payload_is_the_documented_one_with_the_idempotency_key_header() -> None:
    m = one_message()
    cfg = routes_cfg(hook()).routes[0]
    url, body, headers = webhook_request(cfg, "sim", m)  # type: ignore[arg-type]
    assert url == "http://127.0.0.1:9/in"
    data = json.loads(body)
    assert data == payload("sim", m)
    assert set(data) == {
        "version",
        "bench",
        "route",
        "key",
        "kind",
        "priority",
        "escalation",
        "subject",
        "text",
        "events",
    }
    assert set(data["events"][0]) == {"time", "kind", "source", "channel", "priority", "text"}
    assert data["events"][0]["time"] == "2026-01-01T00:00:00.000Z"
    assert headers["Idempotency-Key"] == m.key
    assert headers["Content-Type"] == "application/json"


@pytest.mark.parametrize(
    ("fmt", "check"),
    [
        ("slack", lambda body, h: json.loads(body)["text"].startswith("[sim] 2 alarms\nline")),
        ("teams", lambda body, h: json.loads(body)["title"] == "[sim] 2 alarms"),
        (
            "ntfy",
            lambda body, h: (
                body.startswith("line one")
                and h["Title"] == "[sim] 2 alarms"
                and h["Priority"] == "5"
            ),
        ),
    ],
)
def test_ntfy_slack_and_teams_are_templates_of_the_same_message(
    fmt: str, check: Callable[[str, dict[str, str]], bool]
) -> None:
    cfg = routes_cfg(hook(format=fmt)).routes[0]
    _, body, headers = webhook_request(cfg, "sim", one_message())  # type: ignore[arg-type]
    assert check(body.decode(), headers), body
    assert headers["Idempotency-Key"] == one_message().key


def test_a_custom_template_quotes_each_field_as_json() -> None:
    cfg = routes_cfg(
        hook(format="template", template='{"msg": $subject, "n": $count, "body": $text}')
    ).routes[0]
    _, body, _ = webhook_request(cfg, "sim", one_message())  # type: ignore[arg-type]
    assert json.loads(body) == {"msg": "[sim] 2 alarms", "n": "2", "body": 'line one\nline "two"'}


def test_a_mail_carries_the_key_as_its_message_id_and_escalations_go_to_escalate_to() -> None:
    route = routes_cfg(
        {
            "name": "mail",
            "type": "email",
            "host": "h",
            "from": "b@lab.test",
            "to": ["o@lab.test"],
            "escalate_to": ["boss@lab.test"],
            "escalate_after_s": 60,
        }
    ).routes[0]
    m = one_message()
    msg = email_message(route, "sim", m)  # type: ignore[arg-type]
    assert msg["Message-ID"] == f"<{m.key}@sim.notify>" and msg["To"] == "o@lab.test"
    esc = Outgoing("mail", "k", "escalation", "high", "s", "t", m.notices, escalation=True)
    assert email_message(route, "sim", esc)["To"] == "boss@lab.test"  # type: ignore[arg-type]
