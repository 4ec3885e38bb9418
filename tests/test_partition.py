"""Tests of the Section IV partition (vtube_fleet.core.partition, docs/paper.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtube_fleet.core.controller import TubeArrays
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.partition import (
    DEFAULT_APEX_FACTOR,
    Partition,
    PartitionError,
    alpha_max,
    check_assumption3,
    h_min,
    partition,
)
from vtube_fleet.core.plan import plan_apex, plan_partition, tube_margins
from vtube_fleet.core.tube import Obstacle, Trapezoid
from vtube_fleet.errors import UserError

PARAMS = ControllerParams(r_s=0.25, r_a=0.5, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5)

# The recommended paper-like scenario (n_c = +x, left = +y).
PAPER_TUBE = Trapezoid((0.0, 9.0), (31.0, 4.5), (0.0, -9.0), (31.0, -4.5))
PAPER_OBSTACLES = [Obstacle(c, 0.9) for c in
                   [(10.5, 0.0), (15.0, 1.5), (19.5, -1.5), (24.0, 1.0), (28.5, -0.5)]]

RECT = Trapezoid((0.0, 5.0), (20.0, 5.0), (0.0, -5.0), (20.0, -5.0))
CONVERGING = Trapezoid((0.0, 6.0), (20.0, 4.0), (0.0, -6.0), (20.0, -4.0))
WIDE = Trapezoid((0.0, 12.0), (40.0, 12.0), (0.0, -12.0), (40.0, -12.0))
# A big obstacle and a small one nested in its left side tube, then a sequential one.
NESTED = [Obstacle((20.0, 0.0), 3.0), Obstacle((21.5, 8.5), 0.2)]


def reference_locate(part: Partition, p: np.ndarray) -> int:
    """partition §5 literally, one point at a time."""
    xi = float(part.tube.xi(p))
    best, best_v = -1, math.inf
    for k, t in enumerate(part.sub_tubes):
        if part.xi_start[k] <= xi < part.xi_end[k]:
            viol = max(-float(t.d_Th(p)), -float(t.d_Tr(p)))
            if viol < best_v:
                best, best_v = k, viol
    return best


def sample_in(tube: Trapezoid, n: int, rng: np.random.Generator) -> np.ndarray:
    poly = tube.polygon()
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    pts = rng.uniform(lo, hi, size=(3 * n, 2))
    return pts[tube.contains(pts)][:n]


def check_cover(part: Partition, obstacles: list[Obstacle], n: int = 20000, seed: int = 1):
    """(FourSub1)/(FourSub2) by sampling, plus locate == geometric containment."""
    rng = np.random.default_rng(seed)
    pts = sample_in(part.tube, n, rng)
    in_sub = np.stack([t.contains(pts) for t in part.sub_tubes])  # (K, N)
    in_tri = np.stack([tri.contains(pts) for tri in part.triangles]) if part.triangles else \
        np.zeros((0, len(pts)), dtype=bool)
    n_sub, n_tri = in_sub.sum(axis=0), in_tri.sum(axis=0)
    assert np.all(n_sub + n_tri == 1), "a point of T is uncovered or covered twice"
    # The sub-tubes are obstacle free (they avoid every O').
    for ob in obstacles:
        d = np.hypot(*(pts - ob.center).T)
        assert not np.any(n_sub.astype(bool) & (d <= ob.radius + PARAMS.r_s))
    k = part.locate(pts)
    sel = n_sub == 1
    assert np.array_equal(k[sel], in_sub[:, sel].argmax(axis=0))
    return pts, n_tri


# ------------------------------------------------------------------------------------------
def test_h_min_paper_numbers():
    assert h_min(0.9, PARAMS) == pytest.approx(1.654, abs=5e-4)
    assert DEFAULT_APEX_FACTOR * h_min(0.9, PARAMS) == pytest.approx(2.150, abs=5e-4)
    assert math.degrees(alpha_max(PARAMS)) == pytest.approx(44.05, abs=5e-3)
    # (pothk) is Constraint3 for the isosceles side: sin α_max = R / h_min.
    R = 0.9 + PARAMS.r_s
    a = math.asin(R / h_min(0.9, PARAMS))
    assert 2 * PARAMS.v * math.sin(a / 2) == pytest.approx(PARAMS.v_max_prime)


def test_no_obstacles_gives_the_main_tube():
    part = partition(CONVERGING, [], PARAMS)
    assert part.K == 1 and part.sub_tubes[0] is CONVERGING
    assert part.triangles == () and part.warnings == ()
    pts = np.array([[-3.0, 0.0], [5.0, 1.0], [25.0, 0.0], [5.0, 30.0]])
    assert part.locate(pts).tolist() == [0, 0, 0, 0]
    arrays = TubeArrays.from_tubes(part.sub_tubes)
    assert isinstance(arrays, TubeArrays) and len(arrays) == 1


def test_single_obstacle_four_tubes_numbered_as_in_the_paper():
    ob = Obstacle((10.0, 0.5), 0.9)
    part = partition(CONVERGING, [ob], PARAMS)
    assert part.K == 4
    assert part.names() == ("T_o1", "T_o2", "T_o3", "T_o4")
    tri = part.triangles[0]
    assert tri.remark5 is None and tri.obstacle == 0
    h = DEFAULT_APEX_FACTOR * h_min(0.9, PARAMS)
    R = 0.9 + PARAMS.r_s
    n_c, m = CONVERGING.n_c, CONVERGING.m
    # Apex upstream on the n_c line, (p_o − p_oth)/‖·‖ = n_c, ‖p_o − p_oth‖ = h.
    assert np.allclose((ob.center - tri.p_oth) / np.linalg.norm(ob.center - tri.p_oth), n_c)
    assert np.linalg.norm(ob.center - tri.p_oth) == pytest.approx(h)
    assert float(n_c @ (tri.p_otu - tri.p_otd)) == pytest.approx(0.0, abs=1e-12)
    assert float(m @ (tri.p_otd - tri.p_otu)) > 0  # u on the left, d on the right
    # O' is the incircle: distance from p_o to each side line = R.
    for a, b in ((tri.p_oth, tri.p_otu), (tri.p_oth, tri.p_otd), (tri.p_otu, tri.p_otd)):
        e = (b - a) / np.linalg.norm(b - a)
        dist = abs(e[0] * (ob.center - a)[1] - e[1] * (ob.center - a)[0])
        assert dist == pytest.approx(R)
    before, left, right, after = part.sub_tubes
    assert part.xi_start[0] == -math.inf and part.xi_end[3] == math.inf
    assert part.xi_end[0] == part.xi_start[1] == part.xi_start[2] == pytest.approx(10.0 - h)
    assert part.xi_end[1] == part.xi_end[2] == part.xi_start[3] == pytest.approx(10.0 + R)
    # left tube: right leg = triangle's left side; right tube: left leg = triangle's right side
    assert np.allclose(left.p_r0, tri.p_oth) and np.allclose(left.p_r1, tri.p_otu)
    assert np.allclose(right.p_h0, tri.p_oth) and np.allclose(right.p_h1, tri.p_otd)
    assert np.allclose(before.p_h0, CONVERGING.p_h0) and np.allclose(after.p_r1, CONVERGING.p_r1)
    # Side legs at α to n_c; Constraint3 holds with the default h, so no warnings.
    alpha = math.asin(R / h)
    assert math.acos(float(left.t_r @ n_c)) == pytest.approx(alpha)
    assert part.warnings == ()
    check_cover(part, [ob])


def test_paper_scenario_sequential_obstacles_give_3P_plus_1():
    part = partition(PAPER_TUBE, PAPER_OBSTACLES, PARAMS)
    assert part.K == 3 * 5 + 1
    assert all(t.remark5 is None for t in part.triangles)
    assert part.warnings == ()
    # Sorted by xi_start, then left to right; named T_o1..T_o16.
    assert list(part.xi_start) == sorted(part.xi_start)
    assert part.names() == tuple(f"T_o{k}" for k in range(1, 17))
    _, n_tri = check_cover(part, PAPER_OBSTACLES, seed=2)
    assert n_tri.sum() > 0


@pytest.mark.parametrize("extra, K", [([], 7), ([Obstacle((32.0, 0.0), 0.9)], 10)])
def test_nested_obstacles_give_3P_plus_1(extra, K):
    obstacles = NESTED + extra
    part = partition(WIDE, obstacles, PARAMS)
    assert part.K == K
    assert all(t.remark5 is None for t in part.triangles)
    # The small obstacle's triangle lies inside the big obstacle's left side tube.
    big, small = part.triangles[0], part.triangles[1]
    assert float(WIDE.xi(small.p_oth)) > float(WIDE.xi(big.p_oth))
    assert float(WIDE.xi(small.p_otd)) < float(WIDE.xi(big.p_otu))
    # Sub-tubes: before_1, {before_2, right_1}, {left_2, right_2}, after_2, after_1, ...
    assert part.locate(np.array([21.3, 10.5])) == 3  # left of the small obstacle
    assert part.locate(np.array([21.3, 6.0])) == 4  # between the small and the big one
    assert part.locate(np.array([18.0, -8.0])) == 2  # right of the big one
    check_cover(part, obstacles, seed=3)


@pytest.mark.parametrize("side", ["right", "left"])
def test_remark5_obstacle_near_a_leg(side):
    y = -4.6 if side == "right" else 4.6
    ob = Obstacle((10.0, y), 0.9)
    part = partition(CONVERGING, [ob], PARAMS)
    assert part.K == 3
    tri = part.triangles[0]
    assert tri.remark5 == side
    assert tri.beta == pytest.approx(tri.alpha)  # the apex fits without turning the tangent
    n_c = CONVERGING.n_c
    assert float(n_c @ (tri.p_otu - tri.p_otd)) == pytest.approx(0.0, abs=1e-12)
    if side == "right":  # side [p_oth, p_otd] on the right leg, direction t_r
        e = (tri.p_otd - tri.p_oth) / np.linalg.norm(tri.p_otd - tri.p_oth)
        assert np.allclose(e, CONVERGING.t_r)
        assert float(CONVERGING.d_Tr(tri.p_oth)) == pytest.approx(0.0, abs=1e-9)
        kept = part.sub_tubes[1]
        assert np.allclose(kept.p_r0, tri.p_oth) and np.allclose(kept.p_r1, tri.p_otu)
    else:  # mirror: side [p_oth, p_otu] on the left leg, direction t_h
        e = (tri.p_otu - tri.p_oth) / np.linalg.norm(tri.p_otu - tri.p_oth)
        assert np.allclose(e, CONVERGING.t_h)
        kept = part.sub_tubes[1]
        assert np.allclose(kept.p_h0, tri.p_oth) and np.allclose(kept.p_h1, tri.p_otd)
    # The before tube ends at the new apex and spans the full parent width.
    assert part.xi_end[0] == pytest.approx(float(CONVERGING.xi(tri.p_oth)))
    # The modified triangle contains O' ∩ T.
    rng = np.random.default_rng(4)
    r = (0.9 + PARAMS.r_s) * np.sqrt(rng.uniform(0, 1, 4000))
    th = rng.uniform(0, 2 * np.pi, 4000)
    disc = ob.center + np.stack([r * np.cos(th), r * np.sin(th)], axis=1)
    disc = disc[CONVERGING.contains(disc)]
    assert np.all(tri.contains(disc, tol=1e-9))
    check_cover(part, [ob], seed=5)


def test_remark5_bisection_turns_the_tangent_to_place_the_apex():
    ob = Obstacle((4.2, -4.6), 0.9)  # near the right leg and close to the start base
    part = partition(CONVERGING, [ob], PARAMS)
    tri = part.triangles[0]
    assert tri.remark5 == "right"
    assert tri.alpha < tri.beta <= alpha_max(PARAMS)
    xi_apex = float(CONVERGING.xi(tri.p_oth))
    assert 2 * PARAMS.r_a <= xi_apex <= 2 * PARAMS.r_a + 1e-4  # smallest β that fits
    # The kept side is the tangent at angle β; Constraint3 still holds (β ≤ α_max).
    kept = part.sub_tubes[1]
    assert math.acos(float(kept.t_r @ CONVERGING.n_c)) == pytest.approx(tri.beta)
    assert part.warnings == ()
    check_cover(part, [ob], seed=6)


# --- errors ---------------------------------------------------------------------------------
def test_error_triangle_does_not_fit_in_parent():
    with pytest.raises(PartitionError) as ei:
        partition(RECT, [Obstacle((1.5, 0.0), 0.9)], PARAMS)
    e = ei.value
    assert isinstance(e, UserError) and e.obstacle == 0
    assert str(e).startswith("obstacle #1 at (1.5, 0.0) r_o=0.9: ")
    assert "does not fit" in e.reason and "ξ_A = -0.65" in e.reason


def test_error_two_obstacles_side_by_side_do_not_fit():
    # Same ξ: the second one falls into the first one's side tube, which it cannot fit in.
    obstacles = [Obstacle((10.0, -2.5), 0.9), Obstacle((10.0, 2.0), 0.9)]
    with pytest.raises(PartitionError) as ei:
        partition(WIDE, obstacles, PARAMS)
    # ties go to the more-left obstacle first (y = 2 is left: m = −y), so #1 is the failing one
    assert ei.value.obstacle == 0
    assert "obstacle #1 at (10.0, -2.5) r_o=0.9" in str(ei.value)
    assert "the tube right of obstacle #2" in str(ei.value)


def test_error_obstacle_blocks_the_tube_inverted():
    narrow = Trapezoid((0.0, 1.6), (20.0, 1.6), (0.0, -1.6), (20.0, -1.6))
    with pytest.raises(PartitionError) as ei:
        partition(narrow, [Obstacle((2.0, 0.0), 0.5), Obstacle((12.0, 0.0), 0.9)], PARAMS)
    e = ei.value
    assert e.obstacle == 1
    assert str(e).startswith("obstacle #2 at (12.0, 0.0) r_o=0.9: the obstacle blocks the tube")
    assert "left: inverted" in e.reason and "right: inverted" in e.reason


def test_error_obstacle_blocks_the_tube_assumption3():
    tube = Trapezoid((0.0, 3.4), (20.0, 3.0), (0.0, -3.4), (20.0, -3.0))
    with pytest.raises(PartitionError) as ei:
        partition(tube, [Obstacle((10.0, 0.0), 0.9)], PARAMS)
    assert "blocks the tube" in ei.value.reason
    assert ei.value.reason.count("L ∩ R is not empty") == 2


def test_error_remark5_apex_cannot_be_placed():
    with pytest.raises(PartitionError) as ei:
        partition(CONVERGING, [Obstacle((3.2, -4.6), 0.9)], PARAMS)
    r = ei.value.reason
    assert "Remark 5" in r and "apex cannot be placed" in r and "α_max = 44.05°" in r
    assert "< ξ_s + 2 r_a = 1.0" in r


def test_error_apex_distance_inside_extended_obstacle():
    with pytest.raises(PartitionError, match=r"h = 1.0 m must exceed r_o \+ r_s = 1.15 m"):
        partition(RECT, [Obstacle((10.0, 0.0), 0.9, apex_distance=1.0)], PARAMS)


def test_obstacle_outside_the_tube_strict_and_not():
    ob = [Obstacle((10.0, -7.0), 0.9)]
    with pytest.raises(PartitionError, match="lies outside the tube"):
        partition(RECT, ob, PARAMS)
    part = partition(RECT, ob, PARAMS, strict=False)
    assert part.K == 1 and [w.condition for w in part.warnings] == ["Partition"]


def test_strict_mode_assumption3_prime_on_after_tube():
    ob = [Obstacle((18.5, 0.0), 0.9)]  # base at ξ = 19.65: after tube 0.35 m long
    with pytest.raises(PartitionError) as ei:
        partition(RECT, ob, PARAMS)
    assert ei.value.obstacle == 0
    assert "Assumption3' violated in T_o4 (the tube after obstacle #1): length 0.35 m" in str(
        ei.value)
    part = partition(RECT, ob, PARAMS, strict=False)
    assert part.K == 4
    assert [w.condition for w in part.warnings] == ["Assumption3'"]


def test_constraint3_warning_when_apex_too_close():
    part = partition(RECT, [Obstacle((10.0, 0.0), 0.9, apex_distance=1.5)], PARAMS)
    msgs = [w.message for w in part.warnings]
    assert [w.condition for w in part.warnings] == ["Constraint3", "Constraint3"]
    assert "T_o2" in msgs[0] and "right leg" in msgs[0] and "> v'_max = 1.5" in msgs[0]
    assert "T_o3" in msgs[1] and "left leg" in msgs[1]


def test_narrow_passage_is_reported_even_though_assumption3_letter_holds():
    # Parallel main legs: a side tube has no L area, so L ∩ R = ∅ and M ≠ ∅ by the letter,
    # but its finishing line is 0.41 m wide < what one safety disc needs.
    tube = Trapezoid((0.0, 2.5), (20.0, 2.5), (0.0, -2.5), (20.0, -2.5))
    part = partition(tube, [Obstacle((10.0, 0.0), 0.9)], PARAMS)
    assert part.K == 4
    msgs = [w.message for w in part.warnings if w.condition == "Assumption3'"]
    assert len(msgs) == 2 and all("too narrow to contain one robot" in m for m in msgs)


# --- the switching rule (§5) -----------------------------------------------------------------
@pytest.fixture(scope="module")
def exact():
    """Axis-aligned tube with exactly representable breakpoints: R = 1, h = 2 → ξ_A = 8,
    ξ_B = 11."""
    return partition(RECT, [Obstacle((10.0, 0.0), 0.75, apex_distance=2.0)], PARAMS)


@pytest.mark.parametrize("point, k", [
    ((8.0, 2.0), 1),     # on the shared base before|left → downstream (left)
    ((8.0, -2.0), 2),    # on the shared base before|right → right
    ((8.0, 0.0), 1),     # the apex: left tube (lower index)
    ((7.999, 0.0), 0),
    ((11.0, 0.0), 3),    # on the triangle base → after
    ((11.0, 4.5), 3),    # on the shared base left|after → after
    ((0.0, 0.0), 0),     # the main start base
    ((-1.0, 0.0), 0),    # ξ < 0 → first
    ((20.0, 0.0), 3),    # the finishing line → last
    ((25.0, 3.0), 3),    # ξ ≥ L → last
    ((5.0, 5.0), 0),     # on the main left leg (closed)
    ((9.0, 5.0), 1),
    ((5.0, 7.0), 0),     # laterally outside T → adjacent tube
    ((9.5, 7.0), 1),
    ((9.5, -7.0), 2),
    ((10.9, 1.2), 1),    # inside the triangle, nearer its left side → left tube
    ((10.9, -1.4), 2),
])
def test_locate_shared_edges(exact, point, k):
    p = np.array(point)
    assert exact.locate(p) == k
    assert reference_locate(exact, p) == k


def test_locate_apex_and_base_points(exact):
    tri = exact.triangles[0]
    assert exact.locate(tri.p_oth) == 1
    assert exact.locate(tri.p_otu) == 3 and exact.locate(tri.p_otd) == 3
    paper = partition(PAPER_TUBE, PAPER_OBSTACLES, PARAMS)
    for t in paper.triangles:  # apex → the left side tube, base points → the after tube
        k = int(paper.locate(t.p_oth))
        assert paper.sub_tubes[k].p_r0 is not None and np.allclose(paper.sub_tubes[k].p_r0,
                                                                   t.p_oth)
        k_u, k_d = int(paper.locate(t.p_otu)), int(paper.locate(t.p_otd))
        assert k_u == k_d and paper.xi_start[k_u] == pytest.approx(float(
            PAPER_TUBE.xi(t.p_otu)))


@pytest.mark.parametrize("case", ["paper", "nested", "remark5"])
def test_locate_matches_the_reference_rule_everywhere(case):
    tube, obs = {
        "paper": (PAPER_TUBE, PAPER_OBSTACLES),
        "nested": (WIDE, NESTED + [Obstacle((32.0, 0.0), 0.9)]),
        "remark5": (CONVERGING, [Obstacle((4.2, -4.6), 0.9), Obstacle((12.0, 4.0), 0.9)]),
    }[case]
    part = partition(tube, obs, PARAMS)
    rng = np.random.default_rng(7)
    poly = tube.polygon()
    lo, hi = poly.min(axis=0) - 3.0, poly.max(axis=0) + 3.0  # includes points outside T
    pts = rng.uniform(lo, hi, size=(3000, 2))
    fast = part.locate(pts)
    ref = np.array([reference_locate(part, q) for q in pts])
    assert np.array_equal(fast, ref)


def test_locate_shapes():
    part = partition(PAPER_TUBE, PAPER_OBSTACLES, PARAMS)
    rng = np.random.default_rng(8)
    pts = rng.uniform((0, -8), (31, 8), size=(6, 2))
    k = part.locate(pts)
    assert k.shape == (6,) and k.dtype.kind == "i"
    assert int(part.locate(pts[2])) == k[2]
    assert np.array_equal(part.locate(pts.reshape(2, 3, 2)), k.reshape(2, 3))
    assert np.array_equal(part.locate(pts.tolist()), k)


def test_arrays_follow_the_sub_tube_order():
    part = partition(PAPER_TUBE, PAPER_OBSTACLES, PARAMS)
    arr = TubeArrays.from_tubes(part.sub_tubes)
    assert isinstance(arr, TubeArrays) and len(arr) == part.K
    for k, t in enumerate(part.sub_tubes):
        assert np.allclose(arr.n_h[k], t.n_h) and np.allclose(arr.p_r1[k], t.p_r1)
        assert arr.has_L[k] == t.has_L and arr.has_R[k] == t.has_R


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(2.0, 19.0), st.floats(-6.5, 6.5), st.floats(0.1, 1.5),
                  st.sampled_from([None, 1.0, 1.5, 3.0])),
        min_size=1, max_size=3,
    ),
    st.integers(0, 2**31),
)
def test_property_any_successful_partition_covers_the_tube(obs_spec, seed):
    """Random obstacles: either a PartitionError or a partition that covers T exactly once
    (sub-tubes ∪ triangles), keeps every sub-tube clear of O', and whose fast locate agrees
    with the literal §5 rule everywhere (inside and outside T)."""
    obstacles = [Obstacle((x, y), r, None if f is None else f * h_min(r, PARAMS))
                 for x, y, r, f in obs_spec]
    try:
        part = partition(CONVERGING, obstacles, PARAMS, strict=False)
    except PartitionError as e:
        assert e.obstacle is not None and str(e).startswith(f"obstacle #{e.obstacle + 1} at ")
        return
    kept = [obstacles[t.obstacle] for t in part.triangles]
    assert part.K == 3 * len(kept) + 1 - sum(t.remark5 is not None for t in part.triangles)
    check_cover(part, kept, n=2000, seed=seed)
    rng = np.random.default_rng(seed)
    pts = rng.uniform((-2.0, -9.0), (22.0, 9.0), size=(300, 2))
    assert np.array_equal(part.locate(pts), [reference_locate(part, q) for q in pts])


# ------------------------------------------------------------------------------------------
# SubTubeTracker: locate for a moving swarm, identical to locate at every call
# ------------------------------------------------------------------------------------------
_TRACKER_CASES = {
    "paper": (PAPER_TUBE, PAPER_OBSTACLES),
    "exact": (RECT, [Obstacle((10.0, 0.0), 0.75, apex_distance=2.0)]),
    "nested": (WIDE, NESTED + [Obstacle((32.0, 0.0), 0.9)]),
    "remark5": (CONVERGING, [Obstacle((4.2, -4.6), 0.9), Obstacle((12.0, 4.0), 0.9)]),
    "none": (CONVERGING, []),
}
_TRACKER_PARTS: dict[str, Partition] = {}


def _tracker_part(case: str) -> Partition:
    if case not in _TRACKER_PARTS:
        tube, obs = _TRACKER_CASES[case]
        _TRACKER_PARTS[case] = partition(tube, obs, PARAMS)
    return _TRACKER_PARTS[case]


def _special_points(part: Partition) -> np.ndarray:
    """Apexes, triangle base points, sub-tube corners, base midpoints and points outside T
    laterally: where the §5 rule has its ties and shared edges."""
    pts = [t.polygon() for t in part.triangles] + [t.polygon() for t in part.sub_tubes]
    pts = np.concatenate(pts) if pts else np.zeros((0, 2))
    mids = np.array([(t.p_h0 + t.p_r0) / 2 for t in part.sub_tubes])
    T = part.tube
    out = np.array([T.lh(x) + 1.5 * T.m for x in np.linspace(0, T.length, 5)]
                   + [T.lr(x) - 1.5 * T.m for x in np.linspace(0, T.length, 5)])
    return np.concatenate([pts, mids, out])


@settings(max_examples=80, deadline=None)
@given(
    st.sampled_from(sorted(_TRACKER_CASES)),
    st.integers(0, 2**31),
    st.lists(st.sampled_from([0.0, 1e-15, 1e-12, 1e-10, 1e-9, 1e-7, 1e-4, 3e-3, 0.05, 0.5]),
             min_size=5, max_size=60),
    st.booleans(),
)
def test_tracker_equals_locate_on_random_walks(case, seed, scales, hint):
    """Random walks of step sizes from 0 to 0.5 m (down to 1e-15 m: rounding level) starting
    at and around apexes, shared bases, corners and outside T laterally, with occasional
    jumps onto such points, robots leaving (M changes) and a walk straight across the tube
    side: the tracker returns exactly locate's array at every call."""
    part = _tracker_part(case)
    rng = np.random.default_rng(seed)
    sp = _special_points(part)
    M = 40
    p = sp[rng.integers(0, len(sp), M)] + rng.normal(size=(M, 2)) * rng.choice(
        [0.0, 1e-12, 1e-9, 1e-3, 0.3], size=(M, 1))
    tr = part.tracker()
    lateral = part.tube.m * rng.choice([-1.0, 1.0])
    for scale in scales:
        step = rng.normal(size=p.shape) * scale
        step[0] = lateral * scale  # robot 0 walks across a leg and out of T
        q = p + step
        if rng.random() < 0.15:  # jump exactly onto special points
            idx = rng.integers(0, len(q), 3)
            q[idx] = sp[rng.integers(0, len(sp), 3)]
        if rng.random() < 0.1 and len(q) > 5:  # robots leave
            q = q[rng.random(len(q)) > 0.2]
            q = np.ascontiguousarray(q)
        moved = float(np.hypot(*(q - p).T).max()) if q.shape == p.shape else None
        k = tr.update(q, max_move=moved if hint else None)
        assert np.array_equal(k, part.locate(q)), (case, scale)
        assert not k.flags.writeable
        p = q


