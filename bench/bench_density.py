"""How dense a fleet the safety budget lets through, and what the truth says about it (issue 30).

    python bench/bench_density.py geometry                     # δ, smallest spacing, narrowest tube
    python bench/bench_density.py geometry --tree /work/main   # … with another checkout ("before")
    python bench/bench_density.py fly --seeds 20               # the shipped mock mission, truth
    python bench/bench_density.py fly --mission configs/px4_sitl_3.toml --backend mavsdk --seeds 5
    python bench/bench_density.py fly --family 6 --seeds 3     # a family mission, 6 vehicles
    python bench/bench_density.py fly --seeds 3 --fault push   # the mock's disturbance fault
    python bench/bench_density.py fly --seeds 3 --fault latency
    python bench/bench_density.py geometry --tracking reference                # reference tracking
    python bench/bench_density.py geometry --tracking reference --sigma 0.02   # … RTK (σ 0.02 m)
    python bench/bench_density.py fly --tracking reference --seeds 10
    python bench/bench_density.py fly --tracking reference --estimator rtk --seeds 5
    python bench/bench_density.py fly --tracking reference --seeds 3 --fault slow
    python bench/bench_density.py fly --seeds 5 --fault slow-start  # refused in the hover

``geometry``: for the shipped missions and a family of N-vehicle missions (a straight tube 40 m
long with a pole at x = 22 m, the vehicles on a grid of ⌈√N⌉ columns (even) from x = 3 m), the δ the
runtime computes for the mock's figures (σ = 0.29 m as px4-sih reports, L = 0.1 s as the
runtime measures on the mock), whether each mission is accepted (the same check as the
preflight: ``fleet/margin.slot_violations``), the smallest grid spacing accepted (in a 60 m
wide tube) and the narrowest tube accepted with that spacing (0.05 m steps). ``fly``: flights
on the in-process mock (px4-sih, ground truth from the mock's HIL_STATE_QUATERNION, ``run
--truth``), one after another, each on free ports, printing δ, the outcome and the TRUE
clearances per flight and the worst over the seeds; ``--fault push`` gives every vehicle a 1 s
gust of 0.8 m/s across the tube 30 s after its start (the disturbance it holds against),
``--fault latency`` 40 ms more one-way delay on every link (plus 5 % loss), ``--fault slow``
vehicle 0 following only 40 % of its horizontal command from 30 s after its start (PX4's response
slower than the partition was built for: with reference tracking the tube holds),
``--fault slow-start`` the same from its start (the response check refuses it in the hover,
before the tube; every flight prints the check's worst lag against its model).
``--tracking reference`` flies (and judges the geometry of) every mission with reference tracking
(docs/fleet.md), its own default k; ``--sigma`` the σ the geometry assumes, ``--estimator`` the
mock's estimate error profile in flight (``rtk``: σ = 0.02 m).

``--tree PATH`` runs it with another checkout's ``vtube_fleet`` (the budget before a change):
each part runs in a child process with that tree first on its path. Not part of the tests:
a flight takes about a minute and a half on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

FAMILY = (3, 6, 12, 24)
#: What the runtime measures on the mock (px4-sih): σ reported, L (position age + setpoint
#: delay; the budget adds latency_headroom_s).
MOCK_SIGMA_M = 0.29
MOCK_L_S = 0.1

FAMILY_TEMPLATE = """\
[tube]
p_h0 = [0.0, {half}]
p_h1 = [40.0, {half}]
p_r0 = [0.0, -{half}]
p_r1 = [40.0, -{half}]

[[obstacles]]
center = [22.0, 0.0]
radius = 0.5

[robots]
model = "single_integrator"
r_s = 0.3
r_a = 1.0
v_min = 0.3
v_max = 1.6
positions = {positions}

[controller]
v = 1.0
v_max_prime = 0.5

[mission]
origin_lat_deg = 47.397742
origin_lon_deg = 8.545594
origin_alt_m = 488.0
heading_deg = 0.0
altitude_m = 3.0
rate_hz = 20.0
climb_speed_m_s = 1.5
mission_timeout_s = 180.0
"""


def family_cols(n: int) -> int:
    """The columns of the family's grid: ⌈√N⌉ rounded up to an even number (no slot on the
    pole's axis)."""
    return max(2, 2 * math.ceil(math.sqrt(n) / 2.0))


def family_positions(n: int, spacing: float) -> list[list[float]]:
    """N slots on a grid of :func:`family_cols` columns across the tube (centred on y = 0),
    rows from x = 3."""
    cols = family_cols(n)
    rows = math.ceil(n / cols)
    out = []
    for k in range(n):
        r, c = divmod(k, cols)
        out.append([3.0 + r * spacing, (c - (cols - 1) / 2.0) * spacing])
    assert len(out) == n and rows >= 1
    return out


