"""``vtube-fleet run``, ``vtube-fleet mock-fleet`` and ``vtube-fleet sitl-homes``.

* ``run MISSION.toml [--backend mavlink|mavsdk] [--endpoints URL,URL,…] [--out DIR]``: fly the
  mission. Endpoint i flies slot i; with fewer endpoints than slots only the first slots fly
  (said on stderr), more is an error. Without ``--endpoints`` a sim_stub mock fleet is started
  in this process with its homes in the slots (PX4's port scheme up to 40 vehicles, the mock's
  wide scheme beyond). Writes ``DIR/summary.json`` (always) and ``DIR/recording.rrd``.
  Exit codes: 0 all vehicles exited and landed, every limit kept; 2 a user error (config,
  endpoints, preflight: nothing armed); 3 mission aborted or incomplete; 4 unsafe (a limit was
  broken in the tube, by telemetry or, with ``--truth``, by ground truth); 130 interrupted
  (every vehicle held, then landed). ``--truth`` asks every vehicle for its SITL ground truth
  (HIL_STATE_QUATERNION: PX4 SITL and the mock) and reports the clearance truly flown.
* ``mock-fleet MISSION.toml``: run the sim_stub vehicles placed in the mission's slots until
  interrupted, printing their endpoints (for driving them from other processes).
* ``sitl-homes MISSION.toml``: one line per PX4 SITL instance,
  ``I PX4_HOME_LAT=… PX4_HOME_LON=… PX4_HOME_ALT=…``, so that instance I starts in slot I.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import sys
from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import Any

from vtube_fleet.config.mission import Mission, load_mission
from vtube_fleet.errors import UserError

__all__ = ["fly", "mock_fleet", "parse_endpoint_list", "register", "sitl_home_lines"]

log = logging.getLogger(__name__)

BACKENDS = ("mavlink", "mavsdk")

#: mavlink backend: streams the fleet does not use, switched off on connect (SET_MESSAGE_INTERVAL
#: −1 via rate 0) to save link bandwidth and CPU on both ends: ATTITUDE (100 Hz in the
#: captures), ATTITUDE_QUATERNION, HIGHRES_IMU, ODOMETRY.
UNUSED_STREAMS_OFF: dict[int, float] = {30: 0.0, 31: 0.0, 105: 0.0, 331: 0.0}


class FleetCliError(UserError):
    """A command-line mistake (endpoint count, backend)."""


# ----------------------------------------------------------------------------------------------
# helpers shared by the commands, the tests and the benchmark
# ----------------------------------------------------------------------------------------------
def sitl_home_lines(mission: Mission, count: int | None = None) -> list[str]:
    """``I PX4_HOME_LAT=… PX4_HOME_LON=… PX4_HOME_ALT=…`` for slots 0..count-1."""
    geo = mission.slot_geodetic()
    n = mission.count if count is None else count
    return [f"{i} PX4_HOME_LAT={geo[i, 0]:.7f} PX4_HOME_LON={geo[i, 1]:.7f} "
            f"PX4_HOME_ALT={geo[i, 2]:.2f}" for i in range(n)]


def _homes(mission: Mission, count: int) -> list[tuple[float, float, float]]:
    geo = mission.slot_geodetic()
    return [(float(g[0]), float(g[1]), float(g[2])) for g in geo[:count]]


@contextlib.asynccontextmanager
async def mock_fleet(mission: Mission, count: int | None = None, **kwargs: Any
                     ) -> AsyncIterator[Any]:
    """A ``sim_stub.MockFleet`` whose vehicle i starts in slot i (context manager); PX4's port
    scheme (vehicle i: GCS port 14540+i) up to 40 vehicles, the mock's wide scheme beyond."""
    try:
        from sim_stub import MockFleet, SimStubError
    except ImportError as exc:  # pragma: no cover - sim_stub ships with the package
        raise FleetCliError(f"the built-in mock fleet (sim_stub) is not available: {exc}"
                            ) from None
    n = mission.count if count is None else count
    if not 1 <= n <= mission.count:
        raise FleetCliError(f"--count must be between 1 and {mission.count} (the mission's "
                            f"slots), got {n}")
    kwargs.setdefault("port_scheme", "px4" if n <= 40 else "wide")
    try:
        fleet = MockFleet(n, homes=_homes(mission, n), **kwargs)
        await fleet.start()
    except SimStubError as exc:
        raise FleetCliError(f"mock fleet: {exc}") from None
    try:
        yield fleet
    finally:
        await fleet.stop()


