"""Smooth functions, the nominal Lyapunov-like barrier V_n and vector saturation (Section III-A).

Symbols (paper → code):

* σ(x, d1, d2) (zerofunction) → :func:`sigma`, dσ/dx → :func:`dsigma_dx`. The paper's cubic
  A x³ + B x² + C x + D on (d1, d2) is the smoothstep 1 − t²(3 − 2t), t = (x − d1)/(d2 − d1),
  so σ' vanishes at d1 and d2 and σ'(clip(x, d1, d2)) is 0 outside the band.
* s(x, ε_s) (sat) → :func:`s`, ds/dx → :func:`ds_dx`. The paper defines s for x ≥ 0 only; its
  identity branch is extended below 0 (paper note 3).
* V_n(k, x, d1, d2, ε, ε_s) (Vs) → :func:`V_n`, ∂V_n/∂x → :func:`dV_n_dx` (analytic). V_n
  divides by zero at x = 0, so the distance is clamped at :data:`X_MIN` = 1e-9: a violated
  constraint (x ≤ 0) still pushes the right way, finitely (paper note 3).
* sat(x, a) = κ_a(x) x (vector saturation) → :func:`sat`, κ_a → :func:`kappa`, for (..., 2)
  arrays (or complex arrays holding 2-D vectors).

:class:`BarrierBank` evaluates ∂V_n/∂x for many elements with per-element parameters in few
numpy calls; the controller uses it for all robot–robot and robot–leg barriers of a step at once.
It evaluates the same equation as :func:`dV_n_dx` (tests check they agree everywhere).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "X_MIN",
    "BarrierBank",
    "V_n",
    "dV_n_dx",
    "ds_dx",
    "dsigma_dx",
    "kappa",
    "s",
    "sat",
    "s_knots",
    "sigma",
]

#: Distances fed to V_n are clamped at this value (metres), paper note 3.
X_MIN = 1e-9


# ----------------------------------------------------------------------------------------------
# σ (zerofunction)
# ----------------------------------------------------------------------------------------------
def sigma(x, d1: float, d2: float):
    """σ(x, d1, d2) (zerofunction): 1 for x ≤ d1, 0 for x ≥ d2, the cubic in between.

    Works on arrays; ``d1``/``d2`` may be arrays broadcasting with ``x`` (d1 < d2).
    """
    t = np.clip((np.asarray(x, dtype=float) - d1) / (np.subtract(d2, d1)), 0.0, 1.0)
    a = 1.0 - t
    return a * a * (1.0 + 2.0 * t)


def dsigma_dx(x, d1: float, d2: float):
    """dσ/dx = −6 t (1 − t)/(d2 − d1) with t = clip((x − d1)/(d2 − d1), 0, 1); 0 outside."""
    w = np.subtract(d2, d1)
    t = np.clip((np.asarray(x, dtype=float) - d1) / w, 0.0, 1.0)
    return -6.0 * t * (1.0 - t) / w


# ----------------------------------------------------------------------------------------------
# s (sat in the paper's numbering)
# ----------------------------------------------------------------------------------------------
def s_knots(eps_s: float) -> tuple[float, float]:
    """The knots (x1, x2) of s(x, ε_s): x2 = 1 + ε_s/tan 67.5°, x1 = x2 − ε_s sin 45°."""
    d1, d2 = _knot_offsets(eps_s)
    return 1.0 + d1, 1.0 + d2


def _knot_offsets(eps_s: float) -> tuple[float, float]:
    """(x1 − 1, x2 − 1), computed without cancellation."""
    c2 = eps_s / math.tan(math.radians(67.5))
    return c2 - eps_s * math.sin(math.radians(45.0)), c2


def _check_eps_s(eps_s: float) -> None:
    if not (0.0 < eps_s <= 0.5):
        raise ValueError(f"eps_s must be in (0, 0.5], got {eps_s}")


class _Fillet:
    """s(u, ε_s) around its arc, in δ = u − 1 so that tiny ε_s keep full relative precision.

    With w = clip(δ, δ1, δ2) − δ2 (δ1, δ2 = x1 − 1, x2 − 1) and r = sqrt(ε_s² − w²):
    s = u on the identity branch, 1 − ε_s + r on the arc, 1 beyond; s' = −w/r (1, arc, 0).
    ``h`` returns h = u − s(u) and h' = 1 − s'(u), exactly 0 on the identity branch, so that
    g(x) = (1 + ε)x − d1 s(x/d1) = d1(εu + h(u)) has no cancellation.
    """

    __slots__ = ("eps_s", "es2", "dl1", "dl2", "k0", "c1")

    def __init__(self, eps_s: float) -> None:
        _check_eps_s(eps_s)
        self.eps_s = float(eps_s)
        self.dl1, self.dl2 = _knot_offsets(self.eps_s)
        self.es2 = self.eps_s * self.eps_s
        w0 = self.dl1 - self.dl2  # the value of w for every δ ≤ δ1
        r0 = math.sqrt(self.es2 - w0 * w0)
        self.k0 = self.dl1 - r0  # = −ε_s up to rounding; makes h(δ ≤ δ1) == 0.0 exactly
        self.c1 = -(w0 / r0)  # = 1 up to rounding; makes h'(δ ≤ δ1) == 0.0 exactly

    @property
    def x2(self) -> float:
        return 1.0 + self.dl2

    def wr(self, delta):
        w = np.clip(delta, self.dl1, self.dl2) - self.dl2
        return w, np.sqrt(self.es2 - w * w)

    def h(self, u):
        """(h, h') for u = x/d1: h = u − s(u), h' = 1 − s'(u)."""
        delta = u - 1.0
        w, r = self.wr(delta)
        return (np.maximum(delta, self.dl1) - r) - self.k0, w / r + self.c1


def s(x, eps_s: float):
    """s(x, ε_s) (sat): x for x ≤ x1 (identity extended below 0, paper note 3), the arc
    (1 − ε_s) + sqrt(ε_s² − (x − x2)²) on (x1, x2), 1 for x ≥ x2. C¹ at both knots."""
    f = _Fillet(eps_s)
    x = np.asarray(x, dtype=float)
    delta = x - 1.0
    _, r = f.wr(delta)
    return np.where(delta <= f.dl1, x, (1.0 - f.eps_s) + r)


def ds_dx(x, eps_s: float):
    """ds/dx: 1 for x ≤ x1, −(x − x2)/sqrt(ε_s² − (x − x2)²) on the arc, 0 for x ≥ x2."""
    f = _Fillet(eps_s)
    delta = np.asarray(x, dtype=float) - 1.0
    w, r = f.wr(delta)
    return np.where(delta <= f.dl1, 1.0, -w / r)


# ----------------------------------------------------------------------------------------------
# V_n (Vs)
# ----------------------------------------------------------------------------------------------
def _check_barrier(d1, d2, eps) -> None:
    if not np.all(np.asarray(d1) > 0) or not np.all(np.asarray(d2) > np.asarray(d1)):
        raise ValueError(f"V_n needs 0 < d1 < d2, got d1={d1}, d2={d2}")
    if not np.all(np.asarray(eps) > 0):
        raise ValueError(f"V_n needs eps > 0, got {eps}")


def V_n(k, x, d1, d2, eps, eps_s: float):
    """Nominal Lyapunov-like barrier (Vs): k σ(x, d1, d2) / ((1 + ε) x − d1 s(x/d1, ε_s)).

    ``x`` is clamped at :data:`X_MIN`, so V_n is finite (and maximal) for x ≤ 0. Parameters
    broadcast with ``x``; ``eps_s`` is a scalar.
    """
    _check_barrier(d1, d2, eps)
    f = _Fillet(eps_s)
    x = np.maximum(np.asarray(x, dtype=float), X_MIN)
    u = x / d1
    h, _ = f.h(u)
    g = d1 * (eps * u + h)
    return k * sigma(x, d1, d2) / g


def dV_n_dx(k, x, d1, d2, eps, eps_s: float):
    """∂V_n/∂x of (Vs), analytic: k (σ' g − σ g') / g² with g = (1 + ε)x − d1 s(x/d1, ε_s),
    g' = 1 + ε − s'(x/d1). Always ≤ 0, exactly 0 for x ≥ d2, ≈ −k/(ε x²) for x < d1.

    ``x`` is clamped at :data:`X_MIN` (paper note 3): for x ≤ 0 the value at 1e-9 is
    returned (about −k/(ε·1e-18)), finite and pointing the right way.
    """
    _check_barrier(d1, d2, eps)
    f = _Fillet(eps_s)
    x = np.maximum(np.asarray(x, dtype=float), X_MIN)
    u = x / d1
    h, hp = f.h(u)
    g_hat = eps * u + h  # g / d1
    gp = eps + hp  # dg/dx
    return k * (dsigma_dx(x, d1, d2) * d1 * g_hat - sigma(x, d1, d2) * gp) / (d1 * g_hat) ** 2


class BarrierBank:
    """Per-element parameters (k, d1, d2, ε) of many V_n barriers sharing one ε_s, evaluated
    by :meth:`evaluate` in 13 numpy calls whatever the number of elements.

    Element i is the barrier V_n(k[i], ·, d1[i], d2[i], ε[i], ε_s). An element with k = 0 is
    "σ only": :meth:`evaluate` returns σ(x, d1, d2) for it instead of ∂V_n/∂x (which is 0), so
    the controller gets the σ's of u1'' from the same fused call. ``evaluate(x)`` accepts a
    prefix of the elements (``len(x) <= len(bank)``), so one bank with a large capacity serves
    arrays of varying length.

    Where x ≥ d1·x2 (no constraint violated; the usual case) s(x/d1) ≡ 1, so with
    g = (1 + ε)x − d1 and a = 1 − t = clip((d2 − x)/(d2 − d1), 0, 1): σ = a²(3 − 2a),
    σ' = −6a(1 − a)/(d2 − d1) and, since σ' ≠ 0 only inside the band where g = G0 − G1·a
    (G0 = (1 + ε)d2 − d1, G1 = (1 + ε)(d2 − d1)),

        ∂V_n/∂x = k (σ' g − σ (1 + ε))/g² = a (Q0 + a (R1 + a R2)) / g²

    with Q0 = −6kG0/(d2 − d1), R1 = Q1 − Q0 − 3kₑ, R2 = 2kₑ − Q1, Q1 = 6kG1/(d2 − d1),
    kₑ = k(1 + ε): a cubic in a (Horner), exactly 0 for x ≥ d2. g is carried scaled,
    ĝ = g/g_th with g_th = g(d1·x2), so that "some element is below d1·x2" is the single test
    ĝ.min() < 1; those elements are re-evaluated with the general formula of :func:`dV_n_dx`.
    """

    def __init__(self, k, d1, d2, eps, eps_s: float) -> None:
        k, d1, d2, eps = (np.asarray(a, dtype=float) for a in (k, d1, d2, eps))
        k, d1, d2, eps = np.broadcast_arrays(k, d1, d2, eps)
        if k.ndim != 1:
            raise ValueError("BarrierBank parameters must be 1-D (or scalars broadcast to 1-D)")
        _check_barrier(d1, d2, eps)
        if not np.all(k >= 0):
            raise ValueError("BarrierBank gains k must be >= 0")
        self.fillet = _Fillet(eps_s)
        self.eps_s = float(eps_s)
        self.k, self.d1, self.d2, self.eps = (np.array(a) for a in (k, d1, d2, eps))
        self.sigma_only = so = k == 0
        w = d2 - d1
        # num = c1·a(1 − a) − kₑ·a²(3 − 2a), c1 = −6k g/w, kₑ = k(1 + ε), g = G0 − G1·a
        ke = k * (1.0 + eps)
        m6 = -6.0 * k / w
        q0 = m6 * ((1.0 + eps) * d2 - d1)  # c1 at a = 0
        q1 = -m6 * (1.0 + eps) * w  # −dc1/da
        g_th = d1 * ((1.0 + eps) * self.fillet.x2 - 1.0)  # g at x = d1·x2 (> 0)
        # y = num/ĝ² with ĝ = g/g_th: scale num by 1/g_th². σ-only elements: ĝ ≡ 2, num = 4σ
        s2 = np.where(so, 4.0, 1.0 / (g_th * g_th))
        self._Q0 = np.where(so, 0.0, q0) * s2
        self._R1 = np.where(so, 3.0, q1 - q0 - 3.0 * ke) * s2
        self._R2 = np.where(so, -2.0, 2.0 * ke - q1) * s2
        self._B = 1.0 / w
        self._E1 = np.where(so, 0.0, (1.0 + eps) / g_th)
        self._D1 = np.where(so, -2.0, d1 / g_th)
        self._TH = np.where(so, -np.inf, d1 * self.fillet.x2)
        self._zero = np.zeros(())
        self._one = np.ones(())
        self._sl: tuple = (-1, ())

    def __len__(self) -> int:
        return self.k.shape[0]

    @classmethod
    def concatenate(cls, banks: list[BarrierBank]) -> BarrierBank:
        """One bank holding the elements of ``banks`` in order (same ε_s required)."""
        eps_s = {b.eps_s for b in banks}
        if len(eps_s) != 1:
            raise ValueError(f"banks with different eps_s cannot be concatenated: {eps_s}")
        cat = np.concatenate
        return cls(cat([b.k for b in banks]), cat([b.d1 for b in banks]),
                   cat([b.d2 for b in banks]), cat([b.eps for b in banks]), eps_s.pop())

    #: per-element arrays (all of the bank's length)
    _ELEMENT_ARRAYS = ("k", "d1", "d2", "eps", "sigma_only", "_Q0", "_R1", "_R2", "_B", "_E1",
                       "_D1", "_TH")

    @classmethod
    def concatenate_prefixes(cls, parts: list[tuple[BarrierBank, int]]) -> BarrierBank:
        """One bank holding the first n elements of each bank of ``parts`` = [(bank, n), …],
        in order: what :meth:`concatenate` of banks of those elements gives, element for
        element (each element's coefficients depend on its own parameters only), without
        recomputing the coefficients (a few concatenations instead of ~40 numpy calls)."""
        eps_s = {b.eps_s for b, _ in parts}
        if len(eps_s) != 1:
            raise ValueError(f"banks with different eps_s cannot be concatenated: {eps_s}")
        for b, n in parts:
            if not 0 <= n <= len(b):
                raise ValueError(f"prefix of {n} elements of a bank of {len(b)}")
        new = cls.__new__(cls)
        first = parts[0][0]
        new.fillet, new.eps_s = first.fillet, first.eps_s
        for name in cls._ELEMENT_ARRAYS:
            setattr(new, name, np.concatenate([getattr(b, name)[:n] for b, n in parts]))
        new._zero, new._one = np.zeros(()), np.ones(())
        new._sl = (-1, ())
        return new

    def prefix(self, n: int) -> tuple[np.ndarray, ...]:
        """The band formula's per-element arrays of the first ``n`` elements: (d2, 1/(d2 − d1),
        E1, D1, Q0, R1, R2) (class docstring), for callers that inline :meth:`evaluate`'s
        common path (ĝ = x·E1 − D1 ≥ 1 everywhere; else they must call :meth:`evaluate`)."""
        sl = self._sl
        if sl[0] != n:
            if n > self.k.shape[0]:
                raise ValueError(f"{n} values for a bank of {self.k.shape[0]} elements")
            sl = self._sl = (n, tuple(a[:n] for a in (
                self.d2, self._B, self._E1, self._D1, self._Q0, self._R1, self._R2)))
        return sl[1]

    def evaluate(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """y[i] = ∂V_n/∂x (k[i] > 0) or σ(x[i], d1[i], d2[i]) (k[i] = 0) for i < len(x).

        ``x``: 1-D float64 array. If some element is below d1·x2, values below :data:`X_MIN`
        are clamped IN PLACE (so callers dividing by x afterwards see the clamped value).
        NaN elements give NaN. ``out``: an optional float64 array of len(x) (it may be strided,
        e.g. the real parts of a complex array) receiving y, which is then returned.
        """
        n = x.shape[0]
        sl = self._sl
        if sl[0] != n:
            self.prefix(n)
            sl = self._sl
        _, _, E1, D1, _, _, _ = sl[1]
        if n == 0:
            return np.zeros(0) if out is None else out
        g = x * E1
        g -= D1  # ĝ = g/g_th
        # some x < d1·x2 (or NaN): fix those up with the general formula. g[g.argmin()] is
        # min(g), NaN if any (argmin returns the first NaN), at a third of a reduction's cost
        if not g[g.argmin()] >= 1.0:
            np.maximum(x, X_MIN, out=x)
            idx = np.flatnonzero(g < 1.0)
            xb = x.copy()
            xb[idx] = self._TH[idx]  # any value where the band formula is valid
            y = self._band(xb, xb * E1 - D1, sl[1], out)
            y[idx] = self._general(x[idx], idx)
            return y
        return self._band(x, g, sl[1], out)  # the common path of every step

    def _band(self, x: np.ndarray, g: np.ndarray, sl: tuple, out: np.ndarray | None = None
              ) -> np.ndarray:
        d2, B, _, _, Q0, R1, R2 = sl
        a = d2 - x
        a *= B
        np.maximum(a, self._zero, out=a)  # clip to [0, 1] in place, public ufuncs only
        np.minimum(a, self._one, out=a)
        num = a * R2
        num += R1
        num *= a
        num += Q0
        num *= a
        g *= g
        if out is None:
            num /= g
            return num
        return np.divide(num, g, out=out)

    def dV_dx(self, x: np.ndarray) -> np.ndarray:
        """∂V_n/∂x of all elements (σ-only elements give 0); clamps ``x`` like evaluate."""
        x = np.array(x, dtype=float)
        return np.where(self.sigma_only[: x.shape[0]], 0.0, self.evaluate(x))

    def _general(self, x: np.ndarray, idx: np.ndarray) -> np.ndarray:
        k, d1, d2, eps = self.k[idx], self.d1[idx], self.d2[idx], self.eps[idx]
        u = x / d1
        h, hp = self.fillet.h(u)
        g_hat = eps * u + h
        sig = sigma(x, d1, d2)
        dV = k * (dsigma_dx(x, d1, d2) * d1 * g_hat - sig * (eps + hp)) / (d1 * g_hat) ** 2
        return np.where(self.sigma_only[idx], sig, dV)


# ----------------------------------------------------------------------------------------------
# vector saturation
# ----------------------------------------------------------------------------------------------
def _norm(x: np.ndarray) -> np.ndarray:
    if np.iscomplexobj(x):
        return np.abs(x)
    return np.hypot(x[..., 0], x[..., 1])


def kappa(x, a: float):
    """κ_a(x) = 1 if ‖x‖ ≤ a else a/‖x‖ (for (..., 2) arrays or complex arrays); in (0, 1]."""
    x = np.asarray(x)
    if not np.iscomplexobj(x):
        x = np.asarray(x, dtype=float)
    return a / np.maximum(_norm(x), a)


def sat(x, a: float):
    """sat(x, a) = κ_a(x) x: ``x`` unchanged if ‖x‖ ≤ a, else rescaled to norm a.

    ``x`` has shape (..., 2) (or is complex, one 2-D vector per element); a > 0.
    """
    if not a > 0:
        raise ValueError(f"sat needs a > 0, got {a}")
    x = np.asarray(x)
    if np.iscomplexobj(x):
        return x * kappa(x, a)
    x = np.asarray(x, dtype=float)
    return x * kappa(x, a)[..., None]
