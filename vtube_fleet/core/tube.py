"""Trapezoid virtual tube geometry (Section II-B of the paper) and circular obstacles.

A tube ``T(p_h0, p_h1, p_r0, p_r1)`` has a left leg ``[p_h0, p_h1]``, a right leg
``[p_r0, p_r1]``, a start base ``[p_h0, p_r0]`` and a finishing line ``[p_h1, p_r1]``; the two
bases are parallel. All functions accept points of shape ``(2,)`` or ``(..., 2)`` and are
vectorized over the leading axes.

Symbols (paper → code): n_c → ``n_c``, t_h/t_r → ``t_h``/``t_r``, n_h/n_r (inward) →
``n_h``/``n_r``, d_Th/d_Tr (dtl)/(dtr) → ``d_Th``/``d_Tr``, L_T/R_T exist → ``has_L``/``has_R``,
the longitudinal coordinate ξ(x) = n_cᵀ(x − p_h0) → ``xi`` and the lateral unit vector m (left
→ right) → ``m`` (partition §0).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from vtube_fleet.errors import UserError

__all__ = ["APEX_AUTO", "GeometryError", "Obstacle", "Trapezoid", "perp"]

#: ``Obstacle.apex_distance`` value asking the planner to choose h_k (core/plan.py).
APEX_AUTO = "auto"

_EPS = 1e-12
_PARALLEL = 1e-12  # |n_cᵀn| below this: a leg parallel to n_c (no L/R area)


class GeometryError(UserError):
    """The four points do not form a trapezoid tube as the paper defines it."""


def perp(v: np.ndarray) -> np.ndarray:
    """Rotate 2-D vectors by +90°: (x, y) → (−y, x)."""
    v = np.asarray(v, dtype=float)
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    n = float(np.hypot(v[0], v[1]))
    if n < _EPS:
        raise GeometryError(f"{what} has zero length")
    return v / n


@dataclass(frozen=True, eq=False)
class Trapezoid:
    """A trapezoid virtual tube ``T(p_h0, p_h1, p_r0, p_r1)`` (argument order as in the paper).

    Raises :class:`GeometryError` when the bases are not parallel, a leg does not advance
    along n_c (tᵀn_c ≤ 0), or the legs cross.
    """

    p_h0: np.ndarray
    p_h1: np.ndarray
    p_r0: np.ndarray
    p_r1: np.ndarray
    name: str = field(default="T", compare=False)

    def __post_init__(self) -> None:
        for attr in ("p_h0", "p_h1", "p_r0", "p_r1"):
            v = np.asarray(getattr(self, attr), dtype=float).reshape(-1)
            if v.shape != (2,) or not np.all(np.isfinite(v)):
                raise GeometryError(f"{self.name}: {attr} must be two finite numbers, got {v}")
            v.setflags(write=False)
            object.__setattr__(self, attr, v)
        start = self.p_r0 - self.p_h0
        finish = self.p_r1 - self.p_h1
        if np.hypot(*start) < _EPS or np.hypot(*finish) < _EPS:
            raise GeometryError(f"{self.name}: a base has zero length")
        cross = start[0] * finish[1] - start[1] * finish[0]
        if abs(cross) > 1e-9 * np.hypot(*start) * np.hypot(*finish):
            raise GeometryError(
                f"{self.name}: bases [p_h0, p_r0] and [p_h1, p_r1] are not parallel "
                f"(cross product {cross:.3g})"
            )
        if float(start @ finish) <= 0:
            raise GeometryError(f"{self.name}: bases point in opposite directions (legs cross)")
        if float(self.t_h @ self.n_c) <= 0 or float(self.t_r @ self.n_c) <= 0:
            raise GeometryError(
                f"{self.name}: legs must advance towards the finishing line "
                f"(t_h·n_c = {float(self.t_h @ self.n_c):.3f}, "
                f"t_r·n_c = {float(self.t_r @ self.n_c):.3f})"
            )
        if self.length <= 0:
            raise GeometryError(f"{self.name}: finishing line is not ahead of the start base")

    # ----- directions -------------------------------------------------------------------
    @cached_property
    def n_c(self) -> np.ndarray:
        """Unit normal of the bases, from the start base towards the finishing line."""
        n = perp(_unit(self.p_r0 - self.p_h0, f"{self.name}: start base"))
        return n if float(n @ (self.p_h1 - self.p_h0)) > 0 else -n

    @cached_property
    def m(self) -> np.ndarray:
        """Lateral unit vector ⟂ n_c, pointing from the left leg to the right leg."""
        m = perp(self.n_c)
        return m if float(m @ (self.p_r0 - self.p_h0)) > 0 else -m

    @cached_property
    def t_h(self) -> np.ndarray:
        return _unit(self.p_h1 - self.p_h0, f"{self.name}: left leg")

    @cached_property
    def t_r(self) -> np.ndarray:
        return _unit(self.p_r1 - self.p_r0, f"{self.name}: right leg")

    @cached_property
    def n_h(self) -> np.ndarray:
        """Inward unit normal of the left leg."""
        n = perp(self.t_h)
        inside = (self.p_r0 - self.p_h0) + (self.p_r1 - self.p_h1)
        return n if float(n @ inside) > 0 else -n

    @cached_property
    def n_r(self) -> np.ndarray:
        """Inward unit normal of the right leg."""
        n = perp(self.t_r)
        inside = (self.p_h0 - self.p_r0) + (self.p_h1 - self.p_r1)
        return n if float(n @ inside) > 0 else -n

    @property
    def has_L(self) -> bool:
        """The left area L_T exists iff n_cᵀn_h < 0 (the left leg narrows the tube); a leg
        parallel to n_c up to rounding (|n_cᵀn_h| ≤ 1e-12, e.g. in a rotated segment of a
        route) does not narrow it."""
        return bool(self.n_c @ self.n_h < -_PARALLEL)

    @property
    def has_R(self) -> bool:
        """The right area R_T exists iff n_cᵀn_r < 0 (up to rounding, as :attr:`has_L`)."""
        return bool(self.n_c @ self.n_r < -_PARALLEL)

    # ----- coordinates ------------------------------------------------------------------
    @cached_property
    def length(self) -> float:
        """L = n_cᵀ(p_r1 − p_h0): distance from the start base to the finishing line."""
        return float(self.n_c @ (self.p_r1 - self.p_h0))

    def finish_threshold(self, eps_0: float) -> float:
        """The finishing line as a threshold on n_cᵀx: (TraCondition) −n_cᵀ(x − p_r1) ≤ ε_0
        holds iff n_cᵀx ≥ n_cᵀp_r1 − ε_0 (this value)."""
        return float(self.n_c @ self.p_r1) - float(eps_0)

    def finished(self, x: np.ndarray, eps_0: float) -> np.ndarray:
        """(TraCondition) on this tube: x has reached the finishing line → (…,) bool.

        The one finishing-line test of the project: the simulator, the fleet's plan, the
        lost-vehicle obstacles and the run monitor all use it."""
        return np.asarray(x, dtype=float) @ self.n_c >= self.finish_threshold(eps_0)

    def xi(self, x: np.ndarray) -> np.ndarray:
        """Longitudinal coordinate ξ(x) = n_cᵀ(x − p_h0); 0 on the start base."""
        return (np.asarray(x, dtype=float) - self.p_h0) @ self.n_c

    def d_Th(self, x: np.ndarray) -> np.ndarray:
        """Signed distance to the left leg line, (dtl): n_hᵀ(x − p_h1); > 0 inside."""
        return (np.asarray(x, dtype=float) - self.p_h1) @ self.n_h

    def d_Tr(self, x: np.ndarray) -> np.ndarray:
        """Signed distance to the right leg line, (dtr): n_rᵀ(x − p_r1); > 0 inside."""
        return (np.asarray(x, dtype=float) - self.p_r1) @ self.n_r

    def lh(self, xi: float | np.ndarray) -> np.ndarray:
        """Point of the (infinite) left leg line at longitudinal coordinate ``xi``."""
        xi = np.asarray(xi, dtype=float)[..., None]
        return self.p_h0 + self.t_h * (xi / float(self.t_h @ self.n_c))

    def lr(self, xi: float | np.ndarray) -> np.ndarray:
        """Point of the (infinite) right leg line at longitudinal coordinate ``xi``."""
        xi = (np.asarray(xi, dtype=float) - float(self.xi(self.p_r0)))[..., None]
        return self.p_r0 + self.t_r * (xi / float(self.t_r @ self.n_c))

    def width(self, xi: float | np.ndarray) -> np.ndarray:
        """Lateral width m ᵀ(lr(ξ) − lh(ξ)) of the tube at ``xi``."""
        return (self.lr(xi) - self.lh(xi)) @ self.m

    def contains(self, x: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Membership in T (legs and bases closed), with an optional tolerance in metres."""
        xi = self.xi(x)
        return (
            (self.d_Th(x) >= -tol)
            & (self.d_Tr(x) >= -tol)
            & (xi >= -tol)
            & (xi <= self.length + tol)
        )

    def in_L(self, x: np.ndarray, k_t: float, r_a: float) -> np.ndarray:
        """Membership in the left area L_T = {d_Th < k_t r_a} (empty if n_cᵀn_h ≥ 0)."""
        return self.has_L & (self.d_Th(x) < k_t * r_a)

    def in_R(self, x: np.ndarray, k_t: float, r_a: float) -> np.ndarray:
        """Membership in the right area R_T = {d_Tr < k_t r_a} (empty if n_cᵀn_r ≥ 0)."""
        return self.has_R & (self.d_Tr(x) < k_t * r_a)

    def polygon(self) -> np.ndarray:
        """Vertices in drawing order (4, 2): p_h0, p_h1, p_r1, p_r0."""
        return np.stack([self.p_h0, self.p_h1, self.p_r1, self.p_r0])

    def __repr__(self) -> str:
        pts = ", ".join(
            f"{k}=({v[0]:.3f}, {v[1]:.3f})"
            for k, v in (("p_h0", self.p_h0), ("p_h1", self.p_h1),
                         ("p_r0", self.p_r0), ("p_r1", self.p_r1))
        )
        return f"Trapezoid({self.name}: {pts})"