def parse_endpoint_list(text: str, slots: int) -> list[str]:
    from vtube_fleet.link.endpoints import parse_endpoint

    urls = [u.strip() for u in text.split(",") if u.strip()]
    if not urls:
        raise FleetCliError("--endpoints: no endpoint given")
    if len(urls) > slots:
        raise FleetCliError(f"--endpoints: {len(urls)} endpoints but the mission has only "
                            f"{slots} slots (endpoint i flies slot i)")
    for u in urls:
        parse_endpoint(u)
    if len(set(urls)) != len(urls):
        raise FleetCliError("--endpoints: an endpoint is listed twice")
    return urls


# ----------------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------------
async def fly(
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
) -> Any:
    """Fly ``mission`` (an in-process mock fleet when ``endpoints`` is None); returns the
    :class:`~vtube_fleet.fleet.supervisor.FleetResult`."""
    from vtube_fleet.fleet.supervisor import Supervisor
    from vtube_fleet.link import open_links

    async with contextlib.AsyncExitStack() as stack:
        if endpoints is None:
            fleet = await stack.enter_async_context(
                mock_fleet(mission, **(mock_kwargs or {})))
            endpoints = list(fleet.endpoints)
            if sysids is None:
                sysids = [i + 1 for i in range(len(endpoints))]
        if backend not in BACKENDS:
            raise FleetCliError(f"unknown backend {backend!r} (choose from "
                                f"{', '.join(BACKENDS)})")
        if sysids is None and backend == "mavsdk":
            from vtube_fleet.link.endpoints import parse_endpoint, px4_sitl_sysid

            sysids = [px4_sitl_sysid(parse_endpoint(u).port) or i + 1
                      for i, u in enumerate(endpoints)]
        options = dict(link_options or {})
        if backend == "mavlink":
            options.setdefault("message_rates_hz", dict(UNUSED_STREAMS_OFF))
        links = await stack.enter_async_context(
            open_links(list(endpoints), backend, sysids=sysids, **options))
        sup = Supervisor(mission, links, backend=backend, recorder=recorder, view=view,
                         out_dir=out_dir, **supervisor_kwargs)
        return await sup.run()


def _cmd_run(args: argparse.Namespace) -> int:
    from vtube_fleet.fleet.view import FleetView

    mission = load_mission(args.mission)
    endpoints = None
    if args.endpoints:
        endpoints = parse_endpoint_list(args.endpoints, mission.count)
        if len(endpoints) < mission.count:
            print(f"note: {len(endpoints)} endpoints for {mission.count} slots: flying slots "
                  f"0..{len(endpoints) - 1} only", file=sys.stderr)
            mission = mission.with_vehicles(len(endpoints))
    out = args.out if args.out is not None else Path("runs") / Path(args.mission).stem
    recorder = _recorder(args, out)
    view = FleetView(enabled=not args.quiet)
    mock_kwargs = {"boot_time_scale": args.mock_boot_time_scale,
                   "estimator": args.mock_estimator, "seed": args.mock_seed}
    # the built-in mock always has its ground truth: judge by it too
    truth = args.truth or endpoints is None
    try:
        result = asyncio.run(fly(mission, backend=args.backend, endpoints=endpoints,
                                 out_dir=out, recorder=recorder, view=view,
                                 mock_kwargs=mock_kwargs, truth=truth))
    finally:
        recorder.close()
    print(_closing_line(result, out), file=sys.stderr)
    if result.exit_code not in (0, 130) and result.reason:
        red = "\x1b[31m" if sys.stderr.isatty() else ""
        print(f"{red}error: mission {result.outcome}: {' '.join(result.reason.split())}"
              f"{chr(27) + '[0m' if red else ''}", file=sys.stderr)
    return int(result.exit_code)


