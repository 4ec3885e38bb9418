"""``vtube-fleet agent``: fly one vehicle of a mission, neighbours over MQTT."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any

from vtube_fleet.cli._args import (
    DURATION,
    INDEX,
    add_bus_args,
    add_fence_arg,
    add_recording_args,
    bounded,
    check_out_dir,
    recorder_from_args,
)
from vtube_fleet.cli._signals import interrupt_on_signals
from vtube_fleet.fleet.distributed.coordinator import (
    default_mission_id,
)
from vtube_fleet.fleet.distributed.vehicle_agent import AgentInterrupted, AgentProcess
from vtube_fleet.link.backends import BACKEND_NAMES
from vtube_fleet.outcome import EXIT_INTERRUPTED

__all__ = [
    "register",
]

def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _cmd_agent(args: argparse.Namespace) -> int:
    mission_id = args.mission_id or default_mission_id(args.mission)
    out = (args.out if args.out is not None
           else Path("runs") / mission_id / f"agent-{args.vehicle}")
    check_out_dir(out)  # before anything connects: every exit path writes its summary there
    # a bad --rerun-save / --rerun-connect fails here, before anything connects
    recorder = recorder_from_args(args, out, kind="fleet", app_id="vtube_fleet_agent",
                                  detect_exits=False)
    proc = AgentProcess(
        args.mission, args.vehicle, broker=args.broker, endpoint=args.endpoint,
        backend=args.link, mission_id=args.mission_id, join_timeout_s=args.join_timeout,
        broker_hold_limit_s=args.broker_hold_limit, out=out, recorder=recorder, say=_say,
        credentials=args.credentials, insecure=args.insecure, fence=not args.no_fence,
    )

    async def main() -> int:
        with interrupt_on_signals(proc.interrupt):
            return await proc.run()

    try:
        return asyncio.run(main())
    except AgentInterrupted as exc:
        _say(f"agent {args.vehicle}: {exc or 'interrupted'}")
        return EXIT_INTERRUPTED


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "agent",
        help="fly ONE vehicle of a mission as its own process; neighbours over MQTT",
        description="Fly slot I of MISSION.toml (endpoint I of `vtube-fleet run`) with this "
        "process's own controller; neighbours' states through an MQTT broker. Start one per "
        "vehicle, then `vtube-fleet mission start`. See docs/mqtt.md.",
    )
    p.add_argument("mission", type=Path, help="mission file (scenario + [mission])")
    p.add_argument(
        "--vehicle", type=bounded(INDEX), required=True, metavar="I",
        help="the slot to fly (0-based)",
    )
    p.add_argument(
        "--endpoint",
        default=None,
        metavar="URL",
        help="the vehicle's endpoint (default: PX4 SITL instance I, udpin://127.0.0.1:14540+I)",
    )
    add_bus_args(p)
    p.add_argument(
        "--link",
        choices=BACKEND_NAMES,
        default="mavlink",
        help="vehicle link backend (default mavlink)",
    )
    add_fence_arg(p)
    p.add_argument(
        "--join-timeout",
        type=bounded(DURATION),
        default=600.0,
        metavar="S",
        help="seconds to wait for `mission start` (default 600)",
    )
    p.add_argument(
        "--broker-hold-limit",
        type=bounded(DURATION),
        default=30.0,
        metavar="S",
        help="land after standing still this long without the broker (default 30)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="this agent's summary.json and recording.rrd, from the start command on "
        "(default runs/MISSION_ID/agent-I)",
    )
    add_recording_args(p)
    p.set_defaults(func=_cmd_agent)
