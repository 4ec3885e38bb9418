"""``vtube-fleet check``: validate a scenario and print its partition."""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np

__all__ = [
    "cmd_check",
    "describe_partition",
    "register",
]


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


def register(subparsers: Any) -> None:
    """Add the ``check`` sub-command."""
    p = subparsers.add_parser(
        "check",
        help="validate a scenario and print its partition",
        description="Validate a scenario TOML against the paper's conditions and print the "
        "partition into sub-tubes (exit 0 if valid, 2 otherwise).",
    )
    p.add_argument("config", help="scenario TOML file (see docs/config.md)")
    p.set_defaults(func=cmd_check)