def test_tracker_reuses_the_array_and_relocates_rarely():
    part = _tracker_part("paper")
    rng = np.random.default_rng(3)
    p = np.column_stack([rng.uniform(0.5, 8.0, 60), rng.uniform(-4.0, 4.0, 60)])
    tr = part.tracker()
    k0 = tr.update(p)
    assert tr.update(p.copy()) is k0 and tr.update(p, max_move=0.0) is k0
    v = np.array([2e-3, 0.0])  # 2 mm per call along n_c: 15 m in 7500 calls
    for _ in range(7500):
        p = p + v
        k = tr.update(p, max_move=2e-3)
        if k is not k0:
            assert not np.array_equal(k, k0)
            k0 = k
    assert np.array_equal(k0, part.locate(p))
    assert tr.locates + tr.partial < 7500 / 10 and tr.checks < 7500
    assert tr.partial > tr.locates  # robots crossing boundaries are located on their own
    with pytest.raises(ValueError):
        tr.update(np.zeros((3, 3)))


def test_tracker_handles_nan_rows():
    part = _tracker_part("paper")
    p = np.array([[3.0, 0.0], [np.nan, np.nan], [20.0, 1.0]])
    tr = part.tracker()
    for _ in range(3):
        assert np.array_equal(tr.update(p), part.locate(p))


