"""Tests of the re-partition around lost vehicles (vtube_fleet.core.loss, docs/fleet.md
"Losing a vehicle"): the fallback keeps the paper's guarantee — every sub-tube is valid
(Assumption 3', Constraint 3), T is covered exactly once by sub-tubes and triangles, and no
extended disc O' (configured obstacles and lost vehicles) meets a sub-tube — and the
vehicles that cannot be given a safe sub-tube are told apart."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.missions import MOCK_FLEET, PX4_SITL_3
from vtube_fleet.config.mission import load_mission
from vtube_fleet.core.loss import (
    ClippedTriangle,
    cannot_pass,
    extended_tube,
    group_obstacle,
    moves_forward,
    partition_around_lost,
    partition_past,
    passed,
    repartition_around_lost,
    step_aside,
    wall_clearance,
)
from vtube_fleet.core.partition import (
    Partition,
    PartitionError,
    alpha_max,
    apex_zones,
    check_assumption3,
    check_constraint2,
    h_min,
    partition,
)
from vtube_fleet.core.tube import APEX_AUTO, Obstacle, Trapezoid
from vtube_fleet.fleet.budget import LinkMeasurement, mission_budget
from vtube_fleet.fleet.flight_plan import LOST_APEX_FACTOR, FlightPlan

#: the link the real PX4 SITL flight of px4_sitl_3 measured (its log: position age p95
#: 47.4 ms + setpoint delay 0.3 ms, σ = 0.296 m → δ = 1.677 m, r_s' = 1.977 m)
SITL_LINK = LinkMeasurement(0.0474, 0.0003, 0.2958)


def mission_case(path):
    mission = load_mission(path)
    sc = mission.scenario
    flown = mission_budget(mission, SITL_LINK).inflate(sc.controller)
    r_lost = sc.controller.r_s + mission.config.lost_obstacle_margin_m
    return sc, flown, r_lost


PX4 = mission_case(PX4_SITL_3)
MOCK = mission_case(MOCK_FLEET)


def lost_at(x: float, y: float, r_lost: float, flown) -> Obstacle:
    """A lost vehicle as the fleet makes it (fleet/agent.lost_obstacles)."""
    return Obstacle(np.array([x, y]), r_lost, LOST_APEX_FACTOR * h_min(r_lost, flown))


def certify(part: Partition, discs: list[tuple[np.ndarray, float]], flown, n: int = 6000,
            seed: int = 0) -> None:
    """The paper's conditions on a partition of T, checked independently: every sub-tube
    satisfies Assumption 3' (letter and room for one robot) and Constraint 3; sampled points
    of T are covered exactly once by the sub-tubes and the triangles; no sampled point of a
    sub-tube lies in an extended disc; the switching rule gives each point its sub-tube."""
    for t in part.sub_tubes:
        assert check_assumption3(t, flown, "Assumption3'") == [], t
        assert check_constraint2(t, flown, "Constraint3") == [], t
    rng = np.random.default_rng(seed)
    T = part.tube
    lo, hi = T.polygon().min(axis=0), T.polygon().max(axis=0)
    pts = rng.uniform(lo, hi, size=(3 * n, 2))
    pts = pts[T.contains(pts)][:n]
    in_sub = np.stack([t.contains(pts) for t in part.sub_tubes])
    in_tri = np.stack([tri.contains(pts) for tri in part.triangles])
    # (a point exactly on a shared boundary is in both: the samples never are)
    assert np.all(in_sub.sum(axis=0) + in_tri.sum(axis=0) == 1), "T not covered exactly once"
    free = in_sub.any(axis=0)
    for c, R in discs:
        assert not np.any(free & (np.hypot(*(pts - c).T) < R)), f"a sub-tube enters O' at {c}"
    k = part.locate(pts)
    assert np.array_equal(k[free], in_sub[:, free].argmax(axis=0))


def discs_of(obstacles, flown) -> list[tuple[np.ndarray, float]]:
    return [(o.center, o.radius + flown.r_s) for o in obstacles]


# ----------------------------------------------------------------------------------------------
# the real case
# ----------------------------------------------------------------------------------------------
def test_the_real_px4_sitl_loss_now_re_partitions():
    """px4_sitl_3 flown on real PX4 SITL: vehicle 1 lost at (15.60, −3.15) beside obstacle #1
    at (20.0, 0.5). Today's rules (1.05 h_min, then the planner) give no partition (the run
    aborted); the fallback groups them into one clipped triangle, certified, and the other
    two — where PX4's ground truth had them when the loss was declared — are outside it."""
    sc, flown, r_lost = PX4
    lost = lost_at(15.60, -3.15, r_lost, flown)
    with pytest.raises(PartitionError, match="obstacle #1 at"):
        partition(sc.tube, (*sc.obstacles, lost), flown)
    with pytest.raises(PartitionError):
        partition(sc.tube, (*sc.obstacles, Obstacle(lost.center, r_lost, APEX_AUTO)), flown)
    rp = repartition_around_lost(sc.tube, sc.obstacles, (lost,), flown)
    assert rp.step == "grouped" and rp.grouping is not None
    assert rp.grouping.groups == ((("obstacle", 0), ("lost", 0)),)
    assert rp.grouping.passage == "both" and rp.grouping.clipped
    part = rp.partition
    assert part.tube is sc.tube
    # the group's region is numbered after the inputs; obstacle #1 has no triangle of its own
    assert [t.obstacle for t in part.triangles] == [2]
    assert isinstance(part.triangles[0], ClippedTriangle)
    assert partition_around_lost(sc.tube, sc.obstacles, (lost,), flown).K == part.K
    certify(part, discs_of((*sc.obstacles, lost), flown), flown)
    others = np.array([[18.89, -7.19], [17.97, 6.48]])  # slots 0 and 2, truth, 1 s later
    zones = apex_zones(part, flown)
    assert not cannot_pass(part, others, zones).any()
    assert np.all(wall_clearance(part, others, zones) > 1.0)


