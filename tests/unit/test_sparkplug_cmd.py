"""Commands over Sparkplug, without a broker, on the virtual clock (docs/sparkplug.md
"Commands").

Each channel's DBIRTH announces ``Command/<verb>`` (Boolean, false) and
``Command/last_result`` (String); a DCMD setting ``Command/start`` true is the command path's
``start`` on that channel with the actor ``sparkplug:<primary host>``, answered in DDATA by
``Command/last_result``. Refused (logged with the reason, counted in
``sparkplug.commands_refused``) when commands are disabled, when the primary host's STATE is
not online, for an unknown command and for a device that is not a channel. The NBIRTH waits
for the primary host's STATE online; an offline STATE after the births ends the session
(NDEATH, reconnect with the next bdSeq, wait again). Payloads are built and read by
pysparkplug, the independent library (ADR 0051).
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
from typing import Any

import pysparkplug as ps
import pytest

from supervisor.app.sparkplug import command_handler, screens_url
from supervisor.commands import CommandPath
from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality
from supervisor.publish.sparkplug import (
    CommandSettings,
    Message,
    SparkplugPublisher,
    SparkplugSettings,
)
from supervisor.tags import TagDB, TagSpec

HOST = "scada"
STATE_TOPIC = f"spBv1.0/STATE/{HOST}"
DCMD = "spBv1.0/Lab/DCMD/bench7/"
VERBS = ("start", "hold", "resume", "stop", "abort", "reset", "acknowledge")


class FakeTransport:
    """A connection that records what is published, its subscriptions and reconnections."""

    def __init__(self) -> None:
        self.sent: list[Message] = []
        self.also: tuple[str, ...] = ()
        self.will: Message | None = None
        self.reconnected: list[tuple[Message, Message]] = []

    def start(self, will: Message, ncmd_topic: str, callbacks: Any, *, also: Any = ()) -> None:
        self.will, self.also = will, tuple(also)

    def set_will(self, will: Message) -> None:
        self.will = will

    def publish(self, message: Message) -> bool:
        self.sent.append(message)
        return True

    def reconnect(self, last: Message, will: Message) -> None:
        self.reconnected.append((last, will))
        self.will = will

    def stop(self, last: Message | None) -> None:
        pass


class Rig:
    def __init__(self, commands: CommandSettings | None) -> None:
        self.clock = VirtualClock()
        self.db = TagDB()
        for spec, value in (
            (TagSpec("scan.count", "int"), 1),
            (TagSpec("ch1.voltage", "float", unit="V"), 3.7),
            (TagSpec("psu.connected", "bool"), True),
        ):
            self.db.update(self.db.add(spec), value, Quality.GOOD)
        self.transport = FakeTransport()
        self.asked: list[tuple[str, str, str]] = []
        self.replies: list[Any] = []
        self.pub = SparkplugPublisher(
            self.db,
            self.clock,
            SparkplugSettings("127.0.0.1", 1883, "Lab", "bench7", commands=commands),
            channels=["ch1"],
            devices=["psu"],
            transport=lambda: self.transport,
        )
        self.pub.commander = self.command

    def command(self, channel: str, verb: str, actor: str, reply: Any) -> None:
        self.asked.append((channel, verb, actor))
        self.replies.append(reply)

    def scan(self) -> list[Message]:
        self.clock.advance(0.1)
        self.db.set_scan_time(self.clock.now())
        before = len(self.transport.sent)
        self.pub.on_scan(self.db, self.clock.now())
        self.pub.drain()
        return self.transport.sent[before:]

    def connect(self) -> list[Message]:
        self.pub.start(threaded=False)
        self.pub.connected()
        return self.scan()

    def state(self, online: bool, timestamp_ms: int = 1000) -> None:
        doc = {"online": online, "timestamp": timestamp_ms}
        self.pub.message(STATE_TOPIC, json.dumps(doc).encode())

    def dcmd(self, device: str, *names: str, value: bool = True) -> None:
        now = ps.get_current_timestamp()
        metrics = tuple(ps.Metric(now, n, ps.DataType.BOOLEAN, value=value) for n in names)
        payload = ps.DCmd(timestamp=now, metrics=metrics).encode(include_dtypes=True)
        self.pub.message(DCMD + device, payload)

    def tag(self, name: str) -> Any:
        tag = self.db.get(name)
        assert tag is not None
        return tag.value


def decoded(m: Message) -> Any:
    topic = ps.Topic.from_str(m.topic)
    assert topic.message_type is not None
    return topic.message_type.payload.decode(m.payload)  # type: ignore[union-attr]


def metrics(m: Message) -> dict[str, Any]:
    return {x.name: x.value for x in decoded(m).metrics}


def enabled() -> CommandSettings:
    return CommandSettings(enabled=True, primary_host=HOST)


def online_rig() -> tuple[Rig, list[Message]]:
    rig = Rig(enabled())
    rig.connect()
    rig.state(True)
    return rig, rig.scan()


def test_the_node_subscribes_to_its_dcmds_and_the_primary_hosts_state() -> None:
    rig = Rig(enabled())
    rig.connect()
    assert rig.transport.also == ("spBv1.0/Lab/DCMD/bench7/+", STATE_TOPIC)


def test_the_nbirth_waits_for_the_primary_hosts_state_online() -> None:
    rig = Rig(enabled())
    assert rig.connect() == []  # connected, the host's STATE not seen yet
    assert rig.scan() == []
    rig.state(True)
    births = rig.scan()
    assert [m.topic.split("/")[2] for m in births] == ["NBIRTH", "DBIRTH", "DBIRTH"]
    assert rig.tag("sparkplug.host_online") is True


def test_each_channels_dbirth_announces_its_commands_and_last_result() -> None:
    _, births = online_rig()
    ch1 = {m.name: m for m in decoded(births[1]).metrics}
    for verb in VERBS:
        command = ch1[f"Command/{verb}"]
        assert command.datatype is ps.DataType.BOOLEAN and command.value is False
    assert ch1["Command/last_result"].datatype is ps.DataType.STRING
    assert not any(name.startswith("Command/") for name in metrics(births[2]))  # psu


def test_a_dcmd_is_the_command_path_s_command_with_the_host_as_actor_and_answered() -> None:
    rig, _ = online_rig()
    rig.dcmd("ch1", "Command/start")
    assert rig.asked == [("ch1", "start", "sparkplug:scada")]
    rig.replies[0](True, "")
    [ddata] = rig.scan()
    assert ddata.topic == DCMD.replace("DCMD", "DDATA") + "ch1"
    assert metrics(ddata)["Command/last_result"] == "start: accepted"
    assert rig.tag("sparkplug.commands_accepted") == 1

    rig.dcmd("ch1", "Command/hold")
    rig.replies[1](False, "ch1: hold refused: the chain is not running")
    [ddata] = rig.scan()
    assert metrics(ddata)["Command/last_result"] == (
        "hold: refused: ch1: hold refused: the chain is not running"
    )
    assert rig.tag("sparkplug.commands_refused") == 1

    rig.pub.command(_rebirth())  # a rebirth carries the last answer
    births = rig.scan()
    assert metrics(births[1])["Command/last_result"] == metrics(ddata)["Command/last_result"]


def test_a_command_metric_written_false_asks_nothing() -> None:
    rig, _ = online_rig()
    rig.dcmd("ch1", "Command/start", value=False)
    assert rig.asked == [] and rig.scan() == []
    assert rig.tag("sparkplug.commands_refused") == 0


def test_refused_while_the_primary_host_is_not_online(caplog: pytest.LogCaptureFixture) -> None:
    rig = Rig(enabled())
    rig.connect()
    with caplog.at_level(logging.WARNING):
        rig.dcmd("ch1", "Command/start")
    assert rig.asked == []
    assert "Sparkplug DCMD start on ch1 refused: the primary host application scada is not" in (
        caplog.text
    )
    rig.scan()
    assert rig.tag("sparkplug.commands_refused") == 1

    rig.state(True)
    rig.state(False, timestamp_ms=2000)
    rig.dcmd("ch1", "Command/start")
    assert rig.asked == []
    rig.scan()
    assert rig.tag("sparkplug.commands_refused") == 2


def test_refused_when_commands_are_disabled(caplog: pytest.LogCaptureFixture) -> None:
    rig = Rig(CommandSettings(enabled=False))
    births = rig.connect()  # no primary host: births at once
    assert not any(name.startswith("Command/") for name in metrics(births[1]))
    with caplog.at_level(logging.WARNING):
        rig.dcmd("ch1", "Command/start")
    assert rig.asked == []
    assert "refused: commands over Sparkplug are disabled" in caplog.text
    assert rig.scan() == []  # no metric the births did not announce
    assert rig.tag("sparkplug.commands_refused") == 1


def test_an_unknown_command_or_a_device_that_is_not_a_channel_is_refused() -> None:
    rig, _ = online_rig()
    rig.dcmd("ch1", "Command/fly")
    [ddata] = rig.scan()
    assert metrics(ddata)["Command/last_result"] == "fly: refused: unknown command"
    rig.dcmd("ch1", "voltage")
    [ddata] = rig.scan()
    assert metrics(ddata)["Command/last_result"] == "voltage: refused: unknown command"
    rig.dcmd("psu", "Command/start")
    assert rig.scan() == []  # psu has no Command/last_result
    rig.pub.message(DCMD + "ch1", b"\xff\xff not a payload")
    rig.scan()
    assert rig.asked == []
    assert rig.tag("sparkplug.commands_refused") == 4


def test_the_primary_host_offline_ends_the_session_and_the_next_waits_for_it() -> None:
    rig, births = online_rig()
    assert metrics(births[0])["bdSeq"] == 0
    rig.state(False, timestamp_ms=2000)
    assert rig.scan() == []
    [(death, will)] = rig.transport.reconnected
    assert death.topic == "spBv1.0/Lab/NDEATH/bench7" and decoded(death).bd_seq_metric.value == 0
    assert decoded(will).bd_seq_metric.value == 1  # the next CONNECT's

    rig.pub.connected()
    rig.state(False, timestamp_ms=2000)  # its retained STATE again: no second cycle
    assert rig.scan() == [] and len(rig.transport.reconnected) == 1
    rig.state(True, timestamp_ms=3000)
    births = rig.scan()
    assert births[0].topic.endswith("/NBIRTH/bench7") and metrics(births[0])["bdSeq"] == 1


def test_a_state_older_than_the_last_one_is_ignored() -> None:
    rig, _ = online_rig()
    rig.state(False, timestamp_ms=500)  # a late message of an older session of the host
    rig.pub.message(STATE_TOPIC, b"not json")
    rig.scan()
    assert rig.transport.reconnected == [] and rig.tag("sparkplug.host_online") is True
    rig.dcmd("ch1", "Command/stop")
    assert rig.asked == [("ch1", "stop", "sparkplug:scada")]


def test_the_composition_roots_handler_runs_the_one_command_path_with_the_actor() -> None:
    path = CommandPath(TagDB(), VirtualClock())
    answers: list[tuple[bool, str]] = []

    async def main() -> None:
        handle = command_handler(path, asyncio.get_running_loop())
        done = asyncio.Event()

        def reply(accepted: bool, reason: str) -> None:
            answers.append((accepted, reason))
            done.set()

        await asyncio.to_thread(handle, "ch0", "start", "sparkplug:scada", reply)
        await done.wait()

    asyncio.run(main())
    [event] = path.log
    assert event.actor == "sparkplug:scada" and event.command == "start"
    assert answers == [(False, event.reason)]  # no channel ch0 in this path


def _rebirth() -> bytes:
    now = ps.get_current_timestamp()
    metric = ps.Metric(now, "Node Control/Rebirth", ps.DataType.BOOLEAN, value=True)
    return ps.NCmd(timestamp=now, metrics=(metric,)).encode(include_dtypes=True)


def test_the_node_publishes_its_screens_url_and_its_active_alarms() -> None:
    """What the fleet reads (supervisor/fleet): ``hmi.url`` and ``alarms.active``."""
    active = [0]
    clock = VirtualClock()
    db = TagDB()
    transport = FakeTransport()
    pub = SparkplugPublisher(
        db,
        clock,
        SparkplugSettings("127.0.0.1", 1883, "Lab", "bench7"),
        channels=[],
        devices=[],
        transport=lambda: transport,
        active_alarms=lambda: active[0],
    )
    pub.hmi_url = "http://bench7.lab:8080/"
    pub.start(threaded=False)
    pub.connected()
    pub.on_scan(db, clock.now())
    pub.drain()
    nbirth = {m.name: m for m in decoded(transport.sent[0]).metrics}
    assert nbirth["hmi.url"].datatype is ps.DataType.STRING
    assert nbirth["hmi.url"].value == "http://bench7.lab:8080/"
    assert nbirth["alarms.active"].datatype is ps.DataType.INT64
    assert nbirth["alarms.active"].value == 0

    active[0] = 2
    for _ in range(2):  # the count is taken at a scan's end, published by the next round
        clock.advance(0.1)
        db.set_scan_time(clock.now())
        pub.on_scan(db, clock.now())
        pub.drain()
    ndata = [m for m in transport.sent if "/NDATA/" in m.topic]
    assert metrics(ndata[-1])["alarms.active"] == 2


def test_without_the_hmi_there_is_no_screens_url() -> None:
    rig = Rig(None)
    births = rig.connect()
    assert "hmi.url" not in metrics(births[0])


@pytest.mark.parametrize(
    ("host", "url"),
    [
        ("127.0.0.1", "http://127.0.0.1:8080/"),
        ("bench7.lab", "http://bench7.lab:8080/"),
        ("::1", "http://[::1]:8080/"),
    ],
)
def test_the_screens_url_is_the_hmis_listen_address(host: str, url: str) -> None:
    assert screens_url(host, 8080) == url


def test_an_hmi_on_every_interface_is_linked_by_the_hosts_name() -> None:
    assert screens_url("0.0.0.0", 8080) == f"http://{socket.getfqdn()}:8080/"
