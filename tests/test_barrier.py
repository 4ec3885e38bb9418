"""σ, s, V_n, ∂V_n/∂x, the fused BarrierBank and sat/κ (Section III-A, paper note 3)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtube_fleet.core.barrier import (
    X_MIN,
    BarrierBank,
    V_n,
    ds_dx,
    dsigma_dx,
    dV_n_dx,
    kappa,
    s,
    s_knots,
    sat,
    sigma,
)

PAPER = dict(eps=1e-6, eps_s=1e-6)


def _fd(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


# ----------------------------------------------------------------------------- σ
def test_sigma_is_the_papers_cubic():
    d1, d2 = 0.5, 0.75
    A = -2 / (d1 - d2) ** 3
    B = 3 * (d1 + d2) / (d1 - d2) ** 3
    C = -6 * d1 * d2 / (d1 - d2) ** 3
    D = d2**2 * (3 * d1 - d2) / (d1 - d2) ** 3
    x = np.linspace(d1, d2, 101)
    np.testing.assert_allclose(sigma(x, d1, d2), A * x**3 + B * x**2 + C * x + D, atol=1e-12)
    assert sigma(d1 - 1.0, d1, d2) == 1.0 and sigma(d1, d1, d2) == 1.0
    assert sigma(d2, d1, d2) == 0.0 and sigma(d2 + 3.0, d1, d2) == 0.0
    assert np.all(np.diff(sigma(x, d1, d2)) <= 0)


def test_dsigma_matches_finite_differences_and_vanishes_outside():
    d1, d2 = 0.3, 1.1
    x = np.linspace(d1 + 1e-3, d2 - 1e-3, 57)
    np.testing.assert_allclose(dsigma_dx(x, d1, d2), _fd(lambda t: sigma(t, d1, d2), x, 1e-6),
                               rtol=1e-6, atol=1e-8)
    assert np.all(dsigma_dx(np.array([-1.0, 0.0, d1, d2, 5.0]), d1, d2) == 0.0)


# ----------------------------------------------------------------------------- s
@pytest.mark.parametrize("eps_s", [1e-6, 1e-3, 0.1])
def test_s_is_c1_identity_below_and_one_above(eps_s):
    x1, x2 = s_knots(eps_s)
    assert x1 < 1 < x2
    assert x2 == pytest.approx(1 + eps_s / math.tan(math.radians(67.5)))
    # identity branch, extended below 0 (paper note 3)
    xs = np.array([-5.0, -1e-3, 0.0, 0.3, np.nextafter(x1, 0.0)])
    np.testing.assert_array_equal(s(xs, eps_s), xs)
    np.testing.assert_array_equal(ds_dx(xs, eps_s), 1.0)
    assert np.all(s(np.array([x2, x2 + 1e-9, 3.0]), eps_s) == pytest.approx(1.0, abs=1e-15))
    # C¹ at both knots
    for knot in (x1, x2):
        h = eps_s * 1e-5
        assert s(knot - h, eps_s) == pytest.approx(s(knot + h, eps_s), abs=4 * h)
        assert ds_dx(knot - h, eps_s) == pytest.approx(ds_dx(knot + h, eps_s), abs=1e-2)
    # on the arc: s ≤ min(x, 1) and FD derivative
    u = np.linspace(x1, x2, 41)[1:-1]
    assert np.all(s(u, eps_s) <= np.minimum(u, 1) + 1e-15)
    np.testing.assert_allclose(ds_dx(u, eps_s), _fd(lambda t: s(t, eps_s), u, eps_s * 1e-4),
                               rtol=1e-4, atol=1e-4)


def test_s_rejects_bad_eps():
    with pytest.raises(ValueError):
        s(0.5, 0.0)
    with pytest.raises(ValueError):
        ds_dx(0.5, 2.0)


# ----------------------------------------------------------------------------- V_n
def test_V_n_values_and_properties_paper_parameters():
    d1, d2 = 0.5, 0.75
    # property (3): V_n ≈ k/(εx) for 0 < x < d1
    for x in (0.01, 0.2, 0.45):
        assert V_n(1.0, x, d1, d2, **PAPER) == pytest.approx(1 / (1e-6 * x), rel=1e-9)
        assert dV_n_dx(1.0, x, d1, d2, **PAPER) == pytest.approx(-1 / (1e-6 * x * x), rel=1e-9)
    # huge near d1 (|dV| ~ 1e12 just above d1, paper note 3)
    assert V_n(1.0, d1 * (1 + 1e-7), d1, d2, **PAPER) > 1e5
    assert dV_n_dx(1.0, d1 * (1 + 1e-6), d1, d2, **PAPER) < -1e11
    # property (2): zero beyond d2 (and at d2)
    x = np.array([d2, d2 + 1e-12, 1.0, 1e6])
    assert np.all(V_n(1.0, x, d1, d2, **PAPER) == 0.0)
    assert np.all(dV_n_dx(1.0, x, d1, d2, **PAPER) == 0.0)


def test_V_n_clamps_violated_distances_finitely_and_pushes_the_right_way():
    d1, d2 = 0.25, 0.5
    x = np.array([-3.0, -1e-12, 0.0, X_MIN / 2])
    v = V_n(1.0, x, d1, d2, **PAPER)
    dv = dV_n_dx(1.0, x, d1, d2, **PAPER)
    assert np.all(np.isfinite(v)) and np.all(np.isfinite(dv))
    assert np.all(v == V_n(1.0, X_MIN, d1, d2, **PAPER))
    assert np.all(dv == dV_n_dx(1.0, X_MIN, d1, d2, **PAPER))
    assert np.all(dv < -1e20)  # maximal push (≈ −k/(ε·1e-18))


@settings(max_examples=60, deadline=None)
@given(
    d1=st.floats(0.05, 3.0),
    ratio=st.floats(1.05, 4.0),
    k=st.floats(0.01, 100.0),
    log_eps=st.floats(-12, -1),
    log_eps_s=st.floats(-12, -1.5),
    seed=st.integers(0, 2**32 - 1),
)
def test_dV_n_dx_is_nonpositive_and_matches_finite_differences(d1, ratio, k, log_eps,
                                                               log_eps_s, seed):
    d2, eps, eps_s = d1 * ratio, 10.0**log_eps, 10.0**log_eps_s
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.uniform(-d1, 2 * d2, 200), d1 * (1 + eps_s * rng.uniform(-2, 2, 50))])
    dv = dV_n_dx(k, x, d1, d2, eps, eps_s)
    assert np.all(np.isfinite(dv)) and np.all(dv <= 0)
    assert np.all(V_n(k, x, d1, d2, eps, eps_s) >= 0)
    # finite differences away from the kinks (clamp, fillet knots, d1, d2)
    x1, x2 = s_knots(eps_s)
    kinks = np.array([X_MIN, d1 * x1, d1 * x2, d1, d2])
    h = 1e-7 * np.maximum(x, d1)
    far = np.abs(x[:, None] - kinks[None, :]).min(axis=1) > 1e3 * h
    far &= x > 0
    xf = x[far]
    num = _fd(lambda t: V_n(k, t, d1, d2, eps, eps_s), xf, h[far])
    np.testing.assert_allclose(dv[far], num, rtol=2e-4, atol=1e-9 * np.abs(num).max() + 1e-12)


def test_V_n_rejects_bad_parameters():
    with pytest.raises(ValueError):
        V_n(1.0, 0.3, 0.5, 0.5, 1e-6, 1e-6)
    with pytest.raises(ValueError):
        dV_n_dx(1.0, 0.3, 0.5, 0.7, 0.0, 1e-6)


# ----------------------------------------------------------------------------- BarrierBank
def _random_bank(rng, n, eps_s):
    k = rng.choice([0.0, 1.0, 3.5], n)
    d1 = rng.uniform(0.05, 2.0, n)
    d2 = d1 * rng.uniform(1.05, 3.0, n)
    eps = 10.0 ** rng.uniform(-12, -2, n)
    return BarrierBank(k, d1, d2, eps, eps_s), k, d1, d2, eps


def _reference(x, k, d1, d2, eps, eps_s):
    xc = np.maximum(x, X_MIN)
    return np.where(k == 0, sigma(xc, d1, d2),
                    dV_n_dx(np.where(k == 0, 1.0, k), x, d1, d2, eps, eps_s))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), log_eps_s=st.floats(-12, -1.5),
       violated=st.booleans())
def test_bank_equals_the_reference_formula(seed, log_eps_s, violated):
    eps_s = 10.0**log_eps_s
    rng = np.random.default_rng(seed)
    bank, k, d1, d2, eps = _random_bank(rng, 300, eps_s)
    x = d1 * rng.uniform(1.0 if not violated else -0.5, 3.5, 300)
    if violated:  # elements in the fillet, below d1 and below 0
        x[::5] = d1[::5] * (1 + eps_s * rng.uniform(-1, 1, 60))
    n = int(rng.integers(1, 301))
    y = bank.evaluate(x[:n].copy())
    ref = _reference(x[:n], k[:n], d1[:n], d2[:n], eps[:n], eps_s)
    # within a few ε_s·d1 of d1 the position on the fillet is only known to ~1e-16/ε_s
    # (x/d1 − 1 is rounded), so the two evaluation orders agree to that precision only
    near = np.abs(x[:n] / d1[:n] - 1) < 10 * eps_s
    np.testing.assert_allclose(y[~near], ref[~near], rtol=1e-8, atol=0)
    np.testing.assert_allclose(y[near], ref[near], rtol=1e-8 + 1e-13 / eps_s, atol=0)
    assert np.all(y[k[:n] > 0] <= 0)
    assert np.all(y[(k[:n] > 0) & (x[:n] >= d2[:n])] == 0.0)


def test_bank_clamps_in_place_only_when_needed_and_propagates_nan():
    bank = BarrierBank([1.0, 1.0, 0.0], 0.5, 0.75, 1e-6, 1e-6)
    x = np.array([0.6, 0.7, 0.1])  # σ-only elements never count as violated
    y = bank.evaluate(x)
    assert np.all(x == [0.6, 0.7, 0.1])
    x = np.array([-1.0, 0.7, np.nan])
    y = bank.evaluate(x)
    assert x[0] == X_MIN and np.isfinite(y[:2]).all() and np.isnan(y[2])
    assert bank.evaluate(np.zeros(0)).shape == (0,)
    with pytest.raises(ValueError):
        bank.evaluate(np.ones(4))
    np.testing.assert_allclose(bank.dV_dx([0.6, 0.8, 0.3]),
                               [dV_n_dx(1.0, 0.6, 0.5, 0.75, 1e-6, 1e-6), 0.0, 0.0], rtol=1e-12)


def test_bank_concatenate():
    a = BarrierBank([1.0, 2.0], 0.5, 0.75, 1e-6, 1e-6)
    b = BarrierBank([0.0], 0.2, 0.3, 1e-3, 1e-6)
    c = BarrierBank.concatenate([a, b])
    assert len(c) == 3
    x = np.array([0.55, 0.6, 0.25])
    np.testing.assert_allclose(c.evaluate(x.copy()), np.concatenate(
        [a.evaluate(x[:2].copy()), b.evaluate(x[2:].copy())]))
    with pytest.raises(ValueError):
        BarrierBank.concatenate([a, BarrierBank([1.0], 0.5, 0.75, 1e-6, 1e-3)])
    with pytest.raises(ValueError):
        BarrierBank([-1.0], 0.5, 0.75, 1e-6, 1e-6)


def test_bank_concatenate_prefixes_equals_concatenate_bitwise():
    """Prefixes of big banks give exactly the bank built from those elements (the
    controller's layouts are assembled this way), also on the slow path and with out=."""
    rng = np.random.default_rng(3)
    big = [BarrierBank(rng.uniform(0.5, 2.0, 50), 0.5, 0.75, 1e-6, 1e-6),
           BarrierBank(np.zeros(50), 0.5, 0.75, 1.0, 1e-6),
           BarrierBank(rng.uniform(0.5, 2.0, 80), rng.uniform(0.3, 0.5, 80), 0.9, 1e-4, 1e-6)]
    for n in ([7, 7, 20], [0, 3, 80], [50, 50, 0]):
        pre = BarrierBank.concatenate_prefixes(list(zip(big, n, strict=True)))
        ref = BarrierBank.concatenate([
            BarrierBank(b.k[:m], b.d1[:m], b.d2[:m], b.eps[:m], 1e-6) for b, m in zip(
                big, n, strict=True)])
        assert len(pre) == len(ref) == sum(n)
        for x in (rng.uniform(0.6, 1.2, sum(n)), rng.uniform(-0.1, 1.2, sum(n))):
            out = np.zeros(sum(n), complex)
            y = pre.evaluate(x.copy(), out=out.real)
            assert np.array_equal(y, ref.evaluate(x.copy()))
            assert np.array_equal(out.real, y) and np.all(out.imag == 0)
    with pytest.raises(ValueError):
        BarrierBank.concatenate_prefixes([(big[0], 51)])
    with pytest.raises(ValueError):
        BarrierBank.concatenate_prefixes([(big[0], 1), (BarrierBank([1.0], 0.5, 0.75, 1e-6,
                                                                    1e-3), 1)])


# ----------------------------------------------------------------------------- sat, κ
@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), a=st.floats(1e-3, 1e3), log_scale=st.floats(-6, 30))
def test_sat_bounds_norm_and_keeps_direction(seed, a, log_scale):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(50, 2)) * 10.0**log_scale
    x[0] = 0.0
    u = sat(x, a)
    nx, nu = np.hypot(x[:, 0], x[:, 1]), np.hypot(u[:, 0], u[:, 1])
    assert np.all(nu <= a * (1 + 1e-12))
    small = nx <= a
    np.testing.assert_array_equal(u[small], x[small])
    np.testing.assert_allclose(nu[~small], a, rtol=1e-12)
    cross = x[:, 0] * u[:, 1] - x[:, 1] * u[:, 0]
    assert np.all(np.abs(cross) <= 1e-9 * nx * np.maximum(nu, 1e-300) + 1e-300)
    assert np.all((x * u).sum(axis=1) >= 0)
    kap = kappa(x, a)
    assert np.all((kap > 0) & (kap <= 1))
    np.testing.assert_allclose(u, x * kap[:, None])
    # complex form (one 2-D vector per element) agrees
    z = x[:, 0] + 1j * x[:, 1]
    np.testing.assert_allclose(sat(z, a), u[:, 0] + 1j * u[:, 1])


def test_sat_rejects_nonpositive_bound():
    with pytest.raises(ValueError):
        sat(np.ones((3, 2)), 0.0)
