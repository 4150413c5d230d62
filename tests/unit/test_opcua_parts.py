"""The OPC UA server's parts that need no server: status codes, units, the layout of the
address space, method arguments, the users file and roles, and the scan's feed."""

from __future__ import annotations

from pathlib import Path

import pytest
from asyncua import ua
from commandrig import io_map

from supervisor.commands import Command, EveryoneOperates, ResultKind, Verb
from supervisor.config.users import check_password, hash_password, read_users
from supervisor.core.errors import ConfigError
from supervisor.core.quality import Quality, Reason
from supervisor.core.records import BenchEvent
from supervisor.devices.registry import load_bench
from supervisor.publish.historian import StoredSample
from supervisor.publish.opcua import OpcUaFeed, OpcUaRoles, UserStore, add_user, plan, remove_user
from supervisor.publish.opcua.feed import EVENT_QUEUE, AlarmView
from supervisor.publish.opcua.history import time_average
from supervisor.publish.opcua.methods import (
    METHODS,
    check,
    parse_parameters,
    request,
)
from supervisor.publish.opcua.settings import sampling_interval_s
from supervisor.publish.opcua.statuses import REFUSAL_STATUS, quality_status
from supervisor.publish.opcua.units import eu_information, unit_id
from supervisor.tags import Access, TagDB, TagSpec

S = ua.StatusCodes
VT = ua.VariantType


# --- status codes ---------------------------------------------------------------------------
@pytest.mark.parametrize("quality", list(Quality))
@pytest.mark.parametrize("reason", list(Reason))
def test_every_quality_and_reason_has_a_status_code_of_the_same_severity(
    quality: Quality, reason: Reason
) -> None:
    code = ua.StatusCode(quality_status(quality, reason))
    severity = {
        Quality.GOOD: code.is_good,
        Quality.UNCERTAIN: code.is_uncertain,
        Quality.BAD: code.is_bad,
    }
    assert severity[quality](), (quality, reason, code.name)


@pytest.mark.parametrize(
    ("quality", "reason", "name"),
    [
        (Quality.GOOD, Reason.NONE, "Good"),
        (Quality.GOOD, Reason.FORCED, "GoodLocalOverride"),
        (Quality.UNCERTAIN, Reason.LAST_KNOWN, "UncertainLastUsableValue"),
        (Quality.UNCERTAIN, Reason.INITIAL, "UncertainInitialValue"),
        (Quality.BAD, Reason.NOT_CONNECTED, "BadNoCommunication"),
        (Quality.BAD, Reason.COMM_FAILURE, "BadCommunicationError"),
        (Quality.BAD, Reason.SENSOR_FAILURE, "BadSensorFailure"),
        (Quality.BAD, Reason.STALE, "Bad"),
        (Quality.BAD, Reason.INITIAL, "BadWaitingForInitialData"),
        (Quality.BAD, Reason.NOT_FITTED, "BadOutOfService"),
    ],
)
def test_the_quality_table_of_adr_0014(quality: Quality, reason: Reason, name: str) -> None:
    assert ua.StatusCode(quality_status(quality, reason)).name == name


def test_a_disabled_source_is_out_of_service() -> None:
    class Disabled:  # a reason that will exist: matched by its text
        def __str__(self) -> str:
            return "disabled"

    assert quality_status(Quality.BAD, Disabled()) == S.BadOutOfService  # type: ignore[arg-type]


def test_every_refusal_of_the_command_path_has_a_status_code() -> None:
    kinds = {k.value for k in ResultKind if k is not ResultKind.ACCEPTED}
    assert set(REFUSAL_STATUS) == kinds
    assert REFUSAL_STATUS["refused"] == S.BadInvalidState
    assert REFUSAL_STATUS["forbidden"] == S.BadUserAccessDenied
    assert REFUSAL_STATUS["not found"] == S.BadNotFound
    assert REFUSAL_STATUS["bad argument"] == S.BadInvalidArgument