def _rows_hold(tr, p: np.ndarray) -> np.ndarray:
    """(M,) bool: every row of each point, as set at the tracker's last full locate, is > 0."""
    z = np.ascontiguousarray(p).view(np.complex128)[:, 0]
    return ((tr._C * z).real + tr._B > 0).all(axis=0)


@pytest.mark.parametrize("case", sorted(_TRACKER_CASES))
def test_tracker_rows_are_sufficient_across_every_boundary(case):
    """The tracker's claim, point by point: while a point's rows (set at one full locate and
    then frozen) hold, locate still gives its k. Robots walk in 0.1 mm steps across every
    slab boundary (both ways), and in 1 mm steps laterally through every triangle (where the
    left and right side tubes switch); the rows must also fail once k changed."""
    part = _tracker_part(case)
    T = part.tube
    xi0 = float(T.n_c @ T.p_h0)
    mid = (T.p_h0 + T.p_r0) / 2
    bps = np.unique(np.concatenate([part.xi_start, part.xi_end]))
    bps = bps[np.isfinite(bps)]
    lat = np.linspace(-1.2, 1.2, 9)[:, None] * (T.width(0.0) / 2) * T.m
    walks = []
    for sign in (1.0, -1.0):
        start = [mid + (b - sign * 2e-3 + xi0 - float(T.n_c @ mid)) * T.n_c + lat for b in bps]
        walks.append((np.concatenate(start) if start else mid + lat, sign * 1e-4 * T.n_c, 41))
    rows = []
    for tri in part.triangles:
        xa, xb = float(T.n_c @ tri.p_oth), float(T.n_c @ tri.p_otu)
        for x in np.linspace(xa - 0.01, xb + 0.01, 25):
            rows.append(tri.center + (x - float(T.n_c @ tri.center)) * T.n_c - 3.0 * T.m)
    if rows:
        walks.append((np.array(rows), 1e-3 * T.m, 6001))
    for p, step, n in walks:
        frozen = part.tracker()
        k0 = frozen.update(p).copy()
        tr = part.tracker()
        for _ in range(n):
            k = part.locate(p)
            hold = _rows_hold(frozen, p)
            assert np.array_equal(k[hold], k0[hold])
            assert np.array_equal(tr.update(p, max_move=float(np.hypot(*step))), k)
            p = p + step
        assert not _rows_hold(frozen, p)[k != k0].any()


