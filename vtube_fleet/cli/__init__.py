"""Command-line entry point ``vtube-fleet``.

Each sub-command lives in its own module that exposes ``register(subparsers)``; the module adds
its parser and sets ``func`` (a callable ``func(args) -> int`` returning the exit code). This file
only dispatches and turns :class:`~vtube_fleet.errors.UserError` into a one-line error.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from vtube_fleet import __version__
from vtube_fleet.cli._args import OneLineParser, annotate_help
from vtube_fleet.errors import UserError

__all__ = ["main", "build_parser"]

#: Modules that register sub-commands, in the order they appear in ``--help``.
COMMAND_MODULES: tuple[str, ...] = (
    "vtube_fleet.cli.check",
    "vtube_fleet.cli.sim",
    "vtube_fleet.cli.run",
    "vtube_fleet.cli.mock_fleet",
    "vtube_fleet.cli.sitl_homes",
    "vtube_fleet.cli.sitl",
    "vtube_fleet.cli.review",
    "vtube_fleet.cli.agent",
    "vtube_fleet.cli.mission",
    "vtube_fleet.cli.bus_setup",
    "vtube_fleet.cli.sign_setup",
)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="vtube-fleet",
        description="Fly a swarm through a trapezoid virtual tube containing obstacles.",
    )
    parser.add_argument("--version", action="version", version=f"vtube-fleet {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    annotate_help(parser)  # each declared option's unit and bound, from its key
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # stdout closed early (e.g. `vtube-fleet review run.rrd --json | head`): not an error
        # of ours; silence the interpreter's flush at exit too.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
