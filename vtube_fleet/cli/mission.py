"""``vtube-fleet mission start|abort|status``: the coordinator of the MQTT agents."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import signal
import sys
import time
from pathlib import Path
from typing import Any

from vtube_fleet.artifacts import write_summary
from vtube_fleet.cli._args import add_bus_args
from vtube_fleet.core.metrics import verdict
from vtube_fleet.fleet.distributed.coordinator import Coordinator, MissionRunError
from vtube_fleet.fleet.distributed.monitor import RunMonitor
from vtube_fleet.outcome import EXIT_INCOMPLETE, EXIT_INTERRUPTED, EXIT_OK, EXIT_UNSAFE

__all__ = [
    "register",
]









async def _start(args: argparse.Namespace) -> int:
    loop = asyncio.get_running_loop()
    interrupted = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, interrupted.set)
    async with Coordinator(
        args.mission,
        args.broker,
        mission_id=args.mission_id,
        vehicles=args.vehicles,
        broker_timeout_s=args.broker_timeout,
        max_age_s=args.max_age,
        cells=not args.no_cells,
    ) as co:
        cfg = co.mission.config
        run = co.announce()
        print(
            f"mission {co.mission_id} run {run}: config {co.config_hash} announced on "
            f"{args.broker} (neighbour max age {1000 * co.max_age_s:.0f} ms, cells "
            f"{co.announced.cell_m:g} m); waiting for {co.vehicles} agents",
            file=sys.stderr,
            flush=True,
        )
        ready_timeout = (
            args.ready_timeout
            if args.ready_timeout is not None
            else cfg.connect_timeout_s + cfg.ready_timeout_s
        )
        waiting = asyncio.ensure_future(co.wait_ready(ready_timeout))
        if not await _race(waiting, interrupted):
            await _cancel(waiting)
            co.command("abort")
            await co.bus.sync()
            print("interrupted before start: abort published", file=sys.stderr)
            return EXIT_INTERRUPTED
        co.command("start")
        co.t_start_wall = time.time()
        await co.bus.sync()
        print(f"run {run}: start published ({co.vehicles} vehicles ready)", file=sys.stderr)
        if not args.wait:
            return EXIT_OK
        timeout = (
            args.timeout
            if args.timeout is not None
            else cfg.arm_timeout_s
            + cfg.takeoff_timeout_s
            + cfg.mission_timeout_s
            + cfg.land_timeout_s
        )
        out = args.out if args.out is not None else Path("runs") / co.mission_id
        recorder = _recorder(args, out)
        mon = RunMonitor(
            co.mission, co.vehicles, recorder=recorder, t0_s=co.t_start_wall or time.time()
        )
        if recorder is not None:
            mon._record(
                "log_scene",
                co.mission.with_vehicles(co.vehicles),
                None,
                meta={
                    "kind": "mqtt",
                    "rate_hz": cfg.rate_hz,
                    "run_id": run,
                    "broker": args.broker,
                    "vehicles": co.vehicles,
                },
            )
        outcome = "failed"
        try:
            follow = asyncio.ensure_future(co.follow(timeout, mon))
            if await _race(follow, interrupted):
                outcome = follow.result()
            else:
                await _cancel(follow)
                co.command("abort")
                await co.bus.sync()
                print("interrupted: abort published; the agents hold, then land", file=sys.stderr)
                outcome = "interrupted"
        finally:  # the summary (and the recording) on every exit path
            summary = mon.summary(
                mission_id=co.mission_id,
                run_id=run,
                config_hash=co.config_hash,
                broker=args.broker,
                outcome=outcome,
                lost=co.lost_vehicles(),
                vehicle_states=co.vehicle_table(),
                wall_s=round(time.time() - (co.t_start_wall or time.time()), 3),
            )
            v = verdict(summary)
            if not v.safe:  # THE verdict: a broken limit makes the run unsafe, whatever else
                summary["outcome"] = outcome = "unsafe"
                summary["reason"] = v.summary_line
            path = write_summary(out, summary)
            if recorder is not None:
                mon._record("log_summary", summary)
                mon._record("close")
        print(
            f"{outcome}: {summary.get('exited')}/{co.vehicles} exited; min pair distance "
            f"{_fmt(summary.get('min_pair_distance_m'))} (2 r_s = {summary['pair_limit_m']:.2f} m),"
            f" obstacle centre {_fmt(summary.get('min_obstacle_center_distance_m'))}, "
            f"violations {summary.get('violations')}; state age p50/p99 "
            f"{_fmt(summary.get('state_age_p50_s'), 'ms', 1000)}/"
            f"{_fmt(summary.get('state_age_p99_s'), 'ms', 1000)}; summary {path}",
            file=sys.stderr,
        )
        if outcome == "unsafe":
            print(f"error: mission unsafe: {summary['reason']}", file=sys.stderr)
            return EXIT_UNSAFE
        if outcome == "interrupted":
            return EXIT_INTERRUPTED
        return EXIT_OK if outcome == "completed" else EXIT_INCOMPLETE


def _recorder(args: argparse.Namespace, out: Path) -> Any:
    """The fleet recording of ``start --wait`` (``--rerun-save``, default OUT/recording.rrd)."""
    from vtube_fleet.cli._args import recorder_from_args

    # exits only as RunMonitor decides them (from every state heard, also between two ticks)
    return recorder_from_args(args, out, kind="fleet", app_id="vtube_fleet",
                              detect_exits=False)


def _fmt(v: float | None, unit: str = "m", scale: float = 1.0) -> str:
    return "—" if v is None else f"{v * scale:.2f} {unit}"


async def _race(task: asyncio.Future[Any], event: asyncio.Event) -> bool:
    """Wait for ``task`` or ``event``, whichever comes first; True if ``task`` finished
    (its exception, if any, is raised). The task is left running otherwise."""
    waiter = asyncio.ensure_future(event.wait())
    try:
        done, _ = await asyncio.wait({task, waiter}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        waiter.cancel()
    if task in done:
        task.result()
        return True
    return False


async def _cancel(task: asyncio.Future[Any]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


async def _abort(args: argparse.Namespace) -> int:
    async with Coordinator(
        args.mission, args.broker, mission_id=args.mission_id, broker_timeout_s=args.broker_timeout
    ) as co:
        await co.bus.sync()
        cfg = co.bus.config
        if cfg is None:
            raise MissionRunError(
                f"no run of mission {co.mission_id} announced on {args.broker} (nothing to abort)"
            )
        co.run_id = cfg.run_id
        co.command("abort")
        await co.bus.sync()
        print(f"mission {co.mission_id} run {cfg.run_id}: abort published", file=sys.stderr)
    return EXIT_OK


async def _status(args: argparse.Namespace) -> int:
    async with Coordinator(
        args.mission, args.broker, mission_id=args.mission_id, broker_timeout_s=args.broker_timeout
    ) as co:
        await co.bus.sync()
        cfg = co.bus.config
        if cfg is not None:
            co.run_id = cfg.run_id
            co.vehicles = max(co.vehicles, cfg.vehicles) if cfg.vehicles else co.vehicles
        with contextlib.suppress(TimeoutError):  # listen a moment for live states
            await co.bus.wait_for(lambda: False, args.listen)
        rows = co.vehicle_table()
        cmd = co.bus.command
        info = {
            "mission_id": co.mission_id,
            "broker": args.broker,
            "config_hash": co.config_hash,
            "run": None
            if cfg is None
            else {
                "run_id": cfg.run_id,
                "config_hash": cfg.config_hash,
                "hash_matches": cfg.config_hash == co.config_hash,
                "vehicles": cfg.vehicles,
                "announced_s_ago": round(time.time() - cfg.stamp_s, 1),
                "source": cfg.source,
            },
            "command": None
            if cmd is None
            else {
                "command": cmd.command,
                "run_id": cmd.run_id,
                "s_ago": round(time.time() - cmd.stamp_s, 1),
            },
            "vehicles": rows,
        }
    if args.json:
        print(json.dumps(info, indent=2))
        return EXIT_OK
    print(f"mission {co.mission_id} on {args.broker} (this file's config hash {co.config_hash})")
    if cfg is None:
        print("  no run announced")
    else:
        r = info["run"]
        print(
            f"  run {cfg.run_id}: {cfg.vehicles} vehicles, hash {cfg.config_hash}"
            f"{'' if r['hash_matches'] else ' (DIFFERS from this file)'}, announced "
            f"{r['announced_s_ago']} s ago from {cfg.source}"
        )
    if cmd is not None:
        print(f"  last command: {cmd.command} (run {cmd.run_id}, {info['command']['s_ago']} s ago)")
    print(
        f"  {'id':>3} {'status':<8} {'stage':<12} {'phase':<11} {'x_m':>8} {'y_m':>8} {'age_s':>7}"
    )
    for r in rows:

        def f(v: Any, fmt: str) -> str:
            return "-" if v is None else format(v, fmt)

        print(
            f"  {r['id']:>3} {f(r['status'], '<8')} {f(r['stage'] or '', '<12')} "
            f"{f(r['phase'], '<11')} {f(r['x_m'], '8.2f')} {f(r['y_m'], '8.2f')} "
            f"{f(r['age_s'], '7.1f')}"
        )
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
            type=float,
            default=10.0,
            metavar="S",
            help="seconds to wait for the broker connection (default 10)",
        )
        sp.set_defaults(func=_cmd)

    s = sub.add_parser("start", help="announce a run, wait for every agent, publish start")
    common(s)
    s.add_argument(
        "--vehicles",
        type=int,
        default=None,
        help="fly slots 0..N-1 only (default: every slot of the mission)",
    )
    s.add_argument(
        "--max-age",
        type=float,
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
        type=float,
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
    from vtube_fleet.cli._args import add_recording_args

    add_recording_args(s)
    s.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder of --wait (default: runs/<mission id>)",
    )
    s.add_argument(
        "--timeout",
        type=float,
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
        type=float,
        default=1.0,
        metavar="S",
        help="seconds to listen for live states (default 1)",
    )
    st.add_argument("--json", action="store_true", help="print JSON")
