"""The bus's client interface (:class:`vtube_fleet.bus.client.MqttClient`) on top of gmqtt, for
``bench/bench_mqtt.py --client gmqtt`` (issue 31: is gmqtt within 20 % of our client?).

gmqtt (``pip install gmqtt``) is an asyncio MQTT client: a ``StreamReaderProtocol`` whose read
task splits every chunk into packets and hands each to a package handler, which calls
``on_message(client, topic, payload, qos, properties)``. This adapter gives :class:`MqttBus`
exactly what it uses from our client, with gmqtt's public API where it has one:

* connect with clean session, MQTT 3.1.1, keep-alive, username/password, last will, TLS (an
  :class:`ssl.SSLContext`; asyncio verifies the host name), bounded by ``timeout_s``; a refusal
  (CONNACK code) or a failure is an :class:`MqttError` with one line;
* QoS-0 publish (one ``transport.write`` in gmqtt), QoS-1 publish waiting for the PUBACK
  (gmqtt tells a PUBACK only to its persistent storage of in-flight messages: a storage that
  resolves a future per packet id), SUBSCRIBE / UNSUBSCRIBE waiting for the ack (``on_subscribe``
  / ``on_unsubscribe`` by packet id);
* ``writable`` / ``wait_writable``: the transport's write buffer (limits high=1, low=0 as in
  our client; gmqtt's protocol is asyncio's flow-control mixin, whose drain helper waits);
* the end of the connection (:meth:`wait_closed`): gmqtt's ``on_disconnect``; gmqtt would
  reconnect by itself, the bus does that (with its back-off and re-announcements), so the
  adapter turns gmqtt's own reconnection off when the connection ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import ssl
from collections.abc import Callable, Iterable
from typing import Any

from gmqtt import Client, Message
from gmqtt.mqtt.constants import MQTTv311
from gmqtt.mqtt.handler import MQTTConnectError
from gmqtt.storage import PersistentStorage

from vtube_fleet.bus.client import MqttClient, MqttError, Will

__all__ = ["GmqttClient"]


class _AckStorage(PersistentStorage):
    """gmqtt's in-flight store, also resolving a future when a packet id's PUBACK arrives."""

    def __init__(self) -> None:
        super().__init__()
        self.pushed: int | None = None
        self.acks: dict[int, asyncio.Future[None]] = {}

    def push_message(self, mid: int, raw_package: bytes) -> None:
        super().push_message(mid, raw_package)
        self.pushed = mid

    def remove_message_by_mid(self, mid: int) -> None:
        super().remove_message_by_mid(mid)
        fut = self.acks.pop(mid, None)
        if fut is not None and not fut.done():
            fut.set_result(None)


class GmqttClient:
    """What :class:`~vtube_fleet.bus.mqtt.MqttBus` uses of an MQTT client, on gmqtt."""

    def __init__(self, host: str, port: int, *, client_id: str,
                 on_message: Callable[[str, bytes], None], username: str | None = None,
                 password: str | None = None, will: Will | None = None,
                 tls_context: ssl.SSLContext | None = None, keepalive_s: int = 60,
                 timeout_s: float = 5.0) -> None:
        self.host, self.port = host, port
        self.tls_context = tls_context
        self.keepalive_s = max(1, int(keepalive_s))
        self.timeout_s = timeout_s
        self._storage = _AckStorage()
        will_msg = (None if will is None else
                    Message(will.topic, will.payload, qos=will.qos, retain=will.retain))
        c = Client(client_id, clean_session=True, will_message=will_msg,
                   persistent_storage=self._storage)
        if username is not None:
            c.set_auth_credentials(username, password)
        deliver = on_message

        def message(_client: Any, topic: str, payload: bytes, _qos: int, _props: Any) -> int:
            deliver(topic, payload)
            return 0

        c.on_message = message
        c.on_subscribe = self._on_suback
        c.on_unsubscribe = self._on_unsuback
        c.on_disconnect = self._on_disconnect
        self._c = c
        self._acks: dict[int, asyncio.Future[Any]] = {}
        self._closed: asyncio.Future[None] | None = None

    @classmethod
    def like(cls, own: MqttClient) -> GmqttClient:
        """The same connection as our client ``own`` would open."""
        return cls(own.host, own.port, client_id=own.client_id, on_message=own.on_message,
                   username=own.username, password=own.password, will=own.will,
                   tls_context=own.tls_context, keepalive_s=own.keepalive_s,
                   timeout_s=own.timeout_s)

    # -- lifecycle --------------------------------------------------------------------------
    async def __aenter__(self) -> GmqttClient:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.disconnect()

    async def connect(self) -> None:
        loop = asyncio.get_running_loop()
        self._closed = loop.create_future()
        where = f"{self.host}:{self.port}"
        try:
            async with asyncio.timeout(self.timeout_s):
                await self._c.connect(self.host, self.port,
                                      ssl=self.tls_context if self.tls_context else False,
                                      keepalive=self.keepalive_s, version=MQTTv311)
        except TimeoutError:
            await self._stop()
            raise MqttError(f"no CONNACK from the MQTT broker {where} within "
                            f"{self.timeout_s:g} s") from None
        except MQTTConnectError as exc:
            await self._stop()
            raise MqttError(f"the MQTT broker {where} refused the connection: {exc}") from None
        except (OSError, ssl.SSLError) as exc:
            await self._stop()
            raise MqttError(f"cannot connect to the MQTT broker {where}: {exc}") from None
        conn = self._c._connection  # the transport, for the write-buffer limits
        conn._transport.set_write_buffer_limits(high=1, low=0)

    async def _stop(self) -> None:
        self._c._is_active = False  # no reconnection of gmqtt's own
        with contextlib.suppress(Exception):
            await self._c.disconnect()
        self._lose(MqttError("connection aborted"))

    async def disconnect(self) -> None:
        await self._stop()
        if self._closed is not None and not self._closed.done():
            self._closed.cancel()

    async def wait_closed(self) -> None:
        assert self._closed is not None, "not connected"
        await asyncio.shield(self._closed)

    @property
    def is_connected(self) -> bool:
        return self._closed is not None and not self._closed.done()

    def _on_disconnect(self, _client: Any, _packet: Any, exc: Any = None) -> None:
        self._c._is_active = False  # the bus reconnects, with its back-off
        self._lose(MqttError(f"the MQTT broker {self.host}:{self.port} closed the connection"))

    def _lose(self, exc: MqttError) -> None:
        futs = [*self._acks.values(), *self._storage.acks.values()]
        self._acks.clear()
        self._storage.acks.clear()
        for fut in futs:
            if not fut.done():
                fut.set_exception(exc)
                fut.exception()
        closed = self._closed
        if closed is not None and not closed.done():
            closed.set_exception(exc)
            closed.exception()

    # -- operations -------------------------------------------------------------------------
    def _check(self) -> None:
        if not self.is_connected:
            raise MqttError("not connected to the MQTT broker")

    @property
    def writable(self) -> bool:
        conn = self._c._connection
        return (self.is_connected and conn is not None
                and conn._transport.get_write_buffer_size() == 0)

    async def wait_writable(self) -> None:
        self._check()
        conn = self._c._connection
        if conn._transport.get_write_buffer_size():
            await conn._protocol._drain_helper()

    def publish_nowait(self, topic: str, payload: bytes, retain: bool = False) -> None:
        self._check()
        self._c.publish(topic, payload, qos=0, retain=retain)

    async def publish(self, topic: str, payload: bytes, qos: int = 0, retain: bool = False,
                      timeout: float | None = None) -> None:
        if qos == 0:
            self.publish_nowait(topic, payload, retain)
            await self.wait_writable()
            return
        if qos != 1:
            raise ValueError(f"QoS {qos} is not supported (0 or 1)")
        self._check()
        self._c.publish(topic, payload, qos=1, retain=retain)
        mid = self._storage.pushed
        assert mid is not None
        fut = asyncio.get_running_loop().create_future()
        self._storage.acks[mid] = fut
        await self._wait(fut, timeout, f"publish on {topic}")

    async def subscribe(self, filters: Iterable[tuple[str, int]],
                        timeout: float | None = None) -> list[int]:
        from gmqtt import Subscription

        self._check()
        items = list(filters)
        mid = self._c.subscribe([Subscription(f, qos=q) for f, q in items])
        fut = asyncio.get_running_loop().create_future()
        self._acks[mid] = fut
        return list(await self._wait(fut, timeout, f"subscribe to {items[0][0]}"))

    async def unsubscribe(self, filters: Iterable[str], timeout: float | None = None) -> None:
        self._check()
        items = list(filters)
        mid = self._c.unsubscribe(items)
        fut = asyncio.get_running_loop().create_future()
        self._acks[mid] = fut
        await self._wait(fut, timeout, f"unsubscribe from {items[0]}")

    async def _wait(self, fut: asyncio.Future[Any], timeout: float | None, what: str) -> Any:
        limit = self.timeout_s if timeout is None else timeout
        try:
            async with asyncio.timeout(None if math.isinf(limit) else limit):
                return await fut
        except TimeoutError:
            raise MqttError(f"{what}: no answer from the MQTT broker within {limit:g} s") from None

    def _on_suback(self, _client: Any, mid: int, granted: Any, _props: Any = None) -> None:
        fut = self._acks.pop(mid, None)
        if fut is not None and not fut.done():
            fut.set_result(list(granted))

    def _on_unsuback(self, _client: Any, mid: int, _granted: Any = None) -> None:
        fut = self._acks.pop(mid, None)
        if fut is not None and not fut.done():
            fut.set_result(None)
