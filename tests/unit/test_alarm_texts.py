"""Issue 33, finding 6: alarm texts an operator reads say what happened in words, naming a
signal by its description in the I/O map, the tag behind it kept as the alarm's detail;
and each carries a stable code with its figures (params), which the HMI receives with the
alarm so that a screen in another language can say the same."""

from __future__ import annotations

from supervisor.config.models import EstopConfig
from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality, Reason
from supervisor.hmi.server import alarm_event_json, alarm_json
from supervisor.safety import AlarmManager
from supervisor.safety.alarms import AlarmText
from supervisor.safety.interlocks import Estop
from supervisor.tags import TagDB, TagSpec


def estop_rig() -> tuple[TagDB, AlarmManager, Estop, VirtualClock]:
    clock = VirtualClock()
    alarms = AlarmManager(clock)
    db = TagDB()
    db.add(TagSpec("estop.ok", dtype="bool", initial=True, description="e-stop circuit closed"))
    return db, alarms, Estop(EstopConfig(tag="estop.ok"), db, alarms), clock


def test_the_pressed_estop_is_said_in_words_with_its_code_and_the_tag_as_detail() -> None:
    db, alarms, estop, clock = estop_rig()
    db.update(db["estop.ok"], False)
    estop.evaluate(0.0, 0.1)
    shown = alarm_json(alarms["estop"], clock)
    assert shown["message"] == "Emergency stop pressed (e-stop circuit open)"
    assert (shown["code"], shown["params"]) == (
        "estop.pressed",
        {"signal": "e-stop circuit closed"},
    )
    assert shown["detail"] == "estop.ok is false"
    assert "is false" not in shown["message"]


def test_the_software_estop_and_an_unknown_estop_state_have_their_own_codes() -> None:
    db, alarms, estop, clock = estop_rig()
    estop.press("alice")
    shown = alarm_json(alarms["estop"], clock)
    assert shown["message"] == "Software e-stop pressed by alice"
    assert (shown["code"], shown["params"]) == ("estop.software", {"actor": "alice"})
    db.update(db["estop.ok"], None, Quality.BAD, Reason.COMM_FAILURE)
    estop.evaluate(0.1, 0.1)
    unknown = alarm_json(alarms["estop.unknown"], clock)
    assert unknown["code"] == "estop.unknown"
    assert unknown["message"].startswith("E-stop state unknown: its input e-stop circuit closed")
    assert unknown["detail"].startswith("estop.ok is BAD")


def test_an_alarm_keeps_a_plain_text_for_events_logs_and_files() -> None:
    clock = VirtualClock()
    alarms = AlarmManager(clock)
    a = alarms.declare("x")
    alarms.set(a, True, AlarmText("Something in words", "x.kind", {"n": 1}, "x.tag is false"))
    assert type(a.message) is str and a.message == "Something in words"
    assert type(alarms.history[-1].message) is str
    assert (a.code, a.params, a.detail) == ("x.kind", {"n": 1}, "x.tag is false")
    # A plain text (an alarm without a code yet) has none: the screen shows its message.
    b = alarms.declare("y")
    alarms.set(b, True, "plain")
    assert alarm_json(b, clock)["code"] == "" and alarm_json(b, clock)["params"] == {}


def test_the_journal_s_activation_and_clear_carry_the_code_for_the_screens_language() -> None:
    """The Alarms screen's history says an entry in French from its code, as the active
    list does (issue 33 finding 9); an acknowledgement's text is no alarm message: none."""
    clock = VirtualClock()
    alarms = AlarmManager(clock)
    a = alarms.declare("x")
    alarms.set(a, True, AlarmText("Something in words", "x.kind", {"n": 1}, "x.tag is false"))
    alarms.acknowledge("x", "hmi:otto")
    alarms.set(a, False)
    journal = [alarm_event_json(e) for e in alarms.history]
    assert [(e["transition"], e["code"], e["params"]) for e in journal] == [
        ("activated", "x.kind", {"n": 1}),
        ("acknowledged", "", {}),
        ("cleared", "x.kind", {"n": 1}),
    ]
    assert all(type(e["message"]) is str for e in journal)
