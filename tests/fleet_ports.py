"""Free UDP port ranges for the fleet tests (other test runs on the same machine may be using
PX4's 14540/14580 ranges). Under pytest-xdist each worker picks from its own slice of
15000-28000: two workers checking the same range free at the same moment and then both binding
it is otherwise a race (it failed a suite run once)."""

from __future__ import annotations

import os
import random
import socket

from sim_stub import PortScheme

__all__ = ["PX4_PORTS", "free_ports"]

_LOW, _HIGH = 15000, 28000

#: The xdist group of the tests that bind PX4 SITL's own ports (GCS 14540+i, vehicles
#: 14580+i, GCS links 18570+i: the default port scheme, whose endpoints give the system ids):
#: one at a time (two of them on two workers at once could not both bind; it failed a CI run
#: once). They are ``solo`` too: a later run failed on 18570, bound by another worker.
PX4_PORTS = "px4-ports"


def _slice() -> tuple[int, int]:
    """This process's [low, high) of the port range: the whole range, or its worker's share."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    k = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    width = (_HIGH - _LOW) // max(count, 1)
    low = _LOW + (k % max(count, 1)) * width
    return low, low + width


def free_ports(count: int, avoid: PortScheme | None = None) -> PortScheme:
    """A port scheme whose 2·count UDP ports (GCS and vehicle side) are free now, in this
    worker's slice (GCS ports in its first half, the vehicles' the same offset into its
    second). ``avoid``: a scheme already chosen (whose GCS ports may not be bound yet, as a
    relay's fleet side before the run listens): never the same range."""
    low, high = _slice()
    half = (high - low) // 2
    if count > half - 10:
        raise RuntimeError(f"{count} vehicles do not fit in ports {low}-{high}")
    rng = random.Random()
    for _ in range(200):
        gcs = rng.randrange(low, low + half - count, 10)
        veh = gcs + half
        if avoid is not None and abs(gcs - avoid.gcs_base) < 10 + count:
            continue
        socks = []
        try:
            for port in [*range(gcs, gcs + count), *range(veh, veh + count)]:
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(s)
                s.bind(("127.0.0.1", port))
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
        return PortScheme("test", vehicle_base=veh, gcs_base=gcs)
    raise RuntimeError("no free UDP port range found")
