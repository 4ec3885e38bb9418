"""Free UDP port ranges for the fleet tests (other test runs on the same machine may be using
PX4's 14540/14580 ranges)."""

from __future__ import annotations

import random
import socket

from sim_stub import PortScheme

__all__ = ["free_ports"]


def free_ports(count: int) -> PortScheme:
    """A port scheme whose 2·count UDP ports (GCS and vehicle side) are free now."""
    rng = random.Random()
    for _ in range(200):
        gcs = rng.randrange(15000, 28000, 10)
        veh = gcs + 2000
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
