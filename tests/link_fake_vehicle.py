"""A tiny PX4-like vehicle on a real loopback UDP socket, for the link tests.

Not a simulator (that is ``sim_stub``): it answers commands with scripted MAV_RESULTs (or not at
all), applies ARM / DO_SET_MODE, answers REQUEST_MESSAGE (message first, then the ACK, as PX4
does), replies to TIMESYNC, streams position/health at ``stream_hz`` and records everything it
receives so tests can wait on what the GCS sent.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from vtube_fleet.link import px4

HEALTH_BITS = 0x01 | 0x02 | 0x04 | 0x20 | px4.PREARM_CHECK_BIT
ORIGIN = (47.3977459, 8.5455930, 489.056)


class FakeVehicle(asyncio.DatagramProtocol):
    def __init__(
        self,
        sysid: int = 1,
        *,
        gcs_addr: tuple[str, int] | None = None,
        heartbeat_hz: float = 5.0,
        stream_hz: float = 20.0,
        origin: tuple[float, float, float] = ORIGIN,
    ) -> None:
        self.sysid = sysid
        self.mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self.mav.robust_parsing = True
        self.gcs_addr = gcs_addr
        self.heartbeat_hz = heartbeat_hz
        self.stream_hz = stream_hz
        self.origin = origin
        self.custom_mode = px4.encode_custom_mode(4, 3)
        self.armed = False
        self.health = HEALTH_BITS
        self.north_m = 0.0
        self.script: dict[int, list[int | None]] = {}
        self.statustext_on_reject: str | None = None
        self.received: list[Any] = []
        self.bad = 0
        self._waiters: list[tuple[Callable[[Any], bool], asyncio.Future[Any]]] = []
        self.transport: asyncio.DatagramTransport | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self.streaming = True

    # -- lifecycle ------------------------------------------------------------------------------
    async def start(self, port: int = 0) -> tuple[str, int]:
        loop = asyncio.get_running_loop()
        self.transport, _ = await loop.create_datagram_endpoint(
            lambda: self, local_addr=("127.0.0.1", port)
        )
        self._tasks = [loop.create_task(self._heartbeat_loop()), loop.create_task(self._stream())]
        return self.transport.get_extra_info("sockname")

    async def stop(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except asyncio.CancelledError:
                pass
        if self.transport is not None:
            self.transport.close()

    async def __aenter__(self) -> FakeVehicle:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # -- sending --------------------------------------------------------------------------------
    def send(self, msg: Any) -> None:
        if self.gcs_addr is None or self.transport is None:
            return
        self.transport.sendto(self.pack(msg), self.gcs_addr)

    def pack(self, msg: Any) -> bytes:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) & 0xFF
        return buf

    def send_raw(self, data: bytes) -> None:
        assert self.transport is not None and self.gcs_addr is not None
        self.transport.sendto(data, self.gcs_addr)

    def heartbeat(self) -> Any:
        base = 0x01 | (0x80 if self.armed else 0)
        return self.mav.heartbeat_encode(2, 12, base, self.custom_mode, 4 if self.armed else 3, 3)

    async def _heartbeat_loop(self) -> None:
        while True:
            self.send(self.heartbeat())
            if self.streaming:
                self.send(self._home())
            await asyncio.sleep(1.0 / self.heartbeat_hz)

    def _home(self) -> Any:
        lat, lon, alt = self.origin
        return self.mav.home_position_encode(
            int(lat * 1e7), int(lon * 1e7), int(alt * 1000), 0, 0, 0, [1, 0, 0, 0], 0, 0, 0
        )

    def _origin(self) -> Any:
        lat, lon, alt = self.origin
        return self.mav.gps_global_origin_encode(int(lat * 1e7), int(lon * 1e7), int(alt * 1000))

    async def _stream(self) -> None:
        t0 = time.monotonic()
        while True:
            if self.streaming:
                ms = int((time.monotonic() - t0) * 1000)
                lat, lon, alt = self.origin
                self.send(self.mav.local_position_ned_encode(ms, self.north_m, 0, 0, 0, 0, 0))
                self.send(self.mav.global_position_int_encode(
                    ms, int(lat * 1e7), int(lon * 1e7), int(alt * 1000), 0, 0, 0, 0, 9000
                ))
                self.send(self.mav.sys_status_encode(
                    self.health, self.health, self.health, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0
                ))
                self.send(self.mav.extended_sys_state_encode(0, 2 if self.armed else 1))
                self.send(self.mav.attitude_encode(ms, 0, 0, 0, 0, 0, 0))  # undecoded by the GCS
            await asyncio.sleep(1.0 / self.stream_hz)

    # -- receiving ------------------------------------------------------------------------------
    def datagram_received(self, data: bytes, addr: Any) -> None:
        if self.gcs_addr is None:
            self.gcs_addr = addr
        msgs = self.mav.parse_buffer(data) or []
        for m in msgs:
            if m.get_type() == "BAD_DATA":
                self.bad += 1
                continue
            self.received.append(m)
            self._handle(m)
            for pred, fut in list(self._waiters):
                if not fut.done() and pred(m):
                    fut.set_result(m)

    def _handle(self, m: Any) -> None:
        kind = m.get_type()
        if kind == "TIMESYNC" and m.tc1 == 0:
            self.send(self.mav.timesync_encode(time.monotonic_ns(), m.ts1))
        elif kind == "COMMAND_LONG" and m.target_system == self.sysid:
            self._command(m)

    def _command(self, m: Any) -> None:
        script = self.script.get(m.command)
        if script:
            result = script.pop(0)
        elif m.command in (400, 176, 511, 512, 21, 22):
            result = 0
        else:
            result = 3  # UNSUPPORTED
        if result is None:
            return  # drop: no ACK
        if result == 0:
            if m.command == 400:
                self.armed = m.param1 == 1.0
            elif m.command == 176:
                self.custom_mode = px4.encode_custom_mode(int(m.param2), int(m.param3))
            elif m.command == 512:
                if int(m.param1) == 242:
                    self.send(self._home())
                elif int(m.param1) == 49:
                    self.send(self._origin())
        elif self.statustext_on_reject:
            self.statustext(2, self.statustext_on_reject)
        src = m.get_srcSystem(), m.get_srcComponent()
        self.send(self.mav.command_ack_encode(m.command, result, 0, 0, src[0], src[1]))

    def statustext(self, severity: int, text: str) -> None:
        """PX4 style: chunks of 50 characters sharing an id, chunk_seq 0, 1, …"""
        self._text_id = getattr(self, "_text_id", 0) + 1
        raw = text.encode()
        for seq, i in enumerate(range(0, max(len(raw), 1), 50)):
            self.send(self.mav.statustext_encode(severity, raw[i : i + 50], self._text_id, seq))

    async def wait_for(self, pred: Callable[[Any], bool], timeout_s: float = 5.0) -> Any:
        for m in self.received:
            if pred(m):
                return m
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        entry = (pred, fut)
        self._waiters.append(entry)
        try:
            async with asyncio.timeout(timeout_s):
                return await fut
        finally:
            self._waiters.remove(entry)

    def commands(self, command: int) -> list[Any]:
        return [m for m in self.received if m.get_type() == "COMMAND_LONG" and m.command == command]


def free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RecordingTransport:
    """A transport stub in place of a link's socket: keeps every datagram the link sends."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def sendto(self, data: bytes, addr: Any = None) -> None:
        self.sent.append(bytes(data))

    def is_closing(self) -> bool:
        return False

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return default  # no socket: the link sends through sendto above
