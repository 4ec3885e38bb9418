"""Benchmark: lose one vehicle anywhere in the tube — does the rest of the fleet finish?

    python bench/bench_loss.py screen [--mission configs/px4_sitl_3.toml ...] [--every 0.5]
                                      [--json]
    python bench/bench_loss.py fly    [--mission ...] [--cases 8] [--rules new|today]
                                      [--seed 0] [--only K ...] [--keep DIR] [--json]

For the shipped missions (default ``configs/px4_sitl_3.toml`` and ``configs/mock_fleet.toml``)
a single vehicle is lost at many places and times in the tube:

``screen`` (pure geometry, ~1-2 min for both missions): the mission flown by the simulator with
the radii inflated by the safety budget of the real PX4 SITL flight (position age 47.4 ms +
setpoint delay 0.3 ms, σ = 0.296 m → δ = 1.677 m, r_s' = 1.977 m: ``docs/fleet.md``) gives
the positions; at every ``--every`` seconds each vehicle still in the tube is the lost one,
at its position then (an obstacle of radius r_s + ``lost_obstacle_margin_m``), the others
where they are ``lost_after_s`` later, when the loss is declared. For each loss it tells

* whether the tube can be re-partitioned around it with today's rules (1.05 h_min, then the
  planner: steps 1-2 of ``core/loss.py``) and with the fallback (step 3);
* how many of the others are inside a new triangle (:func:`~vtube_fleet.core.loss.
  cannot_pass`: they cannot be given a safe sub-tube and must hold) — a loss after which
  nobody is is one after which the rest can finish; and how many stay inside with a
  partition of their own (:func:`~vtube_fleet.core.loss.partition_past`: the obstacles they
  have passed left out, as the fleet does);
* how many are within r_s' of a new triangle side (Assumption 1 to the letter);
* for reference, how many have no path at all to the finishing line that keeps their centre
  out of every extended disc and r_s' inside the legs with a lateral slope ≤ tan α_max
  (ignoring each other): no partition under (pothk) could let those pass;
* the time one re-partition takes.

``fly`` (~1 min per flight, run one after another at ``nice`` 10): ``--cases`` losses per
mission, spread over the vehicles and over their time in the tube, each a real flight of the
built-in mock (sim_stub, PX4 SITL's estimate errors, ground truth): vehicle i's link dies
(``silent``: PX4's offboard-loss failsafe lands it) t seconds into the tube. It reports per
flight and in total: re-partitioned (and how), or why not (no partition; or a vehicle inside
the new region: the supervisor then aborts, as for no partition), how many of the others
exited, the ground truth (violations, the first one, worst pair), the outcome. Flights that
the budget watch ended because our own loop stalled (a loaded machine) are counted apart.
``--rules today`` flies today's rules (the fallback switched off).

Run by hand (not in CI).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import math
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sim_stub.ports import free_port_scheme  # noqa: E402
from vtube_fleet.config.mission import Mission, load_mission  # noqa: E402
from vtube_fleet.core import loss  # noqa: E402
from vtube_fleet.core.params import ControllerParams  # noqa: E402
from vtube_fleet.core.partition import PartitionError, alpha_max, apex_zones, h_min  # noqa: E402
from vtube_fleet.core.tube import Obstacle, Trapezoid  # noqa: E402
from vtube_fleet.fleet.budget import LinkMeasurement, mission_budget  # noqa: E402
from vtube_fleet.fleet.flight_plan import LOST_APEX_FACTOR, FlightPlan  # noqa: E402
from vtube_fleet.sim import simulate  # noqa: E402

MISSIONS = ("configs/px4_sitl_3.toml", "configs/mock_fleet.toml")
#: the link the real PX4 SITL flight measured (docs/fleet.md): δ = 1.677 m, r_s' = 1.977 m
SITL_LINK = LinkMeasurement(position_age_s=0.0474, setpoint_delay_s=0.0003, accuracy_m=0.2958)


def today_only() -> None:
    """Today's rules: the fallback (step 3 of core/loss.py) switched off."""
    loss._grouped = lambda *a, **k: (None, 0)  # type: ignore[assignment]


def flown_params(mission: Mission) -> ControllerParams:
    return mission_budget(mission, SITL_LINK).inflate(mission.scenario.controller)


def lost_radius(mission: Mission) -> float:
    return mission.scenario.controller.r_s + mission.config.lost_obstacle_margin_m


