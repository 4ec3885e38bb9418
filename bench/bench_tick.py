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
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from missions import grid_mission  # noqa: E402

from vtube_fleet.config.mission import load_mission  # noqa: E402
from vtube_fleet.fleet.supervisor import Supervisor  # noqa: E402
from vtube_fleet.link.base import GeoPoint, VehicleLink  # noqa: E402
from vtube_fleet.state import Phase  # noqa: E402


class MemoryLink(VehicleLink):
    """A link whose vehicle is a point that flies its last velocity setpoint (no I/O)."""

    def __init__(self, url: str, sysid: int) -> None:
        super().__init__(url, sysid)
        self.v_ned = (0.0, 0.0, 0.0)
        self.sent = 0

    def send_velocity_ned(self, north_m_s: float, east_m_s: float, down_m_s: float,
                          yaw_deg: float | None = None) -> None:
        self.v_ned = (north_m_s, east_m_s, down_m_s)
        self.sent += 1

    @property
    def latency_s(self) -> float | None:
        return 0.002

    async def connect(self, timeout_s: float = 10.0) -> None: ...
    async def arm(self, timeout_s: float = 10.0) -> None: ...
    async def disarm(self) -> None: ...
    async def takeoff(self, altitude_m: float) -> None: ...
    async def land(self) -> None: ...
    async def hold(self) -> None: ...
    async def start_offboard(self) -> None: ...
    async def stop_offboard(self) -> None: ...
    async def close(self) -> None: ...


def build(count: int, phase: str) -> tuple[Supervisor, list[MemoryLink]]:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "tick.toml"
        path.write_text(grid_mission(count, 20.0, 60.0, 5.0)  # [mission] last: L, σ fixed
                        + "latency_s = 0.25\nposition_accuracy_m = 0.29\n")
        mission = load_mission(path)
    links = [MemoryLink(f"udpin://127.0.0.1:{30000 + i}", i % 255 + 1) for i in range(count)]
    f = mission.frame
    lat0, lon0, alt0 = f.lat0_deg, f.lon0_deg, f.alt0_m  # every vehicle's origin: the tube's
    slots = mission.slots
    n, e, d = mission.frame.tube_to_local_ned(slots[:, 0], slots[:, 1],
                                              np.full(count, mission.config.altitude_m),
                                              lat0, lon0, alt0)
    now = time.monotonic()
    for i, link in enumerate(links):
        s = link.state
        s.origin = GeoPoint(lat0, lon0, alt0)
        s.north_m, s.east_m, s.down_m = float(n[i]), float(e[i]), float(d[i])
        s.vn_m_s = s.ve_m_s = s.vd_m_s = 0.0
        s.armed, s.flight_mode, s.landed_state = True, "OFFBOARD", "IN_AIR"
        s.last_position_s = s.last_heartbeat_s = s.last_packet_s = now
        s.pos_accuracy_m = 0.29
    sup = Supervisor(mission, links, fence=False)
    for p in sup.pilots:
        p.set_phase(Phase.TAKEOFF if phase == "takeoff" else Phase.IN_TUBE)
        p.takeoff_xy = np.array(slots[p.vehicle_id], dtype=float)
    sup.stage = phase
    if phase == "tube":
        sup.tube_start_s = sup.t_s()
    return sup, links


def fly(sup: Supervisor, links: list[MemoryLink], ticks: int, prof: cProfile.Profile | None
        ) -> np.ndarray:
    period = sup.cfg.period_s
    out = []
    for k in range(ticks):
        now = time.monotonic()
        if k % 2 == 0:  # telemetry at half the control rate's period: 25 Hz vs 20 Hz ticks
            for link in links:
                s = link.state
                vn, ve, vd = link.v_ned
                s.north_m += 2 * period * vn
                s.east_m += 2 * period * ve
                s.down_m += 2 * period * vd
                s.vn_m_s, s.ve_m_s, s.vd_m_s = vn, ve, vd
                s.last_position_s = now
        if prof is not None:
            prof.enable()
        t0 = time.perf_counter()
        sup._tick()
        out.append(time.perf_counter() - t0)
        if prof is not None:
            prof.disable()
        sup.tick += 1
    return np.asarray(out)


async def main_async(args: argparse.Namespace) -> None:
    logging.disable(logging.WARNING)  # the point vehicles' d̂ drifts (no PX4 loop): warnings
    sup, links = build(args.count, args.phase)
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
