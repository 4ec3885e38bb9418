"""Command-line options shared by several commands (argparse only; no library code).

Every numeric option is declared with a :class:`~vtube_fleet.config.keys.Key` (type, unit,
bounds, meaning) and parsed by :class:`OptionType`, so ``--join-timeout nan``, ``-5`` or ``inf``
is refused with one line naming the option, the value and the bound, before anything connects.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
from pathlib import Path
from typing import Any, NoReturn

from vtube_fleet.config.keys import POSITIVE, Bound, Key
from vtube_fleet.fleet.distributed.coordinator import DEFAULT_BROKER
from vtube_fleet.fleet.sitl import (
    DEFAULT_ANSWER_TIMEOUT_S,
    DEFAULT_PX4_MODEL,
    InstanceCommand,
    SitlError,
    command_template,
    px4_command,
)
from vtube_fleet.recording.api import Recorder, RecordingError
from vtube_fleet.recording.layout import (
    DEFAULT_CONNECT_URL,
    DEFAULT_RECORDING_NAME,
    SIM_MIN_PERIOD_S,
)
from vtube_fleet.recording.live import DEFAULT_BIND, DEFAULT_WEB_PORT
from vtube_fleet.recording.writer import open_recorder

__all__ = [
    "COUNT",
    "DURATION",
    "INDEX",
    "PORT",
    "WEB_PORT",
    "SCALE",
    "SEED",
    "OneLineParser",
    "OptionType",
    "add_bus_args",
    "check_out_dir",
    "add_fence_arg",
    "add_sitl_args",
    "sitl_command_from_args",
    "annotate_help",
    "declared_options",
    "options_table",
    "add_recording_args",
    "bounded",
    "recorder_from_args",
]

#: A duration in seconds (timeouts, waits, ages): finite and > 0 (NaN would wait forever, a
#: negative one fail at once with a misleading cause).
DURATION = Key("duration", "number", "a duration", "s", bound=POSITIVE)
#: A scale factor (e.g. of the mock's boot timeline): finite and > 0.
SCALE = Key("scale", "number", "a scale factor", bound=POSITIVE)
#: A count of vehicles, ticks, …: an integer >= 1.
COUNT = Key("count", "integer", "a count", bound=Bound(1, low_inclusive=True))
#: A 0-based index (a slot): an integer >= 0.
INDEX = Key("index", "integer", "a 0-based index", bound=Bound(0, low_inclusive=True))
#: A UDP port.
PORT = Key("port", "integer", "a UDP port", bound=Bound(1, 65535, low_inclusive=True))
#: The web viewer's TCP port (its data on the next port up).
WEB_PORT = Key("port", "integer", "a TCP port (the next one up is used too)",
               bound=Bound(1, 65534, low_inclusive=True))
#: A random seed (numpy: 0 .. 2^32 - 1).
SEED = Key("seed", "integer", "a random seed", bound=Bound(0, 2**32 - 1, low_inclusive=True))


class OptionType:
    """The argparse ``type`` of a declared option: text → the :class:`Key`'s checked value;
    a refusal names the value and the bound (argparse adds the option's name)."""

    def __init__(self, key: Key) -> None:
        self.key = key
        self.__name__ = key.name  # argparse names the type in some messages

    def __call__(self, text: str) -> Any:
        integer = self.key.kind == "integer"
        try:
            value: Any = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'an integer' if integer else 'a number'}, got {text!r}") from None
        try:
            return self.key.parse(value)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    def __repr__(self) -> str:
        return f"OptionType({self.key.name})"


def bounded(key: Key) -> OptionType:
    """The argparse type of options declared by ``key`` (:data:`DURATION`, :data:`COUNT`, …)."""
    return OptionType(key)


def _parsers(parser: argparse.ArgumentParser, prefix: str
             ) -> list[tuple[str, argparse.ArgumentParser]]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    out = [(prefix, parser)]
    for sub in subs:
        for name, p in sub.choices.items():
            out += _parsers(p, f"{prefix} {name}")
    return out