def test_flight_plan_with_lost_uses_the_fallback_once():
    """FlightPlan.with_lost calls the core function: the same partition, cached (every agent
    reacting to the same loss partitions once)."""
    from vtube_fleet.core.route import Corridor

    sc, flown, r_lost = PX4
    root = FlightPlan.build(Corridor.single(sc.tube, sc.obstacles), flown)
    lost = (lost_at(15.60, -3.15, r_lost, flown),)
    new = root.with_lost(lost)
    ref = partition_around_lost(sc.tube, sc.obstacles, lost, flown)
    part = new.route.segments[0].partition
    assert new.lost == lost and part.K == ref.K
    for a, b in zip(part.sub_tubes, ref.sub_tubes, strict=True):
        assert np.allclose(a.polygon(), b.polygon())
    assert root.with_lost(lost) is new
    assert new.route.zones[0]  # the apex look-ahead of the flown plan covers the new triangle
    # the group's circle is no obstacle of the route: its triangle is numbered after them
    # (the summary looks triangles up by route number: an IndexError ended a real run here)
    assert len(new.route.obstacles) == 2
    assert [t.obstacle for t in new.route.triangles] == [2]
    assert next((t.h for t in new.route.triangles if t.obstacle == 0), None) is None


# ----------------------------------------------------------------------------------------------
# the steps and the shapes
# ----------------------------------------------------------------------------------------------
def test_today_rules_first_when_they_work():
    """A loss far from everything is partitioned as before (step 1, its own triangle)."""
    sc, flown, r_lost = MOCK
    tube = Trapezoid((0.0, 10.0), (60.0, 10.0), (0.0, -10.0), (60.0, -10.0))
    lost = lost_at(40.0, 0.0, r_lost, flown)
    rp = repartition_around_lost(tube, sc.obstacles, (lost,), flown)
    assert rp.step == "as given" and rp.grouping is None
    assert [t.obstacle for t in rp.partition.triangles] == [0, 1]
    assert rp.partition.triangles[1].h == pytest.approx(lost.apex_distance)


