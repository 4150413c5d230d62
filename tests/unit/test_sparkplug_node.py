"""The Sparkplug B edge node without a broker: what it publishes, read back by pysparkplug
(the independent consumer, ADR 0051), on the virtual clock.

The bench is the edge node: NBIRTH with bdSeq, 'Node Control/Rebirth' and the bench-level
tags; one DBIRTH per channel and per device with every tag's value, datatype, unit and
quality (properties) at the sample's time; then NDATA/DDATA with the changes only, one
message per device per scan; seq 0-255 and round; the NDEATH is the will (QoS 1) with a
bdSeq that the retained-state store keeps across restarts; a rebirth request births again
with the same bdSeq; nothing is sent while disconnected, and the scan never waits.
(Store and forward: test_sparkplug_spool.py.)
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pysparkplug as ps
import pytest
from pysparkplug._protobuf import Payload as PbPayload

from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality
from supervisor.publish.retain import RetainStore
from supervisor.publish.sparkplug import (
    MemoryBdSeq,
    Message,
    RetainedBdSeq,
    SparkplugPublisher,
    SparkplugSettings,
)
from supervisor.publish.sparkplug.node import SEQ_MODULO
from supervisor.tags import TagDB, TagSpec

EPOCH_S = 1_767_225_600.0  # VirtualClock's wall time at 0
LIMIT_S = 30.0  # a bound for a loaded machine, not a timing claim


def wait_for(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + LIMIT_S
    while not condition():
        assert time.monotonic() < deadline, f"no {what} within {LIMIT_S:g} s"
        time.sleep(0.01)


class FakeTransport:
    """A connection that records what is published (and can be made to hang)."""

    def __init__(self) -> None:
        self.will: Message | None = None
        self.wills: list[Message] = []
        self.sent: list[Message] = []
        self.ncmd = ""
        self.connected = True
        self.block: threading.Event | None = None
        self.stopped_with: Message | None = None

    def start(self, will: Message, ncmd_topic: str, callbacks: Any) -> None:
        self.ncmd = ncmd_topic
        self.set_will(will)

    def set_will(self, will: Message) -> None:
        self.will = will
        self.wills.append(will)

    def publish(self, message: Message) -> bool:
        if self.block is not None:
            self.block.wait()
        if not self.connected:
            return False
        self.sent.append(message)
        return True

    def stop(self, last: Message | None) -> None:
        self.stopped_with = last


def decoded(m: Message) -> Any:
    """pysparkplug's reading of a message (by its topic's verb)."""
    topic = ps.Topic.from_str(m.topic)
    assert topic.message_type is not None
    return topic.message_type.payload.decode(m.payload)  # type: ignore[union-attr]


def properties(m: Message) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for metric in PbPayload.FromString(m.payload).metrics:
        out[metric.name] = {
            k: getattr(v, v.WhichOneof("value"))
            for k, v in zip(metric.properties.keys, metric.properties.values, strict=True)
        }
    return out


class Rig:
    def __init__(self, bd_seq: Any = None, alarm: Any = None, **settings: Any) -> None:
        self.clock = VirtualClock()
        self.db = TagDB()
        self.tags = {
            s.name: self.db.add(s)
            for s in (
                TagSpec("scan.count", "int"),
                TagSpec("bench.mode", "str"),
                TagSpec("ch1.voltage", "float", unit="V"),
                TagSpec("ch1.chain.step", "str"),
                TagSpec("ch2.current", "float", unit="A"),
                TagSpec("psu.connected", "bool"),
            )
        }
        self.transport = FakeTransport()
        self.threaded = False
        self.pub = SparkplugPublisher(
            self.db,
            self.clock,
            SparkplugSettings("127.0.0.1", 1883, "Lab", "bench7", queue_max_changes=50, **settings),
            channels=["ch1", "ch2"],
            devices=["psu"],
            bd_seq=bd_seq,
            transport=lambda: self.transport,
            alarm=alarm,
        )

    def set(self, name: str, value: Any, quality: Quality = Quality.GOOD) -> None:
        self.db.update(self.tags[name], value, quality)

    def scan(self, dt_s: float = 0.1) -> list[Message]:
        """One scan: the tags as set, the publisher's scan side, one round of its thread."""
        self.clock.advance(dt_s)
        self.db.set_scan_time(self.clock.now())
        before = len(self.transport.sent)
        self.pub.on_scan(self.db, self.clock.now())
        if not self.threaded:
            self.pub.drain()
        return self.transport.sent[before:]

    def start(self, *, threaded: bool = False, bad: tuple[str, ...] = ()) -> list[Message]:
        """The tags set (those in ``bad`` BAD), the edge node started and connected: the
        first scan's messages (the births)."""
        for name, value in (
            ("scan.count", 1),
            ("bench.mode", "auto"),
            ("ch1.voltage", 3.7),
            ("ch1.chain.step", "charge"),
            ("ch2.current", 0.5),
            ("psu.connected", True),
        ):
            self.set(
                name, None if name in bad else value, Quality.BAD if name in bad else Quality.GOOD
            )
        self.threaded = threaded
        self.pub.start(threaded=threaded)
        self.pub.connected()
        return self.scan()