# ----------------------------------------------------------------------------------------------
# apex_distance = "auto": the planner (vtube_fleet.core.plan)
# ----------------------------------------------------------------------------------------------

# Two obstacles too close along n_c for the default h = 1.3 h_min (the tube between the first
# base and the second apex is 0.7 m < 2 r_a); a shorter second triangle fits.
DENSE_TUBE = Trapezoid((0.0, 6.0), (22.0, 5.0), (0.0, -6.0), (22.0, -5.0))
DENSE = [Obstacle((8.0, 0.5), 0.9), Obstacle((12.0, -0.5), 0.9)]
DENSE_ROBOTS = np.array([(1.0 + i, -3.0 + j) for i in range(3) for j in range(7)], float)


def _auto(obs):
    return [Obstacle(o.center, o.radius, "auto") for o in obs]


def test_auto_feasible_where_default_refuses():
    with pytest.raises(PartitionError, match="length 0.7 m ≤ 2 r_a"):
        partition(DENSE_TUBE, DENSE, PARAMS)
    part = partition(DENSE_TUBE, _auto(DENSE), PARAMS, keep_out=DENSE_ROBOTS)
    assert part.apex is not None and part.apex.feasible
    hs = [t.h for t in part.triangles]
    for ob, h in zip(DENSE, hs, strict=True):
        assert h >= h_min(ob.radius, PARAMS)  # (pothk)
    # the default of obstacle #2 is the one that did not fit: the planner shortened it
    assert hs[1] < DEFAULT_APEX_FACTOR * h_min(0.9, PARAMS)
    # every sub-tube satisfies Assumption 3' and Constraint3, nobody starts in a triangle
    assert not part.warnings
    for t in part.sub_tubes:
        assert not check_assumption3(t, PARAMS, "Assumption3'")
    for tri in part.triangles:
        assert not tri.contains(DENSE_ROBOTS).any()


