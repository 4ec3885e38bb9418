"""The vehicle backends: one table of what each can do, read by every command and launcher.

A backend is a way of talking MAVLink to the vehicles (docs/links.md): its name (the
``--backend`` / ``--link`` choice), how to open a fleet of its links (:meth:`Backend.open`), and
its capabilities, which the rest of the program asks instead of comparing names:

* ``signing``: MAVLink 2 signing (``sign-setup``, signed links; docs/security.md);
* ``stream_rates``: set PX4's message intervals (switch off the streams the fleet does not use,
  and restore PX4's own rates at the end of the run);
* ``shared_ids``: all links share one server that tells vehicles apart by system id only, so the
  ids must be unique across the fleet;
* ``source_pinning``: refuse a vehicle's id from another address (docs/security.md).

Adding a backend is one class (a :class:`~vtube_fleet.link.base.VehicleLink` and its opener) and
one line of :data:`BACKENDS`.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass
from typing import Any

from vtube_fleet.link.base import LinkError, VehicleLink
from vtube_fleet.link.endpoints import Endpoint

__all__ = ["BACKENDS", "BACKEND_NAMES", "Backend", "backend"]

#: ``opener(endpoints, sysids, signings, options)``: an async context manager of the links
Opener = Callable[[Sequence[Endpoint], Sequence[int | None], Sequence[Any], dict[str, Any]],
                  contextlib.AbstractAsyncContextManager[list[VehicleLink]]]


@dataclass(frozen=True)
class Backend:
    """One backend (module docstring)."""

    name: str
    description: str
    opener: Callable[[], Opener]  # imported on use (the mavsdk library only when flown)
    signing: bool
    stream_rates: bool
    shared_ids: bool
    source_pinning: bool

    def require_signing(self, url: str) -> None:
        """:class:`~vtube_fleet.link.base.LinkError` if this backend cannot sign (a mission with
        ``signing_key_file`` must fly a backend that can)."""
        if not self.signing:
            raise LinkError(
                f"{url}: the mission requires MAVLink 2 signing ([mission].signing_key_file), "
                f"which the {self.name} backend cannot do; fly it with a backend that signs ("
                + ", ".join(f"run --backend {b.name}, agent --link {b.name}"
                            for b in BACKENDS.values() if b.signing) + ")")

    def open(self, endpoints: Sequence[Endpoint], sysids: Sequence[int | None],
             signings: Sequence[Any], options: dict[str, Any]
             ) -> contextlib.AbstractAsyncContextManager[list[VehicleLink]]:
        """The backend's links for ``endpoints`` (one system id and one signing setting each;
        ``options`` go to the link constructors), closed on exit."""
        return self.opener()(endpoints, sysids, signings, options)


@contextlib.asynccontextmanager
async def _mavlink(endpoints: Sequence[Endpoint], sysids: Sequence[int | None],
                   signings: Sequence[Any], options: dict[str, Any]
                   ) -> AsyncIterator[list[VehicleLink]]:
    from vtube_fleet.link.mavlink import MavlinkLink

    links: list[VehicleLink] = []
    try:
        links = [MavlinkLink(ep, sid, signing=sg, **options)
                 for ep, sid, sg in zip(endpoints, sysids, signings, strict=True)]
        yield links
    finally:
        for link in links:
            with contextlib.suppress(Exception):  # closing must not hide the original error
                await link.close()


@contextlib.asynccontextmanager
async def _mavsdk(endpoints: Sequence[Endpoint], sysids: Sequence[int | None],
                  signings: Sequence[Any], options: dict[str, Any]
                  ) -> AsyncIterator[list[VehicleLink]]:
    from vtube_fleet.link.mavsdk_link import DEFAULT_WATCHDOG_S, MavsdkHub

    options = dict(options)
    watchdog_s = options.pop("watchdog_s", None)
    options.pop("message_rates_hz", None)  # MAVSDK sets the rates it needs itself
    links: list[VehicleLink] = []
    hub = MavsdkHub(watchdog_s=watchdog_s or DEFAULT_WATCHDOG_S)
    await hub.start()
    try:
        links = [hub.link(ep, sid, **options) for ep, sid in zip(endpoints, sysids, strict=True)]
        yield links
    finally:
        for link in links:
            with contextlib.suppress(Exception):
                await link.close()
        await hub.close()


#: Every backend, by name (the CLI's choices, the launcher's and the agent's).
BACKENDS: dict[str, Backend] = {
    "mavlink": Backend(
        "mavlink", "pymavlink codec on asyncio UDP, one socket per vehicle; every setpoint "
        "comes from our control loop", lambda: _mavlink, signing=True, stream_rates=True,
        shared_ids=False, source_pinning=True),
    "mavsdk": Backend(
        "mavsdk", "the in-process MAVSDK library, one server for the whole fleet; it resends "
        "the last setpoint by itself (a watchdog stops offboard when our loop stalls)",
        lambda: _mavsdk, signing=False, stream_rates=False, shared_ids=True,
        source_pinning=False),
}
#: The names, in the table's order (the command lines' choices).
BACKEND_NAMES: tuple[str, ...] = tuple(BACKENDS)


def backend(name: str) -> Backend:
    """The backend called ``name``; :class:`~vtube_fleet.link.base.LinkError` naming the
    choices otherwise."""
    try:
        return BACKENDS[name]
    except KeyError:
        raise LinkError(f"unknown link backend {name!r}; choose one of "
                        f"{', '.join(BACKEND_NAMES)}") from None