# --- units ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("unit", "code", "uid"),
    [("V", "VLT", 5655636), ("A", "AMP", 4279632), ("degC", "CEL", 4408652),
     ("Ah", "AMH", 4279624), ("Wh", "WHR", 5720146), ("s", "SEC", 5457219)],
)  # fmt: skip
def test_units_are_unece_codes_packed_into_an_int32(unit: str, code: str, uid: int) -> None:
    assert unit_id(code) == uid
    assert eu_information(unit).UnitId == uid


def test_watt_is_wtt_packed_the_same_way_and_an_unknown_unit_is_minus_one() -> None:
    assert eu_information("W").UnitId == (ord("W") << 16) | (ord("T") << 8) | ord("T")
    assert eu_information("degC").DisplayName.Text == "°C"
    odd = eu_information("furlong")
    assert (odd.UnitId, odd.DisplayName.Text) == (-1, "furlong")


# --- layout --------------------------------------------------------------------------------
def test_the_layout_names_channel_tags_for_people_and_keeps_node_ids_as_tag_names(
    tmp_path: Path,
) -> None:
    from supervisor.app import build_bench
    from supervisor.core.clock import VirtualClock

    bench = build_bench(load_bench(io_map(tmp_path)), VirtualClock(), in_process=True)
    layout = plan(bench.cfg, bench.db, [a.id for a in bench.alarms or []])
    v = layout.variables
    assert (v["ch0.voltage"].browse, v["ch0.voltage"].kind) == ("Voltage", "analog")
    # The test's state: the channel's StateMachine/CurrentState and its Number.
    assert (v["ch0.chain.state_code"].browse, v["ch0.chain.state_code"].kind) == ("Number", "state")
    assert (v["ch0.chain.state"].browse, v["ch0.chain.state"].kind) == ("CurrentState", "statename")
    assert v["ch0.state"].browse == "DriveState"
    assert v["ch0.chain.eta_s"].browse == "ETA"
    assert v["ch0.chain.alarm"].browse == "Alarm"
    assert v["ch0.limit.charge_a"].browse == "LimitChargeA"
    assert v["ch0.mode"].writable and not v["ch0.voltage"].writable
    assert v["adam.connected"].browse == "Connected"
    assert v["room.temp"].browse == "RoomTemp"
    assert v["scan.period_s"].browse == "ScanPeriodS"
    assert set(v) == set(bench.db.names()), "every tag has a node"
    nodes = [f.node for f in layout.root.walk()]
    assert len(nodes) == len(set(nodes)) and all(n.startswith("/") for n in nodes)


# --- methods -------------------------------------------------------------------------------
START = next(m for m in METHODS if m.name == "Start")


def test_parameters_are_k_equals_v_pairs_as_one_text_or_an_array() -> None:
    assert parse_parameters("v_max=1.8 V; q_max = 1300 mAh;") == {
        "v_max": "1.8 V",
        "q_max": "1300 mAh",
    }
    assert parse_parameters(["v_max=1.8 V", "q_max=1 Ah"]) == {"v_max": "1.8 V", "q_max": "1 Ah"}
    assert parse_parameters("") == {}
    with pytest.raises(ValueError, match="'=1' is not name=value"):
        parse_parameters("=1")


def test_a_call_is_checked_against_the_method_s_declaration() -> None:
    ok = [ua.Variant("r.yaml", VT.String), ua.Variant(["a=1"], VT.String)]
    assert check(START, ok) is None
    bad = check(START, [ua.Variant(3, VT.Int32), ua.Variant("", VT.String)])
    assert bad is not None and bad.status == S.BadInvalidArgument
    assert bad.arg_results == (S.BadTypeMismatch, S.Good)
    assert check(START, ok[:1]).status == S.BadArgumentsMissing  # type: ignore[union-attr]


