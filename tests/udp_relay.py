"""A UDP relay that delays every datagram, both ways: a slow link without netem.

For each vehicle i: the mock vehicle sends to ``relay_port(i)`` (its GCS port in the mock's
port scheme); the relay forwards each datagram, ``delay_s`` later, from a second socket to the
fleet's endpoint ``udpin://HOST:fleet_port(i)``; what the fleet sends back (to that second
socket, the vehicle's address as the fleet sees it) goes, ``delay_s`` later, to the vehicle's
bind port from the first socket. ``loss_pct`` drops datagrams at random (seeded).
"""

from __future__ import annotations

import asyncio
import random
from collections.abc import Sequence


class _Side(asyncio.DatagramProtocol):
    def __init__(self, relay: UdpRelay, i: int, side: str) -> None:
        self.relay, self.i, self.side = relay, i, side
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.relay._forward(self.i, self.side, data, addr)


class UdpRelay:
    """Relay ``count`` vehicle links (module docstring); ``async with`` starts/stops it."""

    def __init__(self, vehicle_ports: Sequence[int], relay_ports: Sequence[int],
                 fleet_ports: Sequence[int], *, delay_s: float, loss_pct: float = 0.0,
                 host: str = "127.0.0.1", seed: int = 0) -> None:
        self.vehicle_ports = list(vehicle_ports)
        self.relay_ports = list(relay_ports)
        self.fleet_ports = list(fleet_ports)
        self.delay_s = float(delay_s)
        self.loss_pct = float(loss_pct)
        self.host = host
        self._rng = random.Random(seed)
        self._near: list[_Side] = []  # faces the vehicle
        self._far: list[_Side] = []  # faces the fleet
        self.forwarded = 0
        self.dropped = 0

    @property
    def endpoints(self) -> list[str]:
        """What the fleet connects to (udpin: it listens)."""
        return [f"udpin://{self.host}:{p}" for p in self.fleet_ports]

    async def __aenter__(self) -> UdpRelay:
        loop = asyncio.get_running_loop()
        for i, port in enumerate(self.relay_ports):
            _, near = await loop.create_datagram_endpoint(
                lambda i=i: _Side(self, i, "near"), local_addr=(self.host, port))
            _, far = await loop.create_datagram_endpoint(
                lambda i=i: _Side(self, i, "far"), local_addr=(self.host, 0))
            self._near.append(near)  # type: ignore[arg-type]
            self._far.append(far)  # type: ignore[arg-type]
        return self

    async def __aexit__(self, *exc: object) -> None:
        for side in self._near + self._far:
            if side.transport is not None:
                side.transport.close()

    def _forward(self, i: int, side: str, data: bytes, addr: tuple[str, int]) -> None:
        if self.loss_pct and self._rng.random() * 100.0 < self.loss_pct:
            self.dropped += 1
            return
        if side == "near":  # vehicle → fleet
            out, dest = self._far[i], (self.host, self.fleet_ports[i])
        else:  # fleet → vehicle
            out, dest = self._near[i], (self.host, self.vehicle_ports[i])

        def send() -> None:
            if out.transport is not None and not out.transport.is_closing():
                out.transport.sendto(data, dest)
                self.forwarded += 1

        asyncio.get_running_loop().call_later(self.delay_s, send)
