"""The fleet's MQTT side: a Sparkplug host application's subscription (paho-mqtt, its own
network thread; docs/fleet.md).

It subscribes to ``spBv1.0/<group>/#`` (QoS 1: a death must not be lost), hands every
message to the ``Fleet`` and publishes the NCMD ``Node Control/Rebirth`` the fleet asks for.
On each (re)connection it asks every node it knows for a rebirth: what happened while it
was away is unknown, births make the picture right again.

Given a host id, it is also a Sparkplug 3.0 host application that says it is there: its
STATE (``spBv1.0/STATE/<host id>``, retained, QoS 1, ``{"online": true, "timestamp": …}``)
after each CONNECT, and the same with ``"online": false`` as that CONNECT's will and on a
clean stop, with the CONNECT's timestamp in both (chapter 5, "Host Application Session
Establishment"): an edge node configured with it as its primary host can tell.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from typing import Any

import paho.mqtt.client as paho

from supervisor.fleet.state import Fleet
from supervisor.publish.sparkplug.node import NAMESPACE, REBIRTH
from supervisor.publish.sparkplug.payload import BOOLEAN, MetricValue, encode

__all__ = ["FleetHost", "rebirth_request"]

log = logging.getLogger(__name__)


def _now_ms() -> int:
    return round(time.time() * 1000)


def rebirth_request(now_ms: int) -> bytes:
    """An NCMD payload: 'Node Control/Rebirth' = true (NCMD carries no seq)."""
    return encode(now_ms, [MetricValue(REBIRTH, BOOLEAN, True, now_ms)], None)


class FleetHost:
    """The fleet's MQTT client (MQTT 3.1.1, clean session)."""

    def __init__(
        self,
        fleet: Fleet,
        host: str,
        port: int,
        *,
        keepalive_s: int = 30,
        host_id: str | None = None,
    ) -> None:
        self.fleet = fleet
        self.host_id = host_id
        self._state_ms = 0  # the timestamp of this CONNECT's STATE (birth and will alike)
        self.host, self.port = host, port
        self.keepalive_s = keepalive_s
        self.connected = False
        self.rebirths_sent = 0
        self._client = paho.Client(
            client_id=f"fleet:{fleet.group}:{os.getpid()}", clean_session=True
        )
        self._client.enable_logger(log)
        self._client.reconnect_delay_set(min_delay=1, max_delay=30)
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = self._on_disconnect
        self._client.on_message = self._on_message

    @property
    def topic(self) -> str:
        return f"{NAMESPACE}/{self.fleet.group}/#"

    @property
    def state_topic(self) -> str:
        return f"{NAMESPACE}/STATE/{self.host_id}"

    def _state(self, online: bool) -> bytes:
        return json.dumps({"online": online, "timestamp": self._state_ms}).encode()

    def _set_will(self) -> None:
        if self.host_id is not None:
            self._state_ms = _now_ms()
            self._client.will_set(self.state_topic, self._state(False), qos=1, retain=True)

    def start(self) -> None:
        """Connect in the background (a broker that is away is retried)."""
        self._set_will()
        self._client.connect_async(self.host, self.port, keepalive=self.keepalive_s)
        self._client.loop_start()

    def stop(self) -> None:
        if self.host_id is not None and self._client.is_connected():
            info = self._client.publish(self.state_topic, self._state(False), qos=1, retain=True)
            if info.rc == paho.MQTT_ERR_SUCCESS:
                # RuntimeError/ValueError: the connection went meanwhile.
                with contextlib.suppress(RuntimeError, ValueError):
                    info.wait_for_publish(timeout=2.0)
        self._client.disconnect()
        self._client.loop_stop()

    def _on_connect(self, client: Any, userdata: Any, flags: Any, rc: int) -> None:
        if rc != 0:
            log.warning(
                "fleet: broker %s:%d refused: %s", self.host, self.port, paho.connack_string(rc)
            )
            return
        client.subscribe(self.topic, qos=1)
        if self.host_id is not None:
            client.publish(self.state_topic, self._state(True), qos=1, retain=True)
        self.connected = True
        log.info("fleet: broker %s:%d connected, %s subscribed", self.host, self.port, self.topic)
        for edge in self.fleet.all_nodes():
            self.ask_rebirth(edge)

    def _on_disconnect(self, client: Any, userdata: Any, rc: int) -> None:
        self.connected = False
        self._set_will()  # the next CONNECT's, with its own timestamp
        if rc != 0:
            log.warning(
                "fleet: broker %s:%d lost (%s); reconnecting",
                self.host,
                self.port,
                paho.error_string(rc),
            )

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        for edge in self.fleet.receive(msg.topic, bytes(msg.payload), _now_ms()):
            self.ask_rebirth(edge)

    def ask_rebirth(self, edge: str) -> None:
        topic = f"{NAMESPACE}/{self.fleet.group}/NCMD/{edge}"
        log.info("fleet: asking %s for a rebirth", edge)
        self._client.publish(topic, rebirth_request(_now_ms()), qos=1)
        self.rebirths_sent += 1