def _closing_line(result: Any, out: Path) -> str:
    s = result.summary

    def f(key: str, unit: str = "m", scale: float = 1.0) -> str:
        v = s.get(key)
        return "—" if v is None else f"{v * scale:.2f} {unit}"

    return (f"{result.outcome}: {s.get('exited')}/{s.get('robots')} exited; clearance flown: "
            f"pair {f('min_pair_distance_m')} (airborne {f('min_pair_distance_airborne_m')}, "
            f"2 r_s = {s.get('pair_limit_m', 0):.2f} m), obstacle centre "
            f"{f('min_obstacle_center_distance_m')}; commanded speed "
            f"{f('min_speed_m_s', 'm/s')}..{f('max_speed_m_s', 'm/s')}, measured "
            f"{f('min_measured_speed_m_s', 'm/s')}..{f('max_measured_speed_m_s', 'm/s')} "
            f"(after the first {s.get('settle_s', 0):.1f} s: "
            f"{f('min_measured_speed_settled_m_s', 'm/s')}..); "
            f"rate {f('achieved_rate_hz', 'Hz')}, tick p99 "
            f"{f('tick_duration_p99_s', 'ms', 1000)}"
            + (f"; TRUE clearance: pair {f('truth_min_pair_distance_m')} (airborne "
               f"{f('truth_min_pair_distance_airborne_m')}), obstacle centre "
               f"{f('truth_min_obstacle_center_distance_m')}, legs "
               f"{f('truth_min_left_leg_distance_m')} / {f('truth_min_right_leg_distance_m')}"
               if s.get("truth") else "")
            + f"; summary {out / 'summary.json'}")


def _recorder(args: argparse.Namespace, out: Path) -> Any:
    try:
        from vtube_fleet.recording import recorder_from_args
    except ImportError:  # pragma: no cover
        from vtube_fleet.recording import NullRecorder

        return NullRecorder()
    return recorder_from_args(args, out, kind="fleet", app_id="vtube_fleet")


# ----------------------------------------------------------------------------------------------
# mock-fleet, sitl-homes
# ----------------------------------------------------------------------------------------------
def _cmd_mock_fleet(args: argparse.Namespace) -> int:
    mission = load_mission(args.mission)

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        import signal

        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, stop.set)
        kwargs: dict[str, Any] = {"boot_time_scale": args.boot_time_scale,
                                  "profile": args.profile, "estimator": args.estimator,
                                  "estimator_shared": args.estimator_shared,
                                  "gcs_link": args.gcs_link, "seed": args.seed}
        if args.gcs_port is not None or args.vehicle_port is not None:
            from sim_stub import PortScheme

            gcs = 14540 if args.gcs_port is None else args.gcs_port
            veh = gcs + 40 if args.vehicle_port is None else args.vehicle_port
            kwargs["port_scheme"] = PortScheme("custom", vehicle_base=veh, gcs_base=gcs)
        async with mock_fleet(mission, args.count, **kwargs) as fleet:
            eps = list(fleet.endpoints)
            print(f"{len(eps)} mock vehicles in the slots of {mission.source}; endpoints:",
                  flush=True)
            print(",".join(eps), flush=True)
            await stop.wait()
        print("mock fleet stopped", file=sys.stderr)

    asyncio.run(main())
    return 0


