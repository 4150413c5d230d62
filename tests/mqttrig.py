"""A real MQTT broker and a Sparkplug consumer that is not the project's code, for the tests.

``Mosquitto`` is Debian's broker (``make mosquitto``; ``make test`` installs it) started on
a free loopback port with a configuration of the test's own (anonymous, no persistence),
stopped by its pid; a missing binary is an error, not a skip, so CI never passes without it.

``SparkplugConsumer`` subscribes to a group with paho-mqtt and decodes every message with
pysparkplug (ADR 0051: the other library, with its own protobuf module generated from the
published sparkplug_b.proto), keeping each one with its MQTT QoS and retain flag; the
'Quality' and 'engUnit' properties, which pysparkplug's metrics leave out, are read from
its protobuf message. It sends a rebirth request the way a host application does.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pysparkplug as ps
from pysparkplug._protobuf import Payload as PbPayload  # the properties (not in ps.Metric)

from supervisor.bench.processes import stop_with_parent
from supervisor.testing import free_tcp_port

__all__ = ["Mosquitto", "Received", "SparkplugConsumer", "mosquitto_binary"]

START_TIMEOUT_S = 15.0
DEBIAN_MOSQUITTO = Path("/usr/sbin/mosquitto")


def mosquitto_binary() -> Path:
    found = shutil.which("mosquitto") or (
        str(DEBIAN_MOSQUITTO) if DEBIAN_MOSQUITTO.exists() else None
    )
    if found is None:
        raise RuntimeError(
            "mosquitto is not installed: `make mosquitto` (Debian package mosquitto)"
        )
    return Path(found)


class Mosquitto:
    """Debian's mosquitto on 127.0.0.1:<free port>, its configuration and log under ``root``."""

    def __init__(self, root: Path, persistent: bool = False) -> None:
        """``persistent``: the broker keeps its clients' sessions across a restart, QoS 0
        messages included (queued for a session whose client is away)."""
        self.binary = mosquitto_binary()
        root.mkdir(parents=True, exist_ok=True)
        self.root = root
        self.port = free_tcp_port()
        self.url = f"mqtt://127.0.0.1:{self.port}"
        self.log = root / "mosquitto.log"
        self.config = root / "mosquitto.conf"
        self.config.write_text(
            f"listener {self.port} 127.0.0.1\n"
            "allow_anonymous true\n"
            + (
                f"persistence true\npersistence_location {root}/\n"
                "queue_qos0_messages true\nmax_queued_messages 0\n"
                if persistent
                else "persistence false\n"
            )
            + f"log_dest file {self.log}\n"
            "log_type error\nlog_type warning\nlog_type notice\n",
            encoding="utf-8",
        )
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self) -> None:
        if self.running:
            return
        self._proc = subprocess.Popen(
            [str(self.binary), "-c", str(self.config)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            stdin=subprocess.DEVNULL,
            preexec_fn=stop_with_parent(),  # no broker left behind by a killed run
        )
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self._accepts():
            if self._proc.poll() is not None:
                raise RuntimeError(f"mosquitto exited with {self._proc.returncode}: {self.log}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"mosquitto did not listen in {START_TIMEOUT_S:g} s")
            time.sleep(0.05)

    def _accepts(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=1):
                return True
        except OSError:
            return False

    def stop(self) -> None:
        """Stop the broker by its pid: SIGTERM, SIGKILL when it does not stop in 10 s."""
        proc, self._proc = self._proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@dataclass(frozen=True)
class Received:
    """One Sparkplug message as the consumer decoded it."""

    topic: ps.Topic
    payload: Any  # pysparkplug's NBirth, DBirth, NData, DData, NDeath...
    raw: bytes
    qos: int
    retain: bool
    at: float  # time.monotonic() on arrival

    @property
    def verb(self) -> str:
        return str(self.topic.message_type)

    @property
    def device(self) -> str | None:
        return self.topic.device_id

    def metrics(self) -> dict[str, Any]:
        """Metric name → pysparkplug Metric (the last of a name)."""
        return {m.name: m for m in self.payload.metrics}

    def properties(self) -> dict[str, dict[str, Any]]:
        """Metric name → its properties (key → value), from the protobuf message."""
        out: dict[str, dict[str, Any]] = {}
        for m in PbPayload.FromString(self.raw).metrics:
            props = {}
            for key, value in zip(m.properties.keys, m.properties.values, strict=True):
                props[key] = getattr(value, value.WhichOneof("value"))
            out[m.name] = props
        return out


class SparkplugConsumer:
    """Every message of ``spBv1.0/<group>/#``, decoded by pysparkplug."""

    def __init__(self, port: int, group: str, session: str | None = None) -> None:
        """``session``: a client id whose session the broker keeps while it is away (and,
        on a persistent broker, across a restart): what is published meanwhile waits."""
        self.group = group
        self.messages: list[Received] = []
        self._lock = threading.Condition()
        self._client = paho.Client(
            client_id=session or f"test-consumer-{os.getpid()}-{id(self)}",
            clean_session=session is None,
        )
        self._client.reconnect_delay_set(min_delay=1, max_delay=1)
        self._client.on_message = self._on_message
        subscribed = threading.Event()
        self._client.on_subscribe = lambda *_: subscribed.set()
        self._client.on_connect = lambda c, *_: c.subscribe(f"spBv1.0/{group}/#", qos=1)
        self._client.connect("127.0.0.1", port, keepalive=10)
        self._client.loop_start()
        if not subscribed.wait(10):
            raise RuntimeError("the consumer could not subscribe")

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        decoded = ps.Message.from_mqtt_message(msg)
        received = Received(
            decoded.topic,
            decoded.payload,
            bytes(msg.payload),
            msg.qos,
            msg.retain,
            time.monotonic(),
        )
        with self._lock:
            self.messages.append(received)
            self._lock.notify_all()

    def of(self, verb: str, device: str | None = None) -> list[Received]:
        with self._lock:
            return [
                m
                for m in self.messages
                if m.verb == verb and (device is None or m.device == device)
            ]

    def wait_for(
        self, check: Callable[[list[Received]], bool], what: str, timeout_s: float = 30.0
    ) -> None:
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while not check(list(self.messages)):
                left = deadline - time.monotonic()
                if left <= 0:
                    seen = [f"{m.verb} {m.device or ''}" for m in self.messages[-20:]]
                    raise AssertionError(f"no {what} within {timeout_s:g} s; last: {seen}")
                self._lock.wait(left)

    def rebirth(self, edge_node: str) -> None:
        """A host application's rebirth request (NCMD 'Node Control/Rebirth' = true)."""
        now = ps.get_current_timestamp()
        ncmd = ps.NCmd(
            timestamp=now,
            metrics=(
                ps.Metric(
                    timestamp=now,
                    name="Node Control/Rebirth",
                    datatype=ps.DataType.BOOLEAN,
                    value=True,
                ),
            ),
        )
        info = self._client.publish(
            f"spBv1.0/{self.group}/NCMD/{edge_node}", ncmd.encode(include_dtypes=True), qos=1
        )
        info.wait_for_publish(timeout=10)

    def close(self) -> None:
        self._client.disconnect()
        self._client.loop_stop()
