"""Benchmark of the offline simulator: time per step.

Every figure is a *difference* between a long and a short run of the same scenario divided by the
difference in steps, so start-up (validation, partition, allocation) cancels out. Each pair of
runs is repeated (``--repeat``) and the minimum and the median of the differences are printed
(the machine is shared), with a calibration line (the cost of two small numpy calls and the
load average) before and after.

1. The paper scenario (configs/paper.toml, dt = 1 ms, 120 robots):
   * "dense": 1 s vs 8 s of simulated time; all 120 robots are in the tube throughout;
   * "whole run": 2 s vs the full run until the last robot exits (robots leave after ~10 s,
     so later steps have fewer robots);
   * the straightforward numpy reference (:func:`reference`: the same equations with (M, M)
     pair matrices, forward Euler; 1 s vs 3 s) on the dense window, and the simulator's speed-up
     over it per integrator (issue 16 asks for x20; the reference ends within 1e-13 m of the
     simulator's euler run).
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

5. ``--callgrind``: instructions per step (valgrind) of the simulator and of the reference on
   the dense window, a count that does not depend on the load of a shared machine.

Run: ``python bench/bench_sim.py [--quick] [--paper-only] [--no-reference] [--repeat N]
[--profile] [--callgrind]`` (single core: nothing here is threaded; numpy's BLAS threads are
not used by the simulator's element-wise operations).
"""

from __future__ import annotations

import argparse
import cProfile
import math
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


def reference(scenario, duration: float) -> tuple[float, int, np.ndarray]:
    """The straightforward numpy reference (issue 2: "O(M²) pair matrices", issue 16's
    419 µs/step): the same simulation written directly from the equations, vectorized over
    robots but with (M, M) pair matrices, the general barrier formula of core/barrier.py on
    every element, partition.locate every step, forward Euler, the per-step safety minima
    (pairs, obstacle centres, legs, speeds) from the same matrices. Only the partition is
    shared with the simulator. Returns (wall s of the loop, steps, final (M, 2) positions with
    NaN for exited robots)."""
    from vtube_fleet.core.barrier import dV_n_dx, sigma
    from vtube_fleet.core.validation import validate_scenario

    c = scenario.controller
    tube, obstacles = scenario.tube, scenario.obstacles
    part, _ = validate_scenario(tube, obstacles, c, scenario.robots.control_points())
    st = lambda a: np.array([getattr(t, a) for t in part.sub_tubes], dtype=float)  # noqa: E731
    n_c, n_h, n_r, t_h, t_r, p_h1, p_r1 = (st(a) for a in
                                           ("n_c", "n_h", "n_r", "t_h", "t_r", "p_h1", "p_r1"))
    has_l = np.array([t.has_L for t in part.sub_tubes], dtype=float)
    has_r = np.array([t.has_R for t in part.sub_tubes], dtype=float)
    oc = np.array([o.center for o in obstacles], dtype=float)
    main_nc, thresh = np.array(tube.n_c), tube.finish_threshold(c.eps_0)
    dt = scenario.sim.dt
    steps = int(math.ceil(duration / dt - 1e-9))
    p = np.array(scenario.robots.positions, dtype=float)
    ids = np.arange(p.shape[0])
    final = np.full_like(p, np.nan)
    mins = np.zeros((steps, 6))
    t0 = time.perf_counter()
    for step in range(steps):
        gone = p @ main_nc >= thresh  # (TraCondition)
        if gone.any():
            final[ids[gone]] = p[gone]
            p, ids = p[~gone], ids[~gone]
            if p.shape[0] == 0:
                break
        k = part.locate(p)
        nc = n_c[k]
        d_th = np.sum((p - p_h1[k]) * n_h[k], axis=1)  # (dtl)
        d_tr = np.sum((p - p_r1[k]) * n_r[k], axis=1)  # (dtr)
        # u1'' (paper note 4)
        s_h = sigma(d_th, c.r_a, c.k_t * c.r_a) * has_l[k]
        s_r = sigma(d_tr, c.r_a, c.k_t * c.r_a) * has_r[k]
        q = nc + s_h[:, None] * (t_h[k] - nc) + s_r[:, None] * (t_r[k] - nc)
        u1 = c.v * q / np.linalg.norm(q, axis=1, keepdims=True)
        # u2 (Vmij) from the (M, M) pair matrix, V_m,ij ≡ 0 beyond r_s + r_a
        d = p[:, None, :] - p[None, :, :]
        dist = np.hypot(d[..., 0], d[..., 1])
        np.fill_diagonal(dist, np.inf)
        i, j = np.nonzero(dist < c.r_s + c.r_a)
        dij = dist[i, j]
        b = -dV_n_dx(c.k2, dij, 2 * c.r_s, c.r_s + c.r_a, c.eps_m, c.eps_s) / dij
        u2 = np.zeros_like(p)
        np.add.at(u2, i, b[:, None] * d[i, j])
        # u3', u4' (Vtli1)/(Vtri1), P_t = I − n_c n_cᵀ
        pt_h = n_h[k] - nc * np.sum(nc * n_h[k], axis=1, keepdims=True)
        pt_r = n_r[k] - nc * np.sum(nc * n_r[k], axis=1, keepdims=True)
        u3 = -dV_n_dx(c.k3, d_th, c.r_s, c.r_a, c.eps_t, c.eps_s)[:, None] * pt_h
        u4 = -dV_n_dx(c.k3, d_tr, c.r_s, c.r_a, c.eps_t, c.eps_s)[:, None] * pt_r
        u = u2 + u3 + u4
        un = np.linalg.norm(u, axis=1, keepdims=True)
        v_c = u1 + u * (c.v_max_prime / np.maximum(un, c.v_max_prime))  # (ModifiedVectorField)
        # safety minima of the step
        speed = np.linalg.norm(v_c, axis=1)
        do = np.sqrt(np.sum((p[:, None, :] - oc[None]) ** 2, axis=2))
        mins[step] = (dist.min(), do.min(), ((p - tube.p_h1) @ tube.n_h).min(),
                      ((p - tube.p_r1) @ tube.n_r).min(), speed.min(), speed.max())
        p = p + dt * v_c
    wall = time.perf_counter() - t0
    final[ids] = p
    return wall, step + 1, final


