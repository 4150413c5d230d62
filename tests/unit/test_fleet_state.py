"""The fleet's state machine (supervisor.fleet.state), fed with the messages of the
project's own edge node code (``Session``: payload.py) and with one built by pysparkplug,
the independent library: births, data by metric name, death with the bdSeq of the births
or of an older session, and a seq gap → a rebirth asked."""

from __future__ import annotations

from typing import Any

import pysparkplug as ps

from supervisor.core.quality import Quality
from supervisor.fleet import Fleet, fleet_json, rebirth_request
from supervisor.fleet.state import REBIRTH_RETRY_MS
from supervisor.publish.sparkplug import Layout, Message, Session, decode
from supervisor.publish.sparkplug.node import Metric, is_rebirth

GROUP = "Lab"
T0 = 1_780_000_000_000


def metric(dtype: str, value: object, unit: str = "") -> Metric:
    return Metric(dtype, unit, value, Quality.GOOD, T0)  # type: ignore[arg-type]


def bench_metrics(voltage: float = 3.7) -> dict[str, Metric]:
    return {
        "scan.count": metric("int", 5),
        "alarms.active": metric("int", 2),
        "hmi.url": metric("str", "http://bench-a:8080/"),
        "ch0.state": metric("str", "on"),
        "ch0.chain.state": metric("str", "running"),
        "ch0.chain.step": metric("str", "charge"),
        "ch0.chain.progress": metric("float", 0.25, "1"),
        "ch0.voltage": metric("float", voltage, "V"),
        "ch0.current": metric("float", -1.5, "A"),
        "ch1.chain.state": metric("str", "idle"),
        "ch1.voltage": metric("float", 3.3, "V"),
        "psu.output": metric("bool", True),
    }


def session(edge: str = "bench-a") -> Session:
    return Session(GROUP, edge, Layout(("ch0", "ch1"), ("psu",)))


def feed(fleet: Fleet, messages: list[Message], now_ms: int = T0) -> list[str]:
    asked: list[str] = []
    for m in messages:
        asked += fleet.receive(m.topic, m.payload, now_ms)
    return asked


def node_json(fleet: Fleet, edge: str = "bench-a") -> dict[str, Any]:
    nodes = {n["id"]: n for n in fleet_json(fleet, connected=True, now_ms=T0)["nodes"]}
    node: dict[str, Any] = nodes[edge]
    return node


def channel(fleet: Fleet, ch: str, edge: str = "bench-a") -> dict[str, Any]:
    channels = node_json(fleet, edge)["channels"]
    assert isinstance(channels, list)
    return next(c for c in channels if c["id"] == ch)


def born(edge: str = "bench-a", bd_seq: int = 7) -> tuple[Fleet, Session]:
    fleet, s = Fleet(GROUP), session(edge)
    assert feed(fleet, s.births(bd_seq, bench_metrics(), T0)) == []
    return fleet, s


def test_births_make_a_node_online_with_its_channels_state_step_v_i_and_progress() -> None:
    fleet, _ = born()
    node = node_json(fleet)
    assert node["online"] is True and node["since_ms"] == T0 and node["bd_seq"] == 7
    assert node["url"] == "http://bench-a:8080/"
    assert node["alarms_active"] == 2
    assert node["devices"] == ["psu"]
    assert channel(fleet, "ch0") == {
        "id": "ch0",
        "online": True,
        "state": "running",
        "step": "charge",
        "voltage_v": 3.7,
        "current_a": -1.5,
        "progress": 0.25,
        "alarm": None,
    }
    assert channel(fleet, "ch1")["step"] is None  # not published: null, never guessed
    body = fleet_json(fleet, connected=True, now_ms=T0)
    assert (body["online"], body["offline"]) == (1, 0)


def test_without_a_url_or_an_alarm_count_published_there_is_none() -> None:
    fleet, s = Fleet(GROUP), session()
    metrics = bench_metrics()
    del metrics["hmi.url"], metrics["alarms.active"]
    feed(fleet, s.births(0, metrics, T0))
    assert node_json(fleet)["url"] is None and node_json(fleet)["alarms_active"] is None