def test_auto_is_deterministic_and_reported():
    a = plan_apex(DENSE_TUBE, _auto(DENSE), PARAMS, DENSE_ROBOTS)
    b = plan_apex(DENSE_TUBE, _auto(DENSE), PARAMS, DENSE_ROBOTS)
    assert a.h == b.h and a.margin_m == b.margin_m  # bit for bit
    p1 = plan_partition(DENSE_TUBE, _auto(DENSE), PARAMS, keep_out=DENSE_ROBOTS)
    p2 = partition(DENSE_TUBE, _auto(DENSE), PARAMS, keep_out=DENSE_ROBOTS)
    for s, t in zip(p1.sub_tubes, p2.sub_tubes, strict=True):
        assert np.array_equal(s.polygon(), t.polygon())
    assert a.h == tuple(t.h for t in p1.triangles)
    assert "apex distances chosen (auto): #1 h = " in a.describe()
    assert a.margin_m > 0 and a.binding is not None


def test_auto_keeps_fixed_apex_distances_and_mixes():
    """A numeric apex distance stays as given; only the "auto" one is chosen."""
    obs = [Obstacle((8.0, 0.5), 0.9, 2.0), Obstacle((12.0, -0.5), 0.9, "auto")]
    part = partition(DENSE_TUBE, obs, PARAMS, keep_out=DENSE_ROBOTS)
    assert part.triangles[0].h == 2.0
    assert part.apex.auto == (False, True)