def test_births_announce_every_tag_with_datatype_unit_quality_and_the_samples_time() -> None:
    rig = Rig()
    rig.db.update(rig.tags["ch1.voltage"], 3.7, source_t=0.042)  # a device's sample time
    births = rig.start(bad=("psu.connected",))

    assert [m.topic for m in births] == [
        "spBv1.0/Lab/NBIRTH/bench7",
        "spBv1.0/Lab/DBIRTH/bench7/ch1",
        "spBv1.0/Lab/DBIRTH/bench7/ch2",
        "spBv1.0/Lab/DBIRTH/bench7/psu",
    ]
    assert all(m.qos == 0 for m in births)
    nbirth, ch1, _, psu = (decoded(m) for m in births)
    assert [b.seq for b in map(decoded, births)] == [0, 1, 2, 3]
    node = {m.name: m for m in nbirth.metrics}
    assert node["bdSeq"].datatype is ps.DataType.INT64 and node["bdSeq"].value == 0
    rebirth = node["Node Control/Rebirth"]
    assert rebirth.datatype is ps.DataType.BOOLEAN and rebirth.value is False
    assert node["scan.count"].datatype is ps.DataType.INT64 and node["scan.count"].value == 1
    assert node["bench.mode"].value == "auto"
    assert not any(n.startswith("sparkplug.") for n in node)  # its own status, never sent
    metrics = {m.name: m for m in ch1.metrics}
    assert set(metrics) == {"voltage", "chain.step"}
    assert metrics["voltage"].datatype is ps.DataType.DOUBLE and metrics["voltage"].value == 3.7
    assert metrics["voltage"].timestamp == round((EPOCH_S + 0.042) * 1000)
    assert metrics["chain.step"].datatype is ps.DataType.STRING
    assert properties(births[1])["voltage"] == {"Quality": 192, "engUnit": "V"}
    assert properties(births[2])["current"]["engUnit"] == "A"
    (connected,) = psu.metrics
    assert connected.name == "connected" and connected.is_null
    assert connected.datatype is ps.DataType.BOOLEAN
    assert properties(births[3])["connected"] == {"Quality": 0}


def test_data_carries_the_changes_only_one_message_per_device_per_scan() -> None:
    rig = Rig()
    rig.start()
    rig.set("ch1.voltage", 3.71)
    rig.set("ch1.chain.step", "rest")
    rig.set("scan.count", 2)
    sent = rig.scan()

    assert [m.topic for m in sent] == ["spBv1.0/Lab/NDATA/bench7", "spBv1.0/Lab/DDATA/bench7/ch1"]
    ndata, ddata = (decoded(m) for m in sent)
    assert [(m.name, m.value) for m in ndata.metrics] == [("scan.count", 2)]
    assert sorted((m.name, m.value) for m in ddata.metrics) == [
        ("chain.step", "rest"),
        ("voltage", 3.71),
    ]
    assert (ndata.seq, ddata.seq) == (4, 5)  # after NBIRTH 0 and DBIRTHs 1-3
    assert rig.scan() == []  # nothing changed: nothing sent

    rig.set("ch2.current", 0.5, Quality.UNCERTAIN)
    (stale,) = rig.scan()
    assert stale.topic.endswith("/DDATA/bench7/ch2")
    assert properties(stale)["current"] == {"Quality": 500}  # Sparkplug's STALE


