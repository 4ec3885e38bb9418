"""Benchmark of the partition planner (``apex_distance = "auto"``, vtube_fleet/core/plan.py):
milliseconds to choose every h_k jointly and build the partition (run by hand; numbers depend
on the machine and its load).

    python bench/bench_plan.py [--repeat N]

1. 5 obstacles: ``configs/paper.toml`` with every obstacle ``"auto"`` and its 120 robots as
   keep-out points (what ``check`` and ``sim`` do).
2. 20 obstacles: a 110 m tube narrowing from 20 m to 12 m, a chain of 20 obstacles
   (r_o = 0.9 m) 5 m apart with alternating lateral offsets, 120 robots in front.
3. Re-planning in flight: the fleet's :meth:`FlightPlan.with_lost` on the shipped mock
   mission (flown radii for L = 0.05 s, σ = 0) around one lost vehicle whose fixed apex
   distance (1.05 h_min) gives no partition, so the planner chooses it (the configured
   obstacle frozen).

For each: the fixed-h partition for comparison, the planner's time (min and median over the
repeats), its trial constructions, and the smallest margin reached.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vtube_fleet.config.mission import load_mission  # noqa: E402
from vtube_fleet.config.scenario import grid_positions, load_scenario  # noqa: E402
from vtube_fleet.core.params import ControllerParams  # noqa: E402
from vtube_fleet.core.partition import (
    h_min,  # noqa: E402
    partition,  # noqa: E402
)
from vtube_fleet.core.plan import plan_partition  # noqa: E402
from vtube_fleet.core.tube import Obstacle, Trapezoid  # noqa: E402
from vtube_fleet.fleet.budget import LinkMeasurement, mission_budget  # noqa: E402
from vtube_fleet.fleet.flight_plan import LOST_APEX_FACTOR, FlightPlan  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _time(fn, repeat: int) -> tuple[float, float, object]:
    out, ts = None, []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        ts.append(1e3 * (time.perf_counter() - t))
    return min(ts), statistics.median(ts), out


def _report(name: str, tube, obstacles, params, keep_out, repeat: int) -> None:
    auto = tuple(dataclasses.replace(o, apex_distance="auto") for o in obstacles)
    fixed_min, fixed_med, _ = _time(lambda: partition(tube, obstacles, params, strict=False),
                                    repeat)
    pmin, pmed, part = _time(lambda: plan_partition(tube, auto, params, strict=False,
                                                    keep_out=keep_out), repeat)
    plan = part.apex
    print(f"{name}: {len(obstacles)} obstacles, {part.K} sub-tubes")
    print(f"  fixed h (1.3 h_min) partition: min {fixed_min:.1f} ms, median {fixed_med:.1f} ms")
    print(f"  planner (auto) + partition:    min {pmin:.1f} ms, median {pmed:.1f} ms; "
          f"{plan.evaluations} trials; feasible {plan.feasible}; smallest margin "
          f"{plan.margin_m:.3f} m")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} ({os.cpu_count()} cores)")

    sc = load_scenario(ROOT / "configs" / "paper.toml")
    _report("paper (configs/paper.toml)", sc.tube, sc.obstacles, sc.controller,
            sc.robots.positions, args.repeat)

    params = ControllerParams(r_s=0.25, r_a=0.5, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5)
    tube = Trapezoid((0.0, 10.0), (110.0, 6.0), (0.0, -10.0), (110.0, -6.0))
    obs = tuple(Obstacle((12.0 + 5.0 * k, (1.5 if k % 2 else -1.5) * (1 + 0.2 * (k % 3))), 0.9)
                for k in range(20))
    robots = grid_positions((0.5, -4.4), 10, 12, 0.8)
    _report("chain of 20", tube, obs, params, robots, args.repeat)

    # in flight: the shipped mock mission flown with δ for L = 0.05 s, σ = 0; a vehicle lost
    # at (8.76, -1.94), where its fixed apex distance 1.05 h_min does not give a partition
    mission = load_mission(ROOT / "configs" / "mock_fleet.toml")
    flown = mission_budget(mission, LinkMeasurement(0.0, 0.0, 0.0)).inflate(
        mission.scenario.controller)
    root = FlightPlan.for_mission(mission, flown)
    r_lost = mission.scenario.controller.r_s + mission.config.lost_obstacle_margin_m
    lost = (Obstacle(np.array([8.76, -1.94]), r_lost, LOST_APEX_FACTOR * h_min(r_lost, flown)),)

    def replan() -> FlightPlan:
        root._cache.clear()
        root._cache[()] = root
        return root.with_lost(lost)

    tmin, tmed, new = _time(replan, args.repeat)
    part = new.route.segments[0].partition
    how = (f"chosen by the planner: h = {part.apex.h[-1]:.3f} m"
           if part.apex is not None else "fixed 1.05 h_min")
    print(f"re-plan around 1 lost vehicle (mock mission, configured obstacle frozen): "
          f"min {tmin:.1f} ms, median {tmed:.1f} ms ({part.K} sub-tubes; lost "
          f"obstacle's h {how}; fixed would be {LOST_APEX_FACTOR * h_min(r_lost, flown):.3f} m)")


if __name__ == "__main__":
    main()
