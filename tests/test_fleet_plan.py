"""The flight plan and the neighbour view: staleness, the controller's commands for any rows,
speed bounds, exits, lost vehicles → obstacles and re-partition, the exit behaviour, the
safety budget, and the "not following its setpoints" fault rule."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from missions import compact_12

from vtube_fleet.core.controller import velocity_command
from vtube_fleet.core.partition import PartitionError
from vtube_fleet.fleet.budget import SafetyBudget
from vtube_fleet.fleet.flight_plan import FlightPlan, exit_velocities, lost_obstacles
from vtube_fleet.fleet.neighbour_view import classify, states_of
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
    return FlightPlan.build(sc.corridor, budget.inflate(sc.controller))


def st(i, x, y, phase=Phase.IN_TUBE, age=0.0, seq=1, vx=1.0, vy=0.0):
    return NeighbourState(i, x, y, vx, vy, phase, NOW - age, seq)


def view_of(states, *, exclude=(), max_age_s=0.5, lost_after_s=1.0):
    return classify(states_of(states, exclude), NOW, max_age_s=max_age_s,
                    lost_after_s=lost_after_s)


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
    v = view_of(states, exclude=[0])
    assert v.live_ids.tolist() == [1, 8]
    assert v.static_ids.tolist() == [2]
    assert v.lost_ids.tolist() == [3, 4]
    np.testing.assert_allclose(v.live_vel, [[1.0, 0.0], [1.0, 0.0]])
    assert v.points().shape == (5, 2)
    # per-state silence limits: a process's own vehicles are lost by its fault rules (inf)
    lim = np.array([math.inf if s.vehicle_id == 3 else 1.0 for s in states if s.vehicle_id])
    v = classify(states_of(states, [0]), NOW, max_age_s=0.5, lost_after_s=lim)
    assert v.static_ids.tolist() == [2, 3] and v.lost_ids.tolist() == [4]


def test_commands_are_the_controller_output(plan) -> None:
    own = np.array([4.0, 0.3])
    states = [st(0, *own), st(1, 5.2, 0.6), st(2, 30.0, 0.0), st(3, 4.5, -1.2, age=0.7)]
    view = view_of(states)
    p = view.points()
    row = int(np.flatnonzero(view.ids() == 0)[0])
    got = plan.commands(p, [row])[0]
    _, k = plan.locate(p)  # the flown switching rule: §5 with the apex look-ahead
    ref = velocity_command(p, k, plan.arrays, plan.flown, rows=[row])[0]
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    # the barrier acts: the command differs from the one without neighbours
    alone = plan.commands(own[None], [0])[0]
    assert not np.allclose(alone, got)


def test_one_row_equals_the_same_row_of_many(plan) -> None:
    """A vehicle's command does not depend on which other rows are asked for: an MQTT agent
    (its own row) and the supervisor (every row) get the same bits."""
    rng = np.random.default_rng(7)
    tube = plan.corridor.segments[0]
    pts: list[np.ndarray] = []
    while len(pts) < 25:
        q = rng.uniform([0.5, -4.5], [18.5, 4.5])
        if tube.contains(q, tol=-1.0) and all(np.hypot(*(q - r)) > 1.0 for r in pts):
            if not any(t.contains(q[None], tol=0.0)[0] for t in plan.route.triangles):
                pts.append(q)
    p = np.array(pts)
    view = view_of([st(i, *p[i]) for i in range(len(p))])
    batch = plan.commands(view.points(), np.arange(len(p)))
    for i in range(len(p)):
        one = plan.commands(view.points(), [i])[0]
        assert one.tobytes() == batch[i].tobytes()


def test_speed_bounds(plan) -> None:
    rng = np.random.default_rng(3)
    params = plan.flown
    p = rng.uniform([0.0, -5.0], [19.0, 5.0], size=(300, 2))
    cmd = plan.commands(p, np.arange(len(p)))
    speed = np.hypot(*cmd.T)
    assert np.all(np.isfinite(speed))
    assert speed.min() >= params.v_min - 1e-9
    assert speed.max() <= params.v_max + 1e-9


def test_exit_condition(plan) -> None:
    tube = plan.corridor.segments[0]
    L = tube.length
    eps = plan.flown.eps_0
    x_finish = float(tube.p_r1[0])
    assert bool(plan.exited(np.array([x_finish - eps / 2, 0.0])))
    assert not bool(plan.exited(np.array([x_finish - 2 * eps, 0.0])))
    assert L == pytest.approx(x_finish)


def test_lost_neighbour_becomes_obstacle_and_repartitions(mission, budget) -> None:
    sc = mission.scenario
    plan = FlightPlan.build(sc.corridor.with_obstacles(()), budget.inflate(sc.controller))
    view = view_of([st(5, 9.0, 1.0, age=2.0)])  # silent for 2 s > lost_after_s
    assert view.lost_ids.tolist() == [5]
    new = plan.with_lost(lost_obstacles(view, plan.corridor, 0.8, plan.flown))
    assert new is not plan
    assert len(new.lost) == 1 and new.lost[0].radius == 0.8
    np.testing.assert_allclose(new.lost[0].center, [9.0, 1.0])
    assert new.route.K > plan.route.K
    # the same loss seen by another process: the cached plan, partitioned once
    said = view_of([st(5, 9.0, 1.0, phase=Phase.LOST)])
    assert plan.with_lost(lost_obstacles(said, plan.corridor, 0.8, plan.flown)) is new
    # lost outside the tube (past the finishing line): no obstacle, no new partition
    out = view_of([st(6, 25.0, 0.0, phase=Phase.LOST)])
    assert lost_obstacles(out, plan.corridor, 0.8, plan.flown) == ()
    assert plan.with_lost(()) is plan


def test_a_vehicle_stopped_just_past_the_finishing_line_is_an_obstacle(plan) -> None:
    """A stopped (holding) vehicle past the last finishing line whose extended disc O'
    reaches back across it — the tail of a queue of exited vehicles — is an obstacle for the
    vehicles still in the tube (they cannot stop under the controller); farther past the line,
    or beside the tube, it is not; a plan around it builds and keeps the tube's vehicles out of
    its O'."""
    L = plan.corridor.segments[0].length
    reach = 0.8 + plan.flown.r_s
    near = view_of([st(7, L + reach - 0.05, 1.0, phase=Phase.HOLDING)])
    got = lost_obstacles(near, plan.corridor, 0.8, plan.flown)
    assert len(got) == 1
    np.testing.assert_allclose(got[0].center, [L + reach - 0.05, 1.0])
    for x, y in ((L + reach + 0.05, 1.0), (L + 0.5, 40.0)):
        far = view_of([st(7, x, y, phase=Phase.HOLDING)])
        assert lost_obstacles(far, plan.corridor, 0.8, plan.flown) == (), (x, y)
    # 1 m past the line: its O' reaches 1.8 m back into the tube; a vehicle there is inside
    # the region around it (no sub-tube: it waits), one beside it is not
    tail = lost_obstacles(view_of([st(7, L + 1.0, 1.0, phase=Phase.HOLDING)]),
                          plan.corridor, 0.8, plan.flown)
    new = plan.with_lost(tail)
    assert new.cannot_pass(np.array([[L - 1.0, 1.0]]))[0]
    assert not new.cannot_pass(np.array([[L - 1.0, -4.0]]))[0]


