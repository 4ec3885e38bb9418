"""``python -m sim_stub --count N [--processes P]``: run N mock PX4 SITL vehicles (in P
processes) until SIGINT/SIGTERM."""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import signal
import sys
from collections.abc import Sequence

from .errors import SimStubError
from .estimator import ESTIMATOR_PROFILES
from .faults import Faults, parse_fault_spec
from .fleet import MockFleet, load_homes
from .ports import PX4, WIDE, PortScheme
from .processes import ProcessFleet
from .scheduler import TICK_HZ_MAX, TICK_HZ_MIN
from .telemetry import GCS_LINK_PROFILES
from .vehicle import DEFAULT_HOME, validate_home

__all__ = ["main", "build_parser"]


def _home(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    if len(parts) != 3:
        raise SimStubError(f"--home must be LAT,LON,ALT (three numbers), got {text!r}")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise SimStubError(f"--home must be LAT,LON,ALT (three numbers), got {text!r}") from None
    return validate_home(values)  # type: ignore[arg-type]


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m sim_stub",
        description="Run mock PX4 SITL vehicles (MAVLink 2 over UDP) in one process (or, with "
        "--processes N, split over N).",
    )
    ap.add_argument("--count", type=int, default=None, help="number of vehicles (default 1)")
    ap.add_argument(
        "--first",
        type=int,
        default=0,
        metavar="I",
        help="the first PX4 instance: vehicle k is instance I+k, with that instance's ports "
        "and sysid I+k+1, as `px4 -i I+k` (default 0; one process per instance: --first I "
        "alone)",
    )
    ap.add_argument(
        "--home",
        default=None,
        help="LAT,LON,ALT start point of every vehicle "
        f"(default PX4 SIH's {DEFAULT_HOME[0]},{DEFAULT_HOME[1]},{DEFAULT_HOME[2]})",
    )
    ap.add_argument(
        "--homes",
        default=None,
        help="file with one LAT,LON,ALT per vehicle (text/CSV lines or a JSON list)",
    )
    ap.add_argument(
        "--spacing",
        type=float,
        default=None,
        help="place the vehicles on a grid this many metres apart around --home",
    )
    ap.add_argument(
        "--processes",
        type=int,
        default=1,
        metavar="N",
        help="split the vehicles over N OS processes (contiguous blocks, one scheduler each, "
        "same ports; about 500 lite vehicles fit one core); default 1",
    )
    ap.add_argument(
        "--tick-hz",
        type=float,
        default=100.0,
        metavar="HZ",
        help="scheduler tick: dynamics at HZ, each vehicle's PX4 logic at HZ/2 (default 100; "
        "50 for large fleets takes ~20%% less CPU, docs/sim_stub.md)",
    )
    ap.add_argument("--seed", type=int, default=0, help="seed for loss/noise/stream phases")
    ap.add_argument(
        "--ports",
        default="px4",
        help="port scheme: px4 (vehicle binds 14580+i, sends to 14540+i; <= 40 "
        "vehicles), wide (24000+i -> 20000+i), or VEHICLE_BASE:GCS_BASE",
    )
    ap.add_argument("--host", default="127.0.0.1", help="address to bind and send to")
    ap.add_argument(
        "--profile",
        choices=("full", "lite"),
        default="full",
        help="telemetry stream set (default full = every stream PX4 sent)",
    )
    ap.add_argument(
        "--estimator",
        choices=tuple(ESTIMATOR_PROFILES),
        default="px4-sih",
        help="estimate-error profile: px4-sih (like real PX4 SITL: ~0.2 m / 0.3 m/s typical, "
        "default), rtk (cm-level), ideal (the estimate is the truth)",
    )
    ap.add_argument(
        "--estimator-shared",
        action="store_true",
        help="every vehicle gets the same estimate-error sequence (as SIH instances do)",
    )
    ap.add_argument(
        "--gcs-link",
        choices=GCS_LINK_PROFILES,
        default="lite",
        help="PX4's GCS link (udp 18570+i -> 14550, as PX4 SITL; ground truth on request): "
        "default streams lite (default), full (as PX4 SITL) or off",
    )
    ap.add_argument(
        "--gcs-link-base",
        type=int,
        default=None,
        metavar="N",
        help="GCS link: vehicle i binds N+i (default 18570 with --ports px4 as PX4 SITL, 28000 "
        "with wide, no GCS link with VEHICLE_BASE:GCS_BASE unless given)",
    )
    ap.add_argument(
        "--gcs-link-port",
        type=int,
        default=None,
        metavar="N",
        help="GCS link: the port every vehicle sends to (default 14550 as PX4 SITL; with "
        "--ports px4, vehicles 10-19 send to 34650 and 20+ to 34750 like PX4)",
    )
    ap.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="[I:]KEY=VAL,...",
        help="fault for vehicle I (or all): loss=PCT, latency=S, gps_noise=M, "
        "die_at=S, die_how=silent|freeze, push_north/push_east=M_S, push_at=S, push_for=S, "
        "slow=GAIN, slow_at=S; "
        "its battery: battery=PCT (the full pack), drain=PCT_PER_MIN (while armed; default "
        "100 as PX4 SITL), battery_floor=PCT (default 50), battery_low=PCT and "
        "battery_low_at=S (the pack drops to PCT then); repeatable",
    )
    return ap


