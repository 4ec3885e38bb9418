"""``vtube-fleet check``: validate a scenario or a mission file and print its partition
(the library function: :func:`vtube_fleet.check.check_file`)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from vtube_fleet.cli._args import bounded
from vtube_fleet.config.keys import Bound, Key
from vtube_fleet.fleet.budget import PX4_SITL_ACCURACY_M, PX4_SITL_LATENCY_S
from vtube_fleet.outcome import EXIT_ERROR

__all__ = [
    "ACCURACY_M",
    "LATENCY_S",
    "cmd_check",
    "register",
]

#: ``--latency-s``: a latency L the vehicles would measure, within [0, 10] s (a mission refuses
#: far less before arming: its ``max_latency_s``, default 0.25 s).
LATENCY_S = Key("latency_s", "number", "a link latency", "s",
                bound=Bound(0.0, 10.0, low_inclusive=True,
                            why="no link to fly a swarm on; missions refuse L > max_latency_s"))
#: ``--accuracy-m``: a position accuracy σ the vehicles would report, within [0, 100] m (a
#: mission waits for far less: its ``max_position_accuracy_m``, default 1 m).
ACCURACY_M = Key("accuracy_m", "number", "a position accuracy", "m",
                 bound=Bound(0.0, 100.0, low_inclusive=True,
                             why="no position fix; missions wait for σ <= "
                                 "max_position_accuracy_m"))


def cmd_check(args: argparse.Namespace) -> int:
    from vtube_fleet.check import check_file

    report = check_file(args.config, latency_s=args.latency_s, accuracy_m=args.accuracy_m,
                        fixes=not args.no_fixes)
    for line in report.lines:
        print(line)
    for line in report.verdict_lines():
        print(line)
    if report.ok:
        return 0
    sys.stdout.flush()  # the report first, then the one error line (README: user errors)
    print(f"error: {report.error_line()}", file=sys.stderr)
    return EXIT_ERROR


def register(subparsers: Any) -> None:
    """Add the ``check`` sub-command."""
    p = subparsers.add_parser(
        "check",
        help="validate a scenario or a mission and print its partition",
        description="Validate a scenario or mission TOML against the paper's conditions and "
        "print the partition into sub-tubes (exit 0 if valid; otherwise the report, then one "
        "line 'error: …' on stderr naming the first violation, and exit 2). A mission is "
        "checked with the flown radii r_s', r_a' of its safety budget, and its margin is "
        "printed: the largest link latency L and accuracy σ it still validates with. When no "
        "partition "
        "exists, the binding constraints and the nearest single changes that fix it are "
        "printed.",
    )
    p.add_argument("config", help="scenario or mission TOML file (docs/config.md)")
    p.add_argument("--latency-s", type=bounded(LATENCY_S), default=None, metavar="S",
                   help="missions: the link latency the vehicles would measure (position age "
                        f"+ setpoint delay; default {PX4_SITL_LATENCY_S:g}: what PX4 SITL "
                        "measures; the mission's latency_headroom_s is added)")
    p.add_argument("--accuracy-m", type=bounded(ACCURACY_M), default=None, metavar="M",
                   help="missions: the position accuracy σ the vehicles would report "
                        f"(default {PX4_SITL_ACCURACY_M:g}: what PX4 SITL reports; RTK: ~0.02)")
    p.add_argument("--no-fixes", action="store_true",
                   help="do not search for the nearest fixes of an infeasible partition")
    p.set_defaults(func=cmd_check)
