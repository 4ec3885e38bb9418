"""``vtube-fleet check`` and ``vtube-fleet sim``: validate a scenario, run the offline simulator.

``check CONFIG`` parses the scenario, validates it against the paper's conditions
(:func:`vtube_fleet.core.validation.validate_scenario`) and prints the partition: the sub-tubes with
their ξ ranges, the circumscribed triangles and which obstacles needed Remark 5. Exit 0 when
valid, 2 with the violations listed otherwise.

``sim CONFIG [--out DIR]`` runs :func:`vtube_fleet.sim.simulate` and writes ``summary.json``,
``trajectory.npz``, ``metrics.npz`` (every step's safety metrics), ``safety.png`` (Fig. 11)
and ``snapshots.png`` into DIR. Exit 0 when every robot exited without a violation, 1 when the
run finished but not cleanly (robots left in the tube, violations), 2 on user errors,
130 on Ctrl-C (the partial results are still written).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from vtube_fleet.errors import UserError

__all__ = ["register", "cmd_check", "cmd_sim", "write_outputs"]


def register(subparsers: Any) -> None:
    """Add the ``check`` and ``sim`` sub-commands."""
    p = subparsers.add_parser(
        "check",
        help="validate a scenario and print its partition",
        description="Validate a scenario TOML against the paper's conditions and print the "
        "partition into sub-tubes (exit 0 if valid, 2 otherwise).",
    )
    p.add_argument("config", help="scenario TOML file (see docs/config.md)")
    p.set_defaults(func=cmd_check)

    s = subparsers.add_parser(
        "sim",
        help="run the offline simulator",
        description="Simulate the swarm with forward Euler and write summary.json, "
        "trajectory.npz, metrics.npz and PNG plots.",
    )
    s.add_argument("config", help="scenario TOML file (see docs/config.md)")
    s.add_argument("--out", metavar="DIR", default=None,
                   help="output directory (default: sim_out/<config name>_<controller>)")
    s.add_argument("--dt", type=float, metavar="S", default=None,
                   help="Euler step in seconds (default: [sim].dt of the config)")
    s.add_argument("--duration", type=float, metavar="S", default=None,
                   help="simulated time in seconds (default: [sim].duration of the config)")
    s.add_argument("--controller", choices=("new", "old", "apf"), default="new",
                   help="new = (ModifiedVectorField), old = (Oldcontroller), apf = Appendix C "
                   "potential term on the main tube (default: new)")
    s.add_argument("--robots", type=int, metavar="N", default=None,
                   help="keep only the first N robots of the config")
    s.add_argument("--record-every", type=int, metavar="K", default=None,
                   help="record every K-th step in trajectory.npz (default: every 10 ms of "
                   "simulated time, coarser if the file would exceed ~40 MB)")
    s.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    from vtube_fleet.recording import add_recording_args

    add_recording_args(s)
    s.set_defaults(func=cmd_sim)


# ----------------------------------------------------------------------------------------
# check
# ----------------------------------------------------------------------------------------


def _pt(p: np.ndarray) -> str:
    return f"({p[0]:.3f}, {p[1]:.3f})"


def _xi(x: float) -> str:
    return f"{x:8.3f}" if math.isfinite(x) else ("    -inf" if x < 0 else "     inf")


def describe_partition(scenario: Any, part: Any) -> list[str]:
    """Human-readable lines describing the partition (sub-tubes, triangles, Remark 5)."""
    lines = []
    tube = scenario.tube
    lines.append(f"sub-tubes: {part.K}")
    for name_tube, xs, xe in zip(part.sub_tubes, part.xi_start, part.xi_end, strict=True):
        a, b = max(float(xs), 0.0), min(float(xe), tube.length)
        lines.append(
            f"  {name_tube.name:6s} xi [{_xi(float(xs))}, {_xi(float(xe))})  "
            f"start base {_pt(name_tube.p_h0)}–{_pt(name_tube.p_r0)}  "
            f"L:{'yes' if name_tube.has_L else 'no '} R:{'yes' if name_tube.has_R else 'no '}"
            f"  ({b - a:.2f} m long)"
        )
    r5 = [tri for tri in part.triangles if tri.remark5 is not None]
    lines.append(f"triangles: {len(part.triangles)}")
    for tri in part.triangles:
        ob = scenario.obstacles[tri.obstacle]
        note = "isosceles"
        if tri.remark5:
            beta = math.degrees(tri.beta)
            note = f"Remark 5: {tri.remark5} side tube dropped, beta = {beta:.2f} deg"
        lines.append(
            f"  obstacle #{tri.obstacle + 1} at {_pt(ob.center)} r_o = {ob.radius:g}: "
            f"h = {tri.h:.3f} m, alpha = {math.degrees(tri.alpha):.2f} deg, apex {_pt(tri.p_oth)}, "
            f"base {_pt(tri.p_otu)}–{_pt(tri.p_otd)}; {note}"
        )
    if r5:
        lines.append("Remark 5 used by obstacle(s): "
                     + ", ".join(f"#{tri.obstacle + 1} ({tri.remark5})" for tri in r5))
    else:
        lines.append("Remark 5 used by obstacle(s): none")
    return lines


def cmd_check(args: argparse.Namespace) -> int:
    from vtube_fleet.config.scenario import load_scenario
    from vtube_fleet.core.validation import validate_scenario

    sc = load_scenario(args.config)
    r = sc.robots
    tube = sc.tube
    part, violations = validate_scenario(tube, sc.obstacles, sc.controller, r.control_points())
    print(f"{sc.source}:")
    print(f"  tube: p_h0 {_pt(tube.p_h0)} p_h1 {_pt(tube.p_h1)} p_r0 {_pt(tube.p_r0)} "
          f"p_r1 {_pt(tube.p_r1)}; length {tube.length:.3f} m, width "
          f"{tube.width(0.0):.3f} -> {tube.width(tube.length):.3f} m")
    print(f"  robots: {r.count} {r.model}, r_s = {r.r_s:g}, r_a = {r.r_a:g}, "
          f"speed in [{r.v_min:g}, {r.v_max:g}] m/s"
          + (f", NID s = {r.nid_distance:g} m" if r.model == "unicycle" else ""))
    c = sc.controller
    print(f"  controller: v = {c.v:g}, v'_max = {c.v_max_prime:g}, k_t = {c.k_t:g}, "
          f"eps_0 = {c.eps_0:g}; sim dt = {sc.sim.dt:g} s, duration = {sc.sim.duration:g} s")
    print(f"  obstacles: {len(sc.obstacles)}")
    if part is not None:
        for line in describe_partition(sc, part):
            print("  " + line)
    if violations:
        print(f"INVALID: {len(violations)} violation{'s' if len(violations) != 1 else ''}:")
        for v in violations:
            print(f"  [{v.condition}] {v.message}")
        return 2
    print("valid")
    return 0


# ----------------------------------------------------------------------------------------
# sim
# ----------------------------------------------------------------------------------------


def _default_out(config: str, controller: str) -> Path:
    return Path("sim_out") / f"{Path(config).stem}_{controller}"


def write_outputs(result: Any, out: Path, *, plots: bool = True) -> list[Path]:
    """Write summary.json, trajectory.npz, metrics.npz and the PNG plots; returns the paths."""
    from vtube_fleet.plots import pick_snapshot_frames, plot_safety, plot_snapshots

    out.mkdir(parents=True, exist_ok=True)
    written = []
    summary_path = out / "summary.json"
    summary_path.write_text(json.dumps(result.summary, indent=2) + "\n")
    written.append(summary_path)

    traj = out / "trajectory.npz"
    np.savez_compressed(traj, **result.trajectory_arrays())
    written.append(traj)

    met = out / "metrics.npz"
    arrays = {"t": result.step_t, **result.metrics.as_dict()}
    if result.metrics_center is not None:
        arrays.update({f"{k}_center": v for k, v in result.metrics_center.as_dict().items()})
    np.savez_compressed(met, **arrays)
    written.append(met)

    if plots:
        sc = result.scenario
        r = sc.robots
        title = (f"{Path(sc.source).name}: {r.count} robots, controller {result.controller}, "
                 f"dt = {result.dt:g} s")
        safety = out / "safety.png"
        plot_safety(safety, result.step_t, result.metrics, r_s=r.r_s, v_min=r.v_min,
                    v_max=r.v_max, obstacle_radii=[o.radius for o in sc.obstacles],
                    title=title, center=result.metrics_center)
        written.append(safety)
        if result.t.size:
            frames = pick_snapshot_frames(result.t, result.pos, 4)
            part = result.partition if result.controller != "apf" else None
            snaps = out / "snapshots.png"
            plot_snapshots(
                snaps, sc.tube, [(float(result.t[i]), result.pos[i]) for i in frames],
                r_s=r.r_s, obstacles=sc.obstacles,
                sub_tubes=part.sub_tubes if part is not None and part.K > 1 else (),
                triangles=part.triangles if part is not None else (),
                headings=None if result.heading is None else [result.heading[i] for i in frames],
                title=title,
            )
            written.append(snaps)
    return written


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
    w(f"{s['steps']} steps of {s['dt_s']:g} s in {s['wall_s']:.2f} s wall "
      f"({s['us_per_step']:.1f} us/step)\n")


def cmd_sim(args: argparse.Namespace) -> int:
    from vtube_fleet.config.scenario import load_scenario
    from vtube_fleet.sim import ProgressBar, simulate

    sc = load_scenario(args.config)
    out = Path(args.out) if args.out else _default_out(args.config, args.controller)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: exists and is not a directory")
    from vtube_fleet.recording import recorder_from_args

    recorder = recorder_from_args(args, out, kind="sim")
    bar = None if args.quiet else ProgressBar(sys.stderr)
    result = None
    try:
        result = simulate(sc, controller=args.controller, dt=args.dt, duration=args.duration,
                          robots=args.robots, record_every=args.record_every, progress=bar,
                          recorder=recorder)
    finally:
        recorder.close()
        if bar is not None:
            note = None
            if result is not None:
                s = result.summary
                note = ("interrupted" if result.interrupted else
                        "all robots exited" if s["all_exited"] else "duration reached")
            bar.close(note)
    written = write_outputs(result, out, plots=not args.no_plots)
    print_summary(result.summary)
    print(f"wrote {', '.join(os.fspath(p) for p in written)}")
    if result.interrupted:
        print("interrupted: results up to the interruption were written", file=sys.stderr)
        return 130
    s = result.summary
    return 0 if s["exited"] == s["robots"] and s["violations"] == 0 else 1
