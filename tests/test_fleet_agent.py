"""The per-vehicle Agent: neighbour table and staleness, setpoint = the core controller,
speed bounds, exits, lost vehicles → obstacles and re-partition, the safety budget."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from missions import compact_12

from vtube_fleet.core.controller import velocity_command
from vtube_fleet.core.partition import PartitionError
from vtube_fleet.fleet.agent import (
    Agent,
    FlightPlan,
    classify,
    exit_velocity,
    fleet_setpoints,
)
from vtube_fleet.fleet.budget import SafetyBudget
from vtube_fleet.state import NeighbourState, Phase

ROOT = Path(__file__).resolve().parents[1]
NOW = 1_000_000.0


@pytest.fixture(scope="module")
def mission():
    return compact_12()


@pytest.fixture(scope="module")
def budget(mission):
    return SafetyBudget.compute(mission.scenario.controller, period_s=0.05, latency_s=0.02,
                                dead_time_s=0.3, t63_s=1.0)


@pytest.fixture()
def plan(mission, budget):
    sc = mission.scenario
    return FlightPlan.build(sc.tube, sc.obstacles, budget.inflate(sc.controller))


def st(i, x, y, phase=Phase.IN_TUBE, age=0.0, seq=1, vx=1.0, vy=0.0):
    return NeighbourState(i, x, y, vx, vy, phase, NOW - age, seq)


def test_budget_formula(mission, budget) -> None:
    p = mission.scenario.controller
    assert budget.delay_s == pytest.approx(0.05 + 0.02 + 0.3 + 1.0)
    assert budget.delta_m == pytest.approx(p.v_max_prime * budget.delay_s)
    flown = budget.inflate(p)
    assert flown.r_s == pytest.approx(p.r_s + budget.delta_m)
    assert flown.r_a == pytest.approx(p.r_a + budget.delta_m)
    assert (flown.v, flown.v_max_prime, flown.v_min, flown.v_max) == (
        p.v, p.v_max_prime, p.v_min, p.v_max)
    text = budget.describe(p)
    assert "(v'_max + D)·(T + L + τ_d + t63) + k σ" in text and f"{budget.delta_m:.3f}" in text
    # the estimate and the disturbance terms (docs/fleet.md): δ = (v'_max + D)·delay + k σ
    full = SafetyBudget.compute(p, period_s=0.05, latency_s=0.02, dead_time_s=0.3, t63_s=1.0,
                                accuracy_m=0.29, accuracy_factor=2.0, disturbance_m_s=0.15)
    assert full.estimate_m == pytest.approx(0.58)
    assert full.disturbance_m == pytest.approx(0.15 * full.delay_s)
    assert full.delta_m == pytest.approx(full.lag_m + full.estimate_m + full.disturbance_m)
    assert full.as_dict()["accuracy_m"] == 0.29
    fixed = SafetyBudget.compute(p, period_s=0.05, latency_s=0.0, dead_time_s=0.3, t63_s=1.0,
                                 override_m=0.2)
    assert fixed.delta_m == 0.2 and fixed.overridden
    with pytest.raises(ValueError, match="latency_s"):
        SafetyBudget.compute(p, period_s=0.05, latency_s=float("nan"), dead_time_s=0.3,
                             t63_s=1.0)


def test_classify_staleness() -> None:
    states = [
        st(0, 1.0, 0.0),                              # self: excluded
        st(1, 2.0, 0.0, age=0.1),                     # live
        st(2, 3.0, 0.0, age=0.7),                     # stale (> max_age) → static point
        st(3, 4.0, 0.0, age=1.5),                     # silent > lost_after → lost
        st(4, 5.0, 0.0, phase=Phase.LOST, age=30.0),  # said LOST (any age) → lost
        st(5, 6.0, 0.0, phase=Phase.LANDED),          # on the ground → ignored
        st(6, 7.0, 0.0, phase=Phase.READY),           # on the ground → ignored
        st(7, float("nan"), 0.0),                     # no position → ignored
        st(8, 8.0, 0.0, phase=Phase.EXITED, age=0.2),  # exited, still flying → live
    ]
    v = classify(states, NOW, max_age_s=0.5, lost_after_s=1.0, exclude=0)
    assert v.live_ids.tolist() == [1, 8]
    assert v.static_ids.tolist() == [2]
    assert v.lost_ids.tolist() == [3, 4]
    np.testing.assert_allclose(v.live_vel, [[1.0, 0.0], [1.0, 0.0]])
    assert v.points().shape == (5, 2)


def test_agent_table_keeps_newest(plan) -> None:
    a = Agent(0, plan, max_age_s=0.5, lost_after_s=1.0)
    a.observe({1: st(1, 2.0, 0.0, seq=5), 0: st(0, 9.0, 9.0)})
    a.observe([st(1, 7.0, 0.0, seq=4)])  # older seq: ignored
    assert set(a.table) == {1}
    assert a.table[1].x_m == 2.0
    a.observe([st(1, 3.0, 0.0, seq=6)])
    assert a.table[1].x_m == 3.0
    assert a.set_phase(Phase.READY) and not a.set_phase(Phase.READY)
    with pytest.raises(ValueError):
        Agent(0, plan, max_age_s=2.0, lost_after_s=1.0)


def test_setpoint_is_the_controller_output(plan) -> None:
    own = np.array([4.0, 0.3])
    a = Agent(0, plan)
    a.observe([st(1, 5.2, 0.6), st(2, 30.0, 0.0), st(3, 4.5, -1.2, age=0.7)])
    view = a.view(NOW)
    sp = a.setpoint(own, view)
    # neighbours within r_s' + r_a': 1 (live) and 3 (static); 2 is far away
    assert sp.neighbours == 2
    p = np.array([own, [5.2, 0.6], [4.5, -1.2]])
    k = plan.locate(p)  # the flown switching rule: §5 with the apex look-ahead
    ref = velocity_command(p, k, plan.arrays, plan.flown, rows=[0])[0]
    np.testing.assert_allclose([sp.vx_m_s, sp.vy_m_s], ref, rtol=0, atol=1e-12)
    assert sp.sub_tube == int(k[0])
    # the barrier acts: the command differs from the one without neighbours
    alone = a.setpoint(own, classify([], NOW, max_age_s=0.5, lost_after_s=1.0))
    assert not np.allclose([alone.vx_m_s, alone.vy_m_s], [sp.vx_m_s, sp.vy_m_s])


def test_batched_equals_per_agent(plan) -> None:
    rng = np.random.default_rng(7)
    tube = plan.tube
    pts = []
    while len(pts) < 25:
        q = rng.uniform([0.5, -4.5], [18.5, 4.5])
        if tube.contains(q, tol=-1.0) and all(np.hypot(*(q - r)) > 1.0 for r in pts):
            if not any(t.contains(q[None], tol=0.0)[0] for t in plan.partition.triangles):
                pts.append(q)
    p = np.array(pts)
    states = [st(i, *p[i]) for i in range(len(p))]
    view = classify(states, NOW, max_age_s=0.5, lost_after_s=1.0)
    batch = fleet_setpoints(plan, view.points(), np.arange(len(p)))
    for i in range(len(p)):
        a = Agent(i, plan)
        a.observe(states)
        sp = a.setpoint(p[i], a.view(NOW))
        np.testing.assert_allclose([sp.vx_m_s, sp.vy_m_s], batch[i], rtol=1e-9, atol=1e-9)


def test_speed_bounds(plan) -> None:
    rng = np.random.default_rng(3)
    params = plan.flown
    p = rng.uniform([0.0, -5.0], [19.0, 5.0], size=(300, 2))
    cmd = fleet_setpoints(plan, p, np.arange(len(p)))
    speed = np.hypot(*cmd.T)
    assert np.all(np.isfinite(speed))
    assert speed.min() >= params.v_min - 1e-9
    assert speed.max() <= params.v_max + 1e-9


def test_exit_condition(plan) -> None:
    a = Agent(0, plan)
    L = plan.tube.length
    eps = plan.flown.eps_0
    x_finish = float(plan.tube.p_r1[0])
    assert a.has_exited([x_finish - eps / 2, 0.0])
    assert not a.has_exited([x_finish - 2 * eps, 0.0])
    assert L == pytest.approx(x_finish)


def test_lost_neighbour_becomes_obstacle_and_repartitions(mission, budget) -> None:
    sc = mission.scenario
    plan = FlightPlan.build(sc.tube, (), budget.inflate(sc.controller))
    a = Agent(0, plan, lost_radius_m=0.8)
    a.observe([st(5, 9.0, 1.0, age=2.0)])  # silent for 2 s > lost_after_s
    view = a.view(NOW)
    assert view.lost_ids.tolist() == [5]
    assert a.update_plan(view)
    assert len(a.plan.lost) == 1 and a.plan.lost[0].radius == 0.8
    np.testing.assert_allclose(a.plan.lost[0].center, [9.0, 1.0])
    assert a.plan.partition.K > plan.partition.K
    # the same loss seen by another agent: the cached plan, partitioned once
    b = Agent(1, plan, lost_radius_m=0.8)
    b.observe([st(5, 9.0, 1.0, phase=Phase.LOST)])
    b.update_plan(b.view(NOW))
    assert b.plan is a.plan
    assert not a.update_plan(view)
    # lost outside the tube (past the finishing line): no obstacle, no new partition
    c = Agent(2, plan)
    c.observe([st(6, 25.0, 0.0, phase=Phase.LOST)])
    assert not c.update_plan(c.view(NOW))


def test_no_valid_partition_raises(plan) -> None:
    a = Agent(0, plan, lost_radius_m=0.8)
    # two lost side by side in the 10 m wide tube: no passage is wide enough for a robot
    # (not even with the fallback: core/loss.py)
    a.observe([st(5, 6.0, -2.5, phase=Phase.LOST), st(6, 6.0, 2.5, phase=Phase.LOST)])
    with pytest.raises(PartitionError, match="nor with the fallback"):
        a.update_plan(a.view(NOW))


def test_exit_velocity_guard(plan) -> None:
    own = np.array([20.0, 0.0])
    v = plan.flown.v
    free = exit_velocity(plan, own, classify([], NOW, max_age_s=0.5, lost_after_s=1.0),
                         stop_distance_m=3.0)
    np.testing.assert_allclose(free, v * plan.tube.n_c)
    # a hovering vehicle 2 m ahead in the corridor → stop
    view = classify([st(1, 22.0, 0.5, phase=Phase.HOLDING, vx=0.0)], NOW, max_age_s=0.5,
                    lost_after_s=1.0)
    assert exit_velocity(plan, own, view, stop_distance_m=3.0) is None
    # one flying on at v ahead, or a hovering one far to the side → keep going
    view = classify([st(1, 22.0, 0.5, phase=Phase.EXITED, vx=v),
                     st(2, 22.0, 4.0, phase=Phase.HOLDING, vx=0.0)], NOW, max_age_s=0.5,
                    lost_after_s=1.0)
    assert exit_velocity(plan, own, view, stop_distance_m=3.0) is not None


def test_apex_look_ahead_switches_before_the_barrier(plan) -> None:
    """Heading straight at a triangle's apex, §5 would switch only on the apex line (inside
    r_s' of the triangle side); the flown rule switches within (r_s' + r_a') / sin α ahead of
    it, where the distance to the side's extended line is still r_s' + r_a'."""
    (z,) = plan.zones
    part, prm = plan.partition, plan.flown
    tri = part.triangles[z.triangle]
    n_c = plan.tube.n_c
    assert z.left is not None and z.right is not None
    depth = (prm.r_s + prm.r_a) / math.sin(tri.alpha)
    assert z.depth_m == pytest.approx(min(depth, z.xi_apex))
    for ahead in (0.05, 0.5 * z.depth_m, z.depth_m - 0.01):
        p = tri.p_oth - ahead * n_c  # on the apex's line, upstream of it
        k0 = int(part.locate(p))
        k = int(plan.locate(p))
        assert k0 == z.before and k == z.left  # (a tie on the apex line: left, as §5)
        side = part.sub_tubes[k]
        assert float(side.d_Tr(p)) == pytest.approx(ahead * math.sin(tri.alpha), rel=1e-6)
    entry = tri.p_oth - (z.depth_m - 1e-6) * n_c
    assert float(part.sub_tubes[z.left].d_Tr(entry)) >= prm.r_s + prm.r_a - 1e-5
    before = tri.p_oth - (z.depth_m + 0.01) * n_c
    assert int(plan.locate(before)) == z.before  # beyond the zone: §5 as printed
    # the paper's rule exactly when asked (the simulator's)
    exact = FlightPlan.build(plan.tube, plan.obstacles, prm, lookahead=False)
    assert exact.zones == () and int(exact.locate(tri.p_oth - 0.5 * n_c)) == z.before