def test_a_loss_near_the_start_base_extends_the_tube_for_the_construction():
    """px4_sitl_3's middle vehicle lost 1 m into the tube: no room for its apex and a tube
    before it longer than 2 r_a; the construction runs in T extended upstream along its legs
    (same leg lines inside T), the vehicles beside it are outside the triangle."""
    sc, flown, r_lost = PX4
    lost = lost_at(4.0, 0.0, r_lost, flown)
    with pytest.raises(PartitionError):
        partition(sc.tube, (*sc.obstacles, Obstacle(lost.center, r_lost, APEX_AUTO)), flown)
    rp = repartition_around_lost(sc.tube, sc.obstacles, (lost,), flown)
    assert rp.grouping is not None and rp.grouping.extension_m[0] > 0.0
    part = rp.partition
    first = part.sub_tubes[0]
    assert float(sc.tube.xi(first.p_h0)) < 0.0  # starts upstream of T's start base
    assert first.d_Th(sc.tube.p_h1) == pytest.approx(0.0, abs=1e-9)  # on T's leg lines
    assert first.d_Tr(sc.tube.p_r1) == pytest.approx(0.0, abs=1e-9)
    assert part.xi_start[0] == -math.inf
    certify(part, discs_of((*sc.obstacles, lost), flown), flown)
    beside = np.array([[5.0, 4.6], [5.0, -4.6]])
    assert not cannot_pass(part, beside, apex_zones(part, flown)).any()
    behind = np.array([[1.0, 0.0]])  # (between the start base and the lost vehicle)
    assert cannot_pass(part, behind).all()


def test_group_obstacle_one_disc_and_containment():
    """One disc gives itself back (h = R / sin α); a group's triangle contains every disc of
    the group, with the sides at exactly α (so h ≥ h_min, (pothk))."""
    sc, flown, _ = PX4
    a = alpha_max(flown)
    one = group_obstacle(sc.tube, np.array([[10.0, 1.0]]), np.array([2.5]), a, flown.r_s)
    assert np.allclose(one.center, [10.0, 1.0])
    assert one.radius + flown.r_s == pytest.approx(2.5)
    assert one.apex_distance == pytest.approx(2.5 / math.sin(a))
    assert one.apex_distance == pytest.approx(h_min(one.radius, flown))
    c = np.array([[15.6, -3.15], [20.0, 0.5], [17.0, 2.0]])
    R = np.array([2.8, 2.5, 1.0])
    for f in (1.0, 1.5, 3.0):
        alpha = math.asin(math.sin(a) / f)
        ob = group_obstacle(sc.tube, c, R, alpha, flown.r_s)
        R_in = ob.radius + flown.r_s
        assert R_in / ob.apex_distance == pytest.approx(math.sin(alpha))
        assert ob.apex_distance >= h_min(ob.radius, flown) * (1 - 1e-9)
        part = partition(extended_tube(Trapezoid((0.0, 40.0), (60.0, 40.0), (0.0, -40.0),
                                                 (60.0, -40.0)), 40.0, 0.0), [ob], flown)
        tri = part.triangles[0]
        ang = np.linspace(0, 2 * np.pi, 90)
        for cj, Rj in zip(c, R, strict=True):
            rim = cj + (Rj - 1e-6) * np.stack([np.cos(ang), np.sin(ang)], axis=1)
            assert tri.contains(rim, tol=1e-9).all()


def test_the_clipped_triangle_region():
    """polygon() is the whole region (apex, kinks, base corners) and contains() agrees with
    it; its sides beyond the kinks are parallel to n_c."""
    sc, flown, r_lost = PX4
    part = partition_around_lost(sc.tube, sc.obstacles, (lost_at(15.6, -3.15, r_lost, flown),),
                                 flown)
    tri = part.triangles[0]
    assert isinstance(tri, ClippedTriangle)
    poly = tri.polygon()
    assert len(poly) == 3 + sum(k is not None for k in tri.kinks)
    kr = tri.kinks[1]
    assert kr is not None and kr[1] == pytest.approx(tri.p_otd[1])  # the right wall ∥ n_c
    inside = poly.mean(axis=0)
    assert tri.contains(inside) and not tri.contains(np.array([tri.p_oth[0] - 0.1,
                                                               tri.p_oth[1]]))
    assert tri.contains(poly, tol=1e-9).all()