def test_data_is_applied_by_metric_name_onto_the_births() -> None:
    fleet, s = born()
    changes = [
        ("ch0.voltage", metric("float", 4.1, "V")),
        ("ch0.chain.step", metric("str", "rest")),
        ("alarms.active", metric("int", 0)),
    ]
    assert feed(fleet, s.data(changes, T0 + 1000)) == []
    assert channel(fleet, "ch0")["voltage_v"] == 4.1
    assert channel(fleet, "ch0")["step"] == "rest"
    assert channel(fleet, "ch0")["current_a"] == -1.5  # unchanged: the birth's
    assert node_json(fleet)["alarms_active"] == 0


def test_a_negative_integer_comes_back_negative() -> None:
    fleet, s = born()
    feed(fleet, s.data([("alarms.active", metric("int", -3))], T0))
    assert node_json(fleet)["alarms_active"] == -3


def test_a_death_with_the_births_bdseq_makes_the_node_offline_since_then() -> None:
    fleet, s = born(bd_seq=7)
    assert feed(fleet, [s.death(7, T0)], now_ms=T0 + 5000) == []
    node = node_json(fleet)
    assert node["online"] is False and node["since_ms"] == T0 + 5000
    assert all(c["online"] is False for c in node["channels"])
    body = fleet_json(fleet, connected=True, now_ms=T0)
    assert (body["online"], body["offline"]) == (0, 1)


def test_a_late_death_of_an_older_session_is_ignored() -> None:
    fleet, s = born(bd_seq=8)
    feed(fleet, [s.death(7, T0)], now_ms=T0 + 5000)
    assert node_json(fleet)["online"] is True and node_json(fleet)["since_ms"] == T0


def test_a_restart_is_online_again_with_the_new_bdseq() -> None:
    fleet, s = born(bd_seq=7)
    feed(fleet, [s.death(7, T0)], now_ms=T0 + 5000)
    feed(fleet, s.births(8, bench_metrics(3.9), T0 + 9000), now_ms=T0 + 9000)
    node = node_json(fleet)
    assert node["online"] is True and node["bd_seq"] == 8 and node["since_ms"] == T0 + 9000
    assert channel(fleet, "ch0")["voltage_v"] == 3.9


def test_a_seq_gap_asks_a_rebirth_once_and_applies_nothing_until_it() -> None:
    fleet, s = born()
    s.data([("ch0.voltage", metric("float", 3.8, "V"))], T0)  # lost on the way
    gap = s.data([("ch0.voltage", metric("float", 3.9, "V"))], T0)
    assert feed(fleet, gap, now_ms=T0 + 100) == ["bench-a"]
    assert node_json(fleet)["in_sync"] is False and node_json(fleet)["seq_gaps"] == 1
    assert channel(fleet, "ch0")["voltage_v"] == 3.7  # not applied
    later = s.data([("ch0.voltage", metric("float", 4.0, "V"))], T0)
    assert feed(fleet, later, now_ms=T0 + 200) == []  # asked already
    assert channel(fleet, "ch0")["voltage_v"] == 3.7
    # the rebirth comes: in sync again, with the current values
    assert feed(fleet, s.births(7, bench_metrics(4.0), T0), now_ms=T0 + 300) == []
    assert node_json(fleet)["in_sync"] is True and channel(fleet, "ch0")["voltage_v"] == 4.0
    assert node_json(fleet)["since_ms"] == T0  # a rebirth is no new session


def test_a_rebirth_that_does_not_come_is_asked_again() -> None:
    fleet, s = born()
    s.data([("ch0.voltage", metric("float", 3.8, "V"))], T0)
    assert feed(fleet, s.data([("ch0.voltage", metric("float", 1, "V"))], T0)) == ["bench-a"]
    again = s.data([("ch0.voltage", metric("float", 2, "V"))], T0)
    assert feed(fleet, again, now_ms=T0 + REBIRTH_RETRY_MS) == ["bench-a"]


