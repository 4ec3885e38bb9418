"""``vtube-fleet run``: fly a mission with PX4 vehicles or the built-in mock fleet."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
from pathlib import Path
from typing import Any

from vtube_fleet.cli._args import (
    SCALE,
    SEED,
    add_fence_arg,
    add_recording_args,
    add_sitl_args,
    bounded,
    check_out_dir,
    recorder_from_args,
    sitl_command_from_args,
)
from vtube_fleet.cli._signals import interrupt_on_signals
from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.launch import (
    FleetCliError,
    fleet_supervisor,
    parse_endpoint_list,
)
from vtube_fleet.fleet.sitl import SitlFleet, instance_lines, sitl_fleet
from vtube_fleet.fleet.supervisor import FleetResult
from vtube_fleet.link.backends import BACKEND_NAMES

__all__ = ["register"]


def _cmd_run(args: argparse.Namespace) -> int:
    from vtube_fleet.fleet.view import FleetView

    mission = load_mission(args.mission)
    sitl = sitl_command_from_args(args)
    if sitl is not None and args.endpoints is not None:
        raise FleetCliError(f"{args.sitl_options[0] if args.sitl_px4 else '--sitl-command'} "
                            f"and --endpoints: give one (the SITL fleet's endpoints are its "
                            f"own)")
    endpoints = None
    if args.endpoints is not None:  # only its absence means "the built-in mock fleet"
        endpoints = parse_endpoint_list(args.endpoints, mission.count)
        if len(endpoints) < mission.count:
            print(f"note: {len(endpoints)} endpoints for {mission.count} slots: flying slots "
                  f"0..{len(endpoints) - 1} only", file=sys.stderr)
            mission = mission.with_vehicles(len(endpoints))
    out = args.out if args.out is not None else Path("runs") / Path(args.mission).stem
    check_out_dir(out)  # before anything connects: every exit path writes its summary there
    recorder = _recorder(args, out)
    view = FleetView(enabled=not args.quiet)
    mock_kwargs = {"boot_time_scale": args.mock_boot_time_scale,
                   "estimator": args.mock_estimator, "seed": args.mock_seed}
    # the built-in mock and SITL always have their ground truth: judge by it too
    truth = args.truth or endpoints is None or sitl is not None
    holder: list[SitlFleet] = []

    def started(fleet: SitlFleet) -> None:
        print(f"sitl: {fleet.count} {fleet.command.name} instances under {fleet.out_dir}:",
              file=sys.stderr, flush=True)
        for line in instance_lines(fleet):
            print(line, file=sys.stderr, flush=True)

    async def main() -> FleetResult:
        async with contextlib.AsyncExitStack() as stack:
            links, sysids = endpoints, None
            if sitl is not None:  # stopped when the stack closes, on every exit path
                fleet = await stack.enter_async_context(sitl_fleet(
                    mission, sitl, out / "sitl", answer_timeout_s=args.sitl_timeout_s,
                    on_start=started, holder=holder))
                links, sysids = fleet.endpoints, fleet.sysids
                print(f"sitl: every instance answers: {','.join(links)}", file=sys.stderr,
                      flush=True)
            sup = await stack.enter_async_context(fleet_supervisor(
                mission, backend=args.backend, endpoints=links, sysids=sysids, out_dir=out,
                recorder=recorder, view=view, mock_kwargs=mock_kwargs, truth=truth,
                fence=not args.no_fence, fix_params=args.fix_params))
            with interrupt_on_signals(sup.interrupt):
                return await sup.run()
        raise AssertionError("unreachable")  # (the stack does not swallow exceptions)

    try:
        result = asyncio.run(main())
    finally:
        recorder.close()
        for fleet in holder:  # the last resort if the event loop died before the stop
            fleet.kill_now()
    print(_closing_line(result, out), file=sys.stderr)
    # interrupted is no failure, unless it left vehicles in the air (or not known to be down)
    if result.reason and (result.exit_code not in (0, 130) or result.summary.get("not_down")):
        red = "\x1b[31m" if sys.stderr.isatty() else ""
        print(f"{red}error: mission {result.outcome}: {' '.join(result.reason.split())}"
              f"{chr(27) + '[0m' if red else ''}", file=sys.stderr)
    return int(result.exit_code)


def _m(v: float | None) -> str:
    return "—" if v is None else f"{v:.2f} m"


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
            + (f"; tracking error p99 {_m(tracking.get('error_p99_m'))}, max "
               f"{_m(tracking.get('error_max_m'))} (e = {_m(tracking.get('budgeted_m'))})"
               if (tracking := s.get("reference_tracking") or {}) else "")
            + (f"; TRUE clearance: pair {f('truth_min_pair_distance_m')} (airborne "
               f"{f('truth_min_pair_distance_airborne_m')}), obstacle centre "
               f"{f('truth_min_obstacle_center_distance_m')}, legs "
               f"{f('truth_min_left_leg_distance_m')} / {f('truth_min_right_leg_distance_m')}"
               if s.get("truth") else "")
            + f"; summary {out / 'summary.json'}")


def _recorder(args: argparse.Namespace, out: Path) -> Any:
    return recorder_from_args(args, out, kind="fleet", app_id="vtube_fleet")


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "run", help="fly a mission with PX4 vehicles (or the built-in mock fleet)",
        description="Fly MISSION.toml: connect, preflight, arm, take off, fly the tube in "
                    "offboard, land. Endpoint i flies slot i. Without --endpoints a sim_stub "
                    "mock fleet is started in-process in the mission's slots; with --sitl "
                    "PATH/TO/px4 one PX4 SITL instance per slot is started first (as `vtube-"
                    "fleet sitl` does) and stopped afterwards.")
    p.add_argument("mission", type=Path, help="mission file (scenario + [mission])")
    p.add_argument("--backend", choices=BACKEND_NAMES, default="mavlink",
                   help="vehicle link backend (default: mavlink)")
    p.add_argument("--endpoints", metavar="URL,URL,...",
                   help="vehicle endpoints in MAVSDK syntax, e.g. udpin://127.0.0.1:14540; "
                        "fewer than the slots fly the first slots; without it (not with an "
                        "empty list, which is an error) the built-in mock fleet flies")
    p.add_argument("--out", type=Path, default=None,
                   help="output folder for summary.json and recording.rrd "
                        "(default: runs/<mission name>)")
    p.add_argument("-q", "--quiet", action="store_true", help="no live status view")
    p.add_argument("--mock-boot-time-scale", type=bounded(SCALE), default=1.0, metavar="S",
                   help="without --endpoints: scale the mock vehicles' boot timeline (PX4 is "
                        "armable ~4 s after boot; 0.3 makes that ~1.2 s)")
    p.add_argument("--mock-estimator", choices=("px4-sih", "rtk", "ideal"), default="px4-sih",
                   help="without --endpoints: the mock vehicles' estimate errors (px4-sih: "
                        "like real PX4 SITL, the default; rtk: cm-level; ideal: none)")
    p.add_argument("--mock-seed", type=bounded(SEED), default=0, metavar="N",
                   help="without --endpoints: seed of the mock vehicles' estimate errors")
    p.add_argument("--truth", action="store_true",
                   help="ask every vehicle for its SITL ground truth (HIL_STATE_QUATERNION; "
                        "PX4 SITL and the mock send it) and judge the clearance truly flown "
                        "too (truth_* summary keys); always on for the built-in mock")
    add_sitl_args(p, binary="--sitl", prefix="sitl-", required=False)
    add_fence_arg(p)
    p.add_argument("--fix-params", action="store_true",
                   help="set the PX4 parameters the audit finds off (MPC_XY_VEL_MAX, "
                        "GF_MAX_VER_DIST, MPC_ACC_HOR, MPC_JERK_AUTO, MPC_Z_VEL_MAX_UP/_DN, "
                        "COM_OF_LOSS_T, COM_OBL_RC_ACT, NAV_DLL_ACT) for the flight and restore "
                        "the old values on exit")
    add_recording_args(p)
    p.set_defaults(func=_cmd_run)