def test_one_passage_when_the_other_side_is_closed():
    """A vehicle lost near a leg, beside the obstacle: the passage on the leg's side is closed,
    so the region goes to that leg (Remark 5: the right side tube dropped) and the other side
    stays open; certified."""
    sc, flown, r_lost = PX4
    lost = lost_at(21.0, -7.4, r_lost, flown)
    rp = repartition_around_lost(sc.tube, sc.obstacles, (lost,), flown)
    assert rp.step == "grouped"
    certify(rp.partition, discs_of((*sc.obstacles, lost), flown), flown)
    assert [t.remark5 for t in rp.partition.triangles] == ["right"]


def test_a_passage_too_narrow_for_one_robot_is_replaced():
    """Steps 1-2 build (the construction only warns) but leave a side tube narrower than one
    robot: the fallback gives one passage wide enough instead."""
    _, flown, r_lost = PX4
    tube = Trapezoid((0.0, 7.0), (30.0, 7.0), (0.0, -7.0), (30.0, -7.0))
    lost = lost_at(12.0, 1.0, r_lost, flown)
    weak = partition(tube, (lost,), flown)
    assert any("too narrow to contain one robot" in w.message for w in weak.warnings)
    rp = repartition_around_lost(tube, (), (lost,), flown)
    assert rp.step == "grouped" and rp.partition.warnings == ()
    certify(rp.partition, discs_of((lost,), flown), flown)


def test_no_partition_names_today_and_the_fallback():
    """A vehicle lost in the middle of an 8 m tube leaves no valid passage: PartitionError
    with today's reason and what the fallback tried."""
    _, flown, r_lost = PX4
    tube = Trapezoid((0.0, 4.0), (30.0, 4.0), (0.0, -4.0), (30.0, -4.0))
    with pytest.raises(PartitionError) as e:
        partition_around_lost(tube, (), (lost_at(12.0, 0.0, r_lost, flown),), flown)
    assert str(e.value).startswith("obstacle #1 at (12.0, 0.0) r_o=0.8: ")
    assert "nor with the fallback" in str(e.value) and "partitions tried" in str(e.value)
    assert e.value.obstacle == 0


@settings(max_examples=25, deadline=None)
@given(st.floats(3.5, 33.0), st.floats(-7.5, 7.5), st.sampled_from(["px4", "mock"]))
def test_property_every_re_partition_is_certified(x, y, which):
    """Anywhere in the tube of either shipped mission: a PartitionError, or a partition that
    meets the paper's conditions with every configured obstacle and the lost vehicle."""
    sc, flown, r_lost = PX4 if which == "px4" else MOCK
    lost = lost_at(x, y, r_lost, flown)
    if min(float(np.hypot(*(lost.center - o.center))) for o in sc.obstacles) < 1.5:
        return  # (a vehicle cannot be lost inside an obstacle)
    try:
        part = partition_around_lost(sc.tube, sc.obstacles, (lost,), flown)
    except PartitionError:
        return
    certify(part, discs_of((*sc.obstacles, lost), flown), flown, n=1500)