def test_seq_runs_0_to_255_and_round_again() -> None:
    rig = Rig()
    rig.start()
    seqs = []
    for i in range(SEQ_MODULO + 10):
        rig.set("scan.count", 10 + i)
        (m,) = rig.scan()
        seqs.append(decoded(m).seq)
    assert seqs[: SEQ_MODULO - 4] == list(range(4, SEQ_MODULO))
    assert seqs[SEQ_MODULO - 4 : SEQ_MODULO + 6] == list(range(10))


def test_the_will_is_an_ndeath_with_qos_1_and_the_births_bdseq() -> None:
    rig = Rig()
    births = rig.start()
    will = rig.transport.will
    assert will is not None
    assert will.topic == "spBv1.0/Lab/NDEATH/bench7" and will.qos == 1
    death = decoded(will)
    bd = death.bd_seq_metric
    assert bd.name == "bdSeq" and bd.datatype is ps.DataType.INT64
    assert bd.value == {m.name: m.value for m in decoded(births[0]).metrics}["bdSeq"]
    pb = PbPayload.FromString(will.payload)
    assert not pb.HasField("seq")  # an NDEATH has no seq (chapter 6)

    rig.pub.close()
    assert rig.transport.stopped_with is not None  # a clean stop publishes it itself
    assert decoded(rig.transport.stopped_with).bd_seq_metric.value == bd.value


def test_bdseq_survives_restarts_in_the_retained_state(tmp_path: Path) -> None:
    path = tmp_path / "state.sqlite"
    seen = []
    for _ in range(3):
        store = RetainStore(path)
        store.open()
        rig = Rig(RetainedBdSeq(store))
        births = rig.start()
        seen.append({m.name: m.value for m in decoded(births[0]).metrics}["bdSeq"])
        rig.pub.close()
        store.close()
    assert seen == [0, 1, 2]

    store = RetainStore(path)
    store.open()
    store.put("sparkplug", {"bd_seq": 255})
    assert store.flush()
    assert RetainedBdSeq(store).load() == 255
    rig = Rig(RetainedBdSeq(store))
    rig.start()
    assert rig.pub.bd_seq == 0  # 255 is followed by 0
    store.close()


def test_a_reconnection_takes_the_next_bdseq_and_nothing_is_sent_offline() -> None:
    rig = Rig(MemoryBdSeq(last=41), spool_max_bytes=0)  # no store and forward
    rig.start()
    assert rig.pub.bd_seq == 42
    rig.transport.connected = False
    rig.pub.disconnected()
    assert decoded(rig.transport.wills[-1]).bd_seq_metric.value == 43  # the next CONNECT's will
    rig.set("ch1.voltage", 3.8)
    assert rig.scan() == []
    assert rig.pub.dropped == 1

    rig.transport.connected = True
    rig.pub.connected()
    births = rig.scan()
    assert births[0].topic.endswith("/NBIRTH/bench7")
    assert {m.name: m.value for m in decoded(births[0]).metrics}["bdSeq"] == 43
    ch1 = {m.name: m.value for m in decoded(births[1]).metrics}
    assert ch1["voltage"] == 3.8  # the value changed while offline, in the new birth