# -- a vehicle in offboard that slows below v_min in the tube: lost (an obstacle) ------------------
def _pilot_in_tube(mission):
    from vtube_fleet.bus import InProcessBus
    from vtube_fleet.fleet.pilot import VehiclePilot
    from vtube_fleet.link import MavlinkLink

    sc = mission.scenario
    plan = FlightPlan.build(sc.tube, sc.obstacles, sc.controller)
    pilot = VehiclePilot(MavlinkLink("udpin://127.0.0.1:24998"), Agent(0, plan), InProcessBus(),
                         mission, on_event=lambda text, vid, level: None)
    pilot.set_phase(Phase.IN_TUBE)
    pilot.xy, pilot._has_pos = np.array([5.0, 0.0]), True
    s = pilot.link.state
    s.armed, s.flight_mode, s.landed_state = True, "OFFBOARD", "IN_AIR"
    pilot._offboard_seen = True
    return pilot


def _fly_at(pilot, speeds, dt: float = 0.05, t0: float = 100.0, moving: float | None = None
            ) -> list[str | None]:
    """``check_faults`` every ``dt`` while the vehicle is commanded v (the mission's nominal
    speed) along the tube and measured at ``speeds[k]``, its estimated position moving at
    that speed (or at ``moving``); the reason given at each tick."""
    v = pilot.mission.scenario.controller.v
    out = []
    for k, speed in enumerate(speeds):
        now = t0 + k * dt
        pilot.link.state.last_position_s = now
        pilot.cmd_xy = np.array([v, 0.0])
        pilot.vel_xy = np.array([speed, 0.0])
        pilot.xy = pilot.xy + [(speed if moving is None else moving) * dt, 0.0]
        out.append(pilot.check_faults(now))
        if pilot.phase == Phase.LOST:
            break
    return out


