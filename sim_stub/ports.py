"""UDP port schemes for mock vehicles.

PX4 SITL instance ``i`` binds its MAVLink "Onboard"/API link to ``127.0.0.1:14580+i`` and sends to
the GCS port ``14540+i`` (README of the captures, 1b). That scheme collides from the 41st vehicle
on: vehicle 40 would bind 14620 and vehicle 0's GCS port 14540+40 = 14580 is vehicle 0's own bind
port. :data:`WIDE` keeps the two ranges 4000 ports apart and below the Linux ephemeral range
(32768+), so it holds up to 4000 vehicles.

PX4 SITL also runs a second MAVLink instance, the **GCS link**: instance ``i`` sends from
``127.0.0.1:18570+i`` to ``14550`` (every instance below 10 to the same GCS port; a GCS tells
them apart by system id), instances 10-19 to 34650 and from 20 on to 34750 (PX4's
``px4-rc.mavlink``; so that instance 10's GCS link does not land on instance 10's API port
14550). Instances 0-9's GCS links still do, from 11 instances on: a client on 14550 then hears
eleven vehicles (vtube_fleet's links refuse such a port; its built-in mock moves the GCS link
of 0-9 to 34550). ``gcs_link_base``/``gcs_link_remotes`` give it; ``None`` means no GCS link
(the schemes tests and benchmarks make with :func:`free_port_scheme`).
"""

from __future__ import annotations

import random
import socket
from dataclasses import dataclass

from .errors import SimStubError

__all__ = ["PortScheme", "PX4", "WIDE", "resolve_port_scheme", "free_port_scheme"]


@dataclass(frozen=True)
class PortScheme:
    """Vehicle ``i`` binds ``vehicle_base + i`` and sends to ``gcs_base + i`` on ``host``; its
    GCS link (if ``gcs_link_base`` is set) binds ``gcs_link_base + i`` and sends to
    ``gcs_link_remote``."""

    name: str
    vehicle_base: int
    gcs_base: int
    host: str = "127.0.0.1"
    gcs_link_base: int | None = None
    #: (first instance, remote port) pairs, ascending: instance i's GCS link sends to the port
    #: of the last pair whose first instance is <= i
    gcs_link_remotes: tuple[tuple[int, int], ...] = ((0, 14550),)

    def gcs_link_port(self, i: int) -> int | None:
        """UDP port vehicle ``i``'s GCS link binds (PX4: 18570+i), None without a GCS link."""
        return None if self.gcs_link_base is None else self.gcs_link_base + i

    def gcs_link_remote(self, i: int) -> int:
        """UDP port vehicle ``i``'s GCS link sends to (PX4: 14550 below instance 10)."""
        port = self.gcs_link_remotes[0][1]
        for first, p in self.gcs_link_remotes:
            if i >= first:
                port = p
        return port

    def vehicle_port(self, i: int) -> int:
        """UDP port the mock vehicle ``i`` binds (PX4: 14580+i)."""
        return self.vehicle_base + i

    def gcs_port(self, i: int) -> int:
        """UDP port the GCS binds for vehicle ``i`` (PX4: 14540+i)."""
        return self.gcs_base + i

    def endpoint(self, i: int) -> str:
        """MAVSDK connection URL the GCS uses for vehicle ``i``, e.g. ``udpin://127.0.0.1:14540``."""
        return f"udpin://{self.host}:{self.gcs_port(i)}"

    def capacity(self) -> int:
        """How many vehicles fit before a vehicle port meets a GCS port or leaves 1..65535."""
        lo, hi = sorted((self.vehicle_base, self.gcs_base))
        gap = hi - lo
        return max(0, min(gap, 65536 - hi))

    def check(self, count: int) -> None:
        """Raise :class:`SimStubError` if ``count`` vehicles do not fit this scheme."""
        if count < 0:
            raise SimStubError(f"vehicle count must be >= 0, got {count}")
        if not (1 <= self.vehicle_base <= 65535 and 1 <= self.gcs_base <= 65535):
            raise SimStubError(
                f"port scheme {self.name!r}: bases must be in 1..65535, got vehicle_base="
                f"{self.vehicle_base}, gcs_base={self.gcs_base}"
            )
        cap = self.capacity()
        if count > cap:
            hint = " (use port_scheme='wide' / --ports wide)" if self.name == "px4" else ""
            raise SimStubError(
                f"port scheme {self.name!r} (vehicles {self.vehicle_base}+i, GCS {self.gcs_base}+i)"
                f" holds at most {cap} vehicles, {count} requested{hint}"
            )
        g = self.gcs_link_base
        if g is not None and count:
            remotes = {self.gcs_link_remote(i) for i in range(count)}
            if not (1 <= g and g + count - 1 <= 65535 and all(1 <= r <= 65535 for r in remotes)):
                raise SimStubError(
                    f"port scheme {self.name!r}: GCS link ports {g}+i for {count} vehicles and "
                    f"remotes {sorted(remotes)} must be in 1..65535")
            lo, hi = g, g + count - 1
            taken = {"vehicle": (self.vehicle_base, self.vehicle_base + count - 1),
                     "GCS": (self.gcs_base, self.gcs_base + count - 1), "GCS link": (lo, hi)}
            for what, (a, b) in taken.items():
                if what != "GCS link" and lo <= b and a <= hi:
                    raise SimStubError(
                        f"port scheme {self.name!r}: GCS link ports {lo}..{hi} overlap the "
                        f"{what} ports {a}..{b}")
                for r in remotes:  # (a remote among the GCS ports is PX4's own scheme from
                    # instance 10 on: 14540+10 = 14550; a client there hears 0-9 too)
                    if what != "GCS" and a <= r <= b:
                        raise SimStubError(
                            f"port scheme {self.name!r}: GCS link remote port {r} is one of "
                            f"the {what} ports {a}..{b}")


PX4 = PortScheme("px4", vehicle_base=14580, gcs_base=14540, gcs_link_base=18570,
                 gcs_link_remotes=((0, 14550), (10, 34650), (20, 34750)))
WIDE = PortScheme("wide", vehicle_base=24000, gcs_base=20000, gcs_link_base=28000)


def resolve_port_scheme(scheme: str | PortScheme) -> PortScheme:
    """``"px4"`` → :data:`PX4`, ``"wide"`` → :data:`WIDE`; a :class:`PortScheme` passes as is."""
    if isinstance(scheme, PortScheme):
        return scheme
    if scheme == "px4":
        return PX4
    if scheme == "wide":
        return WIDE
    raise SimStubError(f"unknown port scheme {scheme!r}: expected 'px4', 'wide' or a PortScheme")


def free_port_scheme(count: int, host: str = "127.0.0.1", *, tries: int = 50) -> PortScheme:
    """A scheme whose ``2 * count`` UDP ports on ``host`` are free right now.

    For tests and benchmarks that must not collide with PX4's default ports or with each other:
    vehicles ``base+i``, GCS ``base+count+i`` with ``base`` random in 21000..31999 (below the
    Linux ephemeral range). The ports are probed by binding and released again, so a race with
    another process is possible but unlikely.
    """
    rng = random.Random()
    for _ in range(tries):
        vbase = rng.randrange(21000, 32000 - 2 * count)
        socks = []
        try:
            for port in range(vbase, vbase + 2 * count):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(s)
                s.bind((host, port))
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
        return PortScheme("free", vbase, vbase + count, host)
    raise SimStubError(f"no free range of {2 * count} UDP ports found on {host} in {tries} tries")
