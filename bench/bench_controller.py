"""Benchmark of the controller core: µs per call of ``velocity_command`` and of the Verlet
neighbour update (run by hand; numbers depend on the machine and its load).

    python bench/bench_controller.py [--quick]

1. Paper-like scenario: 120 robots in a 45 m trapezoid tube with 5 obstacles (r_o = 0.9 m),
   partitioned into 16 sub-tubes, the paper's parameters, dt = 1 ms.
   a. ``velocity_command`` on a fixed state (min over repeats);
   b. a closed loop of single-integrator steps from the starting block: per-step time of
      locate (partition, not this module), the Verlet update, velocity_command and the Euler
      step, averaged over the steps; then the same loop as the simulator runs it:
      SubTubeTracker.update (max_move hint) and CommandEvaluator.step on complex positions;
   c. an agent's call: its own command from itself + its neighbours (``rows=[0]``).
2. Linear growth: M = 120, 1,000 and 10,000 robots at the same density in a long straight tube
   (one tube; pairs from the Verlet list).

A calibration line reports what one 540-element float multiply and one 540-element
``np.abs`` of complex cost right now, and the load average, so runs can be compared.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
import timeit
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vtube_fleet.core.controller import (  # noqa: E402
    CommandEvaluator,
    TubeArrays,
    velocity_command,
)
from vtube_fleet.core.neighbours import VerletPairs, pairs_within  # noqa: E402
from vtube_fleet.core.params import ControllerParams  # noqa: E402
from vtube_fleet.core.partition import partition  # noqa: E402
from vtube_fleet.core.tube import Obstacle, Trapezoid  # noqa: E402

PARAMS = ControllerParams(r_s=0.25, r_a=0.5, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5)
SKIN = 0.3


def per_call_us(fn, number: int, repeat: int = 7) -> float:
    return min(timeit.repeat(fn, number=number, repeat=repeat)) / number * 1e6


def calibration() -> str:
    x = np.random.default_rng(0).uniform(0.5, 1.5, 540)
    y = x[::-1].copy()
    z = x + 1j * y
    mul = per_call_us(lambda: x * y, 20000)
    cab = per_call_us(lambda: np.abs(z), 20000)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"calibration: x*y (540 floats) {mul:.2f} µs, abs (540 complex) {cab:.2f} µs, "
            f"load average {load:.2f}, numpy {np.__version__}")


def paper_scenario():
    tube = Trapezoid([0, 6], [45, 4.5], [0, -6], [45, -4.5], name="T")
    obstacles = [Obstacle([15, 1.0], 0.9), Obstacle([20.5, -1.0], 0.9),
                 Obstacle([26, 0.8], 0.9), Obstacle([31.5, -0.8], 0.9), Obstacle([37, 0.5], 0.9)]
    part = partition(tube, obstacles, PARAMS)
    xs, ys = np.meshgrid(np.linspace(1.0, 11.0, 12), np.linspace(-4.5, 4.5, 10))
    p = np.column_stack([xs.ravel(), ys.ravel()])
    return tube, part, p


def bench_paper(quick: bool) -> None:
    tube, part, p0 = paper_scenario()
    ta = TubeArrays.from_tubes(part.sub_tubes)
    print(f"paper-like scenario: M = {len(p0)}, K = {part.K} sub-tubes, "
          f"{len(part.triangles)} obstacles")

    # a. fixed states along the way (start block, and after 1.5 s and 4 s of flight)
    p = p0.copy()
    vl = VerletPairs(PARAMS.r_s + PARAMS.r_a, SKIN)
    states = {}
    for step in range(4001):
        if step in (0, 1500, 4000):
            states[step] = p.copy()
        k = part.locate(p)
        p = p + 1e-3 * velocity_command(p, k, ta, PARAMS, pairs=vl.candidates(p))
    for step, s in states.items():
        k = part.locate(s)
        pairs = VerletPairs(PARAMS.r_s + PARAMS.r_a, SKIN).candidates(s)
        t = per_call_us(lambda s=s, k=k, pairs=pairs: velocity_command(
            s, k, ta, PARAMS, pairs=pairs), 2000)
        k.setflags(write=False)
        ev = CommandEvaluator(ta, PARAMS)
        z = s.view(np.complex128).ravel()
        te = per_call_us(lambda z=z, k=k, pairs=pairs, ev=ev: ev.step(z, k, pairs), 2000)
        print(f"  a. velocity_command, state at t = {step / 1000:.1f} s "
              f"({len(pairs[0])} candidate pairs): {t:.1f} µs/call; CommandEvaluator.step "
              f"{te:.1f} µs/call")

    # b. closed loop
    n_steps = 1500 if quick else 6000
    p = p0.copy()
    vl = VerletPairs(PARAMS.r_s + PARAMS.r_a, SKIN)
    pc = time.perf_counter_ns
    dt = np.zeros((n_steps, 4))
    for step in range(n_steps):
        a = pc()
        k = part.locate(p)
        b = pc()
        pairs = vl.candidates(p)
        c = pc()
        vc = velocity_command(p, k, ta, PARAMS, pairs=pairs)
        d = pc()
        p = p + 1e-3 * vc
        e = pc()
        dt[step] = (b - a, c - b, d - c, e - d)
    dt /= 1e3
    names = ("locate", "Verlet update", "velocity_command", "Euler")
    print(f"  b. closed loop, {n_steps} steps of 1 ms ({vl.builds} Verlet builds), µs per step "
          "as median / mean:")
    print("     " + ", ".join(f"{nm} {np.median(dt[:, i]):.1f} / {dt[:, i].mean():.1f}"
                              for i, nm in enumerate(names)))
    both = dt[:, 1] + dt[:, 2]
    print(f"     controller + neighbours {np.median(both):.1f} / {both.mean():.1f} "
          f"(90th percentile {np.percentile(both, 90):.1f})")
    # the simulator's way: tracker, evaluator on x + iy, Euler in place
    z = p0.astype(float).view(np.complex128).ravel().copy()
    tr, ev = part.tracker(), CommandEvaluator(ta, PARAMS)
    vl = VerletPairs(PARAMS.r_s + PARAMS.r_a, SKIN)
    max_move = 1e-3 * (PARAMS.v + PARAMS.v_max_prime) * (1 + 1e-6)
    vz = np.empty_like(z)
    for step in range(n_steps):
        q = z.view(np.float64).reshape(-1, 2)
        a = pc()
        k = tr.update(q, max_move)
        b = pc()
        pairs = vl.candidates(q)
        c = pc()
        ev.step(z, k, pairs, out=vz)
        d = pc()
        vz *= 1e-3
        z += vz
        e = pc()
        dt[step] = (b - a, c - b, d - c, e - d)
    dt /= 1e3
    names = ("tracker", "Verlet update", "CommandEvaluator.step", "Euler")
    print(f"     as the simulator ({tr.locates} full locates, {tr.checks} row checks): "
          + ", ".join(f"{nm} {np.median(dt[:, i]):.1f} / {dt[:, i].mean():.1f}"
                      for i, nm in enumerate(names)))

    # c. an agent: itself + its neighbours within r_s + r_a + 1 m
    s = states[1500]
    k = part.locate(s)
    times = []
    for i in range(0, len(s), 7):
        d = np.hypot(*(s - s[i]).T)
        nb = np.flatnonzero((d < PARAMS.r_s + PARAMS.r_a + 1.0) & (np.arange(len(s)) != i))
        local = np.vstack([s[i], s[nb]])
        kl = np.r_[k[i], k[nb]]
        times.append(per_call_us(lambda local=local, kl=kl: velocity_command(
            local, kl, ta, PARAMS, rows=[0]), 500, repeat=3))
    print(f"  c. agent call (rows=[0], itself + ~{len(nb)} neighbours, pairs=None): "
          f"median {statistics.median(times):.1f} µs/call")


def bench_growth(quick: bool) -> None:
    print("linear growth, one long straight tube (6 m wide), Verlet candidate pairs:")
    rng = np.random.default_rng(1)
    sizes = (120, 1000) if quick else (120, 1000, 10000)
    for M in sizes:
        cols = int(np.ceil(M / 7))
        length = cols * 0.8 + 20
        tube = Trapezoid([0, 3], [length, 3], [0, -3], [length, -3])
        ta = TubeArrays.from_tubes([tube])
        xs, ys = np.meshgrid(np.arange(cols) * 0.8 + 1.0, np.linspace(-2.4, 2.4, 7))
        p = np.column_stack([xs.ravel(), ys.ravel()])[:M] + rng.normal(scale=0.02, size=(M, 2))
        k = np.zeros(M, dtype=np.intp)
        vl = VerletPairs(PARAMS.r_s + PARAMS.r_a, SKIN)
        pairs = vl.candidates(p)
        number = max(5, 200_000 // M)
        t = per_call_us(lambda p=p, k=k, ta=ta, pairs=pairs: velocity_command(
            p, k, ta, PARAMS, pairs=pairs), number, repeat=5)
        tb = per_call_us(lambda p=p: pairs_within(p, PARAMS.r_s + PARAMS.r_a + SKIN),
                         max(3, number // 10), repeat=3)
        print(f"  M = {M:6d}: {len(pairs[0]):6d} pairs, velocity_command {t:9.1f} µs/call "
              f"({t / M * 1e3:6.1f} ns/robot), Verlet rebuild (KD-tree) {tb:9.1f} µs")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps, skip M = 10,000")
    args = ap.parse_args()
    print(calibration())
    bench_paper(args.quick)
    bench_growth(args.quick)
    print(calibration())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