def test_auto_keeps_start_positions_out_of_triangles():
    """Robots right in front of an obstacle: the margin objective would like a long triangle
    (wider side tubes), but no start position may be inside one, and they keep r_s clear."""
    ob = [Obstacle((9.0, 0.0), 0.9, "auto")]
    robots = np.array([(5.5, y) for y in (-0.6, 0.0, 0.6)])
    part = partition(DENSE_TUBE, ob, PARAMS, keep_out=robots)
    tri = part.triangles[0]
    assert not tri.contains(robots).any()
    assert part.apex.margin_m > 0
    free = partition(DENSE_TUBE, ob, PARAMS)
    assert free.triangles[0].h > tri.h  # without the robots it would reach further upstream


def test_auto_infeasible_is_reported():
    """Whatever h is, the side passages are too narrow: the plan says so and why; an obstacle
    wider than the tube makes the construction itself fail, naming it."""
    narrow = Trapezoid((0.0, 1.6), (20.0, 1.6), (0.0, -1.6), (20.0, -1.6))
    plan = plan_apex(narrow, [Obstacle((10.0, 0.0), 0.9, "auto")], PARAMS)
    assert not plan.feasible and plan.margin_m < 0
    assert plan.binding.condition == "room for one robot"
    assert "violated by" in plan.binding.describe()
    blocked = Trapezoid((0.0, 1.0), (20.0, 1.0), (0.0, -1.0), (20.0, -1.0))
    with pytest.raises(PartitionError, match="obstacle #1"):
        partition(blocked, [Obstacle((10.0, 0.0), 0.9, "auto")], PARAMS)
    plan = plan_apex(blocked, [Obstacle((10.0, 0.0), 0.9, "auto")], PARAMS)
    assert not plan.feasible and plan.error and plan.failed_obstacle == 0