@dataclass(frozen=True, eq=False)
class Obstacle:
    """A circular obstacle O_k (obstacle): centre p_o,k, radius r_o,k.

    ``apex_distance`` is h_k = ‖p_oth,k − p_o,k‖ of its circumscribed triangle; ``None`` means
    the default 1.3 × the minimum allowed by (pothk), :data:`APEX_AUTO` (``"auto"``) that the
    planner chooses it jointly with the other obstacles' (:mod:`vtube_fleet.core.plan`).
    """

    center: np.ndarray
    radius: float
    apex_distance: float | str | None = None

    def __post_init__(self) -> None:
        c = np.asarray(self.center, dtype=float).reshape(-1)
        if c.shape != (2,) or not np.all(np.isfinite(c)):
            raise GeometryError(f"obstacle centre must be two finite numbers, got {c}")
        c.setflags(write=False)
        object.__setattr__(self, "center", c)
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise GeometryError(f"obstacle radius must be > 0, got {self.radius}")
        if isinstance(self.apex_distance, str):
            if self.apex_distance != APEX_AUTO:
                raise GeometryError(f"obstacle apex_distance must be a number or "
                                    f"{APEX_AUTO!r}, got {self.apex_distance!r}")
        elif self.apex_distance is not None and not (self.apex_distance > 0):
            raise GeometryError(f"obstacle apex_distance must be > 0, got {self.apex_distance}")