def reference_us(scenario, short: float, long: float, repeat: int) -> tuple[float, float]:
    """(min, median) µs per step of :func:`reference`, long minus short runs (after one
    untimed short run, as :func:`per_step_us`)."""
    reference(scenario, short)
    diffs = []
    for _ in range(repeat):
        w1, s1, _ = reference(scenario, short)
        w2, s2, _ = reference(scenario, long)
        diffs.append(1e6 * (w2 - w1) / (s2 - s1))
    return min(diffs), statistics.median(diffs)


def timed(scenario, duration: float, integrator: str | None = None) -> tuple[float, int]:
    t0 = time.perf_counter()
    res = simulate(scenario, duration=duration, record_every=10_000, integrator=integrator)
    wall = time.perf_counter() - t0
    return wall, int(res.summary["steps"])


def per_step_us(scenario, short: float, long: float, repeat: int,
                integrator: str | None = None) -> tuple[float, float, int, int]:
    """(min, median) over ``repeat`` pairs of runs of µs per step, and the two step counts.

    One untimed short run first: the first run in a process also pays one-time costs (the C
    heap growing and page-faulting, first calls), which would inflate the first short run and
    understate the difference (with ``repeat`` 1, e.g. 10,000 robots: 145 instead of ~700
    µs/step)."""
    timed(scenario, short, integrator)
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


def callgrind(integrator: str) -> None:
    """Instructions per step (valgrind's callgrind, "Collected" Ir) of the simulator and of the
    reference on the dense paper window: 1 s vs 2 s runs in child processes (one BLAS thread,
    fixed hash seed). Unlike wall time, the count does not depend on the machine's load; it
    counts work, not time (memory stalls, SIMD width)."""
    import re
    import shutil
    import subprocess

    if shutil.which("valgrind") is None:
        print("error: --callgrind needs valgrind on PATH")
        raise SystemExit(2)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONHASHSEED="0")

    def ir(kind: str, duration: float) -> int:
        cmd = ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable,
               __file__, "--child", kind, str(duration), "--integrators", integrator]
        err = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stderr
        return int(re.search(r"Collected : (\d+)", err).group(1))

    per = {}
    for kind in ("sim", "reference"):
        per[kind] = (ir(kind, 2.0) - ir(kind, 1.0)) / 1000  # 1000 steps of 1 ms
        law = "euler" if kind == "reference" else integrator
        print(f"callgrind, paper dense window, {kind:9s} ({law}): {per[kind]:10.0f} "
              "instructions/step", flush=True)
    print(f"  reference / simulator: x{per['reference'] / per['sim']:.1f} in instructions")


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
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the straightforward numpy reference (reference())")
    ap.add_argument("--profile", action="store_true",
                    help="cProfile the dense paper run and print the top functions")
    ap.add_argument("--callgrind", action="store_true",
                    help="instructions per step of the simulator (first of --integrators) and "
                         "of the reference under valgrind (load-independent; ~5 min)")
    ap.add_argument("--child", nargs=2, metavar=("KIND", "S"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    repeat = args.repeat or (1 if args.quick else 3)
    paper = load_scenario(ROOT / "configs" / "paper.toml")
    if args.child:  # one run measured by --callgrind
        kind, duration = args.child[0], float(args.child[1])
        if kind == "sim":
            simulate(paper, duration=duration, record_every=10_000,
                     integrator=args.integrators.split(",")[0])
        else:
            reference(paper, duration)
        return
    if args.callgrind:
        callgrind(args.integrators.split(",")[0])
        return
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
    if not args.no_reference:
        ref, med = reference_us(paper, 1.0, 3.0, repeat)
        print(f"paper, dense, straightforward numpy reference (O(M²) pairs, euler): {ref:7.1f} / "
              f"{med:5.1f} us/step")
        for integ, us in dense.items():
            print(f"  simulator ({integ}) vs reference: x{ref / us:.1f} (min / min; target x20, "
                  "issue 16)")
        _, s_ref, p_ref = reference(paper, 1.0)
        r = simulate(paper, duration=1.0, integrator="euler", record_every=1)
        p_sim = r.pos[-1]  # the final state, after the last step (the trajectory's last frame)
        print(f"  reference vs simulator (euler) after {s_ref} steps: max |Δp| = "
              f"{np.nanmax(np.abs(p_ref - p_sim)):.1e} m")
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