def declared_options(parser: argparse.ArgumentParser
                     ) -> list[tuple[str, str, Key, str]]:
    """(command, option, key, help) of every option declared with an :class:`OptionType`
    below ``parser`` (the whole ``vtube-fleet`` command line)."""
    out = []
    for prog, p in _parsers(parser, parser.prog):
        for a in p._actions:
            if isinstance(a.type, OptionType) and a.option_strings:
                help_ = getattr(a, "plain_help", a.help)  # (before annotate_help)
                out.append((prog, a.option_strings[-1], a.type.key, help_ or ""))
    return out


def bound_text(key: Key) -> str:
    """``s, > 0`` / ``integer, [1, 65535]``: the unit (or the kind) and the bound of ``key``."""
    assert key.bound is not None
    kind = key.unit or ("integer" if key.kind == "integer" else "number")
    return f"{kind}, {key.bound.text()}"


def annotate_help(parser: argparse.ArgumentParser) -> None:
    """Append each declared option's unit and bound to its ``--help`` text (from its key)."""
    for _prog, p in _parsers(parser, parser.prog):
        for a in p._actions:
            if (isinstance(a.type, OptionType) and a.help is not argparse.SUPPRESS
                    and not hasattr(a, "plain_help")):
                a.plain_help = a.help  # type: ignore[attr-defined]
                a.help = f"{a.help or ''} [{bound_text(a.type.key)}]".lstrip()


def options_table(parser: argparse.ArgumentParser, commands: tuple[str, ...]) -> str:
    """The docs' table of the declared options of ``commands`` (e.g. ``("run", "agent")``):
    command, option, unit, bounds, meaning — generated from the parser (docs/fleet.md)."""
    rows = ["| command | option | unit | bounds | meaning |", "|---|---|---|---|---|"]
    for prog, opt, key, help_ in declared_options(parser):
        words = prog.split()
        if len(words) < 2 or words[1] not in commands:
            continue
        meaning = " ".join(help_.replace("|", "\\|").split())
        rows.append(f"| `{prog}` | `{opt}` | {key.unit} | {key.bound_cell()} | {meaning} |")
    return "\n".join(rows) + "\n"


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line, ``error: PROG: MESSAGE (see PROG
    --help)``, exit 2, like every other user error of the command line."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {self.prog}: {' '.join(message.split())} "
                     f"(see {self.prog} --help)\n")


def add_bus_args(parser: argparse.ArgumentParser) -> None:
    """``--broker`` and ``--mission-id``, the same for ``vtube-fleet agent`` and ``mission``."""
    parser.add_argument(
        "--broker", default=DEFAULT_BROKER, help=f"MQTT broker URL (default {DEFAULT_BROKER})"
    )
    parser.add_argument(
        "--mission-id", default=None, help="topic name of the mission (default: the file name)"
    )
    parser.add_argument(
        "--credentials", type=Path, default=None, metavar="FILE",
        help="this client's broker user, password and CA (a file written by `vtube-fleet "
        "bus-setup`, mode 0600; use with --broker mqtts://HOST:8883)",
    )
    parser.add_argument(
        "--insecure", action="store_true",
        help="allow a plain mqtt:// broker that is not on this machine (no TLS: anyone on the "
        "network can read and forge the fleet's messages)",
    )


def add_fence_arg(parser: argparse.ArgumentParser) -> None:
    """``--no-fence``, the same for ``vtube-fleet run`` (every vehicle) and ``agent`` (its one)."""
    parser.add_argument(
        "--no-fence", action="store_true",
        help="do not upload the tube as the vehicles' PX4 geofence (for setups that forbid "
        "it; a warning says so; docs/fleet.md)",
    )


