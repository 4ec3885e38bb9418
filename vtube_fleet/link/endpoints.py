"""Vehicle endpoints in MAVSDK's connection-URL syntax, and PX4 SITL's port scheme.

Accepted forms (the UDP subset of MAVSDK's ``CliArg``):

* ``udpin://HOST:PORT``: bind ``HOST:PORT`` locally and wait for the vehicle; its address is
  learned from its first packet (what PX4 SITL's "Onboard"/API link expects: PX4 instance ``i``
  sends from 14580+i to 14540+i). An empty host means ``0.0.0.0``.
* ``udpout://HOST:PORT``: send to the vehicle at ``HOST:PORT`` from an ephemeral local port;
  the vehicle learns our address from our heartbeat. ``0.0.0.0`` is invalid here.
* ``udp://HOST:PORT``: MAVSDK's deprecated form: ``udp://:PORT`` and ``udp://0.0.0.0:PORT`` mean
  ``udpin``, any other host means ``udpout``. It is normalised to the explicit scheme.
* ``?sysid=N`` after any of them (ours, not MAVSDK's): the MAVLink system id of the vehicle
  behind the endpoint (1..254). The link flies that id only and refuses every other one
  (docs/links.md, "Identity, source and plausibility"); without it the fleet takes PX4 SITL's
  scheme for ports 14540..14579 and the slot's id (:func:`fleet_sysid`) elsewhere
  (:func:`endpoint_sysid`).

PX4 SITL port scheme (``px4-rc.mavlinksim``): instance ``i`` has its API/Onboard link on
GCS port ``14540 + i`` (remote) and sends from ``14580 + i`` (local). The scheme collides from
the 41st instance on: instance 40's GCS port 14540 + 40 = 14580 is instance 0's own sending
port. :func:`px4_sitl_endpoints` therefore refuses ``n > 40``. It also meets PX4 SITL's *GCS link*
at instance 10: instances 0-9 send their GCS link (from 18570 + i) to 14550 = 14540 + 10, so a
link on instance 10's API port hears ten other vehicles (:data:`PX4_SITL_GCS_PORT`; the link
refuses such a port before arming, docs/links.md).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable
from dataclasses import dataclass

from vtube_fleet.errors import UserError

__all__ = [
    "EndpointError",
    "Endpoint",
    "parse_endpoint",
    "px4_sitl_endpoints",
    "px4_sitl_sysid",
    "fleet_sysid",
    "endpoint_sysid",
    "shared_port_cause",
    "MAX_VEHICLE_SYSIDS",
    "PX4_SITL_GCS_PORT",
    "PX4_SITL_API_PORT",
    "PX4_SITL_MAX_INSTANCES",
]

#: GCS-side port of PX4 SITL instance 0's API/Onboard link (instance i: +i).
PX4_SITL_API_PORT = 14540
#: PX4 sends from 14580 + i, so 14540 + i collides with instance 0 from i = 40 on.
PX4_SITL_MAX_INSTANCES = 40
#: Where PX4 SITL's GCS link sends (instances 0-9; 10-19: 34650, 20+: 34750): the API port of
#: instance 10.
PX4_SITL_GCS_PORT = 14550
#: Vehicle system ids 1..254: MAVLink's are 8-bit, 0 is broadcast and 255 our GCS's own.
MAX_VEHICLE_SYSIDS = 254

_SCHEMES = ("udpin", "udpout", "udp")


class EndpointError(UserError):
    """A malformed endpoint URL or an impossible SITL instance count."""


@dataclass(frozen=True, slots=True)
class Endpoint:
    """A parsed endpoint; ``scheme`` is ``"udpin"`` or ``"udpout"`` (``udp://`` normalised);
    ``sysid``: the vehicle's system id when the URL gives one (``?sysid=N``)."""

    scheme: str
    host: str
    port: int
    sysid: int | None = None

    @property
    def url(self) -> str:
        """The canonical URL, e.g. ``udpin://127.0.0.1:14540`` (``…?sysid=3`` if given)."""
        tail = "" if self.sysid is None else f"?sysid={self.sysid}"
        return f"{self.scheme}://{self.host}:{self.port}{tail}"

    @property
    def transport_url(self) -> str:
        """The URL without our ``?sysid=`` (what MAVSDK's ``add_any_connection`` takes)."""
        return f"{self.scheme}://{self.host}:{self.port}"

    @property
    def listens(self) -> bool:
        """True for ``udpin`` (bind locally, learn the vehicle's address)."""
        return self.scheme == "udpin"

    def __str__(self) -> str:
        return self.url


def parse_endpoint(url: str) -> Endpoint:
    """Parse a MAVSDK-style UDP URL; raise :class:`EndpointError` (one line) if malformed.

    >>> parse_endpoint("udpin://127.0.0.1:14540")
    Endpoint(scheme='udpin', host='127.0.0.1', port=14540)
    >>> parse_endpoint("udp://:14541").url
    'udpin://0.0.0.0:14541'
    """
    if not isinstance(url, str):
        raise EndpointError(
            f"endpoint must be a string like 'udpin://127.0.0.1:14540', got {url!r}"
        )
    text = url.strip()
    text, qmark, query = text.partition("?")
    sysid = _query_sysid(url, query) if qmark else None
    scheme, sep, rest = text.partition("://")
    if not sep:
        raise EndpointError(
            f"endpoint {url!r}: missing scheme, expected 'udpin://HOST:PORT' or 'udpout://HOST:PORT'"
        )
    scheme = scheme.lower()
    if scheme not in _SCHEMES:
        raise EndpointError(
            f"endpoint {url!r}: unsupported scheme {scheme!r} (supported: udpin, udpout, udp)"
        )
    host, colon, port_text = rest.rpartition(":")
    if not colon:
        raise EndpointError(f"endpoint {url!r}: missing ':PORT'")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not port_text.isdigit():
        raise EndpointError(f"endpoint {url!r}: port {port_text!r} is not a number")
    port = int(port_text)
    if not 1 <= port <= 65535:
        raise EndpointError(f"endpoint {url!r}: port {port} outside 1..65535")
    if host and not _valid_host(host):
        raise EndpointError(f"endpoint {url!r}: invalid host {host!r}")
    if scheme == "udp":
        scheme = "udpin" if host in ("", "0.0.0.0") else "udpout"
    if scheme == "udpin" and host == "":
        host = "0.0.0.0"
    if scheme == "udpout" and host in ("", "0.0.0.0"):
        raise EndpointError(
            f"endpoint {url!r}: udpout needs the vehicle's address, not {host or 'an empty host'!r}"
        )
    return Endpoint(scheme, host, port, sysid)


def _query_sysid(url: str, query: str) -> int:
    """``sysid=N`` (the only query we know) → N in 1..254."""
    key, eq, value = query.partition("=")
    if key != "sysid" or not eq:
        raise EndpointError(f"endpoint {url!r}: unknown option {query!r} (the only one is "
                            f"'?sysid=N', the vehicle's MAVLink system id)")
    if not value.isdigit() or not 1 <= int(value) <= MAX_VEHICLE_SYSIDS:
        raise EndpointError(f"endpoint {url!r}: sysid must be 1..{MAX_VEHICLE_SYSIDS} (0 is "
                            f"broadcast, 255 our own GCS id), got {value!r}")
    return int(value)


def _valid_host(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        pass
    labels = host.split(".")
    return all(
        0 < len(lab) <= 63 and lab.replace("-", "").isalnum() and not lab.startswith("-")
        for lab in labels
    )


def px4_sitl_endpoints(n: int, host: str = "127.0.0.1", first_instance: int = 0) -> list[str]:
    """Endpoints of ``n`` PX4 SITL instances: ``udpin://HOST:14540+i`` for each instance ``i``.

    Instance ``i`` has MAVLink system id ``i + 1`` (:func:`px4_sitl_sysid`). Raises
    :class:`EndpointError` for ``n < 1`` or when an instance index reaches 40: PX4's scheme then
    collides (14540 + 40 = 14580 is the port instance 0 sends from).
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise EndpointError(f"number of PX4 SITL instances must be an integer >= 1, got {n!r}")
    if first_instance < 0:
        raise EndpointError(f"first PX4 SITL instance must be >= 0, got {first_instance}")
    last = first_instance + n - 1
    if last >= PX4_SITL_MAX_INSTANCES:
        raise EndpointError(
            f"{n} PX4 SITL instances from instance {first_instance}: instance {last} would use "
            f"port {PX4_SITL_API_PORT + last}, but PX4's port scheme collides from instance "
            f"{PX4_SITL_MAX_INSTANCES} on (14540+40 = 14580 is instance 0's own port); "
            f"at most {PX4_SITL_MAX_INSTANCES} instances"
        )
    parse_endpoint(f"udpin://{host}:{PX4_SITL_API_PORT}")  # validates host
    return [f"udpin://{host}:{PX4_SITL_API_PORT + i}" for i in range(first_instance, last + 1)]


def fleet_sysid(index: int) -> int:
    """The system id of the fleet's vehicle ``index`` (0-based): ``index % 254 + 1``.

    A system id belongs to a link, not to the fleet: every vehicle has its own UDP endpoint,
    so ids only need to be unique among vehicles that share one (one MAVSDK server for all
    links is such a sharing; see :func:`~vtube_fleet.link.open_links`). From the 255th vehicle
    on the ids repeat, as the built-in mock numbers its vehicles.
    """
    return index % MAX_VEHICLE_SYSIDS + 1


def endpoint_sysid(endpoint: str | Endpoint, slot: int) -> int:
    """The system id the fleet's link of ``slot`` flies behind ``endpoint``: the URL's
    ``?sysid=N``, else PX4 SITL's scheme (port 14540 + i → i + 1), else the slot's own
    (:func:`fleet_sysid`)."""
    ep = endpoint if isinstance(endpoint, Endpoint) else parse_endpoint(endpoint)
    if ep.sysid is not None:
        return ep.sysid
    return px4_sitl_sysid(ep.port) or fleet_sysid(slot)


def shared_port_cause(ports: Iterable[int], from_ports: Iterable[int]) -> str:
    """The likely cause of other vehicles' HEARTBEATs on our ``ports`` (``from_ports``: the
    ports they came from): PX4 SITL's GCS link (18570 + i → 14550, the API port of instance
    10), or another vehicle's link pointed here."""
    gcs_link = any(18570 <= p < 18570 + PX4_SITL_MAX_INSTANCES for p in from_ports)
    if PX4_SITL_GCS_PORT in set(ports) or gcs_link:
        return (f"port {PX4_SITL_GCS_PORT} is where PX4 SITL's GCS link sends (instances 0-9, "
                f"from 18570+i), and it is instance 10's API port (14540+10); move the GCS "
                f"link (the -o {PX4_SITL_GCS_PORT} of px4-rc.mavlink) or fly another API port "
                f"scheme (docs/links.md, \"Identity, source and plausibility\")")
    return ("another vehicle's MAVLink link (a GCS link, say) sends to this port, or two PX4 "
            "instances share it")


def px4_sitl_sysid(port: int) -> int | None:
    """The system id PX4 SITL uses on GCS port ``port`` (14540 + i → i + 1), else None."""
    i = port - PX4_SITL_API_PORT
    return i + 1 if 0 <= i < PX4_SITL_MAX_INSTANCES else None
