"""A small asyncio MQTT 3.1.1 client: exactly what :class:`~vtube_fleet.bus.mqtt.MqttBus` needs.

Why not paho-mqtt (through aiomqtt)? Measured on this machine (``bench/bench_mqtt.py``,
``docs/mqtt.md``): paho reads **one packet per socket wake-up** with three ``recv`` calls (type
byte, length byte, body), builds a message object, a topic object and a lock per message, and
every QoS-0 publish goes through a wake-up byte, a writer registration and an
``asyncio.Event`` before the bytes reach the socket. That per-message overhead, not the bus's
own work, is what 100 agents on two cores could not afford. This client is an
:class:`asyncio.Protocol`: every TCP chunk the event loop reads is parsed in one loop (all the
packets in it), each PUBLISH handed to ``on_message(topic, payload)`` at once; a QoS-0 publish
is one ``transport.write``. gmqtt, an asyncio client too, was measured against it in issue 31
(``bench_mqtt.py --client gmqtt``, docs/mqtt.md): 6-8× our receive path per message, +26 % of
the agents' CPU per received state, about 3× the p99 age; this client stays.

What it does: CONNECT (clean session, keep-alive, username/password, last will), TLS (an
:class:`ssl.SSLContext`, hostname verified by the context), PUBLISH QoS 0 and 1 (waits for the
PUBACK) with retain, SUBSCRIBE / UNSUBSCRIBE (waits for the ack), PUBACK for the QoS-1
messages it receives, PINGREQ when either direction was silent for a keep-alive period, and the
end of the connection (:meth:`MqttClient.wait_closed`) when the broker does not answer a ping
within another period, closes the socket or sends garbage. Not supported (not used by the
bus): QoS 2, persistent sessions (no retransmission after a reconnect: the bus re-announces
everything it owns), MQTT 5.

Errors are :class:`MqttError` with one line saying what failed.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
import ssl
import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

__all__ = ["MqttClient", "MqttError", "Will"]

_CONNECT, _CONNACK, _PUBLISH, _PUBACK = 0x10, 0x20, 0x30, 0x40
_SUBSCRIBE, _SUBACK, _UNSUBSCRIBE, _UNSUBACK = 0x82, 0x90, 0xA2, 0xB0
_PINGREQ, _PINGRESP, _DISCONNECT = b"\xc0\x00", 0xD0, b"\xe0\x00"

_CONNACK_CODES = {
    1: "unacceptable protocol version",
    2: "client identifier rejected",
    3: "broker unavailable",
    4: "bad user name or password",
    5: "not authorized",
}
_U16 = struct.Struct("!H")


class MqttError(Exception):
    """The connection failed, was refused, ended, or an operation timed out."""


@dataclass(frozen=True)
class Will:
    """The last will: published by the broker if the connection drops without DISCONNECT."""

    topic: str
    payload: bytes
    qos: int = 0
    retain: bool = False


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        n, digit = divmod(n, 128)
        out.append(digit | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _string(b: bytes) -> bytes:
    if len(b) > 0xFFFF:
        raise MqttError(f"an MQTT string of {len(b)} bytes is longer than 65535")
    return _U16.pack(len(b)) + b


def _packet(header: int, body: bytes) -> bytes:
    return bytes((header,)) + _varint(len(body)) + body


class MqttClient:
    """One MQTT connection (use ``async with``, then ``publish`` / ``subscribe``, and
    :meth:`wait_closed` to learn when it ends). ``on_message(topic, payload)`` is called in the
    event loop for every PUBLISH received, in order, while the chunk it came in is parsed.

    ``timeout_s`` bounds the connect and every operation that waits for the broker (``None``
    or ``math.inf`` in an operation: wait as long as the connection lives).
    """

    def __init__(
        self,
        host: str,
        port: int,
        *,
        client_id: str,
        on_message: Callable[[str, bytes], None],
        username: str | None = None,
        password: str | None = None,
        will: Will | None = None,
        tls_context: ssl.SSLContext | None = None,
        keepalive_s: int = 60,
        timeout_s: float = 5.0,
    ) -> None:
        self.host, self.port = host, port
        self.client_id = client_id
        self.on_message = on_message
        self.username, self.password = username, password
        self.will = will
        self.tls_context = tls_context
        self.keepalive_s = max(1, int(keepalive_s))
        self.timeout_s = timeout_s
        self._transport: asyncio.Transport | None = None
        self._closed: asyncio.Future[None] | None = None
        self._connack: asyncio.Future[int] | None = None
        self._acks: dict[int, asyncio.Future[bytes]] = {}
        self._next_id = 0
        self._buf = b""
        self._last_in = self._last_out = 0.0
        self._ping_sent: float | None = None
        self._keepalive_task: asyncio.Task[None] | None = None
        self._writable: asyncio.Future[None] | None = None  # set while the kernel is full

    # -- lifecycle --------------------------------------------------------------------------
    async def __aenter__(self) -> MqttClient:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.disconnect()

    async def connect(self) -> None:
        """Open the connection and wait for the broker's CONNACK (:class:`MqttError` if it
        refuses, cannot be reached, or does not answer within ``timeout_s``)."""
        loop = asyncio.get_running_loop()
        self._closed = loop.create_future()
        self._connack = loop.create_future()
        where = f"{self.host}:{self.port}"
        try:
            async with asyncio.timeout(self.timeout_s):
                transport, _ = await loop.create_connection(
                    lambda: _Protocol(self), self.host, self.port, ssl=self.tls_context,
                    server_hostname=self.host if self.tls_context is not None else None,
                )
                self._transport = transport  # type: ignore[assignment]
                sock = transport.get_extra_info("socket")
                if sock is not None:
                    with contextlib.suppress(OSError):
                        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                # pause_writing as soon as anything waits in user space, resume_writing once
                # it is all in the kernel (see writable): high=0 would pause a TLS transport
                # after every write (it pauses at size >= high, a plain socket at size > high)
                transport.set_write_buffer_limits(high=1, low=0)
                self._write(self._connect_packet())
                code = await self._connack
        except TimeoutError:
            self._abort()
            raise MqttError(f"no CONNACK from the MQTT broker {where} within "
                            f"{self.timeout_s:g} s") from None
        except (OSError, ssl.SSLError) as exc:
            self._abort()
            raise MqttError(f"cannot connect to the MQTT broker {where}: {exc}") from None
        except BaseException:  # MqttError (lost before the CONNACK), cancelled: no leak
            self._abort()
            raise
        if code != 0:
            self._abort()
            raise MqttError(f"the MQTT broker {where} refused the connection: "
                            f"{_CONNACK_CODES.get(code, f'code {code}')}")
        self._keepalive_task = loop.create_task(self._keepalive())

    def _connect_packet(self) -> bytes:
        flags = 0x02  # clean session
        payload = _string(self.client_id.encode())
        if self.will is not None:
            flags |= 0x04 | (self.will.qos & 3) << 3 | (0x20 if self.will.retain else 0)
            payload += _string(self.will.topic.encode()) + _string(self.will.payload)
        if self.username is not None:
            flags |= 0x80
            payload += _string(self.username.encode())
            if self.password is not None:
                flags |= 0x40
                payload += _string(self.password.encode())
        body = b"\x00\x04MQTT\x04" + bytes((flags,)) + _U16.pack(self.keepalive_s) + payload
        return _packet(_CONNECT, body)

    async def disconnect(self) -> None:
        """Send DISCONNECT (the broker discards the will) and close the connection."""
        t = self._transport
        if t is not None and not t.is_closing():
            t.write(_DISCONNECT)
            t.close()
        self._lose(MqttError("disconnected"))
        closed = self._closed
        if closed is not None and not closed.done():
            closed.cancel()

    def _abort(self) -> None:
        t = self._transport
        if t is not None:
            t.abort()
        self._lose(MqttError("connection aborted"))

    async def wait_closed(self) -> None:
        """Wait until the connection ends; raises the :class:`MqttError` saying why."""
        assert self._closed is not None, "not connected"
        await asyncio.shield(self._closed)

    @property
    def is_connected(self) -> bool:
        return self._closed is not None and not self._closed.done()

    def _lose(self, exc: MqttError) -> None:
        """The connection is over: fail whatever waits for the broker."""
        if self._keepalive_task is not None:
            self._keepalive_task.cancel()
            self._keepalive_task = None
        for fut in (self._connack, self._writable, *self._acks.values()):
            if fut is not None and not fut.done():
                fut.set_exception(exc)
                fut.exception()  # retrieved: nobody may be waiting any more
        self._acks.clear()
        closed = self._closed
        if closed is not None and not closed.done():
            closed.set_exception(exc)
            closed.exception()
        t, self._transport = self._transport, None
        if t is not None and not t.is_closing():
            t.abort()

    # -- operations ---------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        t = self._transport
        if t is None or self._closed is None or self._closed.done():
            raise MqttError("not connected to the MQTT broker")
        t.write(data)
        self._last_out = time.monotonic()

    def _packet_id(self) -> int:
        for _ in range(65535):
            self._next_id = self._next_id % 65535 + 1
            if self._next_id not in self._acks:
                return self._next_id
        raise MqttError("no free MQTT packet id (65535 operations in flight)")

    async def _wait_ack(self, pid: int, timeout: float | None, what: str) -> bytes:
        fut = asyncio.get_running_loop().create_future()
        self._acks[pid] = fut
        limit = self.timeout_s if timeout is None else timeout
        try:
            async with asyncio.timeout(None if math.isinf(limit) else limit):
                return await fut
        except TimeoutError:
            raise MqttError(f"{what}: no answer from the MQTT broker within {limit:g} s") from None
        finally:
            if self._acks.get(pid) is fut:
                del self._acks[pid]

    @property
    def writable(self) -> bool:
        """True while connected and everything written so far is in the kernel."""
        return self._writable is None and self._transport is not None

    async def wait_writable(self) -> None:
        """Wait until everything written so far is in the kernel (:class:`MqttError` if the
        connection ends first)."""
        if self._transport is None:
            raise MqttError("not connected to the MQTT broker")
        writable = self._writable
        if writable is not None:
            await asyncio.shield(writable)

    def publish_nowait(self, topic: str, payload: bytes, retain: bool = False) -> None:
        """Write a QoS-0 PUBLISH now (it never waits: see :attr:`writable`)."""
        self._write(_packet(_PUBLISH | (0x01 if retain else 0), _string(topic.encode()) + payload))

    async def publish(self, topic: str, payload: bytes, qos: int = 0, retain: bool = False,
                      timeout: float | None = None) -> None:
        """QoS 0: written at once; returns when the bytes are in the kernel (it waits only
        while the socket is full). QoS 1: returns when the broker's PUBACK arrived."""
        if qos == 0:
            self.publish_nowait(topic, payload, retain)
            await self.wait_writable()
            return
        t = topic.encode()
        header = _PUBLISH | (0x01 if retain else 0)
        if qos != 1:
            raise ValueError(f"QoS {qos} is not supported (0 or 1)")
        pid = self._packet_id()
        self._write(_packet(header | 0x02, _string(t) + _U16.pack(pid) + payload))
        await self._wait_ack(pid, timeout, f"publish on {topic}")

    async def subscribe(self, filters: Iterable[tuple[str, int]],
                        timeout: float | None = None) -> list[int]:
        """Subscribe to ``(filter, qos)`` pairs; returns the broker's granted QoS per filter
        (0x80: refused, e.g. by the ACL)."""
        items = list(filters)
        pid = self._packet_id()
        body = _U16.pack(pid) + b"".join(_string(f.encode()) + bytes((q,)) for f, q in items)
        self._write(_packet(_SUBSCRIBE, body))
        return list(await self._wait_ack(pid, timeout, f"subscribe to {items[0][0]}"))

    async def unsubscribe(self, filters: Iterable[str], timeout: float | None = None) -> None:
        items = list(filters)
        pid = self._packet_id()
        self._write(_packet(_UNSUBSCRIBE,
                            _U16.pack(pid) + b"".join(_string(f.encode()) for f in items)))
        await self._wait_ack(pid, timeout, f"unsubscribe from {items[0]}")

    async def _keepalive(self) -> None:
        """PINGREQ when either direction was silent for a keep-alive period; the connection is
        lost when a ping stays unanswered (nothing received) for another period."""
        k = self.keepalive_s
        while True:
            await asyncio.sleep(min(0.25, k / 4))
            now = time.monotonic()
            if self._ping_sent is not None:
                if now - self._ping_sent >= k and self._last_in < self._ping_sent:
                    self._lose(MqttError(f"the MQTT broker {self.host}:{self.port} did not "
                                         f"answer a ping within {k} s (keep-alive)"))
                    return
                if self._last_in >= self._ping_sent:
                    self._ping_sent = None
            if self._ping_sent is None and (now - self._last_out >= k or now - self._last_in >= k):
                with contextlib.suppress(MqttError):
                    self._write(_PINGREQ)
                    self._ping_sent = now

    # -- incoming -----------------------------------------------------------------------------
    def _feed(self, data: bytes) -> None:
        """Parse every complete packet of ``self._buf + data`` (the rest waits for more)."""
        self._last_in = time.monotonic()
        buf = self._buf + data if self._buf else data
        n = len(buf)
        i = 0
        on_message = self.on_message
        while n - i >= 2:
            header = buf[i]
            length = buf[i + 1]
            j = i + 2
            if length & 0x80:  # a multi-byte remaining length
                length &= 0x7F
                shift = 7
                while True:
                    if j >= n:
                        self._buf = buf[i:]
                        return
                    b = buf[j]
                    j += 1
                    length |= (b & 0x7F) << shift
                    if not b & 0x80:
                        break
                    shift += 7
                    if shift > 21:
                        raise MqttError("malformed remaining length from the broker")
            end = j + length
            if end > n:
                break
            if header & 0xF0 == _PUBLISH:
                tlen = buf[j] << 8 | buf[j + 1]
                k = j + 2 + tlen
                topic = buf[j + 2:k].decode()
                if header & 0x06:  # QoS 1 (the bus never subscribes with QoS 2)
                    pid = buf[k:k + 2]
                    k += 2
                    self._write(b"\x40\x02" + pid)
                on_message(topic, buf[k:end])
            else:
                self._control(header, buf[j:end])
            i = end
        self._buf = buf[i:] if i < n else b""

    def _control(self, header: int, body: bytes) -> None:
        kind = header & 0xF0
        if kind == _CONNACK:
            if self._connack is not None and not self._connack.done() and len(body) >= 2:
                self._connack.set_result(body[1])
        elif kind in (_PUBACK, _SUBACK & 0xF0, _UNSUBACK):
            if len(body) >= 2:
                fut = self._acks.pop(body[0] << 8 | body[1], None)
                if fut is not None and not fut.done():
                    fut.set_result(body[2:])
        elif kind == _PINGRESP:
            pass  # _last_in was updated
        else:
            raise MqttError(f"unexpected MQTT packet type 0x{header:02x} from the broker")


class _Protocol(asyncio.Protocol):
    def __init__(self, client: MqttClient) -> None:
        self.client = client

    def data_received(self, data: bytes) -> None:
        try:
            self.client._feed(data)
        except (MqttError, IndexError, UnicodeDecodeError) as exc:
            why = exc if isinstance(exc, MqttError) else MqttError(
                f"malformed packet from the MQTT broker ({exc})")
            self.client._lose(why)

    def connection_lost(self, exc: Exception | None) -> None:
        c = self.client
        where = f"{c.host}:{c.port}"
        c._lose(MqttError(f"lost the connection to {where}: {exc}" if exc is not None
                          else f"the MQTT broker {where} closed the connection"))

    def pause_writing(self) -> None:
        c = self.client
        if c._writable is None or c._writable.done():
            c._writable = asyncio.get_running_loop().create_future()

    def resume_writing(self) -> None:
        w, self.client._writable = self.client._writable, None
        if w is not None and not w.done():
            w.set_result(None)