def test_a_vehicle_slower_than_v_min_in_the_tube_becomes_an_obstacle(mission) -> None:
    """Commanded ≥ v_min in the tube, PX4 falls 10–20 % short at most: a vehicle measured below
    max(v_min / 2, 0.05 m/s) for the whole ``unresponsive_s`` window is LOST (an obstacle for
    everyone, issue 9: "slows below v_min in the tube"); 0.8 v_min or a shorter dip is not."""
    v_min = mission.scenario.robots.v_min
    probe = _pilot_in_tube(mission)
    window, dt = probe.unresponsive_s, 0.05
    assert probe.slow_m_s == pytest.approx(max(0.5 * v_min, 0.05))
    n = int(window / dt) + 20  # the window and 1 s more

    for speed in (0.0, 0.4 * v_min):  # stopped, crawling at 0.4 v_min
        pilot = _pilot_in_tube(mission)
        reasons = _fly_at(pilot, [speed] * n, dt)
        assert pilot.phase == Phase.LOST, (speed, reasons[-1])
        first = next(k for k, r in enumerate(reasons) if r is not None)
        assert window <= first * dt <= window + 2 * dt, first * dt  # after the window
        assert reasons[first].startswith(
            f"not following its setpoints: measured speed < {pilot.slow_m_s:g} m/s (v_min / 2)")
        assert pilot.lost_xy is not None and pilot.cmd_xy is None

    pilot = _pilot_in_tube(mission)  # 0.8 v_min: PX4 falling short, still following
    assert not any(_fly_at(pilot, [0.8 * v_min] * n, dt)) and pilot.phase == Phase.IN_TUBE

    pilot = _pilot_in_tube(mission)  # a dip to 0 shorter than the window, twice, then normal
    dip = [0.0] * int(0.8 * window / dt)
    fine = [mission.scenario.controller.v] * 5
    assert not any(_fly_at(pilot, dip + fine + dip + fine, dt)) and pilot.phase == Phase.IN_TUBE

    # the velocity estimate says "slow" but the estimated position moves at v_min (PX4 flies
    # v_c + d̂ under the compensation): not lost
    pilot = _pilot_in_tube(mission)
    assert not any(_fly_at(pilot, [0.0] * (3 * n), dt, moving=v_min))
    assert pilot.phase == Phase.IN_TUBE
