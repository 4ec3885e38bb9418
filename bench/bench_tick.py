"""Benchmark: the supervisor's control tick alone, for N vehicles, in one process, no network.

    python bench/bench_tick.py [--count 1000] [--ticks 200] [--phase tube|takeoff]
                               [--profile-out FILE]

What `bench_fleet.py` measures end to end (sockets, mock processes, a shared machine), this
isolates: the CPU of :meth:`Supervisor._tick` itself (sense, faults, publish, the batched
controller, the setpoints, the measurement), the part of the 50 ms period that grows with the
fleet. The vehicles are in-memory links (:class:`MemoryLink`): their telemetry (local position
and velocity, 25 Hz like ``bench_fleet --lean-streams``, every second tick) is written into the
link state directly, and each setpoint moves its vehicle by ``v · T``, so the controller sees a
fleet that flies the tube. Prints the tick's p50 / p99 / max (ms) and µs per vehicle; the
machine's load is printed too (the numbers are CPU time on one core only if nothing else runs).

Run by hand (not in CI).
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import logging
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from memory_fleet import MemoryLink, fly_telemetry, memory_fleet  # noqa: E402

from vtube_fleet.fleet.supervisor import Supervisor  # noqa: E402
from vtube_fleet.state import Phase  # noqa: E402


def fly(sup: Supervisor, links: list[MemoryLink], ticks: int, prof: cProfile.Profile | None
        ) -> np.ndarray:
    period = sup.cfg.period_s
    out = []
    for k in range(ticks):
        now = time.monotonic()
        if k % 2 == 0:  # telemetry at half the control rate's period: 25 Hz vs 20 Hz ticks
            fly_telemetry(links, 2 * period, now)
        if prof is not None:
            prof.enable()
        t0 = time.perf_counter()
        sup._tick()
        out.append(time.perf_counter() - t0)
        if prof is not None:
            prof.disable()
    return np.asarray(out)


async def main_async(args: argparse.Namespace) -> None:
    logging.disable(logging.WARNING)  # the point vehicles' d̂ drifts (no PX4 loop): warnings
    sup, links = memory_fleet(args.count, args.phase)
    fly(sup, links, 20, None)  # warm-up: caches, the first layouts
    prof = cProfile.Profile() if args.profile_out else None
    cpu0 = time.process_time()
    dur = fly(sup, links, args.ticks, prof)
    cpu = time.process_time() - cpu0
    if prof is not None:
        prof.dump_stats(args.profile_out)
    in_tube = sum(p.phase == Phase.IN_TUBE for p in sup.pilots)
    ms = 1000 * dur
    print(f"{args.count} vehicles, phase {args.phase}, {args.ticks} ticks "
          f"(load {os.getloadavg()[0]:.2f}; {in_tube} still in the tube at the end)")
    print(f"tick p50 {np.percentile(ms, 50):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms, "
          f"max {ms.max():.2f} ms; {1000 * np.median(ms) / args.count:.1f} µs per vehicle "
          f"(median); CPU {1000 * cpu / args.ticks:.2f} ms per tick")
    if not math.isfinite(sup.min_pair_airborne):
        print("(no pairs measured)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=1000)
    ap.add_argument("--ticks", type=int, default=200)
    ap.add_argument("--phase", choices=("tube", "takeoff"), default="tube")
    ap.add_argument("--profile-out", type=Path, default=None, metavar="FILE")
    args = ap.parse_args()
    asyncio.run(main_async(args))


if __name__ == "__main__":
    main()
