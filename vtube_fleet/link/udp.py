"""A UDP socket for one vehicle link that drains its receive queue in bursts.

asyncio's datagram transport reads ONE datagram per readiness callback. With a thousand links
in one event loop an iteration takes milliseconds, so each socket drains at most a few hundred
datagrams per second, and a vehicle that sends more (PX4 before its unused streams are switched
off: ~210 per second) fills its kernel buffer: the kernel then drops whatever comes next,
COMMAND_ACKs and HEARTBEATs included. :class:`DatagramSocket` is a non-blocking socket read by
``loop.add_reader`` that takes up to ``burst`` datagrams per wake-up (one callback for all),
with the transport methods the link uses (``sendto``, ``is_closing``, ``close``,
``get_extra_info``). Errors the kernel reports on the socket (ICMP port unreachable on a
connected ``udpout`` socket while the vehicle is not up yet) go to ``on_error``; a send the
kernel refuses for lack of buffer space is dropped and counted (``tx_dropped``): a setpoint
stream and retried commands tolerate a lost datagram, a blocked event loop would not.
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Callable
from typing import Any

__all__ = ["DatagramSocket", "DEFAULT_BURST"]

#: datagrams read per wake-up at most (then the other sockets get their turn)
DEFAULT_BURST = 64


class DatagramSocket:
    """One bound (``listens``) or connected UDP socket; see the module docstring."""

    def __init__(self, loop: asyncio.AbstractEventLoop, sock: socket.socket,
                 on_datagram: Callable[[bytes, Any], None],
                 on_error: Callable[[OSError], None], burst: int = DEFAULT_BURST) -> None:
        self._loop = loop
        self._sock = sock
        self._on_datagram = on_datagram
        self._on_error = on_error
        self.burst = burst
        self.tx_dropped = 0
        self._closed = False
        loop.add_reader(sock.fileno(), self._readable)

    @classmethod
    async def open(cls, host: str, port: int, *, listens: bool,
                   on_datagram: Callable[[bytes, Any], None],
                   on_error: Callable[[OSError], None],
                   burst: int = DEFAULT_BURST) -> DatagramSocket:
        """Bind to (``listens``) or connect to ``host:port``; :class:`OSError` if impossible."""
        loop = asyncio.get_running_loop()
        infos = await loop.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        if not infos:  # pragma: no cover - getaddrinfo raises instead
            raise OSError(f"cannot resolve {host}")
        family, _, proto, _, addr = infos[0]
        sock = socket.socket(family, socket.SOCK_DGRAM, proto)
        try:
            sock.setblocking(False)
            if listens:
                sock.bind(addr)
            else:
                sock.connect(addr)
        except OSError:
            sock.close()
            raise
        return cls(loop, sock, on_datagram, on_error, burst)

    def _readable(self) -> None:
        recvfrom, handle = self._sock.recvfrom, self._on_datagram
        for _ in range(self.burst):
            try:
                data, addr = recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                self._on_error(exc)
                return
            handle(data, addr)
            if self._closed:
                return

    def sendto(self, data: bytes, addr: Any = None) -> None:
        if self._closed:
            return
        try:
            if addr is None:
                self._sock.send(data)
            else:
                self._sock.sendto(data, addr)
        except (BlockingIOError, InterruptedError):
            self.tx_dropped += 1
        except OSError as exc:
            self._on_error(exc)

    def is_closing(self) -> bool:
        return self._closed

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._loop.remove_reader(self._sock.fileno())
        except (ValueError, RuntimeError):  # loop already closed
            pass
        self._sock.close()

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        try:
            if name == "sockname":
                return self._sock.getsockname()
            if name == "peername":
                return self._sock.getpeername()
        except OSError:
            return default
        if name == "socket":
            return self._sock
        return default
