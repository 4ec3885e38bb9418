"""Time integration of the closed loop: forward Euler, RK4 and the margin-guarded adaptive step.

The paper's guarantees (Theorem 1: pairs ‖p_i − p_j‖ > 2 r_s, legs d_Th, d_Tr > r_s, obstacle
centres ‖p_i − p_o,k‖ > r_o,k + r_s) hold in continuous time. A fixed step can break them:
forward Euler at 1 ms lets a pair close below 2 r_s in some certified scenarios
(docs/config.md, "Integrators"). Three integrators, all on 2-D points as complex numbers
z = x + iy, vectorized over robots:

* ``"euler"``: z ← z + h v(z) (what the simulator did before).
* ``"rk4"``: the classical fourth-order Runge–Kutta step, as the authors' Simulink model
  (``ode4``, fixed step); four controller evaluations per step.
* ``"adaptive"`` (default): forward Euler, but a step is cut in halves (re-evaluating the
  controller at every accepted sub-step) while some barrier margin — pair ‖p_ij‖ − 2 r_s,
  main-tube leg d − r_s, obstacle centre ‖p − p_o‖ − (r_o + r_s) — would lose more than
  ``frac`` of what is left of it over the sub-step (:class:`MarginGuard`). A positive margin
  then stays positive on every sub-step: after n sub-steps it is ≥ (1 − frac)ⁿ of its value,
  evaluated along the straight sub-step segment (closest approach for pairs and obstacle
  centres, end points for legs). Halving stops at h / 2^``max_halvings``; steps that end
  there are counted (``floor_steps``), so the guarantee's limit is visible. Margins already
  ≤ 0 (a violation, counted by the safety metrics) do not constrain the step.

The simulator asks :meth:`MarginGuard.needs_guard` first: when every margin exceeds what one
full step can consume (v_bound·h/frac, 2 v_bound·h/frac for pairs) the step is plain Euler and
costs nothing extra. Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from vtube_fleet.core.metrics import SafetyLimits
from vtube_fleet.core.tube import Obstacle, Trapezoid

__all__ = [
    "ADAPTIVE_FRACTION",
    "ADAPTIVE_MAX_HALVINGS",
    "DEFAULT_INTEGRATOR",
    "INTEGRATORS",
    "AdaptiveStats",
    "MarginGuard",
    "adaptive_state_step",
    "adaptive_step",
    "rk4_step",
]

#: Integrator names understood by the simulator (``[sim].integrator``, ``--integrator``).
INTEGRATORS: tuple[str, ...] = ("adaptive", "rk4", "euler")
#: The default keeps the continuous-time margins at the user's dt (module docstring).
DEFAULT_INTEGRATOR = "adaptive"
#: A sub-step may consume at most this fraction of any positive barrier margin.
ADAPTIVE_FRACTION = 0.5
#: A step is halved at most this many times (h / 1024 at the finest).
ADAPTIVE_MAX_HALVINGS = 10

Pairs = tuple[np.ndarray, np.ndarray]


@dataclass
class AdaptiveStats:
    """Counters of the adaptive integrator: ``guarded_steps`` steps checked by the guard,
    ``split_steps`` of them cut into sub-steps, ``substeps`` sub-steps taken by those,
    ``floor_steps`` sub-steps taken at the finest size although a margin still shrank by more
    than the fraction, ``min_substep_s`` the smallest sub-step (inf if none)."""

    guarded_steps: int = 0
    split_steps: int = 0
    substeps: int = 0
    floor_steps: int = 0
    min_substep_s: float = math.inf

    def as_dict(self) -> dict[str, float | int | None]:
        return {
            "guarded_steps": self.guarded_steps,
            "split_steps": self.split_steps,
            "substeps": self.substeps,
            "floor_steps": self.floor_steps,
            "min_substep_s": None if math.isinf(self.min_substep_s) else self.min_substep_s,
        }


@dataclass(frozen=True, eq=False)
class MarginGuard:
    """The barrier margins of Theorem 1 in the MAIN tube (or, :meth:`with_legs`, in each
    robot's own segment of a route): pairs ‖p_ij‖ − 2 r_s, legs d_Th − r_s and d_Tr − r_s
    (dtl)/(dtr), obstacle centres ‖p − p_o,k‖ − (r_o,k + r_s): each distance minus its
    :class:`~vtube_fleet.core.metrics.SafetyLimits` limit.

    ``frac``: the largest fraction of a positive margin one (sub-)step may consume (the
    integrator's own step-size rule, not a safety limit).
    """

    tube: Trapezoid
    obstacles: Sequence[Obstacle]
    limits: SafetyLimits
    frac: float = ADAPTIVE_FRACTION
    _g: dict = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not 0.0 < self.frac < 1.0:
            raise ValueError(f"frac must be in (0, 1), got {self.frac}")
        t = self.tube
        c = np.array([o.center for o in self.obstacles], dtype=float).reshape(-1, 2)
        lim = self.limits
        orad = np.array([lim.obstacle_center_m(o.radius) for o in self.obstacles], dtype=float)
        object.__setattr__(self, "_g", {
            # d_Th(z) − r_s = Re(z conj(n_h)) − (n_hᵀp_h1 + r_s); same for d_Tr
            "nh": complex(t.n_h[0], -t.n_h[1]), "bh": float(t.n_h @ t.p_h1) + lim.leg_m,
            "nr": complex(t.n_r[0], -t.n_r[1]), "br": float(t.n_r @ t.p_r1) + lim.leg_m,
            "oc": (c[:, 0] + 1j * c[:, 1])[None, :], "orad": orad[None, :],
            "pair": lim.pair_m,
        })

    def with_legs(self, n_h: np.ndarray, c_h: np.ndarray, n_r: np.ndarray,
                  c_r: np.ndarray) -> MarginGuard:
        """The guard with each point's own legs (a route: the legs of the segment each robot
        flies): n_h, n_r (M, 2) inward unit normals, c_h = n_hᵀp_h1, c_r = n_rᵀp_r1 (M,); the
        points given to :meth:`single_margin` and :meth:`accepts` are then these M robots."""
        out = MarginGuard(self.tube, self.obstacles, self.limits, self.frac)
        n_h, n_r = np.asarray(n_h, float), np.asarray(n_r, float)
        lim = self.limits
        out._g.update({
            "nh": n_h[:, 0] - 1j * n_h[:, 1], "bh": np.asarray(c_h, float) + lim.leg_m,
            "nr": n_r[:, 0] - 1j * n_r[:, 1], "br": np.asarray(c_r, float) + lim.leg_m,
            "per_robot": True})
        return out

    # ----- cheap bounds: is a guarded step needed at all? ------------------------------------
    def single_margin(self, z: np.ndarray) -> float:
        """Smallest leg or obstacle-centre margin of the points ``z`` (M,) complex (inf if
        none); may be ≤ 0."""
        if z.shape[0] == 0:
            return math.inf
        g = self._g
        if g.get("per_robot"):
            m = min(float(((z * g["nh"]).real - g["bh"]).min()),
                    float(((z * g["nr"]).real - g["br"]).min()))
        else:
            m = min(float((z * g["nh"]).real.min()) - g["bh"],
                    float((z * g["nr"]).real.min()) - g["br"])
        if g["oc"].shape[1]:
            m = min(m, float((np.abs(z[:, None] - g["oc"]) - g["orad"]).min()))
        return m

    def single_threshold(self, move: float) -> float:
        """A leg/obstacle margin above this cannot lose ``frac`` of itself in a step in which
        no point moves farther than ``move``."""
        return move / self.frac

    def pair_threshold(self, move: float) -> float:
        """The same for the pair margin (both robots move)."""
        return 2.0 * move / self.frac

    def pair_margin(self, min_pair_distance: float) -> float:
        return min_pair_distance - self._g["pair"]

    # ----- the exact test of one (sub-)step ---------------------------------------------------
    def accepts(self, z0: np.ndarray, z1: np.ndarray, pairs: Pairs) -> bool:
        """Whether moving the points from ``z0`` to ``z1`` (M,) complex along straight segments
        keeps every positive margin above (1 − frac) of its value at ``z0``. ``pairs``: (I, J)
        candidates containing every pair within reach of 2 r_s (a neighbour list)."""
        keep = 1.0 - self.frac
        g = self._g
        for n, b in ((g["nh"], g["bh"]), (g["nr"], g["br"])):
            m0 = (z0 * n).real - b
            m1 = (z1 * n).real - b
            if np.any((m0 > 0) & (m1 < keep * m0)):
                return False
        if g["oc"].shape[1]:
            r0 = z0[:, None] - g["oc"]
            m0 = np.abs(r0) - g["orad"]
            dmin = _closest(r0, (z1 - z0)[:, None]) - g["orad"]
            if np.any((m0 > 0) & (dmin < keep * m0)):
                return False
        I, J = pairs
        if I.shape[0]:
            r0 = z0[I] - z0[J]
            m0 = np.abs(r0) - g["pair"]
            dmin = _closest(r0, (z1[I] - z1[J]) - r0) - g["pair"]
            if np.any((m0 > 0) & (dmin < keep * m0)):
                return False
        return True


def _closest(r0: np.ndarray, d: np.ndarray) -> np.ndarray:
    """min over s ∈ [0, 1] of |r0 + s d| (complex arrays, broadcast)."""
    dd = (d * d.conj()).real
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(dd > 0, -(r0 * d.conj()).real / dd, 0.0)
    s = np.clip(s, 0.0, 1.0)
    return np.abs(r0 + s * d)


Rhs = Callable[[np.ndarray, float], np.ndarray]


def rk4_step(z: np.ndarray, v1: np.ndarray, h: float, rhs: Rhs,
             out: np.ndarray | None = None) -> np.ndarray:
    """One classical RK4 step of ż = v(z) from ``z`` (M,) complex with v1 = v(z) given;
    ``rhs(z, move)`` returns v at z (``move``: how far a point may have moved since the previous
    evaluation, for the caller's sub-tube tracking). Returns (or writes to ``out``) the new z."""
    half = 0.5 * h
    v2 = rhs(z + half * v1, half * _vmax(v1)).copy()
    v3 = rhs(z + half * v2, half * (_vmax(v1) + _vmax(v2))).copy()
    v4 = rhs(z + h * v3, h * (_vmax(v2) + _vmax(v3)))
    acc = v1 + 2.0 * v2
    acc += 2.0 * v3
    acc += v4
    acc *= h / 6.0
    return np.add(z, acc, out=out)


def _vmax(v: np.ndarray) -> float:
    return float(np.abs(v).max()) if v.shape[0] else 0.0


Move = Callable[[object, np.ndarray, float], tuple[object, np.ndarray]]
StateRhs = Callable[[object, np.ndarray, float], np.ndarray]


def adaptive_step(z: np.ndarray, v: np.ndarray, h: float, rhs: Rhs, guard: MarginGuard,
                  pairs: Pairs, stats: AdaptiveStats, out: np.ndarray | None = None,
                  max_halvings: int = ADAPTIVE_MAX_HALVINGS) -> np.ndarray:
    """Advance ż = v(z) by ``h`` from ``z`` with v = v(z) given, in Euler sub-steps halved until
    :meth:`MarginGuard.accepts` each (module docstring). ``rhs(z, move)`` evaluates v at an
    accepted sub-step's end (``move``: the largest distance a point moved in it). ``pairs`` must
    stay a valid neighbour list over the whole step. Returns (or writes to ``out``) the new z."""
    state, znew = adaptive_state_step(
        z, z, v, h, lambda s, vv, hs: (s + hs * vv,) * 2, lambda s, zz, mv: rhs(zz, mv),
        guard, pairs, stats, max_halvings)
    if out is None:
        return znew
    out[...] = znew
    return out


def adaptive_state_step(state: object, z: np.ndarray, v: np.ndarray, h: float, move: Move,
                        rhs: StateRhs, guard: MarginGuard, pairs: Pairs, stats: AdaptiveStats,
                        max_halvings: int = ADAPTIVE_MAX_HALVINGS) -> tuple[object, np.ndarray]:
    """:func:`adaptive_step` for a model whose state is not the evaluation point itself (the
    unicycle: state (p, θ), points the (NID) control points): ``move(state, v, hs)`` → (new
    state, its points) is one Euler sub-step under the command ``v``; ``rhs(state, z, move)``
    the command at a state whose points are ``z``. Returns (new state, its points)."""
    stats.guarded_steps += 1
    left = h
    n_sub = 0
    floor = h / (1 << max_halvings)
    cur, zc = state, z
    while True:
        hs = left
        nxt, zn = move(cur, v, hs)
        while not guard.accepts(zc, zn, pairs):
            if hs <= floor * (1 + 1e-9):
                stats.floor_steps += 1
                break
            hs *= 0.5
            nxt, zn = move(cur, v, hs)
        n_sub += 1
        left -= hs
        if n_sub > 1 or left > h * 1e-12:
            stats.min_substep_s = min(stats.min_substep_s, hs)
        if left <= h * 1e-12:
            break
        v = rhs(nxt, zn, float(np.abs(zn - zc).max()) if zn.shape[0] else 0.0)
        cur, zc = nxt, zn
    if n_sub > 1:
        stats.split_steps += 1
        stats.substeps += n_sub
    return nxt, zn
