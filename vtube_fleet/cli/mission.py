"""``vtube-fleet mission start|abort|status``: the coordinator of the MQTT agents."""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path
from typing import Any

from vtube_fleet.cli._args import (
    COUNT,
    DURATION,
    add_bus_args,
    add_recording_args,
    bounded,
    recorder_from_args,
)
from vtube_fleet.cli._signals import interrupt_on_signals
from vtube_fleet.fleet.distributed.coordinator import Coordinator
from vtube_fleet.outcome import EXIT_INTERRUPTED, EXIT_OK, exit_code

__all__ = ["register"]


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _fmt(v: float | None, unit: str = "m", scale: float = 1.0) -> str:
    return "—" if v is None else f"{v * scale:.2f} {unit}"


async def _start(args: argparse.Namespace) -> int:
    stop = asyncio.Event()
    with interrupt_on_signals(lambda _name: stop.set()):
        async with Coordinator(
            args.mission, args.broker, mission_id=args.mission_id, vehicles=args.vehicles,
            broker_timeout_s=args.broker_timeout, max_age_s=args.max_age,
            cells=not args.no_cells, say=_say, credentials=args.credentials,
            insecure=args.insecure,
        ) as co:
            if not await co.start_run(stop, args.ready_timeout):
                return EXIT_INTERRUPTED
            if not args.wait:
                return EXIT_OK
            out = args.out if args.out is not None else Path("runs") / co.mission_id
            # exits only as RunMonitor decides them (from every state heard, also between ticks)
            recorder = recorder_from_args(args, out, kind="fleet", app_id="vtube_fleet",
                                          detect_exits=False)
            res = await co.follow_run(stop, out, recorder, args.timeout)
    s = res.summary
    _say(f"{res.outcome}: {s.get('exited')}/{co.vehicles} exited; min pair distance "
         f"{_fmt(s.get('min_pair_distance_m'))} (2 r_s = {s['pair_limit_m']:.2f} m), obstacle "
         f"centre {_fmt(s.get('min_obstacle_center_distance_m'))}, violations "
         f"{s.get('violations')}; state age p50/p99 {_fmt(s.get('state_age_p50_s'), 'ms', 1000)}/"
         f"{_fmt(s.get('state_age_p99_s'), 'ms', 1000)}; summary {res.summary_path}")
    code = exit_code(res.outcome)
    if code not in (EXIT_OK, EXIT_INTERRUPTED) and res.reason:
        _say(f"error: mission {res.outcome}: {' '.join(res.reason.split())}")
    return code


async def _abort(args: argparse.Namespace) -> int:
    async with Coordinator(args.mission, args.broker, mission_id=args.mission_id,
                           broker_timeout_s=args.broker_timeout, credentials=args.credentials,
                           insecure=args.insecure) as co:
        run_id = await co.abort_announced()
    _say(f"mission {co.mission_id} run {run_id}: abort published")
    return EXIT_OK


async def _status(args: argparse.Namespace) -> int:
    async with Coordinator(args.mission, args.broker, mission_id=args.mission_id,
                           broker_timeout_s=args.broker_timeout, credentials=args.credentials,
                           insecure=args.insecure) as co:
        info = await co.status(args.listen)
    if args.json:
        print(json.dumps(info, indent=2))
        return EXIT_OK
    print(f"mission {info['mission_id']} on {info['broker']} (this file's config hash "
          f"{info['config_hash']})")
    r = info["run"]
    if r is None:
        print("  no run announced")
    else:
        print(f"  run {r['run_id']}: {r['vehicles']} vehicles, hash {r['config_hash']}"
              f"{'' if r['hash_matches'] else ' (DIFFERS from this file)'}, announced "
              f"{r['announced_s_ago']} s ago from {r['source']}")
    cmd = info["command"]
    if cmd is not None:
        print(f"  last command: {cmd['command']} (run {cmd['run_id']}, {cmd['s_ago']} s ago)")
    print(f"  {'id':>3} {'status':<8} {'stage':<12} {'phase':<11} {'x_m':>8} {'y_m':>8} "
          f"{'age_s':>7}")

    def f(v: Any, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    for row in info["vehicles"]:
        print(f"  {row['id']:>3} {f(row['status'], '<8')} {f(row['stage'] or '', '<12')} "
              f"{f(row['phase'], '<11')} {f(row['x_m'], '8.2f')} {f(row['y_m'], '8.2f')} "
              f"{f(row['age_s'], '7.1f')}")
    return EXIT_OK


def _cmd(args: argparse.Namespace) -> int:
    fn = {"start": _start, "abort": _abort, "status": _status}[args.mission_command]
    return asyncio.run(fn(args))


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "mission",
        help="coordinate distributed agents over MQTT: start | abort | status",
        description="The thin coordinator of `vtube-fleet agent` processes: announces a run "
        "(retained config with the mission file's hash), publishes start/abort and reads the "
        "agents' states. It computes nobody's setpoint. See docs/mqtt.md.",
    )
    sub = p.add_subparsers(dest="mission_command", metavar="ACTION")
    sub.required = True

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("mission", type=Path, help="mission file (scenario + [mission])")
        add_bus_args(sp)
        sp.add_argument(
            "--broker-timeout",
            type=bounded(DURATION),
            default=10.0,
            metavar="S",
            help="seconds to wait for the broker connection (default 10)",
        )
        sp.set_defaults(func=_cmd)

    s = sub.add_parser("start", help="announce a run, wait for every agent, publish start")
    common(s)
    s.add_argument(
        "--vehicles",
        type=bounded(COUNT),
        default=None,
        help="fly slots 0..N-1 only (default: every slot of the mission)",
    )
    s.add_argument(
        "--max-age",
        type=bounded(DURATION),
        default=None,
        metavar="S",
        help="oldest neighbour state an agent uses as a live position, budgeted in the "
        "safety margin (default: 3 control periods, at most neighbour_max_age_s)",
    )
    s.add_argument(
        "--no-cells",
        action="store_true",
        help="every agent hears every other (default: spatial cells sized from the mission)",
    )
    s.add_argument(
        "--ready-timeout",
        type=bounded(DURATION),
        default=None,
        metavar="S",
        help="seconds to wait for every agent to join with a READY vehicle "
        "(default: connect_timeout_s + ready_timeout_s)",
    )
    s.add_argument(
        "--wait",
        action="store_true",
        help="follow the flight until every vehicle has landed (or failed) and "
        "write OUT/summary.json",
    )
    add_recording_args(s)
    s.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder of --wait (default: runs/<mission id>)",
    )
    s.add_argument(
        "--timeout",
        type=bounded(DURATION),
        default=None,
        metavar="S",
        help="give up following after S seconds (default: arm + take-off + "
        "mission + land timeouts of the mission)",
    )
    a = sub.add_parser("abort", help="publish abort: every agent holds, then lands")
    common(a)
    st = sub.add_parser("status", help="print the announced run and every vehicle's state")
    common(st)
    st.add_argument(
        "--listen",
        type=bounded(DURATION),
        default=1.0,
        metavar="S",
        help="seconds to listen for live states (default 1)",
    )
    st.add_argument("--json", action="store_true", help="print JSON")