@settings(max_examples=60, deadline=None)
@given(st.floats(4.0, 9.0), st.floats(3.0, 9.0), st.floats(1.0, 3.0), st.floats(1.0, 3.0),
       st.floats(-3.0, 3.0))
def test_margins_agree_with_assumption3(w0, w1, k_t, r_a, skew):
    """The planner's margins are ≥ 0 exactly where check_assumption3 passes (up to its area
    tolerance): the objective measures the conditions the construction tests."""
    tube = Trapezoid((0.0, w0 / 2 + skew), (6.0, w1 / 2), (0.0, -w0 / 2 + skew), (6.0, -w1 / 2))
    p = ControllerParams(r_s=0.2, r_a=r_a, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5,
                         k_t=k_t)
    ms = dict(tube_margins(tube, k_t, r_a, 0.2))
    reasons = " ".join(v.message for v in check_assumption3(tube, p, "Assumption3'"))
    tol = 1e-4
    if "L ∩ R = ∅" in ms and abs(ms["L ∩ R = ∅"]) > tol:
        assert (ms["L ∩ R = ∅"] < 0) == ("L ∩ R is not empty" in reasons)
    if "M ≠ ∅" in ms and abs(ms["M ≠ ∅"]) > tol:
        assert (ms["M ≠ ∅"] < 0) == ("M is empty" in reasons)
    assert (ms["length > 2 r_a"] <= 0) == ("≤ 2 r_a" in reasons)
    if abs(ms["room for one robot"]) > tol:
        assert (ms["room for one robot"] < 0) == ("too narrow" in reasons)