def test_a_plan_holds_stopped_vehicles_that_moved_less_than_their_margin(plan) -> None:
    """FlightPlan.holds: a plan built around a stopped vehicle still holds it (its body, a
    disc of r_s, inside the obstacle) after it moved less than the obstacle's margin; not
    after it moved more, nor a vehicle it has no obstacle for; no stopped vehicle: held."""
    view = view_of([st(5, 9.0, 1.0, phase=Phase.LOST)])
    new = plan.with_lost(lost_obstacles(view, plan.corridor, 0.8, plan.flown))
    body = 0.3  # → margin 0.5 m

    def at(*xy: tuple[float, float]):
        return lost_obstacles(view_of([st(5 + k, x, y, phase=Phase.LOST)
                                       for k, (x, y) in enumerate(xy)]),
                              plan.corridor, 0.8, plan.flown)

    assert new.holds(at((9.3, 1.3)), body)  # 0.42 m
    assert not new.holds(at((9.4, 1.4)), body)  # 0.57 m
    assert not new.holds(at((9.0, 1.0), (3.0, -2.0)), body)  # a second one
    assert new.holds((), body) and not plan.holds(at((9.0, 1.0)), body)


def test_no_valid_partition_raises(plan) -> None:
    # two lost side by side in the 10 m wide tube: no passage is wide enough for a robot
    # (not even with the fallback: core/loss.py)
    view = view_of([st(5, 6.0, -2.5, phase=Phase.LOST), st(6, 6.0, 2.5, phase=Phase.LOST)])
    with pytest.raises(PartitionError, match="nor with the fallback"):
        plan.with_lost(lost_obstacles(view, plan.corridor, 0.8, plan.flown))