# ----------------------------------------------------------------------------------------------
# screening
# ----------------------------------------------------------------------------------------------
def nominal_flight(mission: Mission, flown: ControllerParams, every_s: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(t (T,), positions (T, M, 2), NaN once exited): the simulator flying the mission's
    slots with the flown radii."""
    sc = mission.scenario
    robots = dataclasses.replace(sc.robots, positions=np.asarray(mission.slots, float),
                                 r_s=flown.r_s, r_a=flown.r_a)
    sc = dataclasses.replace(sc, controller=flown, robots=robots).with_sim(
        duration=3.0 * sc.tube.length / flown.v + 20.0)
    every = max(1, int(round(every_s / sc.sim.dt)))
    res = simulate(sc, validate=False, record_every=every)
    return res.t, res.pos


def no_path(tube: Trapezoid, centers: np.ndarray, radii: np.ndarray, starts: np.ndarray,
            slope: float, r_s: float, dw: float = 0.05) -> np.ndarray:
    """(M,) True where a start has no path to the finishing line moving forward with lateral
    slope ≤ ``slope``, keeping its centre outside every disc and ``r_s`` inside the legs
    (a sweep in ξ over a lateral grid of ``dw``; the vehicles ignore each other)."""
    n_c, m = tube.n_c, tube.m
    L = tube.length
    dxi = dw / slope
    xi0 = (starts - tube.p_h0) @ n_c
    w0 = (starts - tube.p_h0) @ m
    cx = (centers - tube.p_h0) @ n_c
    cw = (centers - tube.p_h0) @ m
    lo = min(float((tube.lh(z) - tube.p_h0) @ m) for z in (0.0, L)) - 1.0
    hi = max(float((tube.lr(z) - tube.p_h0) @ m) for z in (0.0, L)) + 1.0
    grid = np.arange(lo, hi + dw, dw)
    reach = np.abs(grid[None, :] - w0[:, None]) <= dw / 2 + 1e-12  # (M, G)
    alive = np.ones(len(starts), bool)
    z = float(xi0.min())
    while z < L and alive.any():
        started = xi0 <= z
        lh = float((tube.lh(z) - tube.p_h0) @ m)
        lr = float((tube.lr(z) - tube.p_h0) @ m)
        free = (grid >= lh + r_s) & (grid <= lr - r_s)
        dz = z - cx
        for j in np.flatnonzero(np.abs(dz) < radii):
            half = math.sqrt(radii[j] ** 2 - dz[j] ** 2)
            free &= ~((grid > cw[j] - half) & (grid < cw[j] + half))
        reach[started] &= free
        alive &= reach.any(axis=1)
        grown = reach.copy()
        grown[:, 1:] |= reach[:, :-1]
        grown[:, :-1] |= reach[:, 1:]
        reach = np.where(started[:, None], grown, reach)
        z += dxi
    return ~alive


def flies_own(tube: Trapezoid, fixed: tuple[Obstacle, ...], stops: Sequence[Obstacle],
              flown: ControllerParams, q: np.ndarray) -> bool:
    """Whether a vehicle at ``q`` inside a region of the partition around ``stops`` has a
    partition of its own (:func:`~vtube_fleet.core.loss.partition_past`) it is outside every
    region of: it flies on with that one (the runtime's rule)."""
    try:
        own = loss.partition_past(tube, fixed, stops, flown, q)
    except PartitionError:
        return False
    return own is not None and loss.wall_clearance(own, q[None], apex_zones(own, flown))[0] >= 0.0


def wait_and_step(tube: Trapezoid, fixed: tuple[Obstacle, ...], lost: Obstacle,
                  others: np.ndarray, trapped: np.ndarray, flown: ControllerParams,
                  r_lost: float, apart: bool = True) -> tuple[bool, int, str]:
    """``on_trapped = "wait"`` on a snapshot: the ``trapped`` of ``others`` stop where they
    are (obstacles); the re-partition around them may trap more, those without a partition
    of their own (:func:`flies_own`; repeated until nobody new is inside); once the rest
    has left, the waiting ones go front-most first, each stepping aside
    (:func:`~vtube_fleet.core.loss.step_aside`) in the partition around the lost one and
    those still waiting; one without a path waits again, once, while others wait (the
    runtime's rule). ``apart``: where there is no common partition, each vehicle flies one
    of its own or waits, and one stepping aside steps straight across into its own (the
    runtime's "no common partition"); else that ends the run. → (everyone finishes, how
    many waited, why not)."""
    def obstacle(q: np.ndarray) -> Obstacle:
        return Obstacle(np.asarray(q, float), r_lost, LOST_APEX_FACTOR * h_min(r_lost, flown))

    waiting = np.asarray(trapped, bool).copy()
    for _ in range(len(others) + 1):
        stops = (lost, *(obstacle(q) for q in others[waiting]))
        try:
            part = loss.repartition_around_lost(tube, fixed, stops, flown).partition
            d = loss.wall_clearance(part, others, apex_zones(part, flown))
            new = (d < 0.0) & ~waiting
        except PartitionError:
            if not apart:
                return False, int(waiting.sum()), "no partition around the waiting ones"
            new = ~waiting
        for j in np.flatnonzero(new):  # past some of them: flies a partition of its own
            if flies_own(tube, fixed, stops, flown, others[j]):
                new[j] = False
        if not new.any():
            break
        waiting |= new
    order = np.flatnonzero(waiting)
    queue = [(int(v), 0) for v in order[np.argsort(-tube.xi(others[order]), kind="stable")]]
    n = len(queue)
    while queue:  # the farthest along first; one without a path waits again, once
        queue.sort(key=lambda e: e[1])  # (stable: those released fewer times first)
        w, tries = queue.pop(0)
        rest = (lost, *(obstacle(others[v]) for v, _ in queue))
        back = 15.0
        try:
            part = loss.repartition_around_lost(tube, fixed, rest, flown).partition
        except PartitionError:
            own = None
            if apart:
                with contextlib.suppress(PartitionError):
                    own = loss.partition_past(tube, fixed, rest, flown, others[w])
            if own is None:
                return False, n, "no partition for one stepping aside"
            part, back = own, 0.0  # (its own: straight across only)
        path = loss.step_aside(tube, part, (*fixed, *rest), flown, others[w],
                               zones=apex_zones(part, flown), max_back_m=back)
        if path is None:
            if tries == 0 and queue:
                queue.append((w, 1))
                continue
            return False, n, "no step aside"
    return True, n, ""


def screen(path: str, every_s: float) -> dict[str, Any]:
    mission = load_mission(ROOT / path)
    sc = mission.scenario
    flown = flown_params(mission)
    r_lost = lost_radius(mission)
    root = FlightPlan.for_mission(mission, flown)
    tri_h = {tr.obstacle: tr.h for tr in root.route.segments[0].partition.triangles}
    fixed = tuple(dataclasses.replace(o, apex_distance=tri_h[i]) if i in tri_h else o
                  for i, o in enumerate(root.corridor.obstacles))  # (as Route.with_lost)
    t, pos = nominal_flight(mission, flown, every_s)
    lag = int(round(mission.config.lost_after_s / every_s))
    slope = math.tan(alpha_max(flown))
    oc = np.array([o.center for o in fixed]).reshape(-1, 2)
    orad = np.array([o.radius + flown.r_s for o in fixed])
    rows = []
    times = []
    for k in range(len(t)):
        for i in range(pos.shape[1]):
            p = pos[k, i]
            if not np.all(np.isfinite(p)) or not bool(sc.tube.contains(p)):
                continue
            if bool(sc.tube.finished(p, flown.eps_0)):
                continue
            k2 = min(k + lag, len(t) - 1)
            others = np.delete(pos[k2], i, axis=0)
            others = others[np.all(np.isfinite(others), axis=1)]
            others = others[~sc.tube.finished(others, flown.eps_0)]
            lost = (Obstacle(p, r_lost, LOST_APEX_FACTOR * h_min(r_lost, flown)),)
            row: dict[str, Any] = {"t_s": float(t[k]), "vehicle": i, "x": float(p[0]),
                                   "y": float(p[1]), "others": len(others)}
            t0 = time.perf_counter()
            try:
                rp = loss.repartition_around_lost(sc.tube, fixed, lost, flown)
            except PartitionError:
                rp = None
            times.append(time.perf_counter() - t0)
            row["step"] = rp.step if rp is not None else None
            row["inside_own"] = 0
            row["wait_ok"], row["waited"], row["wait_why"] = rp is not None, 0, ""
            row["wait_ok_no_apart"] = rp is not None
            if rp is not None and len(others):
                zones = apex_zones(rp.partition, flown)
                d = loss.wall_clearance(rp.partition, others, zones)
                row["inside"] = int(np.count_nonzero(d < 0.0))
                row["within_rs"] = int(np.count_nonzero(d < flown.r_s))
                trapped = np.zeros(len(others), bool)
                for j in np.flatnonzero(d < 0.0):  # each trapped one: a partition of its own?
                    if not flies_own(sc.tube, fixed, lost, flown, others[j]):
                        row["inside_own"] += 1
                        trapped[j] = True
                if trapped.any():
                    row["wait_ok"], row["waited"], row["wait_why"] = wait_and_step(
                        sc.tube, fixed, lost[0], others, trapped, flown, r_lost)
                    row["wait_ok_no_apart"] = wait_and_step(
                        sc.tube, fixed, lost[0], others, trapped, flown, r_lost,
                        apart=False)[0]
            else:
                row["inside"] = row["within_rs"] = 0
            if len(others):
                row["no_path"] = int(np.count_nonzero(no_path(
                    sc.tube, np.vstack([oc, p[None]]), np.append(orad, r_lost + flown.r_s),
                    others, slope, flown.r_s)))
            else:
                row["no_path"] = 0
            rows.append(row)
    n = len(rows)
    today = [r for r in rows if r["step"] in ("as given", "planned")]
    new = [r for r in rows if r["step"] is not None]

    def share(k: int) -> str:
        return f"{k} ({100.0 * k / n:.1f} %)"

    ms = 1000.0 * np.asarray(times)
    out = {
        "mission": path, "losses": n, "every_s": every_s, "r_s_flown": flown.r_s,
        "repartition_today": len(today), "repartition_new": len(new),
        "rest_go_on_today": sum(r["inside"] == 0 for r in today),
        "rest_go_on_new": sum(r["inside"] == 0 for r in new),
        "rest_go_on_own": sum(r["inside_own"] == 0 for r in new),
        "rest_finish_wait": sum(r["wait_ok"] for r in new),
        "rest_finish_wait_no_apart": sum(r["wait_ok_no_apart"] for r in new),
        "wait_fails": {w: sum(not r["wait_ok"] and r["wait_why"] == w for r in new) for w in
                       ("no partition around the waiting ones",
                        "no partition for one stepping aside", "no step aside")},
        "nobody_within_rs_new": sum(r["within_rs"] == 0 for r in new),
        "someone_has_no_path": sum(r["no_path"] > 0 for r in rows),
        "steps": {s: sum(r["step"] == s for r in rows) for s in
                  ("as given", "planned", "grouped", None)},
        "repartition_ms_p50": float(np.percentile(ms, 50)),
        "repartition_ms_max": float(ms.max()),
        "rows": rows,
    }
    print(f"{path}: {n} losses (every {every_s:g} s × each vehicle in the tube; r_s' = "
          f"{flown.r_s:.3f} m)")
    print(f"  re-partitioned: today {share(out['repartition_today'])}, with the fallback "
          f"{share(out['repartition_new'])}")
    print(f"  nobody inside a new triangle (the rest can finish): today "
          f"{share(out['rest_go_on_today'])}, with the fallback {share(out['rest_go_on_new'])}")
    print(f"  nobody inside, with partitions of their own for those past an obstacle "
          f"(FlightPlan.past): {share(out['rest_go_on_own'])}")
    print(f"  the rest finishes, those trapped waiting and then stepping aside (on_trapped = "
          f"\"wait\"): {share(out['rest_finish_wait'])}; not: {out['wait_fails']}; without "
          f"partitions of their own where there is no common one: "
          f"{share(out['rest_finish_wait_no_apart'])}")
    print(f"  nobody within r_s' of a new triangle side: {share(out['nobody_within_rs_new'])}")
    print(f"  someone with no admissible path at all (no partition can help): "
          f"{share(out['someone_has_no_path'])}")
    print(f"  one re-partition: p50 {out['repartition_ms_p50']:.0f} ms, max "
          f"{out['repartition_ms_max']:.0f} ms; steps {out['steps']}")
    return out


# ----------------------------------------------------------------------------------------------
# flights
# ----------------------------------------------------------------------------------------------
def flight_cases(mission: Mission, count: int) -> list[tuple[int, float]]:
    """(vehicle, seconds into the tube) spread over the vehicles and over each one's nominal
    time in the tube (10 % .. 85 %)."""
    flown = flown_params(mission)
    t, pos = nominal_flight(mission, flown, 0.5)
    m = pos.shape[1]
    gone = np.isnan(pos[:, :, 0]) | mission.scenario.tube.finished(
        np.nan_to_num(pos), flown.eps_0)
    exit_s = np.array([float(t[np.argmax(gone[:, i])]) if gone[:, i].any() else float(t[-1])
                       for i in range(m)])
    fracs = np.linspace(0.1, 0.85, count)
    order = np.random.default_rng(7).permutation(m)
    return [(int(order[k % m]), round(float(fracs[k] * exit_s[order[k % m]]), 1))
            for k in range(count)]


async def fly_one(mission: Mission, vehicle: int, at_s: float, seed: int,
                  out_dir: Path) -> dict[str, Any]:
    from vtube_fleet.fleet.launch import fly, mock_fleet
    from vtube_fleet.state import Phase

    n = mission.count
    flown_log: dict[str, Any] = {"killed": None, "repartitions": []}
    sc = mission.scenario

    async with mock_fleet(mission, port_scheme=free_port_scheme(n), boot_time_scale=0.3,
                          seed=seed) as fleet:
        seen_plan: list[Any] = []
        waited: set[int] = set()

        def hook(tick: int, sup: Any) -> None:
            if sup.tube_start_s is None:
                return
            waited.update(q.vehicle_id for q in sup.pilots if q.phase == Phase.WAITING)
            if not seen_plan:
                seen_plan.append(sup.plan)
            p = sup.pilots[vehicle]
            if (flown_log["killed"] is None and sup.t_s() - sup.tube_start_s >= at_s
                    and p.phase == Phase.IN_TUBE):
                flown_log["killed"] = [float(p.xy[0]), float(p.xy[1])]
                fleet.kill(vehicle, "silent")
            if sup.plan is not seen_plan[-1]:
                seen_plan.append(sup.plan)
                plan = sup.plan
                rows = [q for q in sup.pilots if q.phase == Phase.IN_TUBE]
                xy = np.array([q.xy for q in rows]).reshape(-1, 2)
                trapped = plan.cannot_pass(xy) if len(rows) else []
                ids = [q.vehicle_id for q, c in zip(rows, trapped, strict=True) if c]
                own = sorted(sup.pilots[r].vehicle_id for r in sup.ticker.own_plans)
                flown_log["repartitions"].append(
                    {"t_s": round(sup.t_s(), 2), "plan": plan, "inside": ids, "own": own})

        result = await fly(mission, endpoints=fleet.endpoints,
                           sysids=[i + 1 for i in range(n)], out_dir=out_dir, truth=True,
                           tick_hook=hook)
    for rp in flown_log["repartitions"]:  # (how: computed again, after the flight)
        plan = rp.pop("plan")
        rp["lost"] = [[round(float(v), 2) for v in o.center] for o in plan.lost]
        root = seen_plan[0]  # the configured obstacles with the apex distances flown
        tri_h = {t.obstacle: t.h for t in root.route.segments[0].partition.triangles}
        fixed = tuple(dataclasses.replace(o, apex_distance=tri_h[i]) if i in tri_h else o
                      for i, o in enumerate(root.corridor.obstacles))
        try:
            rp["step"] = loss.repartition_around_lost(
                sc.tube, fixed, plan.lost, plan.flown).describe()
        except PartitionError:
            rp["step"] = "?"
    s = result.summary
    others = n - 1
    return {
        "vehicle": vehicle, "at_s": at_s, "killed_at": flown_log["killed"],
        "outcome": result.outcome, "exit_code": result.exit_code,
        "reason": result.reason, "exited": s.get("exited"), "others": others,
        "lost": s.get("lost"), "repartitions": flown_log["repartitions"],
        "waited": sorted(waited), "tube_s": s.get("flight_time_s"),
        "truth_violations": s.get("truth_violations"),
        "truth_min_pair_m": s.get("truth_min_pair_distance_m"),
        "violations": s.get("violations"),
        "first_violation": s.get("first_violation"),
        "rest_finished": s.get("exited") == others,
        "clean": s.get("truth_violations") == 0 and s.get("violations") == 0,
        # the machine, not the loss: the budget watch held the fleet for a stalled loop
        "stalled": result.reason.startswith("safety budget exceeded in flight"),
    }


def fly_cases(path: str, count: int, seed: int, on_trapped: str, only: Sequence[int] = (),
              keep: Path | None = None) -> dict[str, Any]:
    """Fly the first ``count`` cases of :func:`flight_cases` (only those numbered ``only``,
    when given), case k with seed ``seed`` + k; each run's output in ``keep``/case<k> (None:
    a temporary folder)."""
    mission = load_mission(ROOT / path)
    mission = dataclasses.replace(mission, config=dataclasses.replace(
        mission.config, on_trapped=on_trapped))
    rows = []
    for k, (vehicle, at_s) in enumerate(flight_cases(mission, count)):
        if only and k not in only:
            continue
        t0 = time.monotonic()
        with contextlib.ExitStack() as stack:
            if keep is None:
                d = Path(stack.enter_context(tempfile.TemporaryDirectory()))
            else:
                d = keep / f"{Path(path).stem}_case{k}"
            row = asyncio.run(fly_one(mission, vehicle, at_s, seed + k, d))
        row["wall_s"] = round(time.monotonic() - t0, 1)
        rows.append(row)
        rp = row["repartitions"][0] if row["repartitions"] else None
        print(f"  vehicle {vehicle} lost {at_s:g} s into the tube at "
              f"{_pt(row['killed_at'])}: {row['outcome']} (exit {row['exit_code']}), "
              f"{row['exited']}/{row['others']} others exited, truth violations "
              f"{row['truth_violations']}, true pair {_m(row['truth_min_pair_m'])}"
              + (f", waited: {row['waited']}" if row["waited"] else "")
              + (f"; re-partitioned ({rp['step']}), inside a new triangle: {rp['inside']}"
                 f" (flying a partition of their own: {rp['own']})"
                 if rp else "; no re-partition")
              + ("" if rp or row["exit_code"] == 0 else f"; {row['reason'][-200:]}")
              + ("" if not row["first_violation"] else f"; first violation "
                 f"{row['first_violation']}")
              + f" [{row['wall_s']:g} s]", flush=True)
    ok = sum(r["rest_finished"] and r["clean"] for r in rows)
    stalled = sum(r["stalled"] and not r["rest_finished"] for r in rows)
    judged = len(rows) - stalled
    unclean = sum(not r["clean"] for r in rows)
    print(f"{path}: the rest finished, truth-clean, after {ok} of {judged} losses "
          f"({100.0 * ok / max(judged, 1):.0f} %); {unclean} flight(s) not truth-clean; "
          f"{stalled} more not judged (the budget watch held the fleet for our own loop's "
          f"stalls, load average {os.getloadavg()[0]:.1f})")
    return {"mission": path, "cases": len(rows), "judged": judged, "rest_finished_clean": ok,
            "not_clean": unclean, "stalled": stalled, "rows": rows}


def _pt(p: Sequence[float] | None) -> str:
    return "?" if p is None else f"({p[0]:.2f}, {p[1]:.2f})"


def _m(x: float | None) -> str:
    return "—" if x is None else f"{x:.2f} m"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("screen", "fly"):
        p = sub.add_parser(name)
        p.add_argument("--mission", action="append", default=None,
                       help="mission file (repeatable; default: the two shipped missions)")
        p.add_argument("--json", type=Path, default=None, help="write the results here")
        if name == "screen":
            p.add_argument("--every", type=float, default=0.5, help="seconds between losses")
        else:
            p.add_argument("--rules", choices=("new", "today"), default="new")
            p.add_argument("--on-trapped", choices=("wait", "land"), default="wait",
                           help="the mission key on_trapped (default: wait)")
            p.add_argument("--cases", type=int, default=8, help="flights per mission")
            p.add_argument("--seed", type=int, default=0)
            p.add_argument("--only", type=int, action="append", default=[],
                           help="fly only case K of the --cases (repeatable)")
            p.add_argument("--keep", type=Path, default=None,
                           help="keep each flight's output folder here")
    args = ap.parse_args(argv)
    os.nice(10)
    if args.cmd == "fly" and args.rules == "today":
        today_only()
    missions = args.mission or list(MISSIONS)
    if args.cmd == "screen":
        results = [screen(m, args.every) for m in missions]
    else:
        print(f"rules: {args.rules}, on_trapped = {args.on_trapped}")
        results = [fly_cases(m, args.cases, args.seed, args.on_trapped, args.only, args.keep)
                   for m in missions]
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