def _scheme(text: str, host: str, gcs_link_base: int | None = None,
            gcs_link_port: int | None = None) -> PortScheme:
    if text in ("px4", "wide"):
        scheme = dataclasses.replace({"px4": PX4, "wide": WIDE}[text], host=host)
    else:
        try:
            v, g = (int(x) for x in text.split(":"))
        except ValueError:
            raise SimStubError(
                f"--ports must be px4, wide or VEHICLE_BASE:GCS_BASE, got {text!r}"
            ) from None
        scheme = PortScheme("custom", v, g, host)
    if gcs_link_base is not None:
        if not 1 <= gcs_link_base <= 65535:
            raise SimStubError(f"--gcs-link-base must be in 1..65535, got {gcs_link_base}")
        scheme = dataclasses.replace(scheme, gcs_link_base=gcs_link_base)
    if gcs_link_port is not None:
        if not 1 <= gcs_link_port <= 65535:
            raise SimStubError(f"--gcs-link-port must be in 1..65535, got {gcs_link_port}")
        scheme = dataclasses.replace(scheme, gcs_link_remotes=((0, gcs_link_port),))
    return scheme


def _faults(specs: Sequence[str], count: int) -> list[Faults]:
    out = [Faults()] * count
    for spec in specs:
        index, f = parse_fault_spec(spec)
        if index is None:
            out = [f] * count
        elif index >= count:
            raise SimStubError(f"--fault {spec!r}: no vehicle {index} (count is {count})")
        else:
            out[index] = f
    return out


async def _run(fleet: MockFleet | ProcessFleet, profile: str, estimator: str) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    async with fleet:
        procs = (f" in {fleet.processes} processes" if isinstance(fleet, ProcessFleet) else "")
        print(
            f"sim_stub: {fleet.count} vehicle(s){procs}, ports {fleet.ports.name}, "
            f"profile {profile}, estimator {estimator}; Ctrl-C to stop",
            flush=True,
        )
        for line in fleet.describe():
            print(line, flush=True)
        await fleet.serve(stop)
        print("sim_stub: stopping", flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        home = _home(args.home) if args.home is not None else DEFAULT_HOME
        homes = load_homes(args.homes) if args.homes else None
        count = args.count
        if count is None:
            count = len(homes) if homes is not None else 1
        if count < 1:
            raise SimStubError(f"--count must be >= 1, got {count}")
        if args.first < 0:
            raise SimStubError(f"--first must be >= 0, got {args.first}")
        if args.first and args.processes > 1:
            raise SimStubError("--first with --processes > 1: the processes number their "
                               "vehicles from 0; start one process per --first instead")
        if not 1 <= args.processes <= count:
            raise SimStubError(f"--processes must be in 1..{count} (the vehicle count), got "
                               f"{args.processes}")
        if not TICK_HZ_MIN <= args.tick_hz <= TICK_HZ_MAX:
            raise SimStubError(f"--tick-hz must be in {TICK_HZ_MIN:g}..{TICK_HZ_MAX:g}, got "
                               f"{args.tick_hz:g}")
        if homes is not None and len(homes) != count:
            raise SimStubError(f"--count {count} but {args.homes} has {len(homes)} homes")
        kwargs = dict(
            homes=homes,
            home=home,
            spacing_m=args.spacing,
            port_scheme=_scheme(args.ports, args.host, args.gcs_link_base, args.gcs_link_port),
            faults=_faults(args.fault, count),
            seed=args.seed,
            profile=args.profile,
            estimator=args.estimator,
            estimator_shared=args.estimator_shared,
            gcs_link=args.gcs_link,
            tick_hz=args.tick_hz,
        )
        fleet = (ProcessFleet(count, processes=args.processes, **kwargs) if args.processes > 1
                 else MockFleet(count, first=args.first, **kwargs))
        asyncio.run(_run(fleet, args.profile, args.estimator))
    except SimStubError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