# ----------------------------------------------------------------------------------------------
# who cannot pass
# ----------------------------------------------------------------------------------------------
def test_cannot_pass_inside_the_triangle_only():
    """Inside the new triangle: cannot pass (negative clearance); beside it: can (even within
    r_s of its side, unless clearance_m = r_s asks for Assumption 1 to the letter); a NaN
    position is not counted; wall_clearance is min(d_Th, d_Tr) of the sub-tube given."""
    _, flown, r_lost = PX4
    tube = Trapezoid((0.0, 10.0), (40.0, 10.0), (0.0, -10.0), (40.0, -10.0))
    lost = lost_at(20.0, 0.0, r_lost, flown)
    part = partition_around_lost(tube, (), (lost,), flown)
    tri = part.triangles[0]
    behind = np.array([20.0 - 0.5 * tri.h, 0.0])  # on the axis, between apex and disc
    beside_far = np.array([20.0, 7.0])
    # just outside the right side, upstream of the tangent point
    side = (tri.p_otd - tri.p_oth) / np.hypot(*(tri.p_otd - tri.p_oth))
    normal_out = np.array([side[1], -side[0]])
    if normal_out @ (tri.p_otd - tri.p_otu) < 0:
        normal_out = -normal_out
    near = tri.p_oth + 0.4 * tri.h * side + 0.5 * normal_out
    pts = np.array([behind, beside_far, near, [np.nan, np.nan]])
    zones = apex_zones(part, flown)
    d = wall_clearance(part, pts, zones)
    assert d[0] < 0 and d[1] > flown.r_s and 0 < d[2] < flown.r_s and np.isnan(d[3])
    assert cannot_pass(part, pts, zones).tolist() == [True, False, False, False]
    assert cannot_pass(part, pts, zones, clearance_m=flown.r_s).tolist() == [
        True, False, True, False]
    k = part.locate(pts[:3])
    for j in range(3):
        t = part.sub_tubes[int(k[j])]
        if j != 2:  # (the look-ahead does not move these two)
            assert d[j] == pytest.approx(min(float(t.d_Th(pts[j])), float(t.d_Tr(pts[j]))))


# ----------------------------------------------------------------------------------------------
# a partition of its own: the obstacles a vehicle has passed left out
# ----------------------------------------------------------------------------------------------
def test_a_follower_past_the_obstacle_gets_a_partition_of_its_own():
    """px4_sitl_3 (the SITL budget): vehicle 0 lost at (26.3, −7.3) after passing obstacle #1
    on its right, vehicle 1 following it at (22.8, −5.8). The common re-partition groups the
    lost vehicle with obstacle #1 and vehicle 1 is inside the group's region; vehicle 1 has
    passed obstacle #1 (its O' ends at ξ = 22.48 m), so its own partition leaves #1 out: it
    is outside every region there, the lost vehicle's triangle keeps its number, and no point
    of a sub-tube ahead of it (ξ ≥ its ξ) lies in any O' — the one left out included."""
    sc, flown, r_lost = PX4
    assert moves_forward(flown)  # v cos α_max = 0.875 > v'_max = 0.5
    lost = lost_at(26.3, -7.3, r_lost, flown)
    q = np.array([22.8, -5.8])
    common = partition_around_lost(sc.tube, sc.obstacles, (lost,), flown)
    assert cannot_pass(common, q[None], apex_zones(common, flown))[0]
    assert passed(sc.tube, (*sc.obstacles, lost), flown, q).tolist() == [True, False]
    own = partition_past(sc.tube, sc.obstacles, (lost,), flown, q)
    assert own is not None
    assert [t.obstacle for t in own.triangles] == [1]  # the lost disc: len(obstacles) + 0
    assert not cannot_pass(own, q[None], apex_zones(own, flown))[0]
    for t in own.sub_tubes:
        assert check_assumption3(t, flown, "Assumption3'") == [], t
        assert check_constraint2(t, flown, "Constraint3") == [], t
    rng = np.random.default_rng(3)
    pts = rng.uniform([22.8, -10.0], [34.0, 10.0], size=(20000, 2))
    free = np.stack([t.contains(pts) for t in own.sub_tubes]).any(axis=0)
    for c, R in discs_of((*sc.obstacles, lost), flown):
        assert not np.any(free & (np.hypot(*(pts - c).T) < R)), c


