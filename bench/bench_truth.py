"""Seed sweep: the shipped missions on the mock fleet with PX4 SITL's estimate errors (px4-sih),
judged by the ground truth (``run --truth``: HIL_STATE_QUATERNION from every mock vehicle).

    python bench/bench_truth.py                       # mock_fleet + px4_sitl_3, mavlink, 5 seeds
    python bench/bench_truth.py --backend mavsdk --seeds 3 --vehicles 4
    python bench/bench_truth.py --mission configs/px4_sitl_3.toml --seeds 10
    python bench/bench_truth.py --mission configs/route_mock.toml --seeds 3   # a route

One flight per (mission, seed), one after another (each flight uses the whole machine), the mock
vehicles on a free UDP port range (other runs may hold PX4's 14540 range). Prints one line per
flight and, per mission, the worst TRUE clearance against each limit: pair (2 r_s), legs (r_s;
on a route to the segment each vehicle flies), obstacle centre (r_o + r_s). Not part of the
tests: it takes about a minute a flight (two and a half for the route).
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from fleet_ports import free_ports  # noqa: E402

from vtube_fleet.config.mission import load_mission  # noqa: E402
from vtube_fleet.fleet.launch import fly  # noqa: E402

KEYS = ("truth_min_pair_distance_m", "truth_min_pair_distance_airborne_m",
        "truth_min_left_leg_distance_m", "truth_min_right_leg_distance_m",
        "truth_min_obstacle_center_distance_m")


def _f(x: float | None) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.3f}"


async def one(path: Path, backend: str, seed: int, vehicles: int | None) -> dict:
    mission = load_mission(path)
    if vehicles is not None and vehicles < mission.count:
        mission = mission.with_vehicles(vehicles)
    with tempfile.TemporaryDirectory() as out:
        result = await fly(mission, backend=backend, out_dir=Path(out), truth=True,
                           mock_kwargs={"boot_time_scale": 0.3, "seed": seed,
                                        "estimator": "px4-sih",
                                        "port_scheme": free_ports(mission.count)})
    s = result.summary
    return {"outcome": result.outcome, "exit": result.exit_code, **{k: s.get(k) for k in KEYS},
            "violations": s.get("violations"), "truth_violations": s.get("truth_violations"),
            "delta": s["safety_budget"]["delta_m"], "robots": s.get("robots"),
            "segments": s.get("segments"), "flight": s.get("flight_time_s"),
            "r_s": s.get("r_s"), "residual_p99": (s.get("estimate_compensation") or {}).get(
                "residual_p99_m_s")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mission", action="append", type=Path,
                    help="mission file (repeatable; default: both shipped missions)")
    ap.add_argument("--backend", choices=("mavlink", "mavsdk"), default="mavlink")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=100)
    ap.add_argument("--vehicles", type=int, default=None, help="fly only the first N slots")
    args = ap.parse_args()
    missions = args.mission or [ROOT / "configs" / "mock_fleet.toml",
                                ROOT / "configs" / "px4_sitl_3.toml"]
    for path in missions:
        rows = []
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            t0 = time.monotonic()
            r = asyncio.run(one(path, args.backend, seed, args.vehicles))
            rows.append(r)
            print(f"{path.name} {args.backend} seed {seed}: {r['outcome']} (exit {r['exit']}), "
                  f"{r['robots']} vehicles, {r['segments']} segment(s), flight "
                  f"{_f(r['flight'])} s, δ {r['delta']:.3f} m; TRUE pair "
                  f"{_f(r['truth_min_pair_distance_m'])} (airborne "
                  f"{_f(r['truth_min_pair_distance_airborne_m'])}), legs "
                  f"{_f(r['truth_min_left_leg_distance_m'])} / "
                  f"{_f(r['truth_min_right_leg_distance_m'])}, obstacle centre "
                  f"{_f(r['truth_min_obstacle_center_distance_m'])}; violations telemetry "
                  f"{r['violations']} truth {r['truth_violations']}; compensation residual p99 "
                  f"{_f(r['residual_p99'])} m/s; {time.monotonic() - t0:.0f} s", flush=True)

        def worst(key: str, rows: list[dict] = rows) -> float:
            vals = [r[key] for r in rows if r[key] is not None]
            return min(vals) if vals else math.nan

        r_s = rows[0]["r_s"]
        mission = load_mission(path)
        obs = [o.radius + r_s for o in mission.scenario.obstacles]
        print(f"== {path.name} {args.backend}: {len(rows)} runs, "
              f"{sum(r['outcome'] == 'completed' for r in rows)} completed, "
              f"{sum((r['truth_violations'] or 0) > 0 for r in rows)} with truth violations; "
              f"worst TRUE pair {_f(worst('truth_min_pair_distance_m'))} m (limit {2 * r_s:g}), "
              f"airborne {_f(worst('truth_min_pair_distance_airborne_m'))} m, left leg "
              f"{_f(worst('truth_min_left_leg_distance_m'))} m, right leg "
              f"{_f(worst('truth_min_right_leg_distance_m'))} m (limit {r_s:g}), obstacle centre "
              f"{_f(worst('truth_min_obstacle_center_distance_m'))} m (limit "
              f"{min(obs) if obs else math.nan:g})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
