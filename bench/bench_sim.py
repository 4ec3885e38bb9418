"""Benchmark of the offline simulator: time per step.

Every figure is a *difference* between a long and a short run of the same scenario divided by the
difference in steps, so start-up (validation, partition, allocation) cancels out. Each pair of
runs is repeated (``--repeat``) and the minimum and the median of the differences are printed
(the machine is shared), with a calibration line (the cost of two small numpy calls and the
load average) before and after.

1. The paper scenario (configs/paper.toml, dt = 1 ms, 120 robots):
   * "dense": 1 s vs 8 s of simulated time; all 120 robots are in the tube throughout;
   * "whole run": 2 s vs the full run until the last robot exits (robots leave after ~10 s,
     so later steps have fewer robots).
2. Scaling: 120, 1,000 and 10,000 robots in a long straight-ish tube (20 robots abreast, 0.8 m
   apart, 5 obstacles ahead of the block), 0.1 s vs 0.6 s of simulated time at dt = 1 ms
   (0.05 s vs 0.25 s for 10,000 robots).
   Time per step should grow about linearly with M.
3. Integrators (``--integrators``, default adaptive,euler,rk4): the dense paper figure per
   integrator. The default ``adaptive`` must stay within 1.5x of ``euler`` on the paper run
   (issue 11; before the integrators the simulator was plain Euler: 30.5 us/step here).
4. ``--search N``: perturb the obstacle centres of configs/paper.toml at random (x by
   σ = 0.1 m, y by σ = 0.7 m; ``--seed``), keep the draws that validation certifies (what
   ``vtube-fleet check`` tests) and fly each with euler and with the default integrator at
   1 ms; prints one line per certified draw (``--seed 3 --search 150``: 31 certified, draw 25
   breaks pair safety with Euler, min pair 0.4912 m; the default keeps it at 0.5002 m).

Run: ``python bench/bench_sim.py [--quick] [--paper-only] [--repeat N] [--profile]`` (single
core: nothing here is threaded; numpy's BLAS threads are not used by the simulator's
element-wise operations).
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import statistics
import sys
import time
import timeit
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vtube_fleet.config.scenario import load_scenario, parse_scenario  # noqa: E402
from vtube_fleet.sim import simulate  # noqa: E402


def long_tube(m: int, cols: int = 20, spacing: float = 0.8):
    """A long tube holding m robots 20 abreast, with five obstacles beyond the block."""
    rows = -(-m // cols)
    block = rows * spacing
    length = block + 40.0
    half0, half1 = 0.5 * cols * spacing + 4.0, 0.5 * cols * spacing + 2.0
    obstacles = [
        {"center": [block + 6.0 + 6.0 * k, (-1.0) ** k * 2.0], "radius": 0.9} for k in range(5)
    ]
    positions = [
        [0.6 + spacing * (i // cols), -0.5 * (cols - 1) * spacing + spacing * (i % cols)]
        for i in range(m)
    ]
    data = {
        "tube": {"p_h0": [0.0, half0], "p_h1": [length, half1],
                 "p_r0": [0.0, -half0], "p_r1": [length, -half1]},
        "obstacles": obstacles,
        "robots": {"r_s": 0.25, "r_a": 0.5, "v_min": 0.5, "v_max": 3.5, "positions": positions},
        "controller": {"v": 2.0, "v_max_prime": 1.5},
        "sim": {"dt": 0.001, "duration": 1.0},
    }
    return parse_scenario(data, f"long_tube_{m}")


def timed(scenario, duration: float, integrator: str | None = None) -> tuple[float, int]:
    t0 = time.perf_counter()
    res = simulate(scenario, duration=duration, record_every=10_000, integrator=integrator)
    wall = time.perf_counter() - t0
    return wall, int(res.summary["steps"])


def per_step_us(scenario, short: float, long: float, repeat: int,
                integrator: str | None = None) -> tuple[float, float, int, int]:
    """(min, median) over ``repeat`` pairs of runs of µs per step, and the two step counts."""
    diffs = []
    for _ in range(repeat):
        w1, s1 = timed(scenario, short, integrator)
        w2, s2 = timed(scenario, long, integrator)
        diffs.append(1e6 * (w2 - w1) / (s2 - s1))
    return min(diffs), statistics.median(diffs), s1, s2


def calibration() -> str:
    """What two small numpy calls cost right now (as in bench_controller.py) and the load."""
    x = np.random.default_rng(0).uniform(0.5, 1.5, 540)
    y = x[::-1].copy()
    z = x + 1j * y
    per = lambda f: min(timeit.repeat(f, number=20000, repeat=7)) / 20000 * 1e6  # noqa: E731
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"calibration: x*y (540 floats) {per(lambda: x * y):.2f} µs, abs (540 complex) "
            f"{per(lambda: np.abs(z)):.2f} µs, load average {load:.2f}")


def search(draws: int, seed: int) -> None:
    """Random certified perturbations of the paper scenario, flown with euler and the default."""
    import json
    import tomllib

    from vtube_fleet.core.validation import validate_scenario

    base = tomllib.loads((ROOT / "configs" / "paper.toml").read_text())
    rng = np.random.default_rng(seed)
    certified = 0
    for draw in range(draws):
        data = json.loads(json.dumps(base))
        for ob in data["obstacles"]:
            x, y = ob["center"]
            ob["center"] = [round(x + rng.normal(0, 0.1), 3), round(y + rng.normal(0, 0.7), 3)]
        sc = parse_scenario(data, f"draw {draw}")
        _, violations = validate_scenario(sc.tube, sc.obstacles, sc.controller,
                                          sc.robots.control_points())
        if violations:
            continue
        certified += 1
        line = [f"draw {draw:4d} {[o['center'] for o in data['obstacles']]}"]
        for integ in ("euler", "adaptive"):
            s = simulate(sc, integrator=integ, record_every=100_000).summary
            line.append(f"{integ}: min pair {s['min_pair_distance_m']:.4f} m, "
                        f"{s['violations']} violating steps, exited {s['exited']}")
        print("; ".join(line), flush=True)
    print(f"{certified} of {draws} draws certified (seed {seed})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions, skip 10,000 robots")
    ap.add_argument("--paper-only", action="store_true", help="skip the long-tube scaling")
    ap.add_argument("--repeat", type=int, default=None,
                    help="pairs of runs per figure (default 3, 1 with --quick)")
    ap.add_argument("--integrators", default="adaptive,euler,rk4",
                    help="comma-separated integrators for the dense paper figure")
    ap.add_argument("--search", type=int, metavar="N", default=0,
                    help="only the random search of certified scenarios (N draws)")
    ap.add_argument("--seed", type=int, default=3, help="seed of --search (default 3)")
    ap.add_argument("--profile", action="store_true",
                    help="cProfile the dense paper run and print the top functions")
    args = ap.parse_args()
    repeat = args.repeat or (1 if args.quick else 3)
    paper = load_scenario(ROOT / "configs" / "paper.toml")
    if args.search:
        search(args.search, args.seed)
        return

    if args.profile:
        prof = cProfile.Profile()
        prof.enable()
        simulate(paper, duration=4.0, record_every=10_000)
        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(18)

    print(f"numpy {np.__version__}, python {sys.version.split()[0]}, {repeat} repeats: "
          "min / median")
    print(calibration())
    dense = {}
    for integ in args.integrators.split(","):
        us, med, s1, s2 = per_step_us(paper, 1.0, 8.0, repeat, integ)
        dense[integ] = us
        print(f"paper, dense (120 robots in the tube), {integ:8s}: {us:7.1f} / {med:5.1f} "
              f"us/step  (steps {s1} vs {s2})")
    if "adaptive" in dense and "euler" in dense:
        print(f"adaptive / euler: x{dense['adaptive'] / dense['euler']:.2f}")
    full = paper.sim.duration
    us, med, s1, s2 = per_step_us(paper, 2.0, full, repeat)
    print(f"paper, whole run until all exit:      {us:7.1f} / {med:5.1f} us/step  "
          f"(steps {s1} vs {s2})")
    t0 = time.perf_counter()
    res = simulate(paper)
    print(f"paper, one full run: {time.perf_counter() - t0:.2f} s wall for "
          f"{res.summary['steps']} steps (exited {res.summary['exited']}/120, "
          f"violations {res.summary['violations']})")

    sizes = () if args.paper_only else (120, 1000) if args.quick else (120, 1000, 10_000)
    base = None
    for m in sizes:
        sc = long_tube(m)
        short, long = (0.05, 0.25) if m >= 10_000 else (0.1, 0.6)  # ≥ 0.5 s of differences
        us, med, s1, s2 = per_step_us(sc, short, long, repeat if m < 10_000 else 1)
        base = base or us / m
        print(f"long tube, {m:6d} robots: {us:9.1f} / {med:9.1f} us/step  {us / m:6.3f} "
              f"us/step/robot  (x{us / m / base:.2f} per robot vs 120)")
    print(calibration())


if __name__ == "__main__":
    main()