def test_a_call_becomes_a_request_in_the_command_path_s_words() -> None:
    # The recipe as the client named it: the command path finds a name in the recipe
    # folders and refuses a path outside them (ADR 0026), not this layer.
    req = request(
        START,
        "ch0",
        [ua.Variant("slow", VT.String), ua.Variant("v=1 V", VT.String)],
        "opcua:a",
    )
    assert req.args == {"recipe": "slow", "parameters": {"v": "1 V"}}  # type: ignore[union-attr]
    mode = next(m for m in METHODS if m.name == "SetMode")
    assert request(mode, "ch1", [ua.Variant("Manual", VT.String)], "x").args == {  # type: ignore[union-attr]
        "value": "manual"
    }


# --- users and roles -------------------------------------------------------------------------
def test_a_password_is_stored_as_a_salted_scrypt_hash(tmp_path: Path) -> None:
    h1, h2 = hash_password("pw"), hash_password("pw")
    assert h1 != h2 and h1.startswith("scrypt$16384$8$1$")
    assert check_password("pw", h1) and not check_password("PW", h1)
    assert not check_password("pw", "scrypt$1048577$8$1$AA==$AA==")  # work bounded


def test_the_users_file_is_written_by_add_user_and_read_again_when_it_changes(
    tmp_path: Path,
) -> None:
    path = tmp_path / "opcua" / "users.yaml"
    assert add_user(path, "alice", "operator", "a-pw") is True
    assert add_user(path, "alice", "engineer", "b-pw") is False  # replaced
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    store = UserStore(path)
    assert store.authenticate("alice", "a-pw") is None
    user = store.authenticate("alice", "b-pw")
    assert user is not None and (user.role, user.access) == ("engineer", Access.ENGINEER)
    assert store.authenticate("alice", "b-pw") == user  # the second check is remembered
    add_user(path, "bob", "viewer", "c-pw")
    assert store.authenticate("bob", "c-pw") is not None  # no restart
    assert remove_user(path, "bob") and store.authenticate("bob", "c-pw") is None
    with pytest.raises(ConfigError, match="anonymous"):
        add_user(path, "anonymous", "viewer", "x")
    with pytest.raises(ConfigError, match="role 'root'"):
        add_user(path, "eve", "root", "x")


def test_a_bad_users_file_names_its_line(tmp_path: Path) -> None:
    path = tmp_path / "users.yaml"
    path.write_text("users:\n  alice: {role: operator, password: secret}\n", "utf-8")
    with pytest.raises(ConfigError) as e:
        read_users(path)
    assert e.value.location_message().startswith(f"{path}:2:")
    assert "secret" not in e.value.location_message()
    path.write_text("users:\n  alice: {role: admin, password: x}\n", "utf-8")
    with pytest.raises(Exception, match=r"users.yaml:2:"):
        read_users(path)


def test_opc_ua_actors_get_their_role_others_keep_the_old_hook(tmp_path: Path) -> None:
    path = tmp_path / "users.yaml"
    add_user(path, "alice", "operator", "x")
    add_user(path, "bob", "viewer", "x")
    add_user(path, "carol", "engineer", "x")
    roles = OpcUaRoles(UserStore(path), EveryoneOperates())
    assert roles.access_of("opcua:alice") is Access.OPERATOR
    assert roles.access_of("opcua:carol") is Access.ENGINEER
    assert roles.access_of("opcua:bob") is Access.READ_ONLY
    assert roles.access_of("opcua:anonymous") is Access.READ_ONLY
    assert roles.access_of("opcua:gone") is Access.READ_ONLY
    assert roles.access_of("operator") is Access.OPERATOR  # the HTTP API's actor
    hold = Command.channel("ch0", Verb.HOLD, "opcua:bob")
    assert roles.refuses(hold) == "opcua:bob may only read (role viewer): log in as an operator"
    assert roles.refuses(Command.channel("ch0", Verb.HOLD, "opcua:alice")) == ""
    assert roles.refuses(Command.channel("ch0", Verb.HOLD, "operator")) == ""