def test_exit_velocity_guard(plan) -> None:
    own = np.array([[20.0, 0.0]])
    v = plan.flown.v
    free, blocked = exit_velocities(plan, own, view_of([]), stop_distance_m=3.0)
    np.testing.assert_allclose(free[0], v * plan.corridor.segments[-1].n_c)
    assert not blocked[0]
    # a hovering vehicle 2 m ahead in the corridor → stop
    view = view_of([st(1, 22.0, 0.5, phase=Phase.HOLDING, vx=0.0)])
    assert exit_velocities(plan, own, view, stop_distance_m=3.0)[1].tolist() == [True]
    # one flying on at v ahead, or a hovering one far to the side → keep going
    view = view_of([st(1, 22.0, 0.5, phase=Phase.EXITED, vx=v),
                    st(2, 22.0, 4.0, phase=Phase.HOLDING, vx=0.0)])
    assert exit_velocities(plan, own, view, stop_distance_m=3.0)[1].tolist() == [False]
    # many at once: each its own answer
    many = np.array([[20.0, 0.0], [20.0, 4.0], [30.0, 0.0]])
    view = view_of([st(1, 22.0, 0.5, phase=Phase.HOLDING, vx=0.0)])
    assert exit_velocities(plan, many, view, stop_distance_m=3.0)[1].tolist() == [
        True, False, False]


def test_apex_look_ahead_switches_before_the_barrier(plan) -> None:
    """Heading straight at a triangle's apex, §5 would switch only on the apex line (inside
    r_s' of the triangle side); the flown rule switches within (r_s' + r_a') / sin α ahead of
    it, where the distance to the side's extended line is still r_s' + r_a'."""
    (z,) = plan.route.zones[0]
    part, prm = plan.route.segments[0].partition, plan.flown
    tri = part.triangles[z.triangle]
    n_c = plan.corridor.segments[0].n_c
    assert z.left is not None and z.right is not None
    depth = (prm.r_s + prm.r_a) / math.sin(tri.alpha)
    assert z.depth_m == pytest.approx(min(depth, z.xi_apex))
    for ahead in (0.05, 0.5 * z.depth_m, z.depth_m - 0.01):
        p = tri.p_oth - ahead * n_c  # on the apex's line, upstream of it
        k0 = int(part.locate(p))
        k = int(plan.locate(p)[1][0])
        assert k0 == z.before and k == z.left  # (a tie on the apex line: left, as §5)
        side = part.sub_tubes[k]
        assert float(side.d_Tr(p)) == pytest.approx(ahead * math.sin(tri.alpha), rel=1e-6)
    entry = tri.p_oth - (z.depth_m - 1e-6) * n_c
    assert float(part.sub_tubes[z.left].d_Tr(entry)) >= prm.r_s + prm.r_a - 1e-5
    before = tri.p_oth - (z.depth_m + 0.01) * n_c
    assert int(plan.locate(before)[1][0]) == z.before  # beyond the zone: §5 as printed
    # the paper's rule exactly when asked (the simulator's)
    exact = FlightPlan.build(plan.corridor, prm, lookahead=False)
    assert exact.route.zones == ((),)
    assert int(exact.locate(tri.p_oth - 0.5 * n_c)[1][0]) == z.before


# -- a vehicle in offboard that slows below v_min in the tube: lost (an obstacle) ------------------
class _Link:
    """What the fault rules read of a link: its state."""

    closed = False
    latency_s = None

    def __init__(self) -> None:
        from vtube_fleet.link.base import VehicleState

        self.state = VehicleState(endpoint="udpin://127.0.0.1:24998")


