"""Issue 33 finding 7, the server's side: an operator silences the alarm sound of their own
screen (``POST /api/alarms/silence``). A silence changes no alarm (it is not an
acknowledgement) and is recorded, with its actor and time, in the alarms' history beside
the acknowledgements; only the alarms still waiting for an acknowledgement are silenced;
an unknown alarm or a malformed body records nothing."""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
from aiohttp import web
from aiohttp.test_utils import TestClient, TestServer
from pydantic import ValidationError

from supervisor.audit import AUDIT_NAME, AuditLog, read_entries, verify_file
from supervisor.config.models import HmiConfig
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import OperatorError
from supervisor.hmi.silence_api import add_silence_route
from supervisor.safety import AlarmManager, AlarmState, Severity
from supervisor.safety.alarms import AlarmEvent, Transition


@pytest.fixture
def alarms() -> AlarmManager:
    return AlarmManager(VirtualClock())


def raised(alarms: AlarmManager, alarm_id: str, severity: Severity = Severity.HIGH) -> None:
    alarms.set(alarms.declare(alarm_id, severity=severity), True, f"{alarm_id} is on")


def silences(alarms: AlarmManager) -> list[AlarmEvent]:
    return [e for e in alarms.history if e.transition is Transition.SILENCED]


def test_a_silence_is_recorded_with_its_actor_and_changes_no_alarm(alarms: AlarmManager) -> None:
    raised(alarms, "pack.temp.HH")
    writes = alarms.writes
    done = alarms.silence(["pack.temp.HH"], "hmi:otto")
    assert [a.id for a in done] == ["pack.temp.HH"]
    assert alarms["pack.temp.HH"].state is AlarmState.ACTIVE_UNACKED  # still to acknowledge
    assert alarms.writes == writes  # no alarm changed: the checks need not look again
    (ev,) = silences(alarms)
    assert (ev.alarm_id, ev.actor, ev.state) == ("pack.temp.HH", "hmi:otto", ev.state)
    assert ev.wall > 0 and ev.state is AlarmState.ACTIVE_UNACKED


def test_the_listeners_hear_a_silence_as_they_hear_an_acknowledgement(
    alarms: AlarmManager,
) -> None:
    heard: list[tuple[str, str]] = []
    alarms.listeners.append(lambda ev: heard.append((ev.transition.value, ev.actor)))
    raised(alarms, "estop", Severity.CRITICAL)
    alarms.silence(["estop"], "hmi:otto")
    alarms.acknowledge("estop", "hmi:anna")
    assert heard[1:] == [("silenced", "hmi:otto"), ("acknowledged", "hmi:anna")]


def test_only_unacknowledged_alarms_are_silenced_and_an_unknown_one_records_nothing(
    alarms: AlarmManager,
) -> None:
    raised(alarms, "a")
    raised(alarms, "b")
    alarms.acknowledge("b", "hmi:anna")
    assert [a.id for a in alarms.silence(["a", "b", "a"], "hmi:otto")] == ["a"]
    with pytest.raises(OperatorError, match="unknown alarm 'nope'"):
        alarms.silence(["a", "nope"], "hmi:otto")
    assert len(silences(alarms)) == 1


@pytest.fixture
def audit(tmp_path: Path) -> Iterator[AuditLog]:
    trail = AuditLog(tmp_path / AUDIT_NAME).open()
    yield trail
    trail.close()


@pytest.fixture
async def client(
    alarms: AlarmManager, audit: AuditLog
) -> AsyncIterator[TestClient[web.Request, web.Application]]:
    app = web.Application()
    # Who asks: here a header (the login middleware's actor in the supervisor).
    add_silence_route(
        app, lambda: alarms, lambda r: r.headers.get("X-Test-User", "operator"), lambda: audit
    )
    async with TestClient(TestServer(app)) as c:
        yield c


async def test_post_silence_records_the_logged_in_users_silence(
    client: TestClient[web.Request, web.Application], alarms: AlarmManager
) -> None:
    raised(alarms, "estop", Severity.CRITICAL)
    resp = await client.post(
        "/api/alarms/silence", json={"alarms": ["estop"]}, headers={"X-Test-User": "hmi:otto"}
    )
    body = await resp.json()
    assert resp.status == 200, body
    assert body["accepted"] and body["silenced"] == ["estop"] and "hmi:otto" in body["reason"]
    assert [(e.alarm_id, e.actor) for e in silences(alarms)] == [("estop", "hmi:otto")]


async def test_a_silence_is_an_entry_of_the_audit_trail_and_a_refused_one_is_not(
    client: TestClient[web.Request, web.Application], alarms: AlarmManager, audit: AuditLog
) -> None:
    raised(alarms, "estop", Severity.CRITICAL)
    headers = {"X-Test-User": "hmi:otto"}
    await client.post("/api/alarms/silence", json={"alarms": ["nope"]}, headers=headers)
    await client.post("/api/alarms/silence", json={"alarms": ["estop"]}, headers=headers)
    assert audit.flush()
    entries = read_entries(audit.path)
    assert [(e.actor, e.kind, e.target, e.details_json) for e in entries] == [
        ("hmi:otto", "alarm.silence", "estop", {"alarms": ["estop"]})
    ]
    assert verify_file(audit.path).ok


@pytest.mark.parametrize(
    ("body", "status", "why"),
    [
        ({"alarms": ["nope"]}, 404, "unknown alarm 'nope'"),
        ({"alarms": "estop"}, 400, '"alarms": ["alarm id", ...]'),
        ({"alarms": [""]}, 400, '"alarms": ["alarm id", ...]'),
        ({"alarm": ["estop"]}, 400, "unknown member 'alarm'"),
    ],
)
async def test_post_silence_refuses_an_unknown_alarm_or_a_bad_body_and_records_nothing(
    client: TestClient[web.Request, web.Application],
    alarms: AlarmManager,
    body: object,
    status: int,
    why: str,
) -> None:
    raised(alarms, "estop", Severity.CRITICAL)
    resp = await client.post("/api/alarms/silence", json=body)
    answer = await resp.json()
    assert resp.status == status, answer
    assert not answer["accepted"] and why in answer["reason"]
    assert silences(alarms) == []


def test_the_repeat_interval_is_an_hmi_setting_of_ten_seconds_by_default() -> None:
    assert HmiConfig().alarm_sound_repeat_s == 10.0
    assert HmiConfig(alarm_sound_repeat_s=4).alarm_sound_repeat_s == 4.0
    for unbearable in (0.5, 3600):  # a continuous wail, or an alarm heard once an hour
        with pytest.raises(ValidationError, match="alarm_sound_repeat_s"):
            HmiConfig(alarm_sound_repeat_s=unbearable)
