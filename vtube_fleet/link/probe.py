"""Probing UDP ports before any link opens (the SITL launcher, ``fleet/sitl.py``).

* :func:`taken_ports`: which of some UDP ports another process holds now (a bind on the
  wildcard address fails whatever address the holder bound);
* :class:`HeartbeatListener`: binds the ground-station side of one vehicle's link (PX4 SITL
  instance i: 14540+i; :meth:`~HeartbeatListener.aclose` frees it for the link) and resolves
  :attr:`~HeartbeatListener.heard` with the system id of the first autopilot HEARTBEAT that
  arrives (pymavlink parses; a ground station's own HEARTBEAT,
  autopilot INVALID, does not count). PX4 sends on its API link from boot, before anyone
  speaks to it (the first HEARTBEAT 1.3-1.45 s after launch in the captures).
"""

from __future__ import annotations

import asyncio
import errno
import os
import socket
from collections.abc import Iterable
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

__all__ = ["HeartbeatListener", "taken_ports"]


def taken_ports(ports: Iterable[int]) -> dict[int, str]:
    """The UDP ports of ``ports`` that cannot be bound now, each with the reason (``in use``
    or the OS's words); probed by binding the wildcard address and releasing it at once."""
    out: dict[int, str] = {}
    for port in ports:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.bind(("", port))
        except OSError as exc:
            out[port] = "in use" if exc.errno == errno.EADDRINUSE else (
                exc.strerror or os.strerror(exc.errno or 0))
        finally:
            s.close()
    return out


class HeartbeatListener(asyncio.DatagramProtocol):
    """The first autopilot HEARTBEAT on ``host:port`` (see the module docstring); open with
    :meth:`open`, close with :meth:`close`. ``heard``: the sender's system id."""

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        loop = asyncio.get_running_loop()
        self.heard: asyncio.Future[int] = loop.create_future()
        self._closed: asyncio.Future[None] = loop.create_future()
        self.datagrams = 0
        self._mav = mavlink2.MAVLink(None)
        self._mav.robust_parsing = True
        self._transport: asyncio.DatagramTransport | None = None

    @classmethod
    async def open(cls, host: str, port: int) -> HeartbeatListener:
        """Bind ``host:port``; :class:`OSError` if it cannot (a port in use)."""
        loop = asyncio.get_running_loop()
        listener = cls(host, port)
        transport, _ = await loop.create_datagram_endpoint(lambda: listener,
                                                           local_addr=(host, port))
        listener._transport = transport  # type: ignore[assignment]
        return listener

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.datagrams += 1
        if self.heard.done():
            return
        try:
            msgs = self._mav.parse_buffer(data) or []
        except Exception:  # noqa: BLE001 - a datagram that is not MAVLink: not an answer
            return
        for m in msgs:
            if (m.get_type() == "HEARTBEAT"
                    and m.autopilot != mavlink2.MAV_AUTOPILOT_INVALID):
                self.heard.set_result(int(m.get_srcSystem()))
                return

    def connection_lost(self, exc: Exception | None) -> None:
        if not self._closed.done():
            self._closed.set_result(None)

    def close(self) -> None:
        """Close the socket (asyncio closes it on the loop's next round: :meth:`aclose`)."""
        if self._transport is not None:
            self._transport.close()
            self._transport = None
        if not self.heard.done():
            self.heard.cancel()

    async def aclose(self) -> None:
        """Close the socket and wait until it is closed: the port is free on return."""
        had = self._transport is not None
        self.close()
        if had:
            await self._closed