def _in_tube(mission):
    from vtube_fleet.fleet.table import PHASE_CODE, FleetTable

    tab = FleetTable([0], mission)
    tab.phase[0] = PHASE_CODE[Phase.IN_TUBE]
    tab.xy[0], tab.has[0] = (5.0, 0.0), True
    tab.offboard_seen[0] = True
    link = _Link()
    s = link.state
    s.armed, s.flight_mode, s.landed_state = True, "OFFBOARD", "IN_AIR"
    return tab, link


def _fly_at(mission, tab, link, speeds, dt: float = 0.05, t0: float = 100.0,
            moving: float | None = None) -> list[str | None]:
    """The fault rules every ``dt`` while the vehicle is commanded v (the mission's nominal
    speed) along the tube and measured at ``speeds[k]``, its estimated position moving at
    that speed (or at ``moving``); the reason found at each tick."""
    from vtube_fleet.fleet.tick import find_faults, read_links

    v = mission.scenario.controller.v
    out: list[str | None] = []
    for k, speed in enumerate(speeds):
        now = t0 + k * dt
        link.state.last_position_s = now
        tab.cmd[0], tab.cmd_set[0] = (v, 0.0), True
        tab.vel[0] = (speed, 0.0)
        tab.xy[0] = tab.xy[0] + [(speed if moving is None else moving) * dt, 0.0]
        faults, _ = find_faults(tab, read_links([link]), mission, now)
        out.append(faults[0].reason if faults else None)
        if faults:
            break
    return out


def test_a_vehicle_slower_than_v_min_in_the_tube_becomes_an_obstacle(mission) -> None:
    """Commanded ≥ v_min in the tube, PX4 falls 10–20 % short at most: a vehicle measured below
    max(v_min / 2, 0.05 m/s) for the whole ``unresponsive_s`` window is LOST (an obstacle for
    everyone, issue 9: "slows below v_min in the tube"); 0.8 v_min or a shorter dip is not."""
    from vtube_fleet.fleet.tick import slow_m_s, unresponsive_s

    v_min = mission.scenario.robots.v_min
    window, dt = unresponsive_s(mission), 0.05
    slow = slow_m_s(mission)
    assert slow == pytest.approx(max(0.5 * v_min, 0.05))
    n = int(window / dt) + 20  # the window and 1 s more

    for speed in (0.0, 0.4 * v_min):  # stopped, crawling at 0.4 v_min
        tab, link = _in_tube(mission)
        reasons = _fly_at(mission, tab, link, [speed] * n, dt)
        first = next(k for k, r in enumerate(reasons) if r is not None)
        assert window <= first * dt <= window + 2 * dt, first * dt  # after the window
        assert reasons[first].startswith("not following its setpoints: moved ")
        assert f"< {slow:g} m/s (v_min / 2) × the time" in reasons[first], reasons[first]

    tab, link = _in_tube(mission)  # 0.8 v_min: PX4 falling short, still following
    assert not any(_fly_at(mission, tab, link, [0.8 * v_min] * n, dt))

    tab, link = _in_tube(mission)  # a dip to 0 shorter than the window, twice, then normal
    dip = [0.0] * int(0.8 * window / dt)
    fine = [mission.scenario.controller.v] * int(1.5 / dt)
    assert not any(_fly_at(mission, tab, link, dip + fine + dip + fine, dt))

    # frozen in place while the velocity estimate says 2 × v_min / 2 (PX4's velocity estimate
    # can be 0.8 m/s off; a probe flight's frozen vehicle reported 0.3 m/s and was never
    # caught): judged on the position, it is lost after the window
    tab, link = _in_tube(mission)
    reasons = _fly_at(mission, tab, link, [2.0 * slow] * n, dt, moving=0.0)
    first = next((k for k, r in enumerate(reasons) if r is not None), None)
    assert first is not None and window <= first * dt <= window + 2 * dt, reasons[-1]
    assert f"reported speed {2.0 * slow:.2f} m/s" in reasons[first], reasons[first]

    # the velocity estimate says "slow" but the estimated position moves at v_min (PX4 flies
    # v_c + d̂ under the compensation): not lost
    tab, link = _in_tube(mission)
    assert not any(_fly_at(mission, tab, link, [0.0] * (3 * n), dt, moving=v_min))