def family_text(n: int, spacing: float, width: float) -> str:
    pos = [[round(x, 4), round(y, 4)] for x, y in family_positions(n, spacing)]
    return FAMILY_TEMPLATE.format(half=round(width / 2.0, 4), positions=json.dumps(pos))


def with_tracking(text: str, tracking: str) -> str:
    """A mission's text flown with ``tracking`` (its own line replaced, or one added to
    ``[mission]``)."""
    lines = [x for x in text.splitlines() if not x.strip().startswith("tracking =")]
    at = lines.index("[mission]") + 1
    return "\n".join(lines[:at] + [f'tracking = "{tracking}"'] + lines[at:]) + "\n"


def _child(tree: Path | None, *args: str) -> Any:
    """Run this script's hidden ``args`` mode in a child whose ``vtube_fleet`` comes from
    ``tree`` (default: this checkout); its last stdout line is JSON."""
    env = dict(os.environ)
    src = str(tree or ROOT)
    env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["BENCH_DENSITY_TREE"] = src
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), *args], env=env,
                         capture_output=True, text=True, check=False)
    lines = [x for x in out.stdout.splitlines() if x.startswith("{")]
    if out.returncode != 0 or not lines:
        raise SystemExit(f"error: child {' '.join(args)} failed (exit {out.returncode}): "
                         f"{out.stderr.strip().splitlines()[-1:] or out.stdout[-300:]}")
    return json.loads(lines[-1])