# --- the scan's feed ----------------------------------------------------------------------
def test_the_feed_keeps_one_update_per_tag_and_counts_the_replaced_ones() -> None:
    db = TagDB()
    a = db.add(TagSpec("a"))
    feed = OpcUaFeed(db)
    woken: list[int] = []
    first = feed.start(db, lambda: woken.append(1))
    assert {u.name for u in first} == {
        "a",
        "opcua.dropped",
        "opcua.replaced",
        "opcua.queue_depth",
        "opcua.clients",
        "opcua.restarts",
    }
    for k in range(5):  # five scans while the server does not take anything
        db.update(a, float(k))
        feed.on_scan(db, float(k))
    pending = {u.name: u for u in feed.take()}
    assert pending["a"].value == 4.0  # the latest value always gets through
    # The four values it replaced are counted as replaced (by design), not as lost: the
    # Diagnostics screen paints a lost update red (issue 33, finding 6).
    assert feed.replaced >= 4 and feed.dropped == 0
    db.update(a, 9.0)
    feed.on_scan(db, 5.0)
    assert db["opcua.replaced"].value == feed.replaced and woken
    assert db["opcua.dropped"].value == 0


def test_an_update_is_the_tags_state_as_the_scan_left_it() -> None:
    db = TagDB()
    a = db.add(TagSpec("a", unit="V"))
    feed = OpcUaFeed(db)
    feed.start(db, lambda: None)
    db.set_scan_time(7.5)
    db.update(a, None, Quality.BAD, Reason.STALE, source_t=7.25)
    feed.on_scan(db, 7.5)
    (u,) = (u for u in feed.take() if u.name == "a")
    assert u == (a.index, "a", None, Quality.BAD, Reason.STALE, 7.25, 7.5)
    assert (u.tag_index, u.quality, u.reason, u.source_t, u.server_t) == (
        a.index,
        Quality.BAD,
        Reason.STALE,
        7.25,
        7.5,
    )
    db.update(a, 1.5)  # the tag changes on; the update handed over does not
    assert u.value is None


def test_at_a_sampling_interval_the_feed_hands_over_the_latest_values_once_per_interval() -> None:
    db = TagDB()
    a, b = db.add(TagSpec("a")), db.add(TagSpec("b"))
    feed = OpcUaFeed(db)
    feed.sampling_interval_s = 0.05  # a 10 ms scan, a 50 ms sampling interval
    woken: list[float] = []
    feed.start(db, lambda: woken.append(0.0))
    handed: list[tuple[float, dict[str, object]]] = []
    for k in range(20):  # 0.2 s of scans
        t = k * 0.01
        db.update(a, float(k))
        if k == 3:
            db.update(b, 42.0)  # changed once, between two hand-overs
        feed.on_scan(db, t)
        got = {u.name: u.value for u in feed.take() if u.name in ("a", "b")}
        if got:
            handed.append((round(t, 3), got))
    assert [t for t, _ in handed] == [0.0, 0.05, 0.1, 0.15]
    assert [got["a"] for _, got in handed] == [0.0, 5.0, 10.0, 15.0]  # the latest value
    assert handed[1][1]["b"] == 42.0  # changed between two hand-overs: not lost
    assert "b" not in handed[2][1]
    assert len(woken) == 4  # the server is woken once per interval, not once per scan
    assert feed.dropped == 0  # what waits in the tag database is not a dropped update


def test_scans_a_little_late_or_early_on_the_grid_still_hand_over_every_interval() -> None:
    # A 50 ms scan and interval: the first scan started 2 ms late, the others on time or
    # a little late (their jitter). Each one hands over (it handed over every other scan
    # when the grid was drawn from the scans' own times).
    db = TagDB()
    a = db.add(TagSpec("a"))
    feed = OpcUaFeed(db)
    feed.sampling_interval_s = 0.05
    feed.start(db, lambda: None)
    starts = [0.002, 0.0501, 0.1, 0.1503, 0.2, 0.25002, 0.3]
    handed = 0
    for k, t in enumerate(starts):
        db.update(a, float(k))
        feed.on_scan(db, t)
        handed += any(u.name == "a" for u in feed.take())
    assert handed == len(starts)


