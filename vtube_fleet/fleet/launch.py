"""Launching a fleet mission.

The built-in mock fleet in a mission's slots, endpoint lists, PX4 SITL homes, and :func:`fly`
(links + :class:`~vtube_fleet.fleet.supervisor.Supervisor`). Used by ``vtube-fleet run`` /
``mock-fleet`` / ``sitl-homes``, the tests and the benchmarks.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sim_stub.scheduler import TICK_HZ_MAX, TICK_HZ_MIN  # the mock's tick range, for the CLI
from vtube_fleet.config.mission import Mission
from vtube_fleet.errors import UserError

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.fleet.supervisor import FleetResult, Supervisor

__all__ = [
    "TICK_HZ_MAX",
    "TICK_HZ_MIN",
    "FleetCliError",
    "fleet_supervisor",
    "fly",
    "gcs_link_mode",
    "mock_fleet",
    "parse_endpoint_list",
    "sitl_home_lines",
    "sitl_homes",
    "slot_count",
]

log = logging.getLogger(__name__)




class FleetCliError(UserError):
    """A command-line mistake (endpoint count, backend)."""


# ----------------------------------------------------------------------------------------------
# helpers shared by the commands, the tests and the benchmark
# ----------------------------------------------------------------------------------------------
def slot_count(mission: Mission, count: int | None) -> int:
    """``count`` (default: every slot) checked against the mission's slots: 1..slots, placed
    apart and inside the tube (:meth:`Mission.require_slots`)."""
    n = mission.count if count is None else count
    if not 1 <= n <= mission.count:
        raise FleetCliError(f"--count must be between 1 and {mission.count} (the mission's "
                            f"slots), got {n}")
    mission.require_slots(n)  # overlapping slots or slots outside the tube: no vehicles
    return n


def sitl_homes(mission: Mission, count: int | None = None) -> list[dict[str, str]]:
    """The ``PX4_HOME_LAT`` / ``_LON`` / ``_ALT`` environment of PX4 SITL instances
    0..count-1 (:func:`slot_count`), so that instance i starts in slot i."""
    n = slot_count(mission, count)
    geo = mission.slot_geodetic()
    return [{"PX4_HOME_LAT": f"{geo[i, 0]:.7f}", "PX4_HOME_LON": f"{geo[i, 1]:.7f}",
             "PX4_HOME_ALT": f"{geo[i, 2]:.2f}"} for i in range(n)]


def sitl_home_lines(mission: Mission, count: int | None = None) -> list[str]:
    """``I PX4_HOME_LAT=… PX4_HOME_LON=… PX4_HOME_ALT=…`` for slots 0..count-1
    (:func:`sitl_homes`)."""
    return [f"{i} " + " ".join(f"{k}={v}" for k, v in env.items())
            for i, env in enumerate(sitl_homes(mission, count))]


def _homes(mission: Mission, count: int) -> list[tuple[float, float, float]]:
    geo = mission.slot_geodetic()
    return [(float(g[0]), float(g[1]), float(g[2])) for g in geo[:count]]


def gcs_link_mode(requested: str | None, *, custom_ports: bool,
                  gcs_link_base: int | None) -> tuple[str, str]:
    """The mock fleet's GCS link stream set (``lite`` / ``full`` / ``off``) and what to say
    about it. With custom ports (``--gcs-port`` / ``--vehicle-port``) PX4's 18570+i are not
    assumed free: the link is off unless ``gcs_link_base`` says where it goes, and asking
    for it (``requested`` lite/full) without one is a :class:`FleetCliError`."""
    if not custom_ports or gcs_link_base is not None or requested == "off":
        return requested or "lite", ""
    if requested is not None:
        raise FleetCliError(f"--gcs-link {requested} with --gcs-port/--vehicle-port: give "
                            f"--gcs-link-base N too (vehicle i's GCS link binds N+i; PX4: "
                            f"18570), or --gcs-link off")
    return "off", ("no GCS link (custom ports: --gcs-link-base N gives one, vehicle i on "
                   "N+i -> 14550)")


@contextlib.asynccontextmanager
async def mock_fleet(mission: Mission, count: int | None = None, *,
                     gcs_port: int | None = None, vehicle_port: int | None = None,
                     gcs_link_base: int | None = None, gcs_link_port: int | None = None,
                     processes: int = 1, **kwargs: Any) -> AsyncIterator[Any]:
    """A ``sim_stub.MockFleet`` whose vehicle i starts in slot i (context manager); PX4's port
    scheme (vehicle i: GCS port 14540+i) up to 40 vehicles, the mock's wide scheme beyond.
    ``gcs_port`` / ``vehicle_port``: a custom scheme instead (vehicle i: GCS port
    ``gcs_port`` + i, sending from ``vehicle_port`` + i; defaults 14540 and GCS port + 40),
    which has PX4's GCS link (ground truth on request) only with ``gcs_link_base``;
    ``gcs_link_base`` / ``gcs_link_port``: vehicle i's GCS link binds ``gcs_link_base`` + i
    (PX4: 18570) and sends to ``gcs_link_port`` (PX4: 14550), with either scheme;
    ``processes`` > 1: a ``sim_stub.ProcessFleet`` (the vehicles split over that many OS
    processes, same ports; ``endpoints``, ``serve(stop)`` but no in-process vehicles); other
    keyword arguments go to ``MockFleet``. A mock error (also a mock process dying inside the
    ``async with``, reported by ``serve``) is a :class:`FleetCliError` with the mock's exit
    code."""
    try:
        from sim_stub import MockFleet, MockProcessError, PortScheme, ProcessFleet, SimStubError
    except ImportError as exc:  # pragma: no cover - sim_stub ships with the package
        raise FleetCliError(f"the built-in mock fleet (sim_stub) is not available: {exc}"
                            ) from None
    n = slot_count(mission, count)
    if not 1 <= processes <= n:
        raise FleetCliError(f"--processes must be between 1 and {n} (the vehicle count), got "
                            f"{processes}")
    if gcs_port is not None or vehicle_port is not None:
        gcs = 14540 if gcs_port is None else gcs_port
        veh = gcs + 40 if vehicle_port is None else vehicle_port
        kwargs["port_scheme"] = PortScheme("custom", vehicle_base=veh, gcs_base=gcs)
    kwargs.setdefault("port_scheme", "px4" if n <= 40 else "wide")
    if gcs_link_base is not None or gcs_link_port is not None:
        from sim_stub.ports import resolve_port_scheme

        scheme = resolve_port_scheme(kwargs["port_scheme"])
        base = scheme.gcs_link_base if gcs_link_base is None else gcs_link_base
        if base is None:
            raise FleetCliError("--gcs-link-port with --gcs-port/--vehicle-port needs "
                                "--gcs-link-base N too (vehicle i's GCS link binds N+i)")
        remotes = (scheme.gcs_link_remotes if gcs_link_port is None
                   else ((0, gcs_link_port),))
        kwargs["port_scheme"] = dataclasses.replace(scheme, gcs_link_base=base,
                                                    gcs_link_remotes=remotes)
    if gcs_link_port is None and kwargs.get("gcs_link") != "off":
        kwargs["port_scheme"] = _gcs_link_off_api_ports(kwargs["port_scheme"], n)
    if mission.config.signing_key_file and "signing" not in kwargs:
        # the built-in mock holds the mission's keys, as vehicles after `sign-setup` do
        if processes > 1:
            raise FleetCliError("a signing mission (signing_key_file) needs --processes 1: "
                                "the mock's processes are not given keys")
        from vtube_fleet.link.signing import load_key, mission_key_path

        kwargs["signing"] = [load_key(mission_key_path(mission, i))  # type: ignore[arg-type]
                             for i in range(n)]
    try:
        if processes > 1:
            fleet = ProcessFleet(n, processes=processes, homes=_homes(mission, n), **kwargs)
        else:
            fleet = MockFleet(n, homes=_homes(mission, n), **kwargs)
        await fleet.start()
    except SimStubError as exc:
        raise _mock_error(exc) from None
    try:
        yield fleet
    except MockProcessError as exc:  # a child died (ProcessFleet.serve)
        raise _mock_error(exc) from None
    finally:
        await fleet.stop()


#: where the built-in mock's GCS link goes instead of an API port of the fleet (PX4 SITL's
#: 14550 is instance 10's API port; PX4 itself moves instances 10-19 to 34650, 20+ to 34750)
MOCK_GCS_LINK_MOVED_PORT = 34550


def _gcs_link_off_api_ports(scheme: Any, count: int) -> Any:
    """``scheme`` with every GCS link remote that is one of the fleet's API ports (PX4 SITL's
    14550 from 11 vehicles on) moved to :data:`MOCK_GCS_LINK_MOVED_PORT`: the link on that API
    port would hear ten other vehicles and refuse the mission (docs/links.md, "Identity and
    source"). ``python -m sim_stub`` keeps PX4's ports; an explicit ``gcs_link_port`` too."""
    from sim_stub.ports import resolve_port_scheme

    sc = resolve_port_scheme(scheme)
    if sc.gcs_link_base is None:
        return scheme
    api = {sc.gcs_port(i) for i in range(count)}
    moved = tuple((first, MOCK_GCS_LINK_MOVED_PORT if port in api else port)
                  for first, port in sc.gcs_link_remotes)
    if moved == sc.gcs_link_remotes:
        return scheme
    clash = sorted({sc.gcs_link_remote(i) for i in range(count)} & api)
    which = [i for i in range(count) if sc.gcs_link_remote(i) in api]
    log.warning("mock fleet: vehicles %d-%d send their GCS link to %d, not %s: that is the API "
                "port of a vehicle of this fleet (PX4 SITL's scheme collides at instance 10; "
                "docs/links.md)", which[0], which[-1], MOCK_GCS_LINK_MOVED_PORT,
                ", ".join(map(str, clash)))
    return dataclasses.replace(sc, gcs_link_remotes=moved)


def _mock_error(exc: Exception) -> FleetCliError:
    err = FleetCliError(f"mock fleet: {exc}")
    err.exit_code = int(getattr(exc, "exit_code", 2))
    return err


def parse_endpoint_list(text: str, slots: int) -> list[str]:
    from vtube_fleet.link.endpoints import parse_endpoint

    items = [u.strip() for u in text.split(",")]
    urls = [u for u in items if u]
    if not urls:
        raise FleetCliError(f"--endpoints: no endpoint given (got {text!r}); leave "
                            f"--endpoints out to fly the built-in mock fleet")
    if len(urls) != len(items):  # dropped, it would move every later endpoint to another slot
        empty = [i + 1 for i, u in enumerate(items) if not u]
        raise FleetCliError(f"--endpoints: item {', '.join(map(str, empty))} of {len(items)} "
                            f"is empty (got {text!r}); endpoint i flies slot i, so remove the "
                            f"extra comma or fill in the missing endpoint")
    if len(urls) > slots:
        raise FleetCliError(f"--endpoints: {len(urls)} endpoints but the mission has only "
                            f"{slots} slots (endpoint i flies slot i)")
    for u in urls:
        parse_endpoint(u)
    twice = sorted({u for u in urls if urls.count(u) > 1})
    if twice:
        raise FleetCliError(f"--endpoints: {', '.join(twice)} listed twice (slots "
                            f"{', '.join(str(i) for i, u in enumerate(urls) if u in twice)})")
    return urls


# ----------------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------------
@contextlib.asynccontextmanager
async def fleet_supervisor(
    mission: Mission,
    *,
    backend: str = "mavlink",
    endpoints: Sequence[str] | None = None,
    sysids: Sequence[int | None] | None = None,
    out_dir: Path | None = None,
    recorder: Any = None,
    view: Any = None,
    mock_kwargs: dict[str, Any] | None = None,
    link_options: dict[str, Any] | None = None,
    **supervisor_kwargs: Any,
) -> AsyncIterator[Supervisor]:
    """The :class:`~vtube_fleet.fleet.supervisor.Supervisor` of ``mission`` over open links
    (an in-process mock fleet when ``endpoints`` is None); links and mock closed on exit."""
    from vtube_fleet.fleet.supervisor import Supervisor
    from vtube_fleet.link import BACKENDS, TelemetryBounds, endpoint_sysid, fleet_sysid, open_links

    async with contextlib.AsyncExitStack() as stack:
        if endpoints is None:
            fleet = await stack.enter_async_context(
                mock_fleet(mission, **(mock_kwargs or {})))
            endpoints = list(fleet.endpoints)
            if sysids is None:
                sysids = [fleet_sysid(i) for i in range(len(endpoints))]
        if backend not in BACKENDS:
            raise FleetCliError(f"unknown backend {backend!r} (choose from "
                                f"{', '.join(BACKENDS)})")
        if sysids is None:  # every link flies one id (docs/links.md, "Identity, source …")
            sysids = [endpoint_sysid(u, i) for i, u in enumerate(endpoints)]
        options = dict(link_options or {})
        # what the mission's vehicles can fly: the links refuse the rest (docs/security.md)
        options.setdefault("telemetry", TelemetryBounds.for_mission(mission))
        if mission.config.signing_key_file and "signing" not in options:
            from vtube_fleet.link.signing import fleet_signing  # docs/security.md

            options["signing"] = fleet_signing(mission, len(endpoints))
        links = await stack.enter_async_context(
            open_links(list(endpoints), backend, sysids=sysids, **options))
        yield Supervisor(mission, links, backend=backend, recorder=recorder, view=view,
                         out_dir=out_dir, **supervisor_kwargs)


async def fly(mission: Mission, **kwargs: Any) -> FleetResult:
    """Fly ``mission`` (arguments as :func:`fleet_supervisor`); returns the
    :class:`~vtube_fleet.fleet.supervisor.FleetResult`."""
    async with fleet_supervisor(mission, **kwargs) as sup:
        return await sup.run()
