"""Benchmark: control-loop tick time with and without rerun recording, 200 vehicles.

Each tick does what the simulator / supervisor does for the whole swarm: locate every robot's
sub-tube (``Partition.locate``), neighbour candidates (``VerletPairs``), the velocity command
(``controller.velocity_command``, the paper's (ObstacleController)), a forward-Euler step and the
safety metrics (``metrics.SafetyMonitor``) — and then ``recorder.log_tick`` with positions,
velocities, phases, commands and the metrics. The loop is timed with recording off
(``NullRecorder``), on (every tick), and decimated; the time spent inside ``log_tick`` and in
``close`` (final send + flush) is reported separately, with the file size.

Run by hand (numbers go into the docs / report, never into tests):

    python bench/bench_recording.py                 # 200 vehicles, 600 ticks per variant
    python bench/bench_recording.py --rate-hz 20 --ticks 300 --repeat 1   # like the fleet
    python bench/bench_recording.py --rate-hz 20 --live --map             # live streaming

``--map`` anchors the scene geodetically (the ``[mission]`` of configs/mock_fleet.toml), so the
recorder also draws the map (WGS84: the outlines once, every vehicle's GeoPoints and trail).
``--live`` measures only: recording to the file (the baseline), the same with the web viewer
served (``serve_web``: the rerun server, no viewer), and served with a live viewer connected —
the rerun CLI as a gRPC client of the server, receiving the stream as a viewer does (and saving
it), without drawing.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from vtube_fleet.core.controller import TubeArrays, velocity_command
from vtube_fleet.core.metrics import SafetyMonitor
from vtube_fleet.core.neighbours import VerletPairs
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.partition import partition
from vtube_fleet.core.tube import Obstacle, Trapezoid
from vtube_fleet.recording.api import NullRecorder
from vtube_fleet.recording.writer import RerunRecorder, open_recorder


def scene(m: int) -> tuple[Trapezoid, tuple[Obstacle, ...], ControllerParams, np.ndarray]:
    """A wide tube with two obstacles and ``m`` robots on a grid behind them."""
    params = ControllerParams(r_s=0.25, r_a=0.5, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5)
    cols = 20
    rows = int(np.ceil(m / cols))
    width = cols * 1.2 + 4.0
    length = rows * 1.2 + 80.0
    tube = Trapezoid(np.array([0.0, 0.0]), np.array([length, 3.0]), np.array([0.0, width]),
                     np.array([length, width - 3.0]))
    obstacles = (Obstacle(np.array([rows * 1.2 + 30.0, width * 0.35]), 1.0),
                 Obstacle(np.array([rows * 1.2 + 45.0, width * 0.7]), 1.0))
    i, j = np.divmod(np.arange(m), cols)
    pos = np.stack([1.0 + 1.2 * i, 2.6 + 1.2 * j], axis=-1).astype(float)
    return tube, obstacles, params, pos


def run(m: int, ticks: int, recorder_factory, dt: float = 0.05,
        rate_hz: float | None = None, mission: object = None) -> dict[str, float]:
    tube, obstacles, params, p = scene(m)
    part = partition(tube, obstacles, params)
    mon = SafetyMonitor.from_params(tube, obstacles, params)
    verlet = VerletPairs(params.r_s + params.r_a, skin=0.5)
    ids = np.arange(m)
    phases = ["in_tube"] * m
    rec = recorder_factory()

    class _Scn:  # what log_scene reads from a Scenario
        pass

    scn = _Scn()
    scn.tube, scn.obstacles, scn.controller = tube, obstacles, params
    scn.robots = type("R", (), {"count": m, "v_min": params.v_min, "v_max": params.v_max,
                                "positions": p.copy(), "model": "single_integrator",
                                "nid_distance": None})()
    scn.source, scn.sim = "bench", None
    rec.log_scene(scn, part, meta={"dt_s": dt}, mission=mission)
    tick_s: list[float] = []
    log_s: list[float] = []
    prev_tick = 0.0
    cpu0 = time.process_time()
    wall0 = time.perf_counter()
    for k in range(ticks):
        t0 = time.perf_counter()
        sub = part.locate(p)
        pairs = verlet.candidates(p)
        vc = velocity_command(p, sub, TubeArrays.from_tubes(part.sub_tubes), params, pairs=pairs)
        p = p + dt * vc
        sm = mon.evaluate(p, vc, pairs=verlet.candidates(p))
        t1 = time.perf_counter()
        rec.log_tick(t_s=k * dt, tick=k, ids=ids, pos=p, vel=vc, phases=phases, cmd=vc,
                     metrics={"min_pair_distance_m": float(sm.min_pair_distance_m[0]),
                              "min_obstacle_center_distance_m":
                                  float(sm.min_obstacle_center_distance_m[0]),
                              "min_left_leg_distance_m": float(sm.min_left_leg_distance_m[0]),
                              "min_right_leg_distance_m": float(sm.min_right_leg_distance_m[0]),
                              "min_speed_m_s": float(sm.min_speed_m_s[0]),
                              "max_speed_m_s": float(sm.max_speed_m_s[0]),
                              "tick_duration_s": prev_tick})
        t2 = time.perf_counter()
        prev_tick = t2 - t0
        tick_s.append(t2 - t0)
        log_s.append(t2 - t1)
        if rate_hz:  # a paced control loop (the fleet): sleep until the next period
            time.sleep(max(0.0, wall0 + (k + 1) / rate_hz - time.perf_counter()))
    t0 = time.perf_counter()
    rec.close()
    close_s = time.perf_counter() - t0
    client = getattr(rec, "bench_client", None)
    if client is not None:  # the live viewer ends with the server
        client.wait(timeout=60)
    # process CPU (all threads, incl. the recorder's sender) and wall time per tick, close incl.
    cpu_ms = (time.process_time() - cpu0) / ticks * 1e3
    wall_ms = (time.perf_counter() - wall0) / ticks * 1e3
    size = 0
    if isinstance(rec, RerunRecorder) and rec.path is not None:
        size = rec.path.stat().st_size
    tick_ms = np.array(tick_s) * 1e3
    log_ms = np.array(log_s) * 1e3
    return {
        "tick_mean_ms": float(tick_ms.mean()),
        "tick_median_ms": float(np.median(tick_ms)),
        "tick_p99_ms": float(np.percentile(tick_ms, 99)),
        "log_mean_ms": float(log_ms.mean()),
        "log_p99_ms": float(np.percentile(log_ms, 99)),
        "log_max_ms": float(log_ms.max()),
        "close_s": close_s,
        "cpu_ms": cpu_ms,
        "wall_ms": wall_ms,
        "file_mb": size / 1e6,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=200)
    ap.add_argument("--ticks", type=int, default=600)
    ap.add_argument("--repeat", type=int, default=3, help="runs per variant (median reported)")
    ap.add_argument("--rate-hz", type=float, default=None,
                    help="pace the loop like the fleet (e.g. 20); default: back to back (sim)")
    ap.add_argument("--map", action="store_true",
                    help="a geodetic anchor: the recorder draws the map too")
    ap.add_argument("--live", action="store_true",
                    help="file / served / served with a gRPC viewer (module docstring)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_recording_"))
    mission = None
    if args.map:
        from vtube_fleet.config.mission import load_mission

        mission = load_mission(Path(__file__).resolve().parents[1] / "configs"
                               / "mock_fleet.toml").config

    def served(client: bool) -> RerunRecorder:
        import os
        import subprocess

        from vtube_fleet.recording.live import rerun_executable

        port = 19700
        rec = open_recorder(tmp / "w.rrd", kind="fleet", serve_web=port)
        if client:
            rec.bench_client = subprocess.Popen(  # type: ignore[attr-defined]
                [rerun_executable(), rec.web.grpc_url, "--save", str(tmp / "client.rrd"),
                 "--port", str(port + 2), "--bind", "127.0.0.1"],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                env={**os.environ, "RERUN_APP_ONLY": "true"})
        return rec  # type: ignore[return-value]

    variants = [
        ("no recording", lambda: NullRecorder()),
        ("recording, every tick", lambda: open_recorder(tmp / "d1.rrd", decimate=1)),
        ("recording, decimate 5", lambda: open_recorder(tmp / "d5.rrd", decimate=5)),
        ("recording, every tick, no sender thread",
         lambda: open_recorder(tmp / "s1.rrd", decimate=1, background=False)),
    ]
    if args.live:
        variants = [
            ("recording to the file", lambda: open_recorder(tmp / "f.rrd", kind="fleet")),
            ("+ served, no viewer", lambda: served(False)),
            ("+ served, a gRPC viewer connected", lambda: served(True)),
        ]
    pace = f"paced at {args.rate_hz:g} Hz" if args.rate_hz else "back to back"
    print(f"{args.vehicles} vehicles, {args.ticks} ticks per run ({pace}), median of "
          f"{args.repeat} runs")
    print("tick = one control-loop iteration incl. log_tick (caller's thread); log_tick = the "
          "recorder call alone;\ncpu/wall = process CPU time (all threads) and wall time per "
          "tick over the run incl. close")
    print(f"{'variant':<38} {'tick mean':>9} {'median':>8} {'p99':>8} | {'log_tick mean':>13} "
          f"{'p99':>7} {'max':>7} | {'cpu':>7} {'wall':>7} | {'close':>7} {'file':>8}")
    # interleaved (a, b, c, a, b, c, ...): a machine whose load changes hits every variant
    results: dict[str, list[dict[str, float]]] = {name: [] for name, _ in variants}
    for _ in range(args.repeat):
        for name, factory in variants:
            results[name].append(run(args.vehicles, args.ticks, factory, rate_hz=args.rate_hz,
                                     mission=mission))
    for name, _ in variants:
        runs = results[name]
        r = {k: statistics.median(x[k] for x in runs) for k in runs[0]}
        if args.live:
            print(f"{name}: tick p99 of each run " + ", ".join(
                f"{x['tick_p99_ms']:.2f}" for x in runs) + " ms")
        print(f"{name:<38} {r['tick_mean_ms']:8.3f}ms {r['tick_median_ms']:7.3f}ms "
              f"{r['tick_p99_ms']:7.3f}ms | {r['log_mean_ms']:12.3f}ms {r['log_p99_ms']:6.3f}ms "
              f"{r['log_max_ms']:6.3f}ms | {r['cpu_ms']:5.3f}ms {r['wall_ms']:5.3f}ms | "
              f"{r['close_s']:6.3f}s {r['file_mb']:6.2f}MB")


if __name__ == "__main__":
    main()