def test_events_are_not_sampled_the_first_one_the_server_has_not_taken_wakes_it() -> None:
    db = TagDB()
    feed = OpcUaFeed(db)
    feed.sampling_interval_s = 1.0
    woken: list[int] = []
    feed.start(db, lambda: woken.append(1))
    feed.on_scan(db, 0.0)
    feed.on_scan(db, 0.01)
    before = len(woken)
    for ch in range(16):  # every channel changes step in the same scan
        feed.on_event(BenchEvent(0.02, 0.0, "step", f"ch{ch}", "d", "starting step 1 d"))
    assert len(woken) == before + 1  # at once (not at a sampling instant), and once
    assert len(feed.take_events()) == 16
    feed.on_scan(db, 0.02)
    assert len(woken) == before + 1  # nothing new: no wake-up
    feed.on_event(BenchEvent(0.03, 0.0, "step", "ch0", "d", "starting step 2 d"))
    assert len(woken) == before + 2  # taken meanwhile: the next one wakes it again


@pytest.mark.parametrize(
    ("period_s", "configured_s", "expected_s"),
    [
        (0.1, None, 0.1),  # the shipped benches: every scan, as before
        (0.01, None, 0.05),  # a 10 ms scan: 20 samples a second by default
        (0.01, 0.02, 0.02),  # or what the I/O map says
        (0.1, 0.02, 0.1),  # never faster than the tags change
    ],
)
def test_the_sampling_interval_is_the_scan_period_but_not_under_50_ms_by_default(
    period_s: float, configured_s: float | None, expected_s: float
) -> None:
    assert sampling_interval_s(period_s, configured_s) == pytest.approx(expected_s)


def test_events_wait_in_a_bounded_queue_and_the_excess_is_counted() -> None:
    db = TagDB()
    feed = OpcUaFeed(db)
    feed.start(db, lambda: None)
    ev = BenchEvent(0.0, 0.0, "step", "ch0", "d", "starting step 1 d")
    for _ in range(EVENT_QUEUE + 3):
        feed.on_event(ev)
    feed.on_event(BenchEvent(0.0, 0.0, "alarm", "ch0", "x", "x"))  # alarms come as conditions
    assert len(feed.take_events()) == EVENT_QUEUE
    assert feed.dropped == 3
    feed.on_alarm(AlarmView("x", "", 500, "m", "active, unacknowledged", True, False))
    assert [type(e) for e in feed.take_events()] == [AlarmView]


def test_the_feed_does_not_queue_before_the_server_serves() -> None:
    db = TagDB()
    a = db.add(TagSpec("a"))
    feed = OpcUaFeed(db)
    db.update(a, 1.0)
    feed.on_scan(db, 0.0)
    feed.on_event(BenchEvent(0.0, 0.0, "step", "", "", ""))
    assert feed.empty() and feed.dropped == 0


def test_time_average_is_stepped_and_skips_what_had_no_value() -> None:
    good, bad = Quality.GOOD, Quality.BAD
    samples = [
        StoredSample(10.5, 2.0, good),  # 1.0 holds before it (``before``)
        StoredSample(11.0, None, bad),  # no value for [11, 11.5)
        StoredSample(11.5, 4.0, good),
    ]
    before = StoredSample(9.0, 1.0, good)
    got = time_average(samples, before, 10.0, 12.0, 1.0, 2)
    assert got[0] == (pytest.approx(1.5), False)  # 1.0 for 0.5 s, 2.0 for 0.5 s
    assert got[1] == (pytest.approx(4.0), True)  # only [11.5, 12) had a value
    # Nothing before the first sample: that part has no value, the interval is partial.
    assert time_average(samples, None, 10.0, 11.0, 1.0, 1) == [(pytest.approx(2.0), True)]
    assert time_average([], None, 10.0, 11.0, 1.0, 1) == [(None, True)]
