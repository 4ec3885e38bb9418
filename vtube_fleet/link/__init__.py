"""Vehicle links: one small interface (:class:`VehicleLink`), two backends.

* ``mavlink`` (default, :class:`~vtube_fleet.link.mavlink.MavlinkLink`): pymavlink codec on
  asyncio UDP, one socket per vehicle; every setpoint comes from our control loop, so a stalled
  loop triggers PX4's own offboard-loss failsafe.
* ``mavsdk`` (:class:`~vtube_fleet.link.mavsdk_link.MavsdkLink`): the in-process ``mavsdk`` ≥ 4
  asyncio API, one :class:`~vtube_fleet.link.mavsdk_link.MavsdkHub` for the whole fleet; MAVSDK
  resends the last setpoint at 20 Hz by itself, so a watchdog stops offboard (→ Hold) when our
  loop stalls.

See ``docs/links.md``.
"""

from __future__ import annotations

from vtube_fleet.link.base import (
    CommandRejected,
    GeoPoint,
    LinkError,
    LinkTimeout,
    StatusText,
    VehicleLink,
    VehicleState,
)
from vtube_fleet.link.endpoints import (
    Endpoint,
    EndpointError,
    parse_endpoint,
    px4_sitl_endpoints,
    px4_sitl_sysid,
)
from vtube_fleet.link.mavlink import MavlinkLink

__all__ = [
    "BACKENDS",
    "CommandRejected",
    "Endpoint",
    "EndpointError",
    "GeoPoint",
    "LinkError",
    "LinkTimeout",
    "MavlinkLink",
    "StatusText",
    "VehicleLink",
    "VehicleState",
    "parse_endpoint",
    "px4_sitl_endpoints",
    "px4_sitl_sysid",
]

#: Backend names accepted by the fleet (``--link``).
BACKENDS = ("mavlink", "mavsdk")