def test_auto_scenario_flies_with_zero_violations(tmp_path):
    """Done-means of issue 11 item 1: refused with the default apex distances, planned with
    "auto", then flown (vtube_fleet.sim) with every robot through and no violation; the h_k
    chosen are in the summary and the recording."""
    from vtube_fleet.config.scenario import parse_scenario
    from vtube_fleet.recording.reader import load_recording
    from vtube_fleet.recording.writer import open_recorder
    from vtube_fleet.sim import simulate

    doc = {
        "tube": {"p_h0": [0.0, 6.0], "p_h1": [22.0, 5.0], "p_r0": [0.0, -6.0],
                 "p_r1": [22.0, -5.0]},
        "partition": {"apex_distance": "auto"},
        "obstacles": [{"center": list(o.center), "radius": o.radius} for o in DENSE],
        "robots": {"r_s": 0.25, "r_a": 0.5, "v_min": 0.5, "v_max": 3.5,
                   "positions": DENSE_ROBOTS.tolist()},
        "controller": {"v": 2.0, "v_max_prime": 1.5},
        "sim": {"dt": 0.002, "duration": 25.0},
    }
    sc = parse_scenario(doc, "dense.toml")
    assert all(o.apex_distance == "auto" for o in sc.obstacles)
    with open_recorder(tmp_path / "dense.rrd", kind="sim") as rec:
        res = simulate(sc, recorder=rec)
    s = res.summary
    assert s["exited"] == len(DENSE_ROBOTS), s
    assert s["violations"] == 0, s
    assert s["apex_distances_m"] == [t.h for t in res.partition.triangles]
    assert s["apex_distances_m"][1] < DEFAULT_APEX_FACTOR * h_min(0.9, PARAMS)
    meta = load_recording(tmp_path / "dense.rrd").meta
    assert meta["apex_distances_m"] == s["apex_distances_m"]
    assert [o["apex_distance"] for o in meta["obstacles"]] == ["auto", "auto"]


def test_lost_vehicle_repartition_uses_the_planner():
    """FlightPlan.with_lost: a lost vehicle whose fixed apex distance (1.05 h_min) gives no
    partition gets one chosen by the planner; configured "auto" obstacles keep the h_k they
    were flown with (not re-planned under flying vehicles)."""
    import dataclasses

    from tests.missions import MOCK_FLEET
    from vtube_fleet.config.mission import load_mission
    from vtube_fleet.fleet.budget import LinkMeasurement, mission_budget
    from vtube_fleet.fleet.flight_plan import LOST_APEX_FACTOR, FlightPlan

    mission = load_mission(MOCK_FLEET)
    sc = mission.scenario
    flown = mission_budget(mission, LinkMeasurement(0.0, 0.0, 0.0)).inflate(sc.controller)
    configured = tuple(dataclasses.replace(o, apex_distance="auto") for o in sc.obstacles)
    root = FlightPlan.build(sc.corridor.with_obstacles(configured), flown,
                            keep_out=mission.slots)
    h_root = root.route.triangles[0].h
    r = sc.controller.r_s + mission.config.lost_obstacle_margin_m
    fixed = LOST_APEX_FACTOR * h_min(r, flown)
    lost = (Obstacle(np.array([8.76, -1.94]), r, fixed),)
    with pytest.raises(PartitionError):
        partition(sc.tube, [dataclasses.replace(configured[0], apex_distance=h_root), *lost],
                  flown)
    new = root.with_lost(lost)
    part = new.route.segments[0].partition
    assert part.apex is not None and part.apex.feasible
    tri = {t.obstacle: t for t in part.triangles}
    assert tri[0].h == h_root  # frozen
    assert h_min(r, flown) <= tri[1].h != fixed
    assert root.with_lost(lost) is new  # cached: every agent gets the same plan


def test_auto_paper_tube_three_obstacles_flies_safely():
    """Another scenario the default refuses (found by perturbing obstacle positions in the
    shipped paper tube): with "auto" all 120 robots get through with no violation."""
    import dataclasses

    from tests.missions import ROOT
    from vtube_fleet.config.scenario import load_scenario
    from vtube_fleet.core.validation import validate_scenario
    from vtube_fleet.sim import simulate

    sc = load_scenario(ROOT / "configs" / "paper.toml")
    centres = [(11.83, 0.7), (16.42, -2.54), (20.55, -1.97)]
    fixed = tuple(Obstacle(c, 0.9) for c in centres)
    assert validate_scenario(sc.tube, fixed, sc.controller, sc.robots.positions)[1]
    auto = dataclasses.replace(sc, obstacles=tuple(Obstacle(c, 0.9, "auto") for c in centres))
    res = simulate(auto, duration=30.0)
    assert res.summary["exited"] == 120 and res.summary["violations"] == 0, res.summary


def test_auto_with_an_obstacle_outside_the_tube():
    """Non-strict (validation): an obstacle whose O' misses the tube is skipped with a warning,
    the planner still plans the others; strict: it is an error, as with numbers."""
    obs = [Obstacle((12.0, -0.5), 0.9, "auto"), Obstacle((8.0, 30.0), 0.9, "auto"),
           Obstacle((8.0, 0.5), 0.9, "auto")]
    part = partition(DENSE_TUBE, obs, PARAMS, strict=False, keep_out=DENSE_ROBOTS)
    assert [t.obstacle for t in part.triangles] == [0, 2]
    assert part.K == 7 and len({id(t) for t in part.sub_tubes}) == 7
    assert sum("lies outside the tube" in w.message for w in part.warnings) == 1
    ref = partition(DENSE_TUBE, [obs[0], obs[2]], PARAMS, keep_out=DENSE_ROBOTS)
    assert [t.h for t in part.triangles] == [t.h for t in ref.triangles]
    with pytest.raises(PartitionError, match="lies outside the tube"):
        partition(DENSE_TUBE, obs, PARAMS, keep_out=DENSE_ROBOTS)
