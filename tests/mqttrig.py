"""A real MQTT broker and a Sparkplug consumer that is not the project's code, for the tests.

``Mosquitto`` is Debian's broker (``make mosquitto``; ``make test`` installs it) started on
a free loopback port with a configuration of the test's own (anonymous, no persistence
unless asked), stopped by its pid — the lab's ``Broker`` (supervisor/bench/fleetbroker.py);
a missing binary is an error, not a skip, so CI never passes without it.

``SparkplugConsumer`` subscribes to a group with paho-mqtt and decodes every message with
pysparkplug (ADR 0051: the other library, with its own protobuf module generated from the
published sparkplug_b.proto), keeping each one with its MQTT QoS and retain flag; the
'Quality' and 'engUnit' properties, which pysparkplug's metrics leave out, are read from
its protobuf message. It sends a rebirth request the way a host application does.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pysparkplug as ps
import yaml
from pysparkplug._protobuf import Payload as PbPayload  # the properties (not in ps.Metric)

from supervisor.bench.fleetbroker import Broker, mosquitto_binary
from supervisor.testing import free_tcp_port

__all__ = [
    "GROUP",
    "KEEPALIVE_S",
    "Child",
    "Mosquitto",
    "Received",
    "SparkplugConsumer",
    "mosquitto_binary",
    "running_broker",
    "sim_map",
]

ROOT = Path(__file__).resolve().parents[1]
GROUP = "Lab"
KEEPALIVE_S = 5

Mosquitto = Broker
"""The broker of the tests: the lab's own (supervisor/bench/fleetbroker.py)."""


@contextmanager
def running_broker(root: Path, persistent: bool = False) -> Iterator[Mosquitto]:
    server = Mosquitto(root, persistent=persistent)
    server.start()
    try:
        yield server
    finally:
        server.stop()


def sim_map(tmp: Path, broker: Mosquitto, edge: str | None = None, **sparkplug: Any) -> Path:
    """io_maps/sim.yaml on free loopback ports, no login, its state under ``tmp`` (or
    ``tmp/edge``), an edge node of group ``Lab`` (edge node id ``edge``, else the bench
    name ``sim``) with the further ``sparkplug`` keys."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    for dev in data["devices"].values():
        if "port" in dev:
            dev["port"] = free_tcp_port()
    data["hmi"]["port"] = 0
    data["hmi"]["login"] = False
    data.pop("modbus_server", None)
    data.pop("influxdb", None)
    data["opcua"] = {**data.get("opcua", {}), "enabled": False}
    data["state_dir"] = str((tmp / edge if edge else tmp) / "var")
    section = {"broker": broker.url, "group": GROUP, "keepalive_s": KEEPALIVE_S}
    data["sparkplug"] = {**section, **({"edge_node": edge} if edge else {}), **sparkplug}
    path = tmp / f"{edge or 'sim-sparkplug'}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


class Child:
    """A ``supervisor`` command as a child process, ready once it printed ``ready``'s line;
    stopped by its pid."""

    def __init__(self, args: list[str], log_path: Path, ready: str) -> None:
        self._log = log_path.open("a", encoding="utf-8")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "supervisor.cli.main", *args],
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        assert self.proc.stdout is not None
        self.lines: list[str] = []
        for line in self.proc.stdout:
            self.lines.append(line)
            if line.startswith(ready):
                break
        else:
            raise RuntimeError(f"{args[0]} ended before saying {ready!r} (log: {log_path})")

    def kill(self) -> float:
        """SIGKILL; the moment it was sent (time.monotonic())."""
        os.kill(self.proc.pid, signal.SIGKILL)
        t = time.monotonic()
        self.proc.wait()
        self._close()
        return t

    def stop(self) -> int:
        """SIGTERM (SIGKILL after 60 s); its exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._close()
        return self.proc.returncode

    def _close(self) -> None:
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._log.close()


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