def _cmd_sitl_homes(args: argparse.Namespace) -> int:
    mission = load_mission(args.mission)
    n = mission.count if args.count is None else args.count
    if not 1 <= n <= mission.count:
        raise FleetCliError(f"--count must be between 1 and {mission.count}, got {n}")
    for line in sitl_home_lines(mission, n):
        print(line)
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "run", help="fly a mission with PX4 vehicles (or the built-in mock fleet)",
        description="Fly MISSION.toml: connect, preflight, arm, take off, fly the tube in "
                    "offboard, land. Endpoint i flies slot i. Without --endpoints a sim_stub "
                    "mock fleet is started in-process in the mission's slots.")
    p.add_argument("mission", type=Path, help="mission file (scenario + [mission])")
    p.add_argument("--backend", choices=BACKENDS, default="mavlink",
                   help="vehicle link backend (default: mavlink)")
    p.add_argument("--endpoints", metavar="URL,URL,...",
                   help="vehicle endpoints in MAVSDK syntax, e.g. udpin://127.0.0.1:14540; "
                        "fewer than the slots fly the first slots")
    p.add_argument("--out", type=Path, default=None,
                   help="output folder for summary.json and recording.rrd "
                        "(default: runs/<mission name>)")
    p.add_argument("-q", "--quiet", action="store_true", help="no live status view")
    p.add_argument("--mock-boot-time-scale", type=float, default=1.0, metavar="S",
                   help="without --endpoints: scale the mock vehicles' boot timeline (PX4 is "
                        "armable ~4 s after boot; 0.3 makes that ~1.2 s)")
    p.add_argument("--mock-estimator", choices=("px4-sih", "rtk", "ideal"), default="px4-sih",
                   help="without --endpoints: the mock vehicles' estimate errors (px4-sih: "
                        "like real PX4 SITL, the default; rtk: cm-level; ideal: none)")
    p.add_argument("--mock-seed", type=int, default=0, metavar="N",
                   help="without --endpoints: seed of the mock vehicles' estimate errors")
    p.add_argument("--truth", action="store_true",
                   help="ask every vehicle for its SITL ground truth (HIL_STATE_QUATERNION; "
                        "PX4 SITL and the mock send it) and judge the clearance truly flown "
                        "too (truth_* summary keys); always on for the built-in mock")
    try:
        from vtube_fleet.recording import add_recording_args

        add_recording_args(p)
    except ImportError:  # pragma: no cover
        pass
    p.set_defaults(func=_cmd_run)

    m = subparsers.add_parser(
        "mock-fleet", help="run mock PX4 vehicles in a mission's slots until interrupted",
        description="Start sim_stub vehicles placed in the mission's slots (PX4 SITL port "
                    "scheme: vehicle i on udpin://127.0.0.1:14540+i) and run until Ctrl-C.")
    m.add_argument("mission", type=Path)
    m.add_argument("--count", type=int, default=None, help="number of vehicles (default: all "
                                                           "slots)")
    m.add_argument("--boot-time-scale", type=float, default=1.0, metavar="S",
                   help="scale the vehicles' boot timeline (default 1 = as PX4 SITL)")
    m.add_argument("--profile", choices=("full", "lite"), default="full",
                   help="sim_stub stream set: every stream PX4 sends (full) or what clients "
                        "rely on (lite)")
    m.add_argument("--estimator", choices=("px4-sih", "rtk", "ideal"), default="px4-sih",
                   help="the vehicles' estimate errors: px4-sih (like real PX4 SITL, default), "
                        "rtk (cm-level), ideal (none)")
    m.add_argument("--estimator-shared", action="store_true",
                   help="every vehicle gets the same estimate-error sequence (as SIH does)")
    m.add_argument("--gcs-link", choices=("lite", "full", "off"), default="lite",
                   help="PX4's GCS link (udp 18570+i -> 14550; ground truth on request): its "
                        "default stream set (default lite)")
    m.add_argument("--seed", type=int, default=0, help="seed of the estimate errors")
    m.add_argument("--gcs-port", type=int, default=None, metavar="N",
                   help="GCS port of vehicle 0 (vehicle i: N+i; default 14540 as PX4 SITL)")
    m.add_argument("--vehicle-port", type=int, default=None, metavar="N",
                   help="port vehicle 0 sends from (vehicle i: N+i; default GCS port + 40)")
    m.set_defaults(func=_cmd_mock_fleet)

    h = subparsers.add_parser(
        "sitl-homes", help="print PX4_HOME_* for each PX4 SITL instance of a mission",
        description="One line per instance: 'I PX4_HOME_LAT=… PX4_HOME_LON=… PX4_HOME_ALT=…' "
                    "so that PX4 SITL instance I starts in slot I.")
    h.add_argument("mission", type=Path)
    h.add_argument("--count", type=int, default=None)
    h.set_defaults(func=_cmd_sitl_homes)
