"""``vtube-fleet sim``: the offline simulator, its output files and its summary."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from vtube_fleet.artifacts import write_sim_outputs
from vtube_fleet.cli._args import COUNT, add_recording_args, bounded, check_out_dir
from vtube_fleet.config.scenario import scenario_key
from vtube_fleet.core.integrate import INTEGRATORS
from vtube_fleet.outcome import EXIT_INTERRUPTED, EXIT_OK, EXIT_SIM_UNFINISHED

__all__ = [
    "cmd_sim",
    "print_summary",
    "register",
]

def register(subparsers: Any) -> None:
    """Add the ``sim`` sub-command."""
    s = subparsers.add_parser(
        "sim",
        help="run the offline simulator",
        description="Simulate the swarm and write summary.json, trajectory.npz, metrics.npz "
        "and PNG plots. Exit code 0 when every robot exited with every limit kept, 1 when "
        "robots were left in the tube or a limit was broken, 2 for a user error, 130 for "
        "Ctrl-C.",
    )
    s.add_argument("config", help="scenario TOML file (see docs/config.md)")
    s.add_argument("--out", metavar="DIR", default=None,
                   help="output directory (default: sim_out/<config name>_<controller>)")
    s.add_argument("--dt", type=bounded(scenario_key("sim", "dt")), metavar="S", default=None,
                   help="time step in seconds (default: [sim].dt of the config)")
    s.add_argument("--integrator", choices=INTEGRATORS, default=None,
                   help="adaptive = Euler, with steps cut in halves while a barrier margin "
                   "(pair, leg, obstacle) would lose more than half of what is left; rk4 = "
                   "classical Runge-Kutta (single integrator); euler = plain forward Euler "
                   "(default: [sim].integrator of the config, else adaptive)")
    s.add_argument("--uncertified", action="store_true",
                   help="simulate a scenario that fails validation anyway, with the triangles "
                   "circumscribed about O instead of O' as the authors' published code does; "
                   "the summary says certified: false and lists the failed conditions "
                   "(simulation only: `run` never flies an uncertified scenario)")
    s.add_argument("--duration", type=bounded(scenario_key("sim", "duration")), metavar="S",
                   default=None,
                   help="simulated time in seconds (default: [sim].duration of the config)")
    s.add_argument("--controller", choices=("new", "old", "apf"), default="new",
                   help="new = (ModifiedVectorField), old = (Oldcontroller), apf = Appendix C "
                   "potential term on the main tube (default: new)")
    s.add_argument("--robots", type=bounded(COUNT), metavar="N", default=None,
                   help="keep only the first N robots of the config")
    s.add_argument("--record-every", type=bounded(COUNT), metavar="K", default=None,
                   help="record every K-th step in trajectory.npz (default: every 10 ms of "
                   "simulated time, coarser if the file would exceed ~40 MB)")
    s.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_args(s)
    s.set_defaults(func=cmd_sim)


def _default_out(config: str, controller: str) -> Path:
    return Path("sim_out") / f"{Path(config).stem}_{controller}"


def _fmt(x: Any, unit: str = "", nd: int = 3) -> str:
    if x is None:
        return "n/a"
    if isinstance(x, float):
        return f"{x:.{nd}f}{unit}"
    return f"{x}{unit}"


def print_summary(s: dict[str, Any], stream: Any = None) -> None:
    """A few lines with the headline numbers of a summary dict."""
    out = stream or sys.stdout
    w = out.write
    w(f"robots {s['robots']}, exited {s['exited']}, last exit {_fmt(s['last_exit_s'], ' s')}, "
      f"median exit {_fmt(s['median_exit_s'], ' s')}\n")
    w(f"min pair distance {_fmt(s['min_pair_distance_m'], ' m')}, min obstacle centre distance "
      f"{_fmt(s['min_obstacle_center_distance_m'], ' m')}, min leg distance left "
      f"{_fmt(s['min_left_leg_distance_m'], ' m')} / right "
      f"{_fmt(s['min_right_leg_distance_m'], ' m')}\n")
    w(f"speed in [{_fmt(s['min_speed_m_s'], '', 4)}, {_fmt(s['max_speed_m_s'], '', 4)}] m/s, "
      f"violations {s['violations']}"
      + (f" (first at {s['first_violation_s']:.3f} s: "
         + ", ".join(f"{k} {v}" for k, v in s["violations_by_condition"].items() if v) + ")"
         if s["violations"] else "") + "\n")
    if "violations_center" in s:
        w(f"robot centres: min pair {_fmt(s.get('min_pair_distance_m_center'), ' m')}, "
          f"min obstacle centre {_fmt(s.get('min_obstacle_center_distance_m_center'), ' m')}, "
          f"min legs {_fmt(s.get('min_left_leg_distance_m_center'), ' m')} / "
          f"{_fmt(s.get('min_right_leg_distance_m_center'), ' m')}, speed in "
          f"[{_fmt(s.get('min_speed_m_s_center'), '', 4)}, "
          f"{_fmt(s.get('max_speed_m_s_center'), '', 4)}] m/s, "
          f"violations {s['violations_center']}\n")
    st = s.get("integrator_stats") or {}
    split = (f", {st['split_steps']} steps split into {st['substeps']} sub-steps"
             if st.get("split_steps") else "")
    w(f"{s['steps']} steps of {s['dt_s']:g} s ({s.get('integrator', 'euler')}{split}) in "
      f"{s['wall_s']:.2f} s wall ({s['us_per_step']:.1f} us/step)\n")
    if st.get("floor_steps"):
        w(f"warning: {st['floor_steps']} sub-steps reached the finest step with a margin "
          "still shrinking fast\n")
    if s.get("certified") is False:
        failed = s.get("failed_conditions") or []
        w(f"certified: false (triangles about {s.get('triangles_about', 'O')}); "
          f"{len(failed)} failed condition{'s' if len(failed) != 1 else ''}:\n")
        for item in failed:
            w(f"  [{item['condition']}] {item['message']}\n")


def cmd_sim(args: argparse.Namespace) -> int:
    from vtube_fleet.config.scenario import load_scenario
    from vtube_fleet.sim import ProgressBar, simulate

    sc = load_scenario(args.config, extra_sections=("mission",))
    if "mission" in sc.extra:  # (a mission file: its scenario, as configured)
        print("note: a mission file: simulated as its scenario (the physical r_s, r_a; the "
              "fleet flies them inflated by its safety budget, see vtube-fleet check)",
              file=sys.stderr)
    out = Path(args.out) if args.out else _default_out(args.config, args.controller)
    from vtube_fleet.cli._args import recorder_from_args

    check_out_dir(out)  # before simulating: the outputs are written at the end

    recorder = recorder_from_args(args, out, kind="sim")
    bar = None if args.quiet else ProgressBar(sys.stderr)
    result = None
    try:
        result = simulate(sc, controller=args.controller, dt=args.dt, duration=args.duration,
                          robots=args.robots, record_every=args.record_every, progress=bar,
                          recorder=recorder, integrator=args.integrator,
                          uncertified=args.uncertified)
    finally:
        recorder.close()
        if bar is not None:
            note = None
            if result is not None:
                s = result.summary
                note = ("interrupted" if result.interrupted else
                        "all robots exited" if s["all_exited"] else "duration reached")
            bar.close(note)
    written = write_sim_outputs(result, out, plots=not args.no_plots)
    print_summary(result.summary)
    print(f"wrote {', '.join(os.fspath(p) for p in written)}")
    if result.interrupted:
        print("interrupted: results up to the interruption were written", file=sys.stderr)
        return EXIT_INTERRUPTED
    s = result.summary
    return EXIT_OK if s["exited"] == s["robots"] and s["violations"] == 0 else EXIT_SIM_UNFINISHED