def test_data_of_a_node_never_born_here_asks_its_rebirth() -> None:
    s = session()
    s.births(3, bench_metrics(), T0)  # before the fleet started
    fleet = Fleet(GROUP)
    assert feed(fleet, s.data([("ch0.voltage", metric("float", 3.8, "V"))], T0)) == ["bench-a"]
    assert node_json(fleet)["online"] is False and node_json(fleet)["born"] is False
    body = fleet_json(fleet, connected=True, now_ms=T0)
    assert (body["online"], body["offline"]) == (0, 0)  # waiting, not a bench that died
    feed(fleet, s.births(3, bench_metrics(), T0))
    assert node_json(fleet)["online"] is True and node_json(fleet)["born"] is True


def test_a_metric_the_birth_did_not_announce_asks_a_rebirth() -> None:
    fleet, s = born()
    s.born.add("ch0.new_tag")  # the node thinks it announced it
    assert feed(fleet, s.data([("ch0.new_tag", metric("int", 1))], T0)) == ["bench-a"]


def test_other_groups_commands_and_garbage_are_ignored() -> None:
    fleet = Fleet(GROUP)
    assert fleet.receive("spBv1.0/Other/NBIRTH/x", b"", T0) == []
    assert fleet.receive(f"spBv1.0/{GROUP}/NCMD/x", rebirth_request(T0), T0) == []
    assert fleet.receive("spBv1.0/STATE/host", b"{}", T0) == []
    assert fleet.receive(f"spBv1.0/{GROUP}/NBIRTH/x", b"\xff\xff\xff", T0) == []
    assert fleet.nodes == {} and fleet.undecodable == 1


def test_the_rebirth_request_is_an_ncmd_node_control_rebirth_true() -> None:
    assert is_rebirth(decode(rebirth_request(T0)))
    # and pysparkplug reads it as one
    ncmd = ps.NCmd.decode(rebirth_request(T0))
    assert [(m.name, m.value) for m in ncmd.metrics] == [("Node Control/Rebirth", True)]


def test_births_and_data_of_an_independent_edge_node_library() -> None:
    """pysparkplug (not the project's code) builds the NBIRTH, DBIRTH, DDATA and NDEATH."""
    fleet = Fleet(GROUP)
    base = f"spBv1.0/{GROUP}"

    def m(name: str, dt: ps.DataType, value: Any) -> ps.Metric:
        return ps.Metric(timestamp=T0, name=name, datatype=dt, value=value)

    nbirth = ps.NBirth(T0, 0, (m("bdSeq", ps.DataType.INT64, 4),))
    dbirth = ps.DBirth(
        T0,
        1,
        (
            m("chain.state", ps.DataType.STRING, "running"),
            m("voltage", ps.DataType.DOUBLE, 3.6),
            m("current", ps.DataType.FLOAT, 2.0),
            m("chain.step_index", ps.DataType.INT32, -1),
        ),
    )
    ddata = ps.DData(T0, 2, (m("voltage", ps.DataType.DOUBLE, 3.65),))
    for topic, p in (
        (f"{base}/NBIRTH/other", nbirth),
        (f"{base}/DBIRTH/other/ch7", dbirth),
        (f"{base}/DDATA/other/ch7", ddata),
    ):
        assert fleet.receive(topic, p.encode(include_dtypes=True), T0) == []
    ch7 = channel(fleet, "ch7", "other")
    assert ch7["state"] == "running" and ch7["voltage_v"] == 3.65 and ch7["current_a"] == 2.0
    assert fleet.nodes["other"].devices["ch7"].metrics["chain.step_index"] == -1
    assert node_json(fleet, "other")["bd_seq"] == 4
    stale = ps.NDeath(T0, m("bdSeq", ps.DataType.INT64, 3))  # an older session's
    assert fleet.receive(f"{base}/NDEATH/other", stale.encode(include_dtypes=True), T0) == []
    assert node_json(fleet, "other")["online"] is True
    death = ps.NDeath(T0, m("bdSeq", ps.DataType.INT64, 4))
    fleet.receive(f"{base}/NDEATH/other", death.encode(include_dtypes=True), T0 + 1)
    assert node_json(fleet, "other")["online"] is False