def test_a_rebirth_request_births_again_with_the_same_bdseq() -> None:
    rig = Rig()
    rig.start()
    rig.set("ch1.voltage", 3.9)
    rig.scan()
    now = ps.get_current_timestamp()
    request = ps.NCmd(
        timestamp=now,
        metrics=(ps.Metric(now, "Node Control/Rebirth", ps.DataType.BOOLEAN, value=True),),
    )
    rig.pub.command(request.encode(include_dtypes=True))
    rig.set("ch1.voltage", 4.0)  # a change in the same round goes in the birth, not before
    births = rig.scan()

    assert [m.topic.split("/")[2] for m in births] == ["NBIRTH", "DBIRTH", "DBIRTH", "DBIRTH"]
    assert [decoded(m).seq for m in births] == [0, 1, 2, 3]
    assert {m.name: m.value for m in decoded(births[0]).metrics}["bdSeq"] == 0
    assert {m.name: m.value for m in decoded(births[1]).metrics}["voltage"] == 4.0

    rig.pub.command(b"\xff\xff not a payload")  # logged, ignored
    no_rebirth = ps.NCmd(
        timestamp=now,
        metrics=(ps.Metric(now, "Node Control/Rebirth", ps.DataType.BOOLEAN, value=False),),
    )
    rig.pub.command(no_rebirth.encode(include_dtypes=True))
    assert rig.scan() == []


def test_a_tag_added_after_the_births_is_announced_by_a_new_birth() -> None:
    rig = Rig()
    rig.start()
    tag = rig.db.add(TagSpec("ch2.temperature", "float", unit="degC"))
    rig.db.update(tag, 25.0)
    births = rig.scan()
    assert births[0].topic.endswith("/NBIRTH/bench7")
    ch2 = {m.name: m.value for m in decoded(births[2]).metrics}
    assert ch2["temperature"] == 25.0


def test_the_scan_never_waits_for_a_stuck_connection() -> None:
    """A publish that hangs holds the edge node's thread, never the scan: the queue is
    folded past its bound (each tag's latest change kept, the rest counted as dropped),
    and once the connection moves again the latest values are sent."""
    rig = Rig()
    rig.start(threaded=True)
    wait_for(lambda: len(rig.transport.sent) == 4, "births")
    rig.transport.block = threading.Event()
    try:
        for i in range(200):  # far past queue_max_changes (50)
            rig.set("scan.count", 100 + i)
            rig.set("ch1.voltage", 3.0 + i / 1000)
            rig.clock.advance(0.1)
            rig.pub.on_scan(rig.db, rig.clock.now())  # returns: the thread is stuck
        assert rig.pub.dropped > 0
    finally:
        rig.transport.block.set()
    wait_for(
        lambda: any(
            m.topic.endswith("/DDATA/bench7/ch1")
            and decoded(m).metrics[-1].value == pytest.approx(3.199)
            for m in list(rig.transport.sent)
        ),
        "the latest voltage",
    )
    rig.pub.close()


def test_scans_before_the_start_are_not_kept_the_births_carry_the_values_at_the_start() -> None:
    rig = Rig()
    for i in range(3):  # a bench scanning before its edge node starts: nothing piles up
        rig.set("scan.count", 100 + i)
        rig.scan()
    assert rig.pub._queued == 0
    births = rig.start()
    node = {m.name: m.value for m in decoded(births[0]).metrics}
    assert node["scan.count"] == 1  # as set at the start, not a value of before
    assert [m.topic.split("/")[2] for m in births] == ["NBIRTH", "DBIRTH", "DBIRTH", "DBIRTH"]


def test_while_connecting_the_starts_snapshot_is_kept_not_counted_as_dropped() -> None:
    rig = Rig(spool_max_bytes=0)  # no store and forward
    rig.set("ch1.voltage", 3.7)
    rig.pub.start(threaded=False)  # not connected yet
    assert rig.scan() == []
    assert rig.pub.dropped == 0
    rig.set("ch1.voltage", 3.75)
    assert rig.scan() == []
    assert rig.pub.dropped == 1  # a change while offline
    rig.pub.connected()
    births = rig.scan()
    assert {m.name: m.value for m in decoded(births[1]).metrics}["voltage"] == 3.75
