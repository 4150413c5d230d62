"""The MQTT connection of the edge node: paho-mqtt's client on its own network thread
(docs/adr/0051-sparkplug-library.md).

``PahoTransport`` connects without blocking (a broker that is down at start is retried,
like one that goes away later: paho's reconnect with a capped back-off), registers the
NDEATH as the will of each CONNECT, subscribes to the node's NCMD topic with QoS 1 on
every (re)connection before saying it is connected, and hands every NCMD payload over.
Its callbacks run on paho's thread: the publisher only sets flags from them.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import paho.mqtt.client as paho

from supervisor.publish.sparkplug.node import Message

__all__ = ["Callbacks", "PahoTransport", "Transport"]

log = logging.getLogger(__name__)


class Callbacks(Protocol):
    """What the publisher is told (on the transport's thread)."""

    def connected(self) -> None: ...

    def disconnected(self) -> None: ...

    def command(self, payload: bytes) -> None: ...

    def message(self, topic: str, payload: bytes) -> None:
        """A message on one of the ``also`` topics (a DCMD, a STATE)."""
        ...


class Transport(Protocol):
    def start(
        self, will: Message, ncmd_topic: str, callbacks: Callbacks, *, also: Sequence[str] = ()
    ) -> None:
        """Connect; subscribe to ``ncmd_topic`` and to ``also`` on every connection."""
        ...

    def reconnect(self, last: Message, will: Message) -> None:
        """Publish ``last`` (an NDEATH), disconnect, connect again with ``will``."""
        ...

    def set_will(self, will: Message) -> None:
        """The will of the next CONNECT (a reconnection)."""
        ...

    def publish(self, message: Message) -> bool:
        """Queue ``message`` for sending; False when there is no connection now."""
        ...

    def stop(self, last: Message | None) -> None:
        """Publish ``last`` (the NDEATH of a clean stop) if connected, then disconnect."""
        ...


class PahoTransport:
    """``Transport`` over paho-mqtt (MQTT 3.1.1, clean session)."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        client_id: str,
        keepalive_s: int,
        reconnect_min_s: float = 1.0,
        reconnect_max_s: float = 30.0,
    ) -> None:
        self.host, self.port, self.keepalive_s = host, port, keepalive_s
        self._client = paho.Client(client_id=client_id, clean_session=True)
        self._client.enable_logger(log)
        self._client.reconnect_delay_set(
            min_delay=max(1, round(reconnect_min_s)), max_delay=max(1, round(reconnect_max_s))
        )
        # Messages queued while a connection is being made: a session never publishes data
        # before its births, so what waits here is a birth sequence at most (bounded anyway).
        self._client.max_queued_messages_set(10_000)
        self._ncmd = ""
        self._also: tuple[str, ...] = ()
        self._callbacks: Callbacks | None = None
        self._lock = threading.Lock()

    def start(
        self, will: Message, ncmd_topic: str, callbacks: Callbacks, *, also: Sequence[str] = ()
    ) -> None:
        self._ncmd = ncmd_topic
        self._also = tuple(also)
        self._callbacks = callbacks
        client = self._client
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.message_callback_add(ncmd_topic, self._on_ncmd)
        for topic in self._also:
            client.message_callback_add(topic, self._on_message)
        self.set_will(will)
        client.connect_async(self.host, self.port, keepalive=self.keepalive_s)
        client.loop_start()  # retries the first connection too

    def set_will(self, will: Message) -> None:
        with self._lock:
            self._client.will_set(will.topic, will.payload, qos=will.qos, retain=False)

    def _on_connect(self, client: Any, userdata: Any, flags: Any, rc: int) -> None:
        if rc != 0:
            log.warning(
                "MQTT broker %s:%d refused the connection: %s",
                self.host,
                self.port,
                paho.connack_string(rc),
            )
            return
        # Before any birth (chapter 5): the broker handles the SUBSCRIBE before the
        # PUBLISHes that follow it on this connection.
        client.subscribe([(topic, 1) for topic in (self._ncmd, *self._also)])
        log.info("MQTT broker %s:%d connected", self.host, self.port)
        if self._callbacks is not None:
            self._callbacks.connected()

    def _on_disconnect(self, client: Any, userdata: Any, rc: int) -> None:
        if rc != 0:
            log.warning(
                "MQTT broker %s:%d: connection lost (%s); reconnecting",
                self.host,
                self.port,
                paho.error_string(rc),
            )
        if self._callbacks is not None:
            self._callbacks.disconnected()

    def _on_ncmd(self, client: Any, userdata: Any, msg: Any) -> None:
        if self._callbacks is not None:
            self._callbacks.command(bytes(msg.payload))

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        if self._callbacks is None:
            return
        try:
            self._callbacks.message(str(msg.topic), bytes(msg.payload))
        except Exception:  # a bug must not end paho's thread (and the connection with it)
            log.exception("Sparkplug: the message on %s could not be handled", msg.topic)

    def reconnect(self, last: Message, will: Message) -> None:
        # Not from paho's thread (loop_stop joins it): the edge node's thread calls this.
        client = self._client
        self._publish_last(last)
        client.disconnect()
        client.loop_stop()
        self.set_will(will)
        client.connect_async(self.host, self.port, keepalive=self.keepalive_s)
        client.loop_start()

    def _publish_last(self, last: Message) -> None:
        client = self._client
        if client.is_connected():
            info = client.publish(last.topic, last.payload, qos=last.qos)
            if info.rc == paho.MQTT_ERR_SUCCESS:
                # RuntimeError/ValueError: the connection went meanwhile.
                with contextlib.suppress(RuntimeError, ValueError):
                    info.wait_for_publish(timeout=2.0)

    def publish(self, message: Message) -> bool:
        if not self._client.is_connected():
            return False
        info = self._client.publish(message.topic, message.payload, qos=message.qos)
        return bool(info.rc == paho.MQTT_ERR_SUCCESS)

    def stop(self, last: Message | None) -> None:
        client = self._client
        if last is not None:
            self._publish_last(last)
        client.disconnect()  # a clean DISCONNECT: the broker drops the will
        client.loop_stop()


Factory = Callable[[], Transport]