# ----------------------------------------------------------------------------------------------
# geometry (in the child)
# ----------------------------------------------------------------------------------------------
def _geometry_child(tracking: str, sigma: float, missions: list[str]) -> dict[str, Any]:
    from vtube_fleet.config.mission import load_mission
    from vtube_fleet.fleet.budget import LinkMeasurement
    from vtube_fleet.fleet.margin import slot_violations

    measured = LinkMeasurement(MOCK_L_S, 0.0, sigma)

    def judge(path: Path) -> tuple[float, list[str]]:
        if tracking != "as-is":
            path.write_text(with_tracking(path.read_text(), tracking))
        budget, _, _, viol = slot_violations(load_mission(path), measured)
        return budget.delta_m, [v.message for v in viol]

    out: dict[str, Any] = {"missions": {}, "family": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for m in missions:
            copy = Path(tmp) / Path(m).name
            copy.write_text(Path(m).read_text())
            delta, viol = judge(copy)
            out["missions"][Path(m).name] = {"delta_m": delta, "accepted": not viol,
                                             "first_problem": viol[0] if viol else None}
        for n in FAMILY:
            path = Path(tmp) / f"family_{n}.toml"

            def ok(spacing: float, width: float, path: Path = path, n: int = n) -> bool:
                path.write_text(family_text(n, spacing, width))
                return not judge(path)[1]

            lo, hi = 0.6, 8.0  # spacing: bisection to 1 cm in a 60 m wide tube
            if not ok(hi, 60.0):
                out["family"][n] = {"spacing_m": None, "width_m": None}
                continue
            while hi - lo > 0.01:
                mid = 0.5 * (lo + hi)
                lo, hi = (lo, mid) if ok(mid, 60.0) else (mid, hi)
            spacing = math.ceil(hi * 100.0 - 1e-6) / 100.0
            while not ok(spacing, 60.0):
                spacing += 0.01
            cols = family_cols(n)
            wlo, whi = (cols - 1) * spacing, 60.0
            while whi - wlo > 0.05:
                mid = 0.5 * (wlo + whi)
                wlo, whi = (wlo, mid) if ok(spacing, mid) else (mid, whi)
            path.write_text(family_text(n, spacing, whi))
            delta = judge(path)[0]
            out["family"][n] = {"spacing_m": spacing, "width_m": round(whi, 2),
                                "delta_m": delta}
    return out


# ----------------------------------------------------------------------------------------------
# one flight (in the child)
# ----------------------------------------------------------------------------------------------
KEYS = ("truth_min_pair_distance_m", "truth_min_left_leg_distance_m",
        "truth_min_right_leg_distance_m", "truth_min_obstacle_center_distance_m",
        "min_pair_distance_m", "truth_violations", "violations")


def _fly_child(mission: str, backend: str, seed: int, fault: str, vehicles: int,
               tracking: str, estimator: str) -> dict:
    import asyncio

    sys.path.insert(0, str(ROOT / "tests"))
    from fleet_ports import free_ports

    from sim_stub import Faults
    from vtube_fleet.config.mission import load_mission
    from vtube_fleet.fleet.launch import fly

    with tempfile.TemporaryDirectory() as out:
        path = Path(mission)
        if tracking != "as-is":
            path = Path(out) / Path(mission).name
            path.write_text(with_tracking(Path(mission).read_text(), tracking))
        m = load_mission(path)
        if vehicles and vehicles < m.count:
            m = m.with_vehicles(vehicles)
        kw: dict[str, Any] = {"boot_time_scale": 0.3, "seed": seed, "estimator": estimator,
                              "port_scheme": free_ports(m.count)}
        if fault == "push":  # a 1 s gust of 0.8 m/s across the tube (east: tube −y), 30 s in
            kw["faults"] = Faults(push_east_m_s=0.8, push_at_s=30.0, push_for_s=1.0)
        elif fault == "latency":
            kw["faults"] = Faults(latency_s=0.04, loss_pct=5.0)
        elif fault == "slow":  # vehicle 0 follows 40 % of its command from 30 s on
            kw["faults"] = [Faults(slow_gain=0.4, slow_at_s=30.0)] + [None] * (m.count - 1)
        elif fault == "slow-start":  # vehicle 0 follows 40 % of its command from the start
            kw["faults"] = [Faults(slow_gain=0.4, slow_at_s=0.0)] + [None] * (m.count - 1)
        t0 = time.monotonic()
        r = asyncio.run(fly(m, backend=backend, out_dir=Path(out), truth=True,
                            mock_kwargs=kw))
    s = r.summary
    trk = s.get("reference_tracking") or {}
    rc = s.get("response_check") or {}
    rw = s.get("response_watch") or {}
    lags = [x for x in rc.get("lag_start_s", []) + rc.get("lag_stop_s", []) if x is not None]
    return {"outcome": r.outcome, "exit": r.exit_code, "reason": r.reason[:300],
            "response_lag_start_s": rc.get("lag_start_s"), "response_allowed_s":
            rc.get("allowed_lag_s"), "response_tolerance_s": rc.get("tolerance_s"),
            "response_refused": rc.get("refused"), "response_skipped": rc.get("skipped"),
            "response_lag_max_s": max(lags) if lags else None,
            "watch_max_m": rw.get("max_m"), "watch_tolerance_m": rw.get("tolerance_m"),
            "delta_m": s["safety_budget"]["delta_m"], "robots": s.get("robots"),
            "r_s": s.get("r_s"), "tracking_max_m": trk.get("error_max_m"),
            "truth_offset_max_m": trk.get("truth_offset_max_m"),
            "wall_s": round(time.monotonic() - t0, 1), **{k: s.get(k) for k in KEYS}}


# ----------------------------------------------------------------------------------------------
def _f(x: Any) -> str:
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.3f}"


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] in ("_geometry", "_fly"):
        if sys.argv[1] == "_geometry":
            print(json.dumps(_geometry_child(sys.argv[2], float(sys.argv[3]), sys.argv[4:])))
        else:
            _, _, mission, backend, seed, fault, vehicles, tracking, estimator = sys.argv
            print(json.dumps(_fly_child(mission, backend, int(seed), fault, int(vehicles),
                                        tracking, estimator)))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    g = sub.add_parser("geometry", help="δ, smallest spacing, narrowest tube")
    f = sub.add_parser("fly", help="flights on the mock, judged by the truth")
    for p in (g, f):
        p.add_argument("--tree", type=Path, default=None,
                       help="a checkout whose vtube_fleet to use (default: this one)")
        p.add_argument("--json", type=Path, default=None, help="also write the results here")
        p.add_argument("--tracking", choices=("as-is", "velocity", "reference"),
                       default="as-is", help="fly / judge every mission with this tracking "
                       "(default: as each mission says)")
    g.add_argument("--sigma", type=float, default=MOCK_SIGMA_M,
                   help=f"the σ the budget is built on (default {MOCK_SIGMA_M}: px4-sih)")
    f.add_argument("--estimator", choices=("px4-sih", "rtk"), default="px4-sih")
    f.add_argument("--mission", type=Path, default=ROOT / "configs" / "mock_fleet.toml")
    f.add_argument("--family", type=int, default=None,
                   help="fly the family mission of N vehicles at its smallest accepted "
                        "spacing + 0.3 m and narrowest tube + 0.5 m (geometry first)")
    f.add_argument("--backend", choices=("mavlink", "mavsdk"), default="mavlink")
    f.add_argument("--seeds", type=int, default=5)
    f.add_argument("--first-seed", type=int, default=100)
    f.add_argument("--vehicles", type=int, default=0, help="fly only the first N slots")
    f.add_argument("--fault", choices=("none", "push", "latency", "slow", "slow-start"),
                   default="none")
    args = ap.parse_args()
    results: dict[str, Any] = {"tree": str(args.tree or ROOT), "what": args.what}
    if args.what == "geometry":
        shipped = [str(ROOT / "configs" / "mock_fleet.toml"),
                   str(ROOT / "configs" / "px4_sitl_3.toml")]
        geo = _child(args.tree, "_geometry", args.tracking, str(args.sigma), *shipped)
        results.update(geo)
        print(f"tree {results['tree']}: σ = {args.sigma} m, L = {MOCK_L_S} s, tracking "
              f"{args.tracking}")
        for name, r in geo["missions"].items():
            print(f"  {name}: δ = {r['delta_m']:.3f} m, "
                  + ("accepted" if r["accepted"] else f"REFUSED: {r['first_problem']}"))
        for n, r in geo["family"].items():
            if r["spacing_m"] is None:
                print(f"  family {n} vehicles: nothing accepted")
                continue
            print(f"  family {n} vehicles: δ = {r['delta_m']:.3f} m, smallest spacing "
                  f"{r['spacing_m']:.2f} m, narrowest tube {r['width_m']:.2f} m")
    else:
        mission = args.mission
        tmp = None
        if args.family:
            geo = _child(args.tree, "_geometry", args.tracking,
                         str(0.02 if args.estimator == "rtk" else MOCK_SIGMA_M)
                         )["family"][str(args.family)]
            if geo["spacing_m"] is None:
                raise SystemExit(f"error: the family mission of {args.family} vehicles is "
                                 f"accepted at no spacing")
            tmp = tempfile.TemporaryDirectory()
            mission = Path(tmp.name) / f"family_{args.family}.toml"
            mission.write_text(family_text(args.family, geo["spacing_m"] + 0.3,
                                           geo["width_m"] + 0.5))
            print(f"family {args.family}: spacing {geo['spacing_m'] + 0.3:.2f} m, tube "
                  f"{geo['width_m'] + 0.5:.2f} m")
        rows = []
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            r = _child(args.tree, "_fly", str(mission), args.backend, str(seed), args.fault,
                       str(args.vehicles), args.tracking, args.estimator)
            rows.append({"seed": seed, **r})
            print(f"{mission.name} {args.backend} seed {seed} fault {args.fault}: {r['outcome']} "
                  f"(exit {r['exit']}), {r['robots']} vehicles, δ {r['delta_m']:.3f} m; TRUE "
                  f"pair {_f(r['truth_min_pair_distance_m'])}, legs "
                  f"{_f(r['truth_min_left_leg_distance_m'])} / "
                  f"{_f(r['truth_min_right_leg_distance_m'])}, obstacle centre "
                  f"{_f(r['truth_min_obstacle_center_distance_m'])}; violations truth "
                  f"{r['truth_violations']} telemetry {r['violations']}; tracking error max "
                  f"{_f(r['tracking_max_m'])}, TRUE |p − r| max {_f(r['truth_offset_max_m'])}"
                  f"; response lag max {_f(r['response_lag_max_s'])} s (model "
                  f"{r['response_allowed_s']}, tolerance {r['response_tolerance_s']}, refused "
                  f"{r['response_refused']}); response watch max {_f(r['watch_max_m'])} m "
                  f"(tolerance {_f(r['watch_tolerance_m'])} m)"
                  f"; {r['wall_s']:.0f} s" + ("" if r["exit"] == 0 else f"; {r['reason']}"),
                  flush=True)

        def worst(key: str) -> float | None:
            vals = [r[key] for r in rows if r.get(key) is not None]
            return min(vals) if vals else None

        r_s = rows[0]["r_s"] if rows else math.nan
        print(f"== {mission.name} {args.backend} fault {args.fault}: {len(rows)} flights, "
              f"{sum(r['outcome'] == 'completed' for r in rows)} completed, "
              f"{sum((r['truth_violations'] or 0) > 0 for r in rows)} with truth violations; "
              f"worst TRUE pair {_f(worst('truth_min_pair_distance_m'))} m (limit "
              f"{2 * r_s:g}), legs {_f(worst('truth_min_left_leg_distance_m'))} / "
              f"{_f(worst('truth_min_right_leg_distance_m'))} m (limit {r_s:g}), obstacle "
              f"centre {_f(worst('truth_min_obstacle_center_distance_m'))} m", flush=True)
        results["flights"] = rows
        if tmp is not None:
            tmp.cleanup()
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