def add_sitl_args(parser: argparse.ArgumentParser, *, binary: str, prefix: str,
                  required: bool) -> None:
    """The options that start a SITL fleet (``fleet/sitl.py``): ``binary`` (``--px4`` for
    ``sitl``, ``--sitl`` for ``run``) or ``--{prefix}command``, and ``--{prefix}model``,
    ``--{prefix}api-port``, ``--{prefix}vehicle-port``, ``--{prefix}timeout``."""
    g = parser.add_argument_group("SITL fleet (docs/sitl.md)")
    which = g.add_mutually_exclusive_group(required=required)
    which.add_argument(
        binary, dest="sitl_px4", type=Path, default=None, metavar="PATH/TO/px4",
        help="start one PX4 SITL instance per slot with this binary (PX4-Autopilot/build/"
        "px4_sitl_default/bin/px4): instance i in slot i, API port 14540+i")
    which.add_argument(
        f"--{prefix}command", dest="sitl_command", default=None, metavar="'PROG ARGS…'",
        help="start instance i with this command instead of PX4 (split like a shell would; "
        "placeholders {instance}, {sysid}, {home_lat}, {home_lon}, {home_alt}, {api_port}, "
        "{api_port_base}, {vehicle_port}, {vehicle_port_base}, {workdir}; PX4_HOME_* are set "
        "too)")
    g.add_argument(f"--{prefix}model", dest="sitl_model", default=None, metavar="NAME",
                   help=f"PX4_SIM_MODEL of the PX4 instances (default {DEFAULT_PX4_MODEL}: the "
                        f"SIH quadrotor, no Gazebo)")
    g.add_argument(f"--{prefix}api-port", dest="sitl_api_port", type=bounded(PORT),
                   default=None, metavar="N",
                   help="with the command: instance i's API link is N+i on our side (default "
                        "14540, PX4's)")
    g.add_argument(f"--{prefix}vehicle-port", dest="sitl_vehicle_port", type=bounded(PORT),
                   default=None, metavar="N",
                   help="with the command: instance i binds N+i itself (default 14580, PX4's)")
    g.add_argument(f"--{prefix}timeout", dest="sitl_timeout_s", type=bounded(DURATION),
                   default=DEFAULT_ANSWER_TIMEOUT_S, metavar="S",
                   help="every instance must answer (a MAVLink HEARTBEAT on its API port) "
                        f"within S seconds of its start (default {DEFAULT_ANSWER_TIMEOUT_S:g})")
    parser.set_defaults(sitl_options=(binary, f"--{prefix}"))


def sitl_command_from_args(args: argparse.Namespace) -> InstanceCommand | None:
    """The instance command the options of :func:`add_sitl_args` ask for, or None."""
    binary, pre = getattr(args, "sitl_options", ("--px4", "--"))
    if args.sitl_px4 is not None:
        for opt, value in (("api-port", args.sitl_api_port),
                           ("vehicle-port", args.sitl_vehicle_port)):
            if value is not None:
                raise SitlError(f"{pre}{opt} goes with {pre}command: PX4 SITL instance i "
                                f"always uses 14540+i and 14580+i")
        return px4_command(args.sitl_px4, args.sitl_model or DEFAULT_PX4_MODEL)
    if args.sitl_command is not None:
        if args.sitl_model is not None:
            raise SitlError(f"{pre}model goes with {binary} (PX4_SIM_MODEL); give the command "
                            f"its model itself")
        return command_template(args.sitl_command, api_port_base=args.sitl_api_port,
                                vehicle_port_base=args.sitl_vehicle_port,
                                option=f"{pre}command")
    for opt, value in (("model", args.sitl_model), ("api-port", args.sitl_api_port),
                       ("vehicle-port", args.sitl_vehicle_port)):
        if value is not None:
            raise SitlError(f"{pre}{opt} without {binary} or {pre}command: no SITL fleet to "
                            f"start")
    return None


