"""A UDP socket for one vehicle link that drains its receive queue in bursts.

asyncio's datagram transport reads ONE datagram per readiness callback. With a thousand links
in one event loop an iteration takes milliseconds, so each socket drains at most a few hundred
datagrams per second, and a vehicle that sends more (PX4 before its unused streams are switched
off: ~210 per second) fills its kernel buffer: the kernel then drops whatever comes next,
COMMAND_ACKs and HEARTBEATs included. :class:`DatagramSocket` is a non-blocking socket read by
``loop.add_reader`` that takes up to ``burst`` datagrams per wake-up (one callback for all),
with the transport methods the link uses (``sendto``, ``is_closing``, ``close``,
``get_extra_info``). ``on_datagram(data, addr, now)`` gets each datagram with a
``time.monotonic()`` reading taken when the hub's round began (every datagram of the round was
queued by then: an upper bound on its arrival). Errors the kernel reports on the socket
(ICMP port unreachable on a connected ``udpout`` socket while the vehicle is not up yet) go to
``on_error``; a send the kernel refuses for lack of buffer space is dropped and counted
(``tx_dropped``): a setpoint stream and retried commands tolerate a lost datagram, a blocked
event loop would not.

**One wake-up for all sockets** (Linux, issue 16). A fleet's links are not registered with the
event loop one by one: they share a :class:`DatagramHub`, one ``epoll`` of their own whose file
descriptor is the only one the loop watches. When it is readable, the hub asks it which sockets
have data and reads ONE datagram from each, in rounds, until none is left or
:data:`HUB_ROUNDS` rounds have passed (the loop then calls it again: the fleet's other work
gets its turn between). A round reads all its datagrams first and then hands them to their
sockets' handlers (a read's kernel work evicts the handlers' objects from the caches). So a
datagram costs one ``recvfrom`` and no callback of the loop of its own, and a socket whose
queue is empty is never read in vain (with a reader per socket, the read that finds the queue
empty costs as much as the one that found a datagram). Each socket is drained in order; the
sockets take turns, as in bursts. Elsewhere (no ``epoll``) each socket
has its own reader and reads up to ``burst`` datagrams per wake-up.
"""

from __future__ import annotations

import asyncio
import logging
import select
import socket
import time
import weakref
from collections.abc import Callable
from typing import Any

__all__ = ["DEFAULT_BURST", "HUB_ROUNDS", "DatagramHub", "DatagramSocket"]

log = logging.getLogger(__name__)

#: datagrams read per wake-up at most (then the other sockets get their turn)
DEFAULT_BURST = 64
#: rounds of one datagram per ready socket that :class:`DatagramHub` reads per wake-up
HUB_ROUNDS = 8


class DatagramHub:
    """The datagram sockets of one event loop behind one ``epoll`` (module docstring)."""

    _hubs: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, DatagramHub] = (
        weakref.WeakKeyDictionary())

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._epoll = select.epoll()
        self._sockets: dict[int, DatagramSocket] = {}
        loop.add_reader(self._epoll.fileno(), self._ready)

    @classmethod
    def of(cls, loop: asyncio.AbstractEventLoop) -> DatagramHub | None:
        """The loop's hub (made on first use); None where there is no ``epoll``."""
        if not hasattr(select, "epoll"):  # pragma: no cover - Linux has it
            return None
        hub = cls._hubs.get(loop)
        if hub is None or hub._epoll.closed:
            hub = cls._hubs[loop] = cls(loop)
        return hub

    def add(self, ds: DatagramSocket, fd: int) -> None:
        self._epoll.register(fd, select.EPOLLIN)
        self._sockets[fd] = ds

    def remove(self, fd: int) -> None:
        if self._sockets.pop(fd, None) is None:
            return
        try:
            self._epoll.unregister(fd)
        except (OSError, ValueError):  # already closed
            pass
        if not self._sockets:  # the last one: give the loop its descriptor back
            try:
                self._loop.remove_reader(self._epoll.fileno())
            except (ValueError, RuntimeError):  # loop already closed
                pass
            self._epoll.close()
            if self._hubs.get(self._loop) is self:
                del self._hubs[self._loop]

    def _ready(self) -> None:
        poll, sockets, clock = self._epoll.poll, self._sockets, time.monotonic
        for _ in range(HUB_ROUNDS):
            events = poll(0)
            if not events:
                return
            now = clock()  # every datagram of the round was queued by now
            # the round's reads first, then its handlers: a read's kernel work evicts the
            # handlers' objects from the caches, so interleaved each handler starts cold
            got = []
            for fd, _mask in events:
                ds = sockets.get(fd)
                if ds is None:
                    continue
                try:
                    got.append((ds, *ds._recvfrom(65536)))
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError as exc:
                    ds._on_error(exc)
            for ds, data, addr in got:
                if ds._closed:  # (closed by a handler before it)
                    continue
                try:
                    ds._on_datagram(data, addr, now)
                except Exception:  # a handler's bug must not lose the rest of the round
                    log.exception("datagram handler failed")
            if not sockets:  # the last socket closed meanwhile (and with it the epoll)
                return


class DatagramSocket:
    """One bound (``listens``) or connected UDP socket; see the module docstring."""

    def __init__(self, loop: asyncio.AbstractEventLoop, sock: socket.socket,
                 on_datagram: Callable[[bytes, Any, float], None],
                 on_error: Callable[[OSError], None], burst: int = DEFAULT_BURST) -> None:
        self._loop = loop
        self._sock = sock
        self._on_datagram = on_datagram
        self._on_error = on_error
        self.burst = burst
        self.tx_dropped = 0
        self._closed = False
        self._fd = sock.fileno()
        self._recvfrom = sock.recvfrom
        self._hub = DatagramHub.of(loop)
        if self._hub is not None:
            self._hub.add(self, self._fd)
        else:  # pragma: no cover - Linux has epoll
            loop.add_reader(self._fd, self._readable)

    @classmethod
    async def open(cls, host: str, port: int, *, listens: bool,
                   on_datagram: Callable[[bytes, Any, float], None],
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
        """Up to ``burst`` queued datagrams, in order."""
        recvfrom, handle = self._recvfrom, self._on_datagram
        for _ in range(self.burst):
            try:
                data, addr = recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                self._on_error(exc)
                return
            handle(data, addr, time.monotonic())
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
        if self._hub is not None:
            self._hub.remove(self._fd)
        else:  # pragma: no cover - Linux has epoll
            try:
                self._loop.remove_reader(self._fd)
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
