"""``vtube-fleet sitl``: start one PX4 SITL instance per slot of a mission, wait until every
one answers, print the endpoints, and stop them all on Ctrl-C (the library:
:mod:`vtube_fleet.fleet.sitl`)."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any

from vtube_fleet.cli._args import COUNT, add_sitl_args, bounded, sitl_command_from_args
from vtube_fleet.cli._signals import interrupt_on_signals
from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.sitl import SitlFleet, instance_lines, sitl_fleet

__all__ = ["register"]


def _say(text: str) -> None:
    print(text, flush=True)


def _cmd_sitl(args: argparse.Namespace) -> int:
    mission = load_mission(args.mission)
    command = sitl_command_from_args(args)
    assert command is not None  # (argparse: --px4 or --command is required)
    out = args.out if args.out is not None else Path("runs") / Path(args.mission).stem
    holder: list[SitlFleet] = []

    async def main() -> int:
        task = asyncio.current_task()
        assert task is not None
        stop = asyncio.Event()
        signals: list[str] = []
        serving = False

        def on_signal(name: str) -> None:
            signals.append(name)
            if serving:
                stop.set()
            else:  # still starting: give up, stop what runs (a second one: at once)
                task.cancel()

        def started(fleet: SitlFleet) -> None:
            _say(f"sitl: {fleet.count} {command.name} instances for {mission.source} under "
                 f"{fleet.out_dir} (waiting up to {args.sitl_timeout_s:g} s for each to "
                 f"answer):")
            for line in instance_lines(fleet):
                _say(line)

        with interrupt_on_signals(on_signal):
            try:
                async with sitl_fleet(mission, command, out / "sitl", count=args.count,
                                      answer_timeout_s=args.sitl_timeout_s, on_start=started,
                                      holder=holder) as fleet:
                    _say("sitl: every instance answers:")
                    for line in instance_lines(fleet, answered=True):
                        _say(line)
                    urls = ",".join(fleet.endpoints)
                    _say(f"endpoints: {urls}")
                    _say(f"fly them: vtube-fleet run {args.mission} --truth --endpoints {urls}")
                    _say("Ctrl-C stops them (instances.json and each instance's log: "
                         f"{fleet.out_dir})")
                    serving = True
                    watch = asyncio.ensure_future(fleet.watch())
                    stopped = asyncio.ensure_future(stop.wait())
                    try:
                        await asyncio.wait({watch, stopped}, return_when=asyncio.FIRST_COMPLETED)
                    finally:
                        for f in (watch, stopped):
                            f.cancel()
                    if not stop.is_set():
                        died = watch.result()
                        print(f"error: {command.name} instance {died.index} (pid {died.pid}) "
                              f"exited with code {died.process.returncode if died.process else '?'}"
                              f"; its log: {died.log_path}; stopping the others",
                              file=sys.stderr, flush=True)
                        return 1
                    _say(f"sitl: {signals[-1]}: stopping {fleet.count} instances")
            except asyncio.CancelledError:
                print(f"sitl: {signals[-1] if signals else 'cancelled'} while starting: "
                      f"instances stopped", file=sys.stderr, flush=True)
                return 130
        _say("sitl: stopped")
        return 0

    try:
        return asyncio.run(main())
    finally:
        for fleet in holder:  # the last resort if the event loop died before stop() ran
            fleet.kill_now()


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "sitl", help="start one PX4 SITL instance per slot of a mission (Ctrl-C stops them)",
        description="Start one PX4 SITL instance per slot of MISSION (SIH by default): "
                    "instance i in slot i (PX4_HOME_* as sitl-homes prints), in its own "
                    "working directory OUT/sitl/instance-I with its log beside it, API port "
                    "14540+i. Wait until every instance answers (a MAVLink HEARTBEAT), print "
                    "the endpoints for `run --endpoints`, and stop them all on Ctrl-C. "
                    "(`run --sitl PATH` does this and flies.)")
    p.add_argument("mission", type=Path, help="mission file (scenario + [mission])")
    add_sitl_args(p, binary="--px4", prefix="", required=True)
    p.add_argument("--count", type=bounded(COUNT), default=None,
                   help="the first N slots only (default: every slot)")
    p.add_argument("--out", type=Path, default=None,
                   help="output folder: the instances go to OUT/sitl (default: runs/<mission "
                        "name>, as `run`'s)")
    p.set_defaults(func=_cmd_sitl)
