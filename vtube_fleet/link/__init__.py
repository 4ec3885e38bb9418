"""Vehicle links: one small interface (:class:`VehicleLink`), the backends of
:data:`~vtube_fleet.link.backends.BACKENDS` (one table: name, opener, capabilities):

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

from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from typing import Any

from vtube_fleet.link.backends import BACKEND_NAMES, BACKENDS, Backend
from vtube_fleet.link.backends import backend as backend_named
from vtube_fleet.link.base import (
    CommandRejected,
    GeoPoint,
    LinkConflict,
    LinkError,
    LinkTimeout,
    StatusText,
    VehicleLink,
    VehicleState,
)
from vtube_fleet.link.endpoints import (
    MAX_VEHICLE_SYSIDS,
    Endpoint,
    EndpointError,
    endpoint_sysid,
    fleet_sysid,
    parse_endpoint,
    px4_sitl_endpoints,
    px4_sitl_sysid,
)
from vtube_fleet.link.guard import TelemetryBounds
from vtube_fleet.link.mavlink import MavlinkLink

__all__ = [
    "BACKENDS",
    "BACKEND_NAMES",
    "Backend",
    "CommandRejected",
    "Endpoint",
    "EndpointError",
    "GeoPoint",
    "LinkConflict",
    "LinkError",
    "LinkTimeout",
    "MavlinkLink",
    "open_links",
    "StatusText",
    "TelemetryBounds",
    "VehicleLink",
    "VehicleState",
    "parse_endpoint",
    "px4_sitl_endpoints",
    "px4_sitl_sysid",
    "fleet_sysid",
    "endpoint_sysid",
]


@asynccontextmanager
async def open_links(
    endpoints: Sequence[str],
    backend: str = "mavlink",
    *,
    sysids: Sequence[int | None] | None = None,
    watchdog_s: float | None = None,
    trim_streams: bool = True,
    **options: Any,
) -> AsyncIterator[list[VehicleLink]]:
    """Create (not connect) one link per endpoint with ``backend`` (a name of
    :data:`~vtube_fleet.link.backends.BACKENDS`); close them all on exit.

    ``sysids`` (optional, one per endpoint) pins system ids; an endpoint's ``?sysid=N`` pins
    its own (a different id in ``sysids`` is an error); otherwise the mavsdk backend uses PX4
    SITL's scheme (port 14540 + i → i + 1) and the mavlink link locks onto the first
    autopilot it hears (the fleet always pins: :func:`endpoint_sysid`). ``watchdog_s`` is the
    mavsdk backend's stall limit (ignored by ``mavlink``, whose stall is caught by PX4's own
    failsafe). ``trim_streams``: a backend that sets stream rates switches off the streams the
    fleet does not use (:data:`~vtube_fleet.link.mavlink.UNUSED_STREAMS_OFF`; PX4's rates are
    given back when the links close). ``options`` go to the link constructor (e.g.
    ``command_timeout_s`` for mavlink; ``telemetry``: the :class:`TelemetryBounds` of the
    plausibility checks, None turns them off; ``pin_source=False`` accepts the vehicle's id
    from any address: both test switches, docs/security.md). ``signing``: one
    :class:`~vtube_fleet.link.signing.LinkSigning` (or None) per endpoint, mavlink only (the
    mavsdk backend refuses). Connecting is left to the caller (concurrently, with its own
    timeouts and error report).
    """
    kind = backend_named(backend)
    eps = [parse_endpoint(e) for e in endpoints]
    urls = [e.transport_url for e in eps]
    dupes = sorted({u for u in urls if urls.count(u) > 1})
    if dupes:
        raise EndpointError(f"endpoint listed more than once: {', '.join(dupes)}")
    ids = list(sysids) if sysids is not None else [None] * len(eps)
    if len(ids) != len(eps):
        raise LinkError(f"{len(ids)} system ids for {len(eps)} endpoints")
    for k, (e, s) in enumerate(zip(eps, ids, strict=True)):
        if e.sysid is not None:
            if s is not None and s != e.sysid:
                raise LinkError(f"{e.url}: system id {s} given for an endpoint that says "
                                f"sysid={e.sysid}")
            ids[k] = e.sysid
    bad = [(e.url, s) for e, s in zip(eps, ids, strict=True)
           if s is not None and (isinstance(s, bool) or not 1 <= int(s) <= 255)]
    if bad:
        raise LinkError(f"{bad[0][0]}: system id must be 1..255, got {bad[0][1]}"
                        + (f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""))
    if kind.shared_ids:
        # one server holds every link and tells systems apart by id only
        seen: dict[int, str] = {}
        for e, s in zip(eps, ids, strict=True):
            if s is not None and s in seen:
                raise LinkError(
                    f"system id {s} is used by {seen[s]} and {e.url}: the {kind.name} backend "
                    f"serves all links from one server, which needs unique ids "
                    f"(at most {MAX_VEHICLE_SYSIDS} vehicles); use --link mavlink, whose "
                    f"links are separate")
            if s is not None:
                seen[s] = e.url
    signing = options.pop("signing", None)
    signings = list(signing) if isinstance(signing, (list, tuple)) else [signing] * len(eps)
    if len(signings) != len(eps):
        raise LinkError(f"{len(signings)} signing settings for {len(eps)} endpoints")
    if any(sg is not None for sg in signings):
        kind.require_signing(eps[0].url)
    if watchdog_s is not None:
        options["watchdog_s"] = watchdog_s
    if kind.stream_rates and trim_streams:
        from vtube_fleet.link.mavlink import UNUSED_STREAMS_OFF

        options["message_rates_hz"] = {**UNUSED_STREAMS_OFF,
                                       **(options.get("message_rates_hz") or {})}
    async with kind.open(eps, ids, signings, options) as links:
        yield links
