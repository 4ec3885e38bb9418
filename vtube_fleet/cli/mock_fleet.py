"""``vtube-fleet mock-fleet``: mock PX4 vehicles in a mission's slots until interrupted."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any

from vtube_fleet.cli._args import COUNT, PORT, SCALE, SEED, bounded
from vtube_fleet.cli._signals import interrupt_on_signals
from vtube_fleet.config.keys import Bound, Key
from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.launch import TICK_HZ_MAX, TICK_HZ_MIN, gcs_link_mode, mock_fleet

__all__ = ["register"]

#: The mock's scheduler tick, within the range sim_stub supports.
TICK_HZ = Key("tick_hz", "number", "a tick rate", "Hz",
              bound=Bound(TICK_HZ_MIN, TICK_HZ_MAX, low_inclusive=True, interval=True))


def _cmd_mock_fleet(args: argparse.Namespace) -> int:
    mission = load_mission(args.mission)
    gcs_link, note = gcs_link_mode(
        args.gcs_link, custom_ports=args.gcs_port is not None or args.vehicle_port is not None,
        gcs_link_base=args.gcs_link_base)

    async def main() -> None:
        stop = asyncio.Event()
        with interrupt_on_signals(lambda _name: stop.set()):
            async with mock_fleet(
                mission, args.count, gcs_port=args.gcs_port, vehicle_port=args.vehicle_port,
                gcs_link_base=args.gcs_link_base if gcs_link != "off" else None,
                gcs_link_port=args.gcs_link_port if gcs_link != "off" else None,
                boot_time_scale=args.boot_time_scale, profile=args.profile,
                estimator=args.estimator, estimator_shared=args.estimator_shared,
                gcs_link=gcs_link, seed=args.seed, processes=args.processes,
                tick_hz=args.tick_hz,
            ) as fleet:
                eps = list(fleet.endpoints)
                print(f"{len(eps)} mock vehicles in the slots of {mission.source}; endpoints:",
                      flush=True)
                print(",".join(eps), flush=True)
                if note:
                    print(note, file=sys.stderr, flush=True)
                await fleet.serve(stop)
        print("mock fleet stopped", file=sys.stderr)

    asyncio.run(main())
    return 0


def register(subparsers: Any) -> None:
    m = subparsers.add_parser(
        "mock-fleet", help="run mock PX4 vehicles in a mission's slots until interrupted",
        description="Start sim_stub vehicles placed in the mission's slots (PX4 SITL port "
                    "scheme: vehicle i on udpin://127.0.0.1:14540+i) and run until Ctrl-C.")
    m.add_argument("mission", type=Path)
    m.add_argument("--count", type=bounded(COUNT), default=None,
                   help="number of vehicles (default: all slots)")
    m.add_argument("--boot-time-scale", type=bounded(SCALE), default=1.0, metavar="S",
                   help="scale the vehicles' boot timeline (default 1 = as PX4 SITL)")
    m.add_argument("--profile", choices=("full", "lite"), default="full",
                   help="sim_stub stream set: every stream PX4 sends (full) or what clients "
                        "rely on (lite)")
    m.add_argument("--estimator", choices=("px4-sih", "rtk", "ideal"), default="px4-sih",
                   help="the vehicles' estimate errors: px4-sih (like real PX4 SITL, default), "
                        "rtk (cm-level), ideal (none)")
    m.add_argument("--estimator-shared", action="store_true",
                   help="every vehicle gets the same estimate-error sequence (as SIH does)")
    m.add_argument("--gcs-link", choices=("lite", "full", "off"), default=None,
                   help="PX4's GCS link (udp 18570+i -> 14550; ground truth on request): its "
                        "default stream set (default lite; off with --gcs-port/--vehicle-port "
                        "unless --gcs-link-base is given)")
    m.add_argument("--processes", type=bounded(COUNT), default=1, metavar="N",
                   help="split the vehicles over N OS processes (one scheduler each, same "
                        "ports; about 500 lite vehicles fit one core); default 1")
    m.add_argument("--tick-hz", type=bounded(TICK_HZ), default=100.0, metavar="HZ",
                   help="the mock's scheduler tick: dynamics at HZ, each vehicle's PX4 logic "
                        "at HZ/2 (default 100, what the dynamics were fitted at; 50 takes "
                        "about a third less CPU for large fleets, docs/sim_stub.md)")
    m.add_argument("--seed", type=bounded(SEED), default=0, help="seed of the estimate errors")
    m.add_argument("--gcs-port", type=bounded(PORT), default=None, metavar="N",
                   help="GCS port of vehicle 0 (vehicle i: N+i; default 14540 as PX4 SITL)")
    m.add_argument("--vehicle-port", type=bounded(PORT), default=None, metavar="N",
                   help="port vehicle 0 sends from (vehicle i: N+i; default GCS port + 40)")
    m.add_argument("--gcs-link-base", type=bounded(PORT), default=None, metavar="N",
                   help="port vehicle i's GCS link binds: N+i (default 18570 as PX4 SITL; "
                        "none with --gcs-port/--vehicle-port unless given)")
    m.add_argument("--gcs-link-port", type=bounded(PORT), default=None, metavar="N",
                   help="port every vehicle's GCS link sends to (default 14550 as PX4 SITL)")
    m.set_defaults(func=_cmd_mock_fleet)