def test_no_partition_of_its_own_before_an_obstacle_or_when_commands_may_turn_back():
    """Nothing passed (upstream of obstacle #1, or beside it): None. With the paper's speeds
    (v = 2, v'_max = 1.5: v cos α_max = 1.44 < v'_max) a command may move a vehicle back along
    n_c, so nothing is ever left out."""
    sc, flown, r_lost = PX4
    lost = lost_at(26.3, -7.3, r_lost, flown)
    for q in ([10.0, -5.0], [20.0, -5.0]):
        assert partition_past(sc.tube, sc.obstacles, (lost,), flown, np.array(q)) is None
    fast = dataclasses.replace(flown, v=2.0, v_max_prime=1.5, v_max=3.5)
    assert not moves_forward(fast)
    q = np.array([22.8, -5.8])
    assert partition_past(sc.tube, sc.obstacles, (lost,), fast, q) is None
    # nor when the estimate compensation's residual D may outrun the margin (0.375 m/s here)
    assert moves_forward(flown, residual_m_s=0.25) and not moves_forward(flown, 0.4)
    assert partition_past(sc.tube, sc.obstacles, (lost,), flown, q, residual_m_s=0.4) is None
    # an obstacle the caller keeps (a route: it meets a later segment) is never left out
    assert partition_past(sc.tube, sc.obstacles, (lost,), flown, q,
                          keep=np.array([True, False])) is None


def test_a_plan_of_its_own_only_for_the_papers_controller():
    """FlightPlan.past: the follower of the first test gets a plan of its own (obstacle #1
    left out) under the paper's controller, none under another law (the bound on the
    commands that makes it sound is the paper's)."""
    sc, flown, r_lost = PX4
    mission = load_mission(PX4_SITL_3)
    lost = (lost_at(26.3, -7.3, r_lost, flown),)
    q = np.array([22.8, -5.8])
    got = FlightPlan.for_mission(mission, flown).past(lost, q, residual_m_s=0.25)
    assert got is not None and np.allclose(got[1], [[20.0, 0.5]])
    assert FlightPlan.for_mission(mission, flown, kind="old").past(lost, q) is None


# ----------------------------------------------------------------------------------------------
# stepping aside: a waiting vehicle's way out of a region
# ----------------------------------------------------------------------------------------------
def _path_clear(p, q, obstacles, flown, tube) -> bool:
    xs = p + np.linspace(0.0, 1.0, 400)[:, None] * (q - p)
    for o in obstacles:
        if np.any(np.hypot(*(xs - o.center).T) <= o.radius + flown.r_s):
            return False
    return bool(np.all(np.minimum(tube.d_Th(xs), tube.d_Tr(xs)) >= flown.r_s - 1e-9))


def _behind_a_lost_one():
    """A 20 m wide tube, a vehicle lost on its axis at x = 20 (the SITL budget), its
    partition, and a point 3 m behind it on the axis: (flown, tube, lost, partition, zones,
    point)."""
    _, flown, r_lost = PX4
    tube = Trapezoid((0.0, 10.0), (40.0, 10.0), (0.0, -10.0), (40.0, -10.0))
    lost = lost_at(20.0, 0.0, r_lost, flown)
    part = partition_around_lost(tube, (), (lost,), flown)
    return flown, tube, lost, part, apex_zones(part, flown), np.array([17.0, 0.0])


