"""Controller (ModifiedVectorField)/(Oldcontroller)/Appendix C against a loop-based reference,
speed bounds for any state (hypothesis), term directions on simple configurations, rows=."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtube_fleet.core.barrier import X_MIN, dV_n_dx, sat, sigma
from vtube_fleet.core.controller import (
    CommandEvaluator,
    TubeArrays,
    u1pp,
    u2,
    u3p_u4p,
    u5,
    velocity_command,
)
from vtube_fleet.core.neighbours import VerletPairs, pairs_within
from vtube_fleet.core.params import ControllerParams, ParameterError
from vtube_fleet.core.tube import Obstacle, Trapezoid
from vtube_fleet.errors import UserError

PAPER = ControllerParams(r_s=0.25, r_a=0.5, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5)


# ------------------------------------------------------------------------------ helpers
def make_tube(phi=0.0, w0=6.0, length=20.0, a_h=0.0, a_r=0.0, origin=(0.0, 0.0), name="T"):
    """Tube with n_c at angle ``phi``; leg angles a_h, a_r > 0 narrow the tube."""
    c, s = math.cos(phi), math.sin(phi)
    rot = np.array([[c, -s], [s, c]])
    loc = np.array([[0.0, w0 / 2], [length, w0 / 2 - length * math.tan(a_h)],
                    [0.0, -w0 / 2], [length, -w0 / 2 + length * math.tan(a_r)]])
    pts = loc @ rot.T + np.asarray(origin)
    return Trapezoid(*pts, name=name)


def reference(p, k, tubes, params, kind="new", obstacles=()):
    """Straightforward per-robot evaluation of the paper's equations (with paper notes 1,
    3, 4, 6), using only the public barrier functions."""
    P = params
    p = np.asarray(p, dtype=float)
    M = len(p)
    out = np.zeros((M, 2))
    for i in range(M):
        T = tubes[k[i]]
        d_h, d_r = float(T.d_Th(p[i])), float(T.d_Tr(p[i]))
        s_h = sigma(d_h, P.r_a, P.k_t * P.r_a) if T.has_L else 0.0
        s_r = sigma(d_r, P.r_a, P.k_t * P.r_a) if T.has_R else 0.0
        q = T.n_c + s_h * (T.t_h - T.n_c) + s_r * (T.t_r - T.n_c)
        u1 = P.v * q / np.linalg.norm(q)
        Pt = np.eye(2) - np.outer(T.n_c, T.n_c)
        u34 = (-dV_n_dx(P.k3, d_h, P.r_s, P.r_a, P.eps_t, P.eps_s) * (Pt @ T.n_h)
               - dV_n_dx(P.k3, d_r, P.r_s, P.r_a, P.eps_t, P.eps_s) * (Pt @ T.n_r))
        uu2 = np.zeros(2)
        for j in range(M):
            if j == i:
                continue
            pij = p[i] - p[j]
            d = float(np.hypot(*pij))
            b = -dV_n_dx(P.k2, d, 2 * P.r_s, P.r_s + P.r_a, P.eps_m, P.eps_s) / max(d, X_MIN)
            uu2 += b * pij
        uu5 = np.zeros(2)
        for ob in obstacles:
            dp = p[i] - ob.center
            d = float(np.hypot(*dp))
            uu5 -= dV_n_dx(P.k4, d, ob.radius + P.r_s, ob.radius + P.r_a, P.eps_o,
                           P.eps_s) / max(d, X_MIN) * dp
        if kind == "old":
            out[i] = sat(u1 + uu2 + u34, P.v_max)
        else:
            out[i] = u1 + sat(uu2 + u34 + uu5, P.v_max_prime)
    return out


def speeds(v):
    return np.hypot(v[:, 0], v[:, 1])


def alpha_max(params):
    return 2 * math.asin(min(1.0, params.v_max_prime / (2 * params.v)))


# ------------------------------------------------------------------------------ params, arrays
def test_params_validation():
    assert issubclass(ParameterError, UserError)
    ok = dict(r_s=0.25, r_a=0.5, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5)
    ControllerParams(**ok)
    for bad in (dict(r_a=0.2), dict(r_s=-1.0), dict(v=float("nan")), dict(k_t=0.9),
                dict(eps_m=0.0), dict(eps_s=0.5), dict(v_min=4.0), dict(v_max_prime="x")):
        with pytest.raises(ParameterError) as e:
            ControllerParams(**{**ok, **bad})
        assert next(iter(bad)) in str(e.value)


def test_tube_arrays_from_tubes_and_distances():
    tubes = [make_tube(a_h=0.2, a_r=-0.1), make_tube(phi=0.7, a_h=-0.3, a_r=0.25)]
    ta = TubeArrays.from_tubes(tubes)
    assert len(ta) == 2 and ta.n_c.shape == (2, 2)
    assert list(ta.has_L) == [True, False] and list(ta.has_R) == [False, True]
    rng = np.random.default_rng(0)
    p = rng.normal(size=(30, 2)) * 5
    k = rng.integers(0, 2, 30)
    want_h = [tubes[kk].d_Th(pp) for pp, kk in zip(p, k, strict=True)]
    np.testing.assert_allclose(ta.d_Th(p, k), want_h)
    want_r = [tubes[kk].d_Tr(pp) for pp, kk in zip(p, k, strict=True)]
    np.testing.assert_allclose(ta.d_Tr(p, k), want_r)
    with pytest.raises(ValueError):
        TubeArrays.from_tubes([])


# ------------------------------------------------------------------------------ reference
@pytest.mark.parametrize("kind", ["new", "old", "apf"])
def test_matches_reference_on_a_crowded_multi_tube_state(kind):
    rng = np.random.default_rng(11)
    tubes = [make_tube(a_h=0.3, a_r=0.2, length=8.0),
             make_tube(origin=(20.0, 0.0), a_h=-0.2, a_r=0.35, w0=4.0, length=4.0),
             make_tube(phi=0.4, origin=(0.0, 9.0), a_h=0.1, a_r=0.1, w0=3.0, length=8.0)]
    M = 90
    p = np.column_stack([rng.uniform(-1, 24, M), rng.uniform(-4, 4, M)])
    p[:10] = p[10:20] + rng.normal(scale=0.2, size=(10, 2))  # close pairs, some violating
    p[20] = p[21]  # coincident robots
    p[22] = tubes[0].lh(5.0)  # exactly on a leg
    p[23] = tubes[0].lh(6.0) - 0.3 * tubes[0].n_h  # outside the tube
    k = rng.integers(0, 3, M)
    obstacles = (Obstacle([8.0, 0.5], 0.9), Obstacle([15.0, -1.0], 0.6))
    ob = obstacles if kind == "apf" else ()
    v = velocity_command(p, k, TubeArrays.from_tubes(tubes), PAPER, kind=kind, obstacles=ob)
    ref = reference(p, k, tubes, PAPER, kind, ob)
    np.testing.assert_allclose(v, ref, rtol=0, atol=1e-9)


def test_term_functions_match_reference_terms():
    rng = np.random.default_rng(5)
    tubes = [make_tube(a_h=0.3, a_r=0.3, length=8.0),
             make_tube(phi=-0.5, a_h=-0.1, a_r=0.2, w0=4.0)]
    ta = TubeArrays.from_tubes(tubes)
    p = rng.uniform(-1, 8, (40, 2)) * [2, 0.6]
    k = rng.integers(0, 2, 40)
    P = PAPER
    U1 = u1pp(p, k, ta, P)
    U34 = u3p_u4p(p, k, ta, P)
    U2 = u2(p, P)
    for i in range(40):
        T = tubes[k[i]]
        s_h = sigma(T.d_Th(p[i]), P.r_a, P.k_t * P.r_a) if T.has_L else 0.0
        s_r = sigma(T.d_Tr(p[i]), P.r_a, P.k_t * P.r_a) if T.has_R else 0.0
        q = T.n_c + s_h * (T.t_h - T.n_c) + s_r * (T.t_r - T.n_c)
        np.testing.assert_allclose(U1[i], P.v * q / np.linalg.norm(q), atol=1e-12)
        Pt = np.eye(2) - np.outer(T.n_c, T.n_c)
        want = (-dV_n_dx(P.k3, T.d_Th(p[i]), P.r_s, P.r_a, P.eps_t, P.eps_s) * (Pt @ T.n_h)
                - dV_n_dx(P.k3, T.d_Tr(p[i]), P.r_s, P.r_a, P.eps_t, P.eps_s) * (Pt @ T.n_r))
        np.testing.assert_allclose(U34[i], want, rtol=1e-8, atol=1e-12)
        want2 = np.zeros(2)
        for j in range(40):
            if j != i:
                d = np.hypot(*(p[i] - p[j]))
                want2 -= dV_n_dx(P.k2, d, 2 * P.r_s, P.r_s + P.r_a, P.eps_m, P.eps_s) / max(
                    d, X_MIN) * (p[i] - p[j])
        np.testing.assert_allclose(U2[i], want2, rtol=1e-8, atol=1e-9)
    obs = [Obstacle([3.0, 1.0], 0.9)]
    U5 = u5(p, obs, P)
    for i in range(40):
        dp = p[i] - obs[0].center
        d = np.hypot(*dp)
        want5 = -dV_n_dx(P.k4, d, 0.9 + P.r_s, 0.9 + P.r_a, P.eps_o, P.eps_s) / max(d, X_MIN) * dp
        np.testing.assert_allclose(U5[i], want5, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------ speed bounds
@st.composite
def scenarios(draw):
    v_min = draw(st.floats(0.0, 2.0))
    vp = draw(st.floats(0.05, 3.0))
    v = v_min + vp + draw(st.floats(0.0, 1.0))  # Constraint1: v − v'_max ≥ v_min
    v_max = v + vp + draw(st.floats(0.0, 1.0))  # Constraint1: v + v'_max ≤ v_max
    r_s = draw(st.floats(0.05, 1.0))
    params = ControllerParams(
        r_s=r_s, r_a=r_s * draw(st.floats(1.1, 3.0)), v_min=v_min, v_max=v_max, v=v,
        v_max_prime=vp, k2=10 ** draw(st.floats(-2, 2)), k3=10 ** draw(st.floats(-2, 2)),
        k_t=draw(st.floats(1.0, 3.0)), eps_m=10 ** draw(st.floats(-12, -2)),
        eps_t=10 ** draw(st.floats(-12, -2)), eps_s=10 ** draw(st.floats(-12, -2)))
    am = alpha_max(params) * 0.999  # Constraint2/3 for narrowing legs
    tubes = []
    for t in range(draw(st.integers(1, 4))):
        a_h = draw(st.floats(-1.2, am))
        a_r = draw(st.floats(-1.2, am))
        w0 = draw(st.floats(1.0, 12.0))
        length = draw(st.floats(1.0, 30.0))
        shrink = length * (math.tan(a_h) + math.tan(a_r))
        if shrink > 0.9 * w0:  # keep the legs from crossing
            length *= 0.9 * w0 / shrink
        tubes.append(make_tube(phi=draw(st.floats(-3.2, 3.2)), w0=w0, length=length, a_h=a_h,
                               a_r=a_r, origin=(draw(st.floats(-5, 5)), draw(st.floats(-5, 5))),
                               name=f"T{t}"))
    M = draw(st.integers(1, 60))
    seed = draw(st.integers(0, 2**32 - 1))
    return params, tubes, M, seed


def _state(tubes, M, seed):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-12, 12, (M, 2))
    if M > 4:
        p[1] = p[0]  # coincident
        p[2] = p[3] + rng.normal(scale=1e-6, size=2)  # nearly coincident
        p[4] = tubes[0].lh(rng.uniform(0, tubes[0].length))  # on a leg
    if M > 10:
        p[5:10] = p[10] + rng.normal(scale=0.1, size=(5, 2))  # a tight cluster
    k = rng.integers(0, len(tubes), M)
    return p, k


@settings(max_examples=150, deadline=None)
@given(scenarios(), st.sampled_from(["new", "apf"]))
def test_speed_stays_within_bounds_for_any_state(scen, kind):
    params, tubes, M, seed = scen
    p, k = _state(tubes, M, seed)
    obstacles = (Obstacle([0.0, 0.0], 1.0), Obstacle(p[0] + 0.1, 0.5)) if kind == "apf" else ()
    v = velocity_command(p, k, TubeArrays.from_tubes(tubes), params, kind=kind,
                         obstacles=obstacles)
    assert np.all(np.isfinite(v))
    sp = speeds(v)
    assert np.all(sp >= params.v_min * (1 - 1e-9))
    assert np.all(sp <= params.v_max * (1 + 1e-9))


@settings(max_examples=60, deadline=None)
@given(scenarios())
def test_old_controller_respects_only_the_maximum_speed(scen):
    params, tubes, M, seed = scen
    p, k = _state(tubes, M, seed)
    v = velocity_command(p, k, TubeArrays.from_tubes(tubes), params, kind="old")
    assert np.all(np.isfinite(v))
    assert np.all(speeds(v) <= params.v_max * (1 + 1e-9))


def test_old_controller_can_stall_where_the_new_one_cannot():
    # a neighbour straight ahead at the distance where ‖u2‖ = v cancels u1'' = v n_c
    P = PAPER
    lo, hi = 2 * P.r_s, P.r_s + P.r_a
    for _ in range(200):
        d = 0.5 * (lo + hi)
        if -dV_n_dx(P.k2, d, 2 * P.r_s, P.r_s + P.r_a, P.eps_m, P.eps_s) > P.v:
            lo = d
        else:
            hi = d
    ta = TubeArrays.from_tubes([make_tube(w0=6.0)])
    p = np.array([[5.0, 0.0], [5.0 + d, 0.0]])
    old = speeds(velocity_command(p, [0, 0], ta, P, kind="old"))
    new = speeds(velocity_command(p, [0, 0], ta, P, kind="new"))
    assert old[0] < 1e-6 < P.v_min  # (Oldcontroller) stalls: the paper's comparison
    assert new[0] == pytest.approx(P.v - P.v_max_prime)  # = v_min, reached exactly
    assert new[0] >= P.v_min * (1 - 1e-12)
    assert old[1] == pytest.approx(P.v_max) and new[1] == pytest.approx(P.v + P.v_max_prime)


# ------------------------------------------------------------------------------ directions
def test_u1pp_is_v_nc_in_the_middle_area_and_v_th_near_a_narrowing_leg():
    P = PAPER
    tube = make_tube(phi=0.3, w0=8.0, a_h=0.25, a_r=0.2, length=12.0)
    ta = TubeArrays.from_tubes([tube])
    xi = 6.0
    mid = (tube.lh(xi) + tube.lr(xi)) / 2
    # along the inward normal of the left leg, at several distances
    foot = tube.p_h0 + tube.t_h * ((xi - 0.0) / float(tube.t_h @ tube.n_c))
    ds = np.array([0.3, P.r_a, 0.5 * (P.r_a + P.k_t * P.r_a), P.k_t * P.r_a, 2.0])
    pts = np.vstack([mid, foot + ds[:, None] * tube.n_h])
    u = u1pp(pts, np.zeros(len(pts), int), ta, P)
    np.testing.assert_allclose(u[0], P.v * tube.n_c, atol=1e-12)  # middle area
    np.testing.assert_allclose(u[1], P.v * tube.t_h, atol=1e-12)  # σ = 1 (d ≤ r_a)
    np.testing.assert_allclose(u[2], P.v * tube.t_h, atol=1e-12)
    np.testing.assert_allclose(u[4], P.v * tube.n_c, atol=1e-12)  # σ = 0 (d ≥ k_t r_a)
    np.testing.assert_allclose(u[5], P.v * tube.n_c, atol=1e-12)
    # in the transition band the direction lies strictly between n_c and t_h
    cross = lambda a, b: a[0] * b[1] - a[1] * b[0]  # noqa: E731
    assert cross(tube.n_c, u[3]) * cross(tube.n_c, tube.t_h) > 0
    assert cross(u[3], tube.t_h) * cross(tube.n_c, tube.t_h) > 0
    np.testing.assert_allclose(speeds(u), P.v)


def test_u1pp_ignores_a_diverging_leg():
    tube = make_tube(w0=4.0, a_h=-0.3, a_r=0.0)  # left leg diverges, right leg parallel
    assert not tube.has_L and not tube.has_R
    p = np.array([tube.lh(3.0) + 0.1 * tube.n_h, tube.lr(3.0) + 0.1 * tube.n_r])
    u = u1pp(p, np.zeros(2, int), TubeArrays.from_tubes([tube]), PAPER)
    np.testing.assert_allclose(u, [PAPER.v * tube.n_c] * 2, atol=1e-12)


def test_leg_terms_push_inwards_and_are_orthogonal_to_nc():
    P = PAPER
    tube = make_tube(phi=-0.4, w0=6.0, a_h=0.3, a_r=0.15, length=10.0)
    ta = TubeArrays.from_tubes([tube])
    m = tube.m  # lateral unit vector, left → right
    near_left = [tube.lh(x) + d * tube.n_h for x, d in ((2.0, 0.3), (5.0, 0.45), (8.0, -0.2))]
    near_right = [tube.lr(x) + d * tube.n_r for x, d in ((2.0, 0.3), (5.0, 0.01), (7.0, -1.0))]
    p = np.array(near_left + near_right)
    u = u3p_u4p(p, np.zeros(len(p), int), ta, P)
    np.testing.assert_allclose(u @ tube.n_c, 0.0, atol=1e-9 * np.abs(u).max())  # Remark 4
    assert np.all(u[:3] @ m > 0)  # pushed right, away from the left leg
    assert np.all(u[3:] @ m < 0)
    # far from both legs: no leg term; the whole command is u1''
    mid = np.array([(tube.lh(4.0) + tube.lr(4.0)) / 2])
    assert np.all(u3p_u4p(mid, [0], ta, P) == 0.0)
    np.testing.assert_allclose(velocity_command(mid, [0], ta, P), [P.v * tube.n_c], atol=1e-12)
    # and the full command of a robot at the left leg steers right of u1''
    v = velocity_command(p[:1], [0], ta, P)
    assert float((v[0] - u1pp(p[:1], [0], ta, P)[0]) @ m) > 0


def test_pair_is_pushed_apart_symmetrically():
    P = PAPER
    tube = make_tube(w0=10.0)
    ta = TubeArrays.from_tubes([tube])
    p = np.array([[5.0, 0.0], [5.3, 0.45]])
    U = u2(p, P)
    d = p[0] - p[1]
    assert float(U[0] @ d) > 0 and abs(U[0][0] * d[1] - U[0][1] * d[0]) < 1e-9 * np.abs(U).max()
    np.testing.assert_allclose(U[1], -U[0], rtol=1e-12)
    # beyond r_s + r_a they do not interact at all
    far = np.array([[5.0, 0.0], [5.0, P.r_s + P.r_a + 1e-9]])
    assert np.all(u2(far, P) == 0.0)
    # the command moves them apart relative to u1''
    v = velocity_command(p, [0, 0], ta, P)
    assert float((v[0] - v[1]) @ d) > 0


def test_neighbours_in_other_sub_tubes_count_and_each_robot_uses_its_own_tube():
    P = PAPER
    # two sub-tubes in sequence sharing the base x = 10 (a "before" and an "after" tube)
    a = make_tube(w0=6.0, length=10.0, a_h=0.05, a_r=0.05)
    b = make_tube(w0=6.0 - 20 * math.tan(0.05), length=10.0, origin=(10.0, 0.0), a_h=-0.1)
    ta = TubeArrays.from_tubes([a, b])
    p = np.array([[9.8, 0.0], [10.3, 0.2]])  # 0.54 m apart, across the shared base
    k = np.array([0, 1])
    v = velocity_command(p, k, ta, P)
    v_alone = np.vstack([velocity_command(p[:1], k[:1], ta, P),
                         velocity_command(p[1:], k[1:], ta, P)])
    assert not np.allclose(v, v_alone)  # u2 acts across sub-tubes (paper note 6)
    np.testing.assert_allclose(v, reference(p, k, [a, b], P), atol=1e-9)
    # the same point evaluated in another sub-tube gets that tube's geometry
    q = np.array([a.lh(9.0) + 0.3 * a.n_h])
    assert not np.allclose(velocity_command(q, [0], ta, P), velocity_command(q, [1], ta, P))


# ------------------------------------------------------------------------------ rows, pairs
def test_rows_agent_view_equals_the_swarm_view():
    rng = np.random.default_rng(2)
    tubes = [make_tube(a_h=0.3, a_r=0.3, length=8.0), make_tube(origin=(0, 7), a_h=0.1, a_r=0.0)]
    ta = TubeArrays.from_tubes(tubes)
    M = 120
    p = np.column_stack([rng.uniform(0, 15, M), rng.uniform(-3, 9, M)])
    k = rng.integers(0, 2, M)
    full = velocity_command(p, k, ta, PAPER)
    rows = np.array([5, 17, 3])
    np.testing.assert_allclose(velocity_command(p, k, ta, PAPER, rows=rows), full[rows],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(velocity_command(p, k[rows], ta, PAPER, rows=rows), full[rows],
                               rtol=0, atol=1e-12)
    # an agent: itself first, then whoever it hears about within r_s + r_a (and some more)
    for i in (0, 40, 77):
        d = np.hypot(*(p - p[i]).T)
        nb = np.flatnonzero((d <= 1.5) & (np.arange(M) != i))
        local = np.vstack([p[i], p[nb]])
        cmd = velocity_command(local, np.r_[k[i], k[nb]], ta, PAPER, rows=[0])
        np.testing.assert_allclose(cmd[0], full[i], rtol=0, atol=1e-12)
        # several rows at once, pairs=None (all pairs touching the rows are candidates)
        cmd2 = velocity_command(local, np.r_[k[i], k[nb]], ta, PAPER, rows=[0, 1])
        np.testing.assert_allclose(cmd2[0], full[i], rtol=0, atol=1e-12)


def test_pairs_argument_superset_and_none_give_the_same_commands():
    rng = np.random.default_rng(4)
    tube = make_tube(w0=6.0)
    ta = TubeArrays.from_tubes([tube])
    p = np.column_stack([rng.uniform(0, 8, 80), rng.uniform(-2.5, 2.5, 80)])
    k = np.zeros(80, int)
    v_none = velocity_command(p, k, ta, PAPER)
    exact = pairs_within(p, PAPER.r_s + PAPER.r_a)
    wide = pairs_within(p, 3.0)
    np.testing.assert_array_equal(velocity_command(p, k, ta, PAPER, pairs=exact), v_none)
    np.testing.assert_allclose(velocity_command(p, k, ta, PAPER, pairs=wide), v_none, atol=1e-15)
    # writeable (uncached) and read-only (cached) pair arrays agree, also when called again
    I, J = np.array(wide[0]), np.array(wide[1])
    np.testing.assert_allclose(velocity_command(p, k, ta, PAPER, pairs=(I, J)), v_none,
                               atol=1e-15)
    p2 = p + 0.01
    np.testing.assert_allclose(velocity_command(p2, k, ta, PAPER, pairs=wide),
                               velocity_command(p2, k, ta, PAPER), atol=1e-15)
    # lists work too
    v_list = velocity_command(p.tolist(), k.tolist(), ta, PAPER, pairs=(I.tolist(), J.tolist()))
    np.testing.assert_allclose(v_list, v_none, atol=1e-15)


def test_nan_rows_do_not_affect_the_others():
    rng = np.random.default_rng(6)
    tube = make_tube(w0=6.0, a_h=0.2, a_r=0.2, length=10.0)
    ta = TubeArrays.from_tubes([tube])
    p = np.column_stack([rng.uniform(0, 6, 50), rng.uniform(-2, 2, 50)])
    k = np.zeros(50, int)
    ref = velocity_command(p, k, ta, PAPER)
    q = p.copy()
    q[[3, 30]] = np.nan  # exited
    pairs = pairs_within(q, PAPER.r_s + PAPER.r_a)  # excludes them
    v = velocity_command(q, k, ta, PAPER, pairs=pairs)
    assert np.all(np.isnan(v[[3, 30]]))
    others = np.setdiff1d(np.arange(50), [3, 30])
    keep = np.setdiff1d(np.arange(50), [3, 30])
    ref2 = velocity_command(p[keep], k[keep], ta, PAPER)
    np.testing.assert_allclose(v[others], ref2, atol=1e-12)
    assert np.all(np.isfinite(ref))


def test_empty_swarm_and_bad_arguments():
    ta = TubeArrays.from_tubes([make_tube()])
    assert velocity_command(np.zeros((0, 2)), np.zeros(0, int), ta, PAPER).shape == (0, 2)
    p = np.array([[1.0, 0.0], [2.0, 0.0]])
    with pytest.raises(ValueError, match="sub-tube"):
        velocity_command(p, [0, 1], ta, PAPER)
    with pytest.raises(ValueError, match="sub-tube"):
        velocity_command(p, [0, -1], ta, PAPER)
    with pytest.raises(ValueError):
        velocity_command(p, [0], ta, PAPER)
    with pytest.raises(ValueError):
        velocity_command(p, [0.0, 0.0], ta, PAPER)
    with pytest.raises(ValueError):
        velocity_command(p, [0, 0], ta, PAPER, kind="fast")
    with pytest.raises(ValueError):
        velocity_command(p, [0, 0], ta, PAPER, kind="apf")
    with pytest.raises(ValueError):
        velocity_command(p, [0, 0], ta, PAPER, pairs=(np.array([0]), np.array([5])))
    with pytest.raises(ValueError):
        velocity_command(p, [0, 0], ta, PAPER, rows=[2])
    with pytest.raises(ValueError):
        velocity_command(p, [0, 0], ta, PAPER, rows=[1, 1])
    with pytest.raises(ValueError):
        velocity_command(p[:, :1], [0, 0], ta, PAPER)


# ------------------------------------------------------------------------------ CommandEvaluator
@pytest.mark.parametrize("kind", ["new", "old", "apf"])
def test_command_evaluator_equals_velocity_command_bitwise(kind):
    """The simulator's entry point gives exactly velocity_command's result while k, the pair
    list and the robot count change under it (cached constants must follow), with read-only
    (cached) and writeable (re-derived) k and pairs, into ``out`` or a new array."""
    rng = np.random.default_rng(12)
    tubes = [make_tube(a_h=0.3, a_r=0.2, length=8.0),
             make_tube(phi=0.5, origin=(8.0, 0.0), a_h=-0.2, a_r=0.35, w0=4.0, length=4.0),
             make_tube(phi=-0.3, origin=(0.0, 9.0), a_h=0.1, a_r=0.1, w0=3.0, length=8.0)]
    ta = TubeArrays.from_tubes(tubes)
    ob = (Obstacle([8.0, 0.5], 0.9),) if kind == "apf" else ()
    ev = CommandEvaluator(ta, PAPER, kind, ob)
    M = 70
    p = np.column_stack([rng.uniform(-1, 14, M), rng.uniform(-3, 10, M)])
    p[5] = p[6] + 1e-3  # a violating pair (slow path of the barriers)
    k = rng.integers(0, 3, M).astype(np.intp)
    k.setflags(write=False)
    pairs = pairs_within(p, 1.5)
    out = np.empty((M, 2))
    for step in range(12):
        if step == 3:  # a new k (the tracker's array changes)
            k = k.copy()
            k[:10] = (k[:10] + 1) % 3
            k.setflags(write=False)
        if step == 5:  # robots jump next to others: a new pair list with new close pairs
            p[20:30] = p[40:50] + 0.3
            pairs = pairs_within(p, 1.2)
        if step == 7:  # robots leave: new M, new k and pairs
            p = np.ascontiguousarray(p[10:])
            M = p.shape[0]
            k = np.ascontiguousarray(k[10:])
            k.setflags(write=False)
            pairs = pairs_within(p, 1.5)
            out = np.empty((M, 2))
        kk = k.copy() if step == 9 else k  # writeable k: re-gathered
        pp = (np.array(pairs[0]), np.array(pairs[1])) if step == 10 else pairs
        want = velocity_command(p, kk, ta, PAPER, pairs=pp, kind=kind, obstacles=ob)
        got = ev(p, kk, pp, out=out) if step % 2 else ev(p, kk, pp)
        assert np.array_equal(got, want, equal_nan=True), step
        if step % 2:
            assert np.shares_memory(got, out)
        p = p + 0.01 * want


def test_command_evaluator_checks_its_arguments():
    ta = TubeArrays.from_tubes([make_tube()])
    ev = CommandEvaluator(ta, PAPER)
    p = np.array([[1.0, 0.0], [2.0, 0.0]])
    pairs = pairs_within(p, 1.0)
    k0 = np.zeros(2, np.intp)
    assert ev(np.zeros((0, 2)), np.zeros(0, np.intp), pairs_within(np.zeros((0, 2)), 1.0)
              ).shape == (0, 2)
    with pytest.raises(ValueError, match="sub-tube"):
        ev(p, np.array([0, 1]), pairs)
    with pytest.raises(ValueError, match="sub-tube"):
        ev(p, np.array([0, -1]), pairs)
    with pytest.raises(ValueError):
        ev(p, np.zeros(3, np.intp), pairs)
    with pytest.raises(ValueError):
        ev(p.tolist(), k0, pairs)
    with pytest.raises(ValueError):
        ev(p, k0, (np.array([0]), np.array([5])))
    with pytest.raises(ValueError):
        ev(p, k0, pairs, out=np.empty((3, 2)))
    with pytest.raises(ValueError):
        CommandEvaluator(ta, PAPER, "fast")
    with pytest.raises(ValueError):
        CommandEvaluator(ta, PAPER, "apf")


def test_command_evaluator_tracks_the_minimum_pair_distance():
    """track_min_pair: the smallest candidate-pair distance of the last call, the number the
    safety metrics compute from the same list (inf without pairs)."""
    from vtube_fleet.core.metrics import SafetyMonitor

    rng = np.random.default_rng(13)
    tube = make_tube(w0=8.0, length=12.0)
    ta = TubeArrays.from_tubes([tube])
    ev = CommandEvaluator(ta, PAPER, track_min_pair=True)
    mon = SafetyMonitor(tube, np.zeros((0, 2)), np.zeros(0), PAPER.r_s, PAPER.v_min,
                        PAPER.v_max, PAPER.r_s + PAPER.r_a)
    p = np.column_stack([rng.uniform(0, 10, 60), rng.uniform(-3, 3, 60)])
    p[7] = p[8] + [1e-12, 0.0]  # coincident up to 1e-12 m (below the barriers' clamp)
    k = np.zeros(60, np.intp)
    k.setflags(write=False)
    pairs = pairs_within(p, 1.5)
    ev(p, k, pairs)
    want = mon.evaluate(p, pairs=pairs).min_pair_distance_m[0]
    assert ev.min_pair_distance == want == pytest.approx(1e-12, rel=1e-3)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    ev(p, k, empty)
    assert ev.min_pair_distance == math.inf
    assert CommandEvaluator(ta, PAPER).min_pair_distance == math.inf  # not tracked


@pytest.mark.parametrize("kind", ["new", "old", "apf"])
def test_command_evaluator_element_subset_is_bitwise_the_full_evaluation(kind, monkeypatch):
    """step(move=...) skips the elements that are exactly 0 (legs/σ beyond max(r_a, k_t r_a),
    pairs beyond r_s + r_a) while the points move less than ACTIVE_SKIN: over a closed loop
    with sub-tube changes, new pair lists, a violating pair and a sparse phase (no pair
    within reach: the minimum comes from all candidates), every command and every minimum
    pair distance is bitwise velocity_command's / the candidates' minimum."""
    from vtube_fleet.core import controller as ctl
    from vtube_fleet.core.neighbours import VerletPairs

    rng = np.random.default_rng(21)
    tubes = [make_tube(a_h=0.25, a_r=0.2, length=10.0, w0=7.0),
             make_tube(phi=0.4, origin=(10.0, 0.0), a_h=-0.1, a_r=0.3, w0=4.0, length=5.0)]
    ta = TubeArrays.from_tubes(tubes)
    ob = (Obstacle([6.0, 0.5], 0.9),) if kind == "apf" else ()
    ev = CommandEvaluator(ta, PAPER, kind, ob, track_min_pair=True)
    M = 60
    p = np.column_stack([rng.uniform(0.5, 9.0, M), rng.uniform(-2.8, 2.8, M)])
    p[3] = p[4] + [0.2, 0.0]  # a violating pair (the barriers' general formula)
    dt = 1e-3
    move = dt * (PAPER.v + PAPER.v_max_prime) * (1 + 1e-6)
    verlet = VerletPairs(PAPER.r_s + PAPER.r_a, 0.375)
    k = (p[:, 0] > 8.0).astype(np.intp)
    k.setflags(write=False)
    fast = 0
    real_core = ctl._Active.core

    def counting_core(self, z, *args):
        nonlocal fast
        fast += 1
        return real_core(self, z, *args)

    monkeypatch.setattr(ctl._Active, "core", counting_core)
    for step in range(400):
        if step == 300:  # sparse phase: a 12 x 5 grid 1 m apart (> r_s + r_a + 2 ACTIVE_SKIN)
            p = np.column_stack([1.0 + np.arange(M) % 12, -2.0 + np.arange(M) // 12])
        knew = (p[:, 0] > 8.0).astype(np.intp)
        if not np.array_equal(knew, k):
            k = knew
            k.setflags(write=False)
        pairs = verlet.candidates(p)
        want = velocity_command(p, k, ta, PAPER, pairs=pairs, kind=kind, obstacles=ob)
        z = p.view(np.complex128).ravel()
        got = ev.step(z, k, pairs, move=move).view(np.float64).reshape(M, 2)
        assert got.tobytes() == want.tobytes(), step
        d = np.abs(z[pairs[0]] - z[pairs[1]])
        assert ev.min_pair_distance == (d.min() if d.size else math.inf), step
        p = p + dt * want
    assert fast > 300  # the subset served most steps


def test_element_subset_takes_the_general_formula_when_a_margin_comes_near(monkeypatch):
    """The element subset skips the test ĝ ≥ 1 of the band formula (BarrierBank) while the
    smallest pair distance and a bound on the leg distances show it holds (_band_floor); a
    robot driven through a leg and a pair driven into each other must still get the general
    formula at the steps where they need it, bitwise as velocity_command."""
    from vtube_fleet.core import controller as ctl
    from vtube_fleet.core.barrier import BarrierBank

    for E1, D1 in ((3.9, 0.97), (1.0 + 1e-6, 1.0), (7.3e-3, 2.5e-3)):
        x0 = ctl._band_floor(E1, D1)
        assert x0 * E1 - D1 >= 1.0 and math.nextafter(x0, 0.0) * E1 - D1 < 1.0 + 1e-12
    ta = TubeArrays.from_tubes([make_tube(a_h=0.1, a_r=0.05, length=12.0, w0=6.0)])
    ev = CommandEvaluator(ta, PAPER, "new", track_min_pair=True)
    general = {"n": 0}
    evaluate = BarrierBank.evaluate

    def counted(self, x, out=None):
        general["n"] += int(not np.min(x * self._E1[: x.shape[0]] - self._D1[: x.shape[0]])
                            >= 1.0)
        return evaluate(self, x, out)

    monkeypatch.setattr(BarrierBank, "evaluate", counted)
    real_core = ctl._Active.core
    fast = {"n": 0}

    def counting_core(self, z, *args):
        fast["n"] += 1
        return real_core(self, z, *args)

    monkeypatch.setattr(ctl._Active, "core", counting_core)
    verlet = VerletPairs(PAPER.r_s + PAPER.r_a, 0.375)
    grid = np.column_stack([1.0 + np.arange(20) % 5, -1.2 + 0.8 * (np.arange(20) // 5)])
    k = np.zeros(24, np.intp)
    k.setflags(write=False)
    dt = 1e-3
    move = 3.5 * dt * (1 + 1e-6)
    for step in range(700):
        s = step * dt * 3.5
        extra = np.array([[8.0, 1.5 + s],  # through the left leg (d_Th from 0.7 to < 0)
                          [8.0, -2.0 - 0.5 * s],  # through the right leg (from 0.6)
                          [10.0, 0.0 + 0.5 * s], [10.0, 1.2 - 0.5 * s]])  # into each other
        p = np.ascontiguousarray(np.vstack([grid + [s, 0.0], extra]))
        pairs = verlet.candidates(p)
        n0 = general["n"]
        want = velocity_command(p, k, ta, PAPER, pairs=pairs)
        need = general["n"] > n0
        got = ev.step(p.view(np.complex128).ravel(), k, pairs, move=move)
        assert got.view(np.float64).reshape(-1, 2).tobytes() == want.tobytes(), step
        if need:  # the subset needed the general formula too
            assert general["n"] == n0 + 2, step
    assert general["n"] > 200 and fast["n"] > 600  # (subset and full evaluation alike)


def test_new_sub_tubes_of_a_few_robots_take_the_short_path(monkeypatch):
    """CommandEvaluator.step: when the read-only k differs from the last call's in a few
    robots (the sub-tube tracker's changes) and the pairs are the same, those robots'
    constants and leg/σ elements are patched on the short path (_new_k); the commands are
    bitwise velocity_command's at every step."""
    from vtube_fleet.core import controller as ctl

    tubes = [make_tube(a_h=0.25, a_r=0.2, length=10.0, w0=7.0),
             make_tube(phi=0.4, origin=(10.0, 0.0), a_h=-0.1, a_r=0.3, w0=4.0, length=5.0)]
    ta = TubeArrays.from_tubes(tubes)
    ev = CommandEvaluator(ta, PAPER, "new", track_min_pair=True)
    served = {"n": 0}
    new_k = ctl.CommandEvaluator._new_k

    def counted(self, *args):
        v = new_k(self, *args)
        served["n"] += v is not None
        return v

    monkeypatch.setattr(ctl.CommandEvaluator, "_new_k", counted)
    M = 30
    # a slanted line of robots 0.9 m apart moving downstream: they cross x = 8 one by one
    p0 = np.column_stack([np.linspace(5.5, 8.4, M), np.linspace(-2.6, 2.6, M)])
    I, J = np.triu_indices(M, 1)
    pairs = (I.astype(np.int64), J.astype(np.int64))
    for a in pairs:
        a.setflags(write=False)
    k = np.zeros(M, np.intp)
    k.setflags(write=False)
    dt, v = 1e-3, 2.0
    move = dt * v * (1 + 1e-6)
    for step in range(1500):
        p = p0 + [v * dt * step, 0.0]
        knew = (p[:, 0] > 8.0).astype(np.intp)
        if not np.array_equal(knew, k):
            k = knew
            k.setflags(write=False)
        want = velocity_command(p, k, ta, PAPER, pairs=pairs)
        got = ev.step(np.ascontiguousarray(p).view(np.complex128).ravel(), k, pairs, move=move)
        assert got.view(np.float64).reshape(-1, 2).tobytes() == want.tobytes(), step
    assert served["n"] >= 20
