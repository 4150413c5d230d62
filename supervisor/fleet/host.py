"""The fleet's MQTT side: a Sparkplug host application's subscription (paho-mqtt, its own
network thread; docs/fleet.md).

It subscribes to ``spBv1.0/<group>/#`` (QoS 1: a death must not be lost), hands every
message to the ``Fleet`` and publishes the NCMD ``Node Control/Rebirth`` the fleet asks for.
On each (re)connection it asks every node it knows for a rebirth: what happened while it
was away is unknown, births make the picture right again.
"""

from __future__ import annotations

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

    def __init__(self, fleet: Fleet, host: str, port: int, *, keepalive_s: int = 30) -> None:
        self.fleet = fleet
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

    def start(self) -> None:
        """Connect in the background (a broker that is away is retried)."""
        self._client.connect_async(self.host, self.port, keepalive=self.keepalive_s)
        self._client.loop_start()

    def stop(self) -> None:
        self._client.disconnect()
        self._client.loop_stop()

    def _on_connect(self, client: Any, userdata: Any, flags: Any, rc: int) -> None:
        if rc != 0:
            log.warning(
                "fleet: broker %s:%d refused: %s", self.host, self.port, paho.connack_string(rc)
            )
            return
        client.subscribe(self.topic, qos=1)
        self.connected = True
        log.info("fleet: broker %s:%d connected, %s subscribed", self.host, self.port, self.topic)
        for edge in self.fleet.all_nodes():
            self.ask_rebirth(edge)

    def _on_disconnect(self, client: Any, userdata: Any, rc: int) -> None:
        self.connected = False
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