def test_a_vehicle_behind_a_lost_one_steps_aside_into_a_sub_tube():
    """A vehicle at rest 3 m behind a lost one, on its axis (inside its triangle: it cannot
    pass, and no command of the controller gets it out: the cone behind a stopped vehicle).
    Straight across only (no step back): the nearest point across n_c inside a sub-tube (by
    the clearance asked), on a path outside every O' and r_s inside the legs; the left side
    on a tie. With steps back allowed: the straight line back and across is shorter (the
    triangle narrows towards its apex) and clear, so it takes that. p itself when it is
    already outside every region."""
    flown, tube, lost, part, zones, p = _behind_a_lost_one()
    assert cannot_pass(part, p[None], zones)[0]
    via, q = step_aside(tube, part, (lost,), flown, p, zones=zones, max_back_m=0.0)
    assert np.array_equal(via, p)
    assert q[0] == pytest.approx(17.0) and q[1] > 0.0  # left, on a tie
    assert wall_clearance(part, q[None], zones)[0] >= 0.3
    assert _path_clear(p, q, (lost,), flown, tube)
    # the nearest: a step 5 cm shorter is still inside (or too near the side)
    back = q - 0.05 * np.array([0.0, 1.0])
    assert wall_clearance(part, back[None], zones)[0] < 0.3
    across_m = float(np.hypot(*(q - p)))
    via, q = step_aside(tube, part, (lost,), flown, p, zones=zones)
    assert np.array_equal(via, p) and q[0] < 17.0 and q[1] > 0.0
    assert float(np.hypot(*(q - p))) < across_m
    assert wall_clearance(part, q[None], zones)[0] >= 0.3
    assert _path_clear(p, q, (lost,), flown, tube)
    # off the axis: the nearer side
    _, q2 = step_aside(tube, part, (lost,), flown, np.array([17.0, -0.4]), zones=zones)
    assert q2[1] < -0.4
    free = np.array([5.0, 6.0])
    via, q = step_aside(tube, part, (lost,), flown, free, zones=zones)
    assert np.array_equal(via, free) and np.array_equal(q, free)


def test_stepping_aside_backs_away_first_when_across_is_closed():
    """The same vehicle with an obstacle on either side of it, whose O' it would enter on
    its way straight across while still inside: it backs away (the straight line back and
    across, clear of them). With two more obstacles that the straight line would pass too
    near, it backs away along −n_c first (out of their reach), then crosses: every leg of
    the path clear. No way back (nothing behind the start base): none."""
    flown, tube, lost, part, zones, p = _behind_a_lost_one()
    sides = tuple(Obstacle(np.array([17.0, y]), 0.5, None) for y in (3.5, -3.5))
    obs = (lost, *sides)
    via, q = step_aside(tube, part, obs, flown, p, zones=zones)
    assert np.array_equal(via, p) and q[0] < 17.0
    assert wall_clearance(part, q[None], zones)[0] >= 0.3
    assert _path_clear(p, q, obs, flown, tube)
    corner = tuple(Obstacle(np.array([15.0, y]), 0.3, None) for y in (2.5, -2.5))
    assert not _path_clear(p, q, (*obs, *corner), flown, tube)
    obs = (*obs, *corner)
    via, q = step_aside(tube, part, obs, flown, p, zones=zones)
    assert via[1] == pytest.approx(0.0) and via[0] < 17.0  # back along the axis first
    assert q[0] == pytest.approx(via[0]) and abs(q[1]) > 0.0
    assert wall_clearance(part, q[None], zones)[0] >= 0.3
    assert _path_clear(p, via, obs, flown, tube) and _path_clear(via, q, obs, flown, tube)
    assert not _path_clear(p, q, obs, flown, tube)  # (the straight line is not)
    # no way back either (nothing behind the start base): none
    assert step_aside(tube, part, obs, flown, p, zones=zones, max_back_m=0.0) is None


def test_the_flight_plan_steps_aside_in_the_vehicles_segment():
    """FlightPlan.step_aside: px4_sitl_3 re-planned around a vehicle lost behind obstacle #1
    (the SITL budget); a vehicle waiting right behind the lost one gets a path into a
    sub-tube of that plan, clear of every obstacle of the route."""
    from vtube_fleet.config.mission import load_mission as load

    mission = load(PX4_SITL_3)
    _, flown, r_lost = PX4
    root = FlightPlan.for_mission(mission, flown)
    lost = lost_at(12.0, -6.0, r_lost, flown)
    plan = root.with_lost((lost,))
    p = np.array([8.5, -6.0])
    assert plan.cannot_pass(p[None])[0]
    via, q = plan.step_aside(p)
    assert not plan.cannot_pass(q[None])[0]
    tube = plan.route.segments[0].tube
    assert _path_clear(p, via, plan.all_obstacles, flown, tube)
    assert _path_clear(via, q, plan.all_obstacles, flown, tube)
