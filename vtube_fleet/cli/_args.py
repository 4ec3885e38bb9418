"""Command-line options shared by several commands (argparse only; no library code)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from vtube_fleet.fleet.distributed.coordinator import DEFAULT_BROKER
from vtube_fleet.recording.api import Recorder, RecordingError
from vtube_fleet.recording.layout import (
    DEFAULT_CONNECT_URL,
    DEFAULT_RECORDING_NAME,
    SIM_MIN_PERIOD_S,
)
from vtube_fleet.recording.writer import open_recorder

__all__ = [
    "add_bus_args",
    "add_recording_args",
    "recorder_from_args",
]


def add_bus_args(parser: argparse.ArgumentParser) -> None:
    """``--broker`` and ``--mission-id``, the same for ``vtube-fleet agent`` and ``mission``."""
    parser.add_argument(
        "--broker", default=DEFAULT_BROKER, help=f"MQTT broker URL (default {DEFAULT_BROKER})"
    )
    parser.add_argument(
        "--mission-id", default=None, help="topic name of the mission (default: the file name)"
    )


def add_recording_args(parser: argparse.ArgumentParser, *, default_decimate: int | None = None
                       ) -> None:
    """Add ``--rerun-save``, ``--rerun-connect``, ``--rerun-decimate`` and ``--no-rerun``."""
    g = parser.add_argument_group("recording (rerun)")
    g.add_argument("--rerun-save", metavar="PATH", type=Path, default=None,
                   help=f"write the rerun recording here (default: OUT/{DEFAULT_RECORDING_NAME})")
    g.add_argument("--rerun-connect", metavar="ADDR", nargs="?", const=DEFAULT_CONNECT_URL,
                   default=None,
                   help="also stream to a live rerun viewer (default address "
                        f"{DEFAULT_CONNECT_URL}; HOST:PORT or a port also work)")
    g.add_argument("--rerun-decimate", metavar="N", type=int, default=default_decimate,
                   help="record every N-th control tick / simulation step "
                        "(default: each command's own choice)")
    g.add_argument("--no-rerun", action="store_true",
                   help="do not write a recording (and ignore --rerun-save)")


def recorder_from_args(
    args: argparse.Namespace,
    out_dir: str | os.PathLike[str] | None,
    *,
    kind: str = "sim",
    app_id: str = "vtube_fleet",
    decimate: int = 1,
    **options: Any,
) -> Recorder:
    """The recorder the command line asks for (see :func:`add_recording_args`).

    ``decimate`` is used unless ``--rerun-decimate`` was given. For ``kind="sim"`` without
    ``--rerun-decimate``, frames are recorded at most every :data:`SIM_MIN_PERIOD_S` of
    simulated time (25 per simulated second: smooth in the viewer, a fraction of the cost of
    the simulator's 100 frames/s); ``--rerun-decimate N`` counts the simulator's own frames
    instead. Without ``--rerun-save`` the file is ``out_dir/recording.rrd`` (no file when
    ``out_dir`` is ``None``).
    """
    if getattr(args, "no_rerun", False):
        save = None
    else:
        save = getattr(args, "rerun_save", None)
        if save is None and out_dir is not None:
            save = Path(out_dir) / DEFAULT_RECORDING_NAME
    connect = getattr(args, "rerun_connect", None)
    dec = getattr(args, "rerun_decimate", None)
    if dec is None:
        dec = decimate
        if kind == "sim":
            options.setdefault("min_period_s", SIM_MIN_PERIOD_S)
    if not (isinstance(dec, int) and dec >= 1):
        raise RecordingError(f"--rerun-decimate must be an integer >= 1, got {dec}")
    if kind == "sim":
        # The simulator is one CPU-bound thread: a sender thread would only fight it for the
        # GIL (measured: up to +0.5 s on the 1.2 s paper loop); sending in-line costs little.
        options.setdefault("background", False)
    return open_recorder(save, connect=connect, app_id=app_id, decimate=dec, kind=kind,
                         **options)
