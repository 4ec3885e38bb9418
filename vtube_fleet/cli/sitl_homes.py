"""``vtube-fleet sitl-homes``: ``PX4_HOME_*`` for each PX4 SITL instance of a mission."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from vtube_fleet.cli._args import COUNT, bounded
from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.launch import sitl_home_lines

__all__ = ["register"]


def _cmd_sitl_homes(args: argparse.Namespace) -> int:
    for line in sitl_home_lines(load_mission(args.mission), args.count):
        print(line)
    return 0


def register(subparsers: Any) -> None:
    h = subparsers.add_parser(
        "sitl-homes", help="print PX4_HOME_* for each PX4 SITL instance of a mission",
        description="One line per instance: 'I PX4_HOME_LAT=… PX4_HOME_LON=… PX4_HOME_ALT=…' "
                    "so that PX4 SITL instance I starts in slot I.")
    h.add_argument("mission", type=Path)
    h.add_argument("--count", type=bounded(COUNT), default=None,
                   help="the first N slots only (default: every slot)")
    h.set_defaults(func=_cmd_sitl_homes)