# -- a route ------------------------------------------------------------------------------------
def test_a_routes_plan_exits_at_the_last_line_and_replans_the_segment_a_vehicle_stopped_in(
        budget) -> None:
    """configs/route_mock.toml (three segments): only a vehicle flying the LAST segment exits,
    at its finishing line; the exit behaviour flies the last segment's n_c; a vehicle stopped
    in S2 becomes an obstacle of S2 alone (S1's and S3's partitions are the same objects), one
    stopped in the S1 → S2 junction's overlap of both, one past the route's finishing line of
    none; commands are the controller's in each vehicle's own segment."""
    from vtube_fleet.config.mission import load_mission

    mission = load_mission(ROOT / "configs" / "route_mock.toml")
    sc = mission.scenario
    plan = FlightPlan.for_mission(mission, budget.inflate(sc.controller))
    route = plan.route
    assert route.S == 3 and plan.corridor is sc.corridor
    last = sc.corridor.segments[-1]
    eps = plan.flown.eps_0
    at_end = 0.5 * (last.lh(last.length - eps / 2) + last.lr(last.length - eps / 2))[None]
    assert plan.exited(at_end, np.array([2])).tolist() == [True]
    assert plan.exited(at_end, np.array([1])).tolist() == [False]  # not flying the last one
    assert route.beyond_finish_m(at_end)[0] == pytest.approx(-eps / 2)
    v, _ = exit_velocities(plan, at_end, view_of([]), stop_distance_m=3.0)
    np.testing.assert_allclose(v[0], plan.flown.v * last.n_c)
    # a vehicle stopped in the middle of S2
    s2 = sc.corridor.segments[1]
    mid2 = 0.5 * (s2.lh(0.5 * s2.length) + s2.lr(0.5 * s2.length))
    lost = lost_obstacles(view_of([st(3, *mid2, phase=Phase.HOLDING)]), plan.corridor, 0.8,
                          plan.flown)
    new = plan.with_lost(lost)
    assert len(new.lost) == 1 and plan.with_lost(lost) is new
    assert [len(s.obstacle_ids) for s in new.route.segments] == [1, 1, 1]
    assert new.route.segments[1].obstacle_ids == (2,)  # route-numbered after #1, #2
    assert new.route.segments[0].partition is route.segments[0].partition
    assert new.route.segments[2].partition is route.segments[2].partition
    assert new.segments_of_lost(0) == ["S2"]
    # in the S1 → S2 overlap (on the mitre, 30 % of the way from its inner corner): an
    # obstacle of both segments; in the middle of the mitre the planner alone cannot
    # re-partition around it, and the refusal names the segment; the fallback (core/loss.py,
    # every plan's default) finds a partition whose every segment validates
    inner, outer = sc.corridor.geometry.mitre_corners(0)
    both = 0.7 * inner + 0.3 * outer
    assert all(t.contains(both) for t in sc.corridor.segments[:2])
    lost2 = lost_obstacles(view_of([st(4, *both, phase=Phase.LOST)]), plan.corridor, 0.8,
                           plan.flown)
    assert plan.with_lost(lost2).segments_of_lost(0) == ["S1", "S2"]
    middle = lost_obstacles(view_of([st(4, *(0.5 * (inner + outer)), phase=Phase.LOST)]),
                            plan.corridor, 0.8, plan.flown)
    plain = FlightPlan.for_mission(mission, budget.inflate(sc.controller), replan=None)
    with pytest.raises(PartitionError, match=r"^segment S2: obstacle #3 at \(40.0, 0.0\)"):
        plain.with_lost(middle)
    fallback = plan.with_lost(middle)
    assert fallback.segments_of_lost(0) and fallback.route.K > route.K
    # past the route's last finishing line: not an obstacle (Assumption 2)
    gone = 0.5 * (last.lh(last.length + 3.0) + last.lr(last.length + 3.0))
    assert lost_obstacles(view_of([st(5, *gone, phase=Phase.LOST)]), plan.corridor, 0.8,
                          plan.flown) == ()
    # commands: the controller's in each vehicle's own segment
    p = np.array([mid2, [10.0, 0.0]])
    seg = np.array([1, 0])
    got = plan.commands(p, [0, 1], seg)
    _, k = route.locate(p, seg)
    assert route.segment_of[k].tolist() == [1, 0]
    ref = velocity_command(p, k, plan.arrays, plan.flown)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