def add_recording_args(parser: argparse.ArgumentParser, *, default_decimate: int | None = None
                       ) -> None:
    """Add ``--rerun-save``, ``--rerun-connect``, ``--rerun-serve-web`` (alias ``--serve-web``),
    ``--rerun-bind``, ``--rerun-viewer`` (alias ``--viewer``), ``--rerun-decimate`` and
    ``--no-rerun``."""
    g = parser.add_argument_group("recording (rerun)")
    g.add_argument("--rerun-save", metavar="PATH", type=Path, default=None,
                   help=f"write the rerun recording here (default: OUT/{DEFAULT_RECORDING_NAME})")
    g.add_argument("--rerun-connect", metavar="ADDR", nargs="?", const=DEFAULT_CONNECT_URL,
                   default=None,
                   help="also stream to a live rerun viewer (default address "
                        f"{DEFAULT_CONNECT_URL}; HOST:PORT or a port also work)")
    g.add_argument("--rerun-serve-web", "--serve-web", metavar="PORT", nargs="?",
                   type=bounded(WEB_PORT), const=DEFAULT_WEB_PORT, default=None,
                   help="serve the live view to a browser: the rerun web viewer on PORT "
                        f"(default {DEFAULT_WEB_PORT}), its data (gRPC) on PORT + 1; the URL to "
                        "open is printed at the start (docs/recording.md)")
    g.add_argument("--rerun-bind", metavar="ADDR", default=DEFAULT_BIND,
                   help="address --rerun-serve-web listens on (default "
                        f"{DEFAULT_BIND}: this machine only; 0.0.0.0: every interface, for a "
                        "browser on another computer)")
    g.add_argument("--rerun-viewer", "--viewer", action="store_true",
                   help="spawn the native rerun viewer and stream to it (it stays open after "
                        "the run; needs a display); on the port --rerun-connect names, else "
                        "9876; a viewer already listening there is used")
    g.add_argument("--rerun-decimate", metavar="N", type=bounded(COUNT), default=default_decimate,
                   help="record every N-th control tick / simulation step "
                        "(default: each command's own choice)")
    g.add_argument("--no-rerun", action="store_true",
                   help="do not write a recording (and ignore --rerun-save)")


def check_out_dir(out: str | os.PathLike[str], option: str = "--out") -> None:
    """Raise :class:`~vtube_fleet.errors.UserError` unless ``out`` can hold a run's files: an
    existing folder, or one that can be made, in which a file can be written. Tried for real
    (missing folders made, a probe file written, then all of it removed again: nothing is
    left behind by a run refused later), so that a command never finds out at its end that its
    summary cannot be written (as root, ``os.access`` says yes to /proc)."""
    from vtube_fleet.errors import UserError

    path = Path(out)
    if path.exists() and not path.is_dir():
        raise UserError(f"{option} {path}: exists and is not a folder")
    made: list[Path] = []  # the folders made here, deepest first
    p = path
    while not p.exists() and p != p.parent:
        made.append(p)
        p = p.parent
    try:
        for d in reversed(made):
            d.mkdir()
        fd, probe = tempfile.mkstemp(dir=path, prefix=".vtube-fleet-write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UserError(f"{option} {path}: cannot write there: {exc.strerror or exc}") from None
    finally:
        for d in made:
            with contextlib.suppress(OSError):
                d.rmdir()


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
    serve = getattr(args, "rerun_serve_web", None)
    if serve is not None:
        options.update(serve_web=serve, serve_bind=getattr(args, "rerun_bind", DEFAULT_BIND))
    if getattr(args, "rerun_viewer", False):
        # the viewer is spawned where --rerun-connect points (this machine; default port 9876)
        from urllib.parse import urlparse

        from vtube_fleet.recording.writer import normalize_connect_url

        u = urlparse(normalize_connect_url(connect))
        if u.hostname not in ("127.0.0.1", "localhost", "::1"):
            raise RecordingError(f"--rerun-viewer starts the viewer on this machine: "
                                 f"--rerun-connect {connect} is not a local address")
        options.update(viewer=True, viewer_port=u.port or 9876)
        connect = None
    rec = open_recorder(save, connect=connect, app_id=app_id, decimate=dec, kind=kind,
                        **options)
    web = getattr(rec, "web", None)
    if web is not None:
        print(f"live view: open {web.url} in a browser (the rerun web viewer; the page on port "
              f"{web.web_port}, its data on port {web.grpc_port}, listening on {web.bind})",
              file=sys.stderr, flush=True)
    if getattr(rec, "viewer_url", None) is not None:
        print(f"live view: streaming to the rerun viewer at {rec.viewer_url}"  # type: ignore
              + ("" if getattr(rec, "viewer_pid", None) is None
                 else f" (started, process {rec.viewer_pid})"), file=sys.stderr, flush=True)
    return rec
