"""Sparkplug store and forward, on the virtual clock, read back by pysparkplug (issue 35).

While the broker is unreachable the changes the edge node would have sent wait in a spool
(SQLite, bounded in bytes); after the births of the next session they are replayed oldest
first, every metric flagged ``is_historical`` with the sample's own timestamp, and only
then does live data resume. Past the bound the oldest samples are dropped, counted
(``sparkplug.spool_dropped``) and alarmed (``sparkplug.spool_full``, medium); a broker
away longer than the grace raises ``sparkplug.disconnected``. A spool left by a run is
replayed after the next run's births.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from test_sparkplug_node import EPOCH_S, Rig, decoded

from supervisor.core.quality import Quality
from supervisor.publish.sparkplug import (
    ALARM_DISCONNECTED,
    ALARM_SPOOL_FULL,
    ALARMS,
    Message,
    SampleSpool,
)
from supervisor.publish.sparkplug.node import Metric


def verbs(messages: list[Message]) -> list[str]:
    return ["/".join(m.topic.split("/")[2:3] + m.topic.split("/")[4:]) for m in messages]


def metrics(messages: list[Message], device: str) -> list[Any]:
    """Every metric of the data messages of ``device`` ("" for the node), in order."""
    out: list[Any] = []
    for m in messages:
        parts = m.topic.split("/")
        if parts[2] in ("NDATA", "DDATA") and (parts[4:] or [""])[0] == device:
            out.extend(decoded(m).metrics)
    return out


def go_offline(rig: Rig) -> None:
    rig.transport.connected = False
    rig.pub.disconnected()


def come_back(rig: Rig) -> list[Message]:
    rig.transport.connected = True
    rig.pub.connected()
    return rig.scan()


class Alarms:
    def __init__(self) -> None:
        self.active: dict[str, bool] = {}
        self.calls: list[tuple[str, bool, str]] = []

    def __call__(self, alarm_id: str, on: bool, message: str) -> None:
        self.active[alarm_id] = on
        self.calls.append((alarm_id, on, message))


def test_offline_changes_are_replayed_after_the_births_oldest_first_flagged_historical() -> None:
    rig = Rig()
    rig.start()
    go_offline(rig)
    set_at: list[int] = []
    for i in range(5):
        rig.set("ch1.voltage", 3.80 + i / 100)
        rig.set("scan.count", 10 + i)
        set_at.append(round((EPOCH_S + rig.clock.now()) * 1000))
        assert rig.scan() == []  # nothing sent offline
    assert rig.pub.spool is not None and rig.pub.spool.waiting == 10
    assert rig.pub.dropped == 0

    sent = come_back(rig)
    # The births first (a new session, seq from 0), then the replay, in one round.
    assert verbs(sent)[:4] == ["NBIRTH", "DBIRTH/ch1", "DBIRTH/ch2", "DBIRTH/psu"]
    replay = sent[4:]
    assert verbs(replay) == ["NDATA", "DDATA/ch1"]
    assert [decoded(m).seq for m in sent] == list(range(6))
    voltage = metrics(replay, "ch1")
    assert [m.value for m in voltage] == pytest.approx([3.80, 3.81, 3.82, 3.83, 3.84])
    assert [m.timestamp for m in voltage] == set_at  # the samples' own times, oldest first
    counts = metrics(replay, "")
    assert [m.value for m in counts] == [10, 11, 12, 13, 14]
    assert all(m.is_historical for m in voltage + counts)
    assert rig.pub.spool.waiting == 0 and rig.pub.replayed == 10

    # Live data resumes, not historical.
    rig.set("ch1.voltage", 3.9)
    live = rig.scan()
    assert verbs(live) == ["DDATA/ch1"]
    (now,) = metrics(live, "ch1")
    assert now.value == 3.9 and not now.is_historical


def test_data_handed_over_just_before_a_loss_was_noticed_is_replayed_as_history() -> None:
    """Data is QoS 0: what was handed to MQTT after the broker went, before paho noticed,
    is lost without a word (found under load: a broker stop lost the scan.count values of
    those moments). What was sent within 1.5 keep-alives of the loss is replayed after the
    next births, flagged historical; what was sent before that is not."""
    rig = Rig(keepalive_s=10)
    rig.start()
    rig.set("scan.count", 1)
    rig.scan()
    rig.scan(dt_s=20.0)  # 1 was sent more than 15 s before the loss
    for n in (2, 3):
        rig.set("scan.count", n)
        assert verbs(rig.scan()) == ["NDATA"]  # sent live (the broker may be gone)
    go_offline(rig)
    rig.set("scan.count", 4)
    assert rig.scan() == []
    sent = come_back(rig)
    assert verbs(sent)[0] == "NBIRTH"
    replay = [m for m in sent if "BIRTH" not in m.topic]
    counts = metrics(replay, "")
    assert [m.value for m in counts] == [2, 3, 4]
    assert all(m.is_historical for m in counts)


def test_a_message_that_cannot_be_handed_over_is_spooled_not_lost() -> None:
    rig = Rig()
    rig.start()
    rig.transport.connected = False  # the connection went; paho has not said so yet
    rig.set("ch1.voltage", 3.71)
    rig.set("ch2.current", 0.6)
    assert rig.scan() == []
    assert rig.pub.spool is not None and rig.pub.spool.waiting == 2
    assert rig.pub.dropped == 0
    rig.pub.disconnected()
    sent = come_back(rig)
    replay = sent[4:]
    assert [m.value for m in metrics(replay, "ch1")] == [3.71]
    assert [m.value for m in metrics(replay, "ch2")] == [0.6]
    assert all(m.is_historical for m in metrics(replay, "ch1") + metrics(replay, "ch2"))


def test_a_change_superseded_in_the_reconnections_round_is_history_not_lost() -> None:
    """Two changes of a tag reach the edge node in the round of the reconnection: the
    births carry the later one, the earlier is replayed as history."""
    rig = Rig()
    rig.start()
    go_offline(rig)
    rig.set("ch1.voltage", 3.81)
    rig.clock.advance(0.1)
    rig.db.set_scan_time(rig.clock.now())
    rig.pub.on_scan(rig.db, rig.clock.now())  # queued, not yet handled by the thread
    rig.set("ch1.voltage", 3.82)
    sent = come_back(rig)  # both batches in one round, connected again
    born = {m.name: m.value for m in decoded(sent[1]).metrics}
    assert born["voltage"] == 3.82
    replayed = metrics(sent[4:], "ch1")
    assert [(m.value, m.is_historical) for m in replayed] == [(3.81, True)]


def test_the_bound_drops_the_oldest_counts_them_and_raises_spool_full() -> None:
    alarms = Alarms()
    rig = Rig(alarm=alarms, spool_max_bytes=2000)
    rig.start()
    go_offline(rig)
    for i in range(100):
        rig.set("ch1.voltage", 3.0 + i / 1000)
        rig.scan()
    spool = rig.pub.spool
    assert spool is not None and spool.waiting_bytes <= 2000
    assert spool.dropped == 100 - spool.waiting > 0
    rig.scan()  # the status tags: at the scan's end, before the edge node's round
    assert rig.db.get("sparkplug.spool_dropped").value == spool.dropped  # type: ignore[union-attr]
    assert rig.db.get("sparkplug.spool_depth").value == spool.waiting  # type: ignore[union-attr]
    assert alarms.active[ALARM_SPOOL_FULL] is True
    kept = spool.waiting

    sent = come_back(rig)
    replayed = metrics(sent[4:], "ch1")
    # The newest samples survive, in order: the last `kept` of the 100.
    assert [m.value for m in replayed] == pytest.approx(
        [3.0 + i / 1000 for i in range(100)][-kept:]
    )
    rig.scan()
    assert alarms.active[ALARM_SPOOL_FULL] is False  # the spool emptied
    assert dict((s.id, s.severity) for s in ALARMS)[ALARM_SPOOL_FULL] == "medium"


def test_the_disconnected_alarm_waits_for_its_grace_and_clears_on_reconnection() -> None:
    alarms = Alarms()
    rig = Rig(alarm=alarms, disconnected_alarm_s=10.0)
    rig.start()
    go_offline(rig)
    for _ in range(99):  # 9.9 s
        rig.scan()
    assert not alarms.active.get(ALARM_DISCONNECTED, False)
    rig.scan(0.2)
    assert alarms.active[ALARM_DISCONNECTED] is True
    assert "unreachable" in alarms.calls[-1][2]
    come_back(rig)
    rig.scan()
    assert alarms.active[ALARM_DISCONNECTED] is False


def test_a_spool_left_by_a_run_is_replayed_after_the_next_runs_births(tmp_path: Path) -> None:
    path = tmp_path / "sparkplug-spool.sqlite"
    first = Rig(spool_path=path)
    first.start()
    go_offline(first)
    for i in range(3):
        first.set("ch1.voltage", 3.5 + i / 10)
        first.scan()
    first.pub.close()  # stopped while the broker was away: the samples stay on disk

    second = Rig(spool_path=path)
    sent = second.start()  # connected: births, then the first run's samples
    assert verbs(sent)[:4] == ["NBIRTH", "DBIRTH/ch1", "DBIRTH/ch2", "DBIRTH/psu"]
    replayed = metrics(sent[4:], "ch1")
    assert [m.value for m in replayed] == pytest.approx([3.5, 3.6, 3.7])
    assert all(m.is_historical for m in replayed)
    assert second.pub.spool is not None and second.pub.spool.waiting == 0
    second.pub.close()
    third = SampleSpool(path, 1 << 20)
    third.open()
    assert third.waiting == 0  # sent once, not again on the next start
    third.close()


@pytest.mark.parametrize(
    ("dtype", "value"),
    [
        ("float", 3.14159265358979),
        ("float", -0.0),
        ("float", math.inf),
        ("int", -(2**62)),
        ("int", 0),
        ("bool", True),
        ("bool", False),
        ("str", "CC-CV étape 3"),
        ("str", ""),
        ("float", None),
    ],
)
def test_every_kind_of_sample_comes_back_from_the_spool_as_it_went_in(
    tmp_path: Path, dtype: Any, value: Any
) -> None:
    spool = SampleSpool(tmp_path / "s.sqlite", 1 << 20)
    spool.open()
    m = Metric(dtype, "V", value, Quality.UNCERTAIN if value is not None else Quality.BAD, 42)
    spool.append([("ch1.x", m)])
    spool.close()
    again = SampleSpool(tmp_path / "s.sqlite", 1 << 20)
    again.open()
    ((_, tag, back),) = again.oldest(10)
    assert tag == "ch1.x" and back == m and type(back.value) is type(value)
    again.close()


def test_a_nan_sample_comes_back_as_nan(tmp_path: Path) -> None:
    spool = SampleSpool(None, 1 << 20)
    spool.append([("ch1.x", Metric("float", "", math.nan, Quality.GOOD, 1))])
    ((_, _, back),) = spool.oldest(1)
    assert isinstance(back.value, float) and math.isnan(back.value)


def test_an_unreadable_spool_is_moved_aside_and_a_new_one_started(tmp_path: Path) -> None:
    path = tmp_path / "sparkplug-spool.sqlite"
    path.write_bytes(b"not a database at all" * 100)
    spool = SampleSpool(path, 1 << 20)
    spool.open()
    assert spool.moved_to is not None and spool.moved_to.exists()
    assert spool.waiting == 0
    spool.append([("x", Metric("int", "", 1, Quality.GOOD, 1))])
    assert spool.waiting == 1
    spool.close()


def test_a_spool_that_cannot_be_opened_leaves_the_node_publishing_without_one(
    tmp_path: Path,
) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the state folder should be")
    rig = Rig(spool_path=blocker / "sparkplug-spool.sqlite")
    births = rig.start()
    assert rig.pub.spool is None and len(births) == 4
    go_offline(rig)
    rig.set("ch1.voltage", 3.9)
    rig.scan()
    assert rig.pub.dropped == 1  # counted, as without store and forward
