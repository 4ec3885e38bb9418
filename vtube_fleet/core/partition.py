"""Partition of a trapezoid virtual tube containing obstacles (Section IV-A of the paper).

The construction is the one pinned down in ``docs/paper.md`` ("The partition"):

* each obstacle O_k (obstacle) is grown to O'_k of radius R_k = r_o,k + r_s (ExtObstacle) and
  wrapped in an isosceles circumscribed triangle I_k whose incircle is O'_k, apex
  p_oth,k = p_o,k − h_k n_c upstream, base on the line ξ = ξ(p_o,k) + R_k;
  h_k ≥ h_min,k (pothk), default 1.3 h_min,k, configurable per obstacle
  (:attr:`~vtube_fleet.core.tube.Obstacle.apex_distance`), or ``"auto"``: chosen jointly by
  the planner (:mod:`vtube_fleet.core.plan`, Remark 6);
* obstacles are taken farthest from the finishing line first (ties: more-left first); each one
  splits the sub-tube that contains its centre into ``before``, ``left``, ``right`` and ``after``
  sub trapezoid tubes (FourSub1)/(FourSub2);
* a side tube that is inverted or violates Assumption 3' is dropped and the triangle is modified
  as in Remark 5 (one side on the parent's leg, the other the passage-side tangent of O'_k at
  angle β ∈ [α, α_max] to n_c); both sides invalid → :class:`PartitionError`;
* the sub-tubes are sorted by (ξ_start, lateral position of the start-base midpoint) and named
  ``T_o1, T_o2, …`` (for P = 1: before, left, right, after, as the paper numbers them).

:meth:`Partition.locate` implements the switching rule (ObstacleController) with the shared-edge
conventions of partition §5. Everything here is pure numpy.
"""

from __future__ import annotations

import dataclasses
import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

from vtube_fleet.core.text import compact_number as _num
from vtube_fleet.core.text import obstacle_label
from vtube_fleet.core.tube import GeometryError, Obstacle, Trapezoid
from vtube_fleet.errors import UserError

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.core.params import ControllerParams
    from vtube_fleet.core.plan import ApexPlan

_F64 = np.dtype(np.float64)  # (dtypes of the built-in types are singletons: tested by identity)
_C128, _mul, _add = np.complex128, np.multiply, np.add  # (update's check: one lookup each)

__all__ = [
    "ApexZone",
    "DEFAULT_APEX_FACTOR",
    "LOCATE_TOL",
    "Partition",
    "PartitionBuilder",
    "PartitionError",
    "SubTubeNode",
    "SubTubeTracker",
    "Triangle",
    "Violation",
    "alpha_max",
    "apex_lookahead",
    "apex_zones",
    "check_assumption3",
    "check_constraint2",
    "h_min",
    "lookahead_depth",
    "partition",
]

#: Default apex distance h_k = DEFAULT_APEX_FACTOR × h_min,k (partition §2).
DEFAULT_APEX_FACTOR = 1.3

#: Tolerance (metres) of the point-location rule: a point within this distance upstream of a
#: base counts as on it, and among candidates whose violations differ by less than it the lower
#: index wins. It makes the shared-edge rules of §5 hold despite rounding (e.g. at the apex).
LOCATE_TOL = 1e-9

_REL_TOL = 1e-9  # relative tolerance of the ≤ comparisons in Constraint2/3
_AREA_TOL = 1e-9  # m²: an intersection with less area than this is "zero area"


# ----------------------------------------------------------------------------------------------
# Small value types
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Violation:
    """One violated condition of the paper: its name (e.g. ``"Constraint3"``) and a message
    carrying the numbers, e.g. ``Constraint1 violated: v + v'_max = 4.0 > v_max = 3.5``."""

    condition: str
    message: str

    def __str__(self) -> str:
        return self.message


class PartitionError(UserError):
    """The tube cannot be partitioned around an obstacle.

    ``obstacle`` is the 0-based index of the obstacle in the sequence given to
    :func:`partition` (the message counts from 1: ``obstacle #2 at (12.0, 0.0) r_o=0.9``) or
    ``None`` when the problem is not tied to one obstacle; ``reason`` is the message without the
    obstacle prefix.
    """

    def __init__(self, obstacle: int | None, reason: str, where: str = "") -> None:
        self.obstacle = obstacle
        self.reason = reason
        super().__init__(f"{where}: {reason}" if where else reason)


@dataclass(frozen=True, eq=False)
class Triangle:
    """Circumscribed triangle I_k of one obstacle (apex p_oth, base points p_otu (left) and
    p_otd (right)).

    ``obstacle`` is the 0-based index of the obstacle in the input sequence, ``center`` its
    centre p_o, ``radius_ext`` R = r_o + r_s (the incircle O', ExtObstacle), ``h`` the apex
    distance used, ``alpha`` = asin(R/h) the half apex angle of the isosceles triangle.
    ``remark5`` is ``None`` for the isosceles triangle, else the side whose sub-tube was dropped
    (``"right"``: T_o3 = ∅ as in the paper's Fig. 7(b); the side [p_oth, p_otd] then lies on the
    parent's right leg, direction t_r), and ``beta`` the angle of the kept tangent side to n_c
    (= alpha when isosceles).
    """

    obstacle: int
    center: np.ndarray
    radius_ext: float
    h: float
    alpha: float
    p_oth: np.ndarray
    p_otu: np.ndarray
    p_otd: np.ndarray
    remark5: Literal["left", "right"] | None = None
    beta: float = 0.0

    def polygon(self) -> np.ndarray:
        """Vertices (3, 2): p_oth, p_otu, p_otd."""
        return np.stack([self.p_oth, self.p_otu, self.p_otd])

    def contains(self, x: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Closed membership of points (..., 2) in the triangle, with a tolerance in metres."""
        x = np.asarray(x, dtype=float)
        poly = self.polygon()
        sgn = 1.0 if _cross2(poly[1] - poly[0], poly[2] - poly[0]) > 0 else -1.0
        ok = np.ones(x.shape[:-1], dtype=bool)
        for a, b in ((poly[0], poly[1]), (poly[1], poly[2]), (poly[2], poly[0])):
            e = b - a
            # signed distance to the edge line, > 0 on the interior side
            d = sgn * (e[0] * (x[..., 1] - a[1]) - e[1] * (x[..., 0] - a[0])) / np.hypot(*e)
            ok &= d >= -tol
        return ok


# ----------------------------------------------------------------------------------------------
# (pothk) and the per-tube conditions
# ----------------------------------------------------------------------------------------------
def alpha_max(params: ControllerParams) -> float:
    """Steepest leg angle to n_c allowed by Constraint2/3 for a narrowing leg:
    2 v sin(α/2) ≤ v'_max ⇔ α ≤ α_max = 2 asin(v'_max / 2v) (44.05° for v = 2, v'_max = 1.5).
    """
    return 2.0 * math.asin(min(params.v_max_prime / (2.0 * params.v), 1.0))


def h_min(r_o: float, params: ControllerParams) -> float:
    """Smallest apex distance ‖p_oth − p_o‖ allowed by (pothk):
    (r_s + r_o) / ((v'_max/v) √(1 − v'_max²/(4v²))) = R / sin α_max.

    With r_o = 0.9, r_s = 0.25, v = 2, v'_max = 1.5 this is 1.654 m. When α_max ≥ 90° (only
    for v'_max ≥ √2 v) every triangle satisfies Constraint3 and R = r_o + r_s is returned.
    """
    R = float(r_o) + params.r_s
    a = alpha_max(params)
    return R if a >= math.pi / 2 else R / math.sin(a)


def check_constraint2(
    tube: Trapezoid, params: ControllerParams, condition: str = "Constraint2", label: str = ""
) -> list[Violation]:
    """(Constraint2) for the main tube, (Constraint3) for a sub-tube: v‖n_c − t_h‖ ≤ v'_max if
    L exists and v‖n_c − t_r‖ ≤ v'_max if R exists. ``label`` names the tube in messages."""
    out = []
    where = f" in {label}" if label else ""
    for side, t, t_name, has in (
        ("left", tube.t_h, "t_h", tube.has_L),
        ("right", tube.t_r, "t_r", tube.has_R),
    ):
        if not has:
            continue
        val = params.v * float(np.hypot(*(tube.n_c - t)))
        if val > params.v_max_prime * (1.0 + _REL_TOL):
            ang = math.degrees(math.acos(max(-1.0, min(1.0, float(t @ tube.n_c)))))
            out.append(Violation(condition, (
                f"{condition} violated{where}: {side} leg: v‖n_c − {t_name}‖ = {_num(val)} > "
                f"v'_max = {_num(params.v_max_prime)} (leg at {_num(ang, 2)}° to n_c, "
                f"steepest allowed {_num(math.degrees(alpha_max(params)), 2)}°)"
            )))
    return out


def _cross2(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _clip(poly: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Sutherland–Hodgman: the part of the convex polygon ``poly`` (N, 2) where
    normalᵀx ≥ offset (closed half-plane)."""
    if len(poly) == 0:
        return poly
    s = poly @ normal - offset
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        sa, sb = s[i], s[(i + 1) % n]
        if sa >= 0:
            out.append(a)
        if (sa >= 0) != (sb >= 0):
            out.append(a + (b - a) * (sa / (sa - sb)))
    return np.array(out, dtype=float).reshape(-1, 2)


def _area(poly: np.ndarray) -> float:
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def _assumption3_reasons(tube: Trapezoid, params: ControllerParams) -> list[str]:
    """Reasons why ``tube`` violates Assumption 3 (empty if it holds), evaluated exactly by
    half-plane clipping of the trapezoid polygon: L ∩ R has zero area, M ≠ ∅, and
    n_cᵀ(p_r1 − p_r0) > 2 r_a."""
    reasons = []
    d = params.k_t * params.r_a
    poly = tube.polygon()
    # d_Th(x) = n_hᵀx − n_hᵀp_h1 ; d_Tr(x) = n_rᵀx − n_rᵀp_r1.
    oh, orr = float(tube.n_h @ tube.p_h1), float(tube.n_r @ tube.p_r1)
    if tube.has_L and tube.has_R:
        lr = _clip(_clip(poly, -tube.n_h, -(oh + d)), -tube.n_r, -(orr + d))
        area = _area(lr)
        if area > _AREA_TOL:
            reasons.append(
                f"L ∩ R is not empty (area {_num(area)} m²: somewhere both legs are closer "
                f"than k_t r_a = {_num(d)} m; bases {_num(float(tube.width(0.0)))} m and "
                f"{_num(float(tube.width(tube.length)))} m wide)"
            )
    mid = poly
    if tube.has_L:
        mid = _clip(mid, tube.n_h, oh + d)
    if tube.has_R:
        mid = _clip(mid, tube.n_r, orr + d)
    if len(mid) == 0:
        reasons.append(
            f"M is empty (no point is k_t r_a = {_num(d)} m from both narrowing legs; bases "
            f"{_num(float(tube.width(0.0)))} m and {_num(float(tube.width(tube.length)))} m wide)"
        )
    length = float(tube.n_c @ (tube.p_r1 - tube.p_r0))
    if not length > 2.0 * params.r_a:
        reasons.append(f"length {_num(length)} m ≤ 2 r_a = {_num(2.0 * params.r_a)} m")
    return reasons


def _width_reasons(tube: Trapezoid, params: ControllerParams) -> list[str]:
    """"Wide enough to contain at least one robot" taken literally: at each base some centre
    must have d_Th ≥ r_s and d_Tr ≥ r_s, i.e. the base width w ≥ r_s (1/cos θ_h + 1/cos θ_r)
    with θ the leg angles to n_c. (For a tube with a leg parallel to n_c the letter of
    Assumption 3 — L ∩ R = ∅, M ≠ ∅ — does not imply this.)"""
    need = params.r_s * (1.0 / float(tube.t_h @ tube.n_c) + 1.0 / float(tube.t_r @ tube.n_c))
    out = []
    for base, z in (("start base", 0.0), ("finishing line", tube.length)):
        w = float(tube.width(z))
        if w < need:
            out.append(f"too narrow to contain one robot: its {base} is {_num(w)} m wide, a "
                       f"safety disc of radius r_s = {_num(params.r_s)} m needs {_num(need)} m "
                       f"between the legs")
    return out


def check_assumption3(
    tube: Trapezoid, params: ControllerParams, condition: str = "Assumption3", label: str = ""
) -> list[Violation]:
    """Assumption 3 (main tube) / Assumption 3' (a sub-tube, ``condition="Assumption3'"``):
    L ∩ R = ∅ (zero area), M ≠ ∅, n_cᵀ(p_r1 − p_r0) > 2 r_a, and — the assumption's words
    "wide enough to contain at least one robot" — room for one safety disc at both bases; one
    :class:`Violation` per failing part, with the numbers."""
    where = f" in {label}" if label else ""
    return [
        Violation(condition, f"{condition} violated{where}: {r}")
        for r in _assumption3_reasons(tube, params) + _width_reasons(tube, params)
    ]


# ----------------------------------------------------------------------------------------------
# Point location (§5)
# ----------------------------------------------------------------------------------------------
class _Locator:
    """Precomputed stacked arrays for the §5 rule over K tubes sharing n_c.

    score_k(p) = min(d_Th,k(p), d_Tr,k(p)) = −viol_k(p) comes from one batched matmul
    (n_h and n_r of all tubes stacked as (2, 2, K)) as min(n_hᵀp, n_rᵀp + δ) − n_hᵀp_h1 with
    δ = n_hᵀp_h1 − n_rᵀp_r1; the half-open slab test is a ``searchsorted`` of ξ into the
    sorted base coordinates and a (slabs, K) table holding −n_hᵀp_h1 for candidates and −inf
    otherwise; k(p) = argmax (first on ties). 7 numpy calls in all.
    """

    def __init__(self, tubes: Sequence[Trapezoid], xs: np.ndarray, xe: np.ndarray,
                 n_c: np.ndarray, xi0: float) -> None:
        K = len(tubes)
        A = np.empty((2, 2, K))
        bh = np.empty(K)
        br = np.empty(K)
        for k, t in enumerate(tubes):
            A[0, :, k] = t.n_h
            A[1, :, k] = t.n_r
            bh[k] = float(t.n_h @ t.p_h1)
            br[k] = float(t.n_r @ t.p_r1)
        # Lower indices get a bonus below LOCATE_TOL so that ties up to rounding go to the
        # smallest index (the apex rule).
        bonus = LOCATE_TOL * (K - np.arange(K)) / (K + 1)
        bh -= bonus
        br -= bonus
        self.A = A
        self.delta = bh - br
        self.n_c = np.array(n_c, dtype=float)
        bp = np.unique(np.concatenate([xs[np.isfinite(xs)], xe[np.isfinite(xe)]]))
        # slab j = [lo[j], hi[j]) in ξ; a point within LOCATE_TOL upstream of a base counts as
        # on it (→ downstream). Compare raw n_cᵀp with ξ-breakpoints shifted by n_cᵀp_h0.
        self.bps = bp + (xi0 - LOCATE_TOL)
        lo = np.concatenate([[-np.inf], bp])
        hi = np.concatenate([bp, [np.inf]])
        cand = (xs[None, :] <= lo[:, None]) & (xe[None, :] >= hi[:, None])
        self.cand = cand
        self.bh, self.br = bh, br
        self.pen = np.where(cand, -bh[None, :], -np.inf)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, dtype=float)
        if p.ndim > 2:
            return self(p.reshape(-1, 2)).reshape(p.shape[:-1])
        D = p @ self.A  # (2, M, K) or (2, K)
        D[1] += self.delta
        return self.finish(D, p)[0]

    def finish(self, D: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(k, slab index) from D = [n_hᵀp, n_rᵀp + δ] of every tube (overwrites D[0])."""
        s = np.minimum(D[0], D[1], out=D[0])
        slab = self.bps.searchsorted(p @ self.n_c, "right")
        s += self.pen.take(slab, axis=0)
        return s.argmax(axis=-1), slab


# ----------------------------------------------------------------------------------------------
# The partition
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Partition:
    """Result of :func:`partition`.

    ``sub_tubes`` are named ``T_o1, T_o2, …`` in the order of (``xi_start``, lateral position of
    the start-base midpoint); ``xi_start``/``xi_end`` (K,) are the ξ of each sub-tube's start base
    and finishing line in the main tube's coordinate ξ(x) = n_cᵀ(x − p_h0), with −inf/+inf when
    that base is one of the main tube's bases (partition §3). ``triangles`` are in the order
    of the input obstacles (obstacles skipped in non-strict mode have none), ``warnings`` are
    :class:`Violation` s (Constraint3 / Assumption3' per sub-tube, skipped obstacles).
    """

    tube: Trapezoid
    sub_tubes: tuple[Trapezoid, ...]
    xi_start: np.ndarray
    xi_end: np.ndarray
    triangles: tuple[Triangle, ...] = ()
    warnings: tuple[Violation, ...] = ()
    #: how the ``"auto"`` apex distances were chosen (:class:`vtube_fleet.core.plan.ApexPlan`;
    #: ``None``: every h_k was given or the default)
    apex: ApexPlan | None = None
    _locator: _Locator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        xs = np.asarray(self.xi_start, dtype=float).reshape(-1)
        xe = np.asarray(self.xi_end, dtype=float).reshape(-1)
        xs.setflags(write=False)
        xe.setflags(write=False)
        object.__setattr__(self, "xi_start", xs)
        object.__setattr__(self, "xi_end", xe)
        object.__setattr__(self, "_locator", _Locator(
            self.sub_tubes, xs, xe, self.tube.n_c, float(self.tube.n_c @ self.tube.p_h0)))

    @property
    def K(self) -> int:
        """Number of sub-tubes."""
        return len(self.sub_tubes)

    def locate(self, p: np.ndarray) -> np.ndarray:
        """Sub-tube index k(p) of points (..., 2) → (...) int, the switching rule
        (ObstacleController) as in partition §5.

        Candidates are the sub-tubes whose half-open slab ξ_start ≤ ξ(p) < ξ_end contains p; the
        chosen one minimises viol_k = max(−d_Th,k, −d_Tr,k) (≤ 0 iff p is inside), ties to the
        smallest index. So a point on a shared base belongs to the downstream tube, the apex
        p_oth to the left tube, a point outside T laterally to the adjacent tube, ξ < 0 to the
        first and ξ ≥ L to the last. Comparisons use a tolerance of ``LOCATE_TOL`` = 1 nm.
        """
        return self._locator(p)

    def tracker(self) -> SubTubeTracker:
        """A :class:`SubTubeTracker`: ``locate`` for a moving swarm, re-run only when needed."""
        return SubTubeTracker(self)

    def names(self) -> tuple[str, ...]:
        """The sub-tube names, ``("T_o1", "T_o2", …)``."""
        return tuple(t.name for t in self.sub_tubes)


class SubTubeTracker:
    """:meth:`Partition.locate` for points that move a little between calls, exactly.

    :meth:`update` returns, for every ``p``, an array equal element for element to
    ``partition.locate(p)``, but runs the full locate only when a point may have changed its
    sub-tube. At each full locate, every point i gets a few half-planes ("rows") on whose
    intersection locate provably returns the same k_i; each later call evaluates the rows
    (4 one-dimensional numpy calls for all points, with 2-D points as complex numbers z = x + iy)::

        Re(C_ri z_i) + B_ri > 0 for every row r        (C_ri: unit normal, B_ri: offset)

    and re-runs the full locate only when one fails. The rows of a point in slab s (the
    candidates are the tubes whose half-open ξ-range contains s) choosing tube k:

    * slab: ξ_s,lo < n_cᵀp < ξ_s,hi (the candidate set is unchanged), with ±W = 10⁴ m (or 100×
      the size of the tube, if larger) around the tube for the unbounded first/last slab;
    * a lateral window |mᵀ(p − c)| < W (bounds |p|, hence the rounding errors below);
    * against every other candidate j, with j's active leg a_j, β_j at the locate (the one
      giving score_j = min(n_h,jᵀp − b_h,j, n_r,jᵀp − b_r,j), ties bonuses included):
      (n_h,k − a_j)ᵀp − (b_h,k − β_j) > 0 and (n_r,k − a_j)ᵀp − (b_r,k − β_j) > 0, which
      imply score_k − score_j > 0 since score_j ≤ a_jᵀp − β_j: k still wins outright, so the
      tie rule (lower index) never decides.

    Every row is normalized (|C| = 1, so its value is a distance) and shifted by a tolerance
    of 1e-9 m + 1e-14 × (size of the scene) (about 90 ε: the rounding of these rows and of
    locate's own scores is below 10 ε × size), so "the rows computed in floats are > 0"
    implies "locate computed in floats gives k". Rows are tabulated per (slab, k, active legs
    of the others), so locating (all points or a few) costs about 20 numpy calls.

    ``update(p, max_move=d)``: the caller promises that no point moved farther than ``d``
    since the previous call (the simulator: v_max·dt); the rows are then evaluated only when
    the moves summed since the last evaluation may have used up the smallest row value. A
    change in the number of points forces a full locate (rows follow positions, not robot
    identities, so re-ordered or replaced points are handled by the rows themselves); when
    rows fail, only those points are located again (:meth:`_partial`). ``locates`` counts
    the full locates, ``partial`` the partial ones, ``checks`` the row evaluations.
    """

    #: absolute part of the row tolerance (metres)
    ABS_TOL = 1e-9
    #: relative part (× the scene size S): ~90 machine epsilons
    REL_TOL = 1e-14

    def __init__(self, partition: Partition) -> None:
        loc = partition._locator
        self._loc = loc
        self.locates = 0
        self.partial = 0
        self.checks = 0
        self._k = np.zeros(0, np.intp)
        self._k.setflags(write=False)
        self._C: np.ndarray | None = None
        self._B: np.ndarray | None = None
        self._slack = -math.inf
        self._M = -1
        self._shape: tuple = ()  # (M, 2) once the rows are set
        self._check: tuple | None = None  # update()'s 1-D row check (set by _full)
        self._rows: dict = {}  # row code → its rows as Python numbers (_partial_few)
        self._tables = self._build_tables(partition)
        self._one = self._one_point_tables() if self._tables is not None else None

    # --- tables -----------------------------------------------------------------------------
    def _build_tables(self, part: Partition) -> tuple | None:
        loc = self._loc
        cand = loc.cand
        nslab, K = cand.shape
        cm1 = int(cand.sum(axis=1).max()) - 1
        if nslab * K << cm1 > 1 << 16:  # pragma: no cover - absurd numbers of side tubes
            return None
        n_c = loc.n_c
        m = np.array([-n_c[1], n_c[0]])
        polys = [part.tube.polygon()] + [t.polygon() for t in part.sub_tubes]
        pts = np.concatenate(polys)
        center = pts.mean(axis=0)
        size = float(np.hypot(*(pts - center).T).max())
        W = max(1e4, 100.0 * size)
        bps = loc.bps
        finite = np.abs(np.concatenate([bps, loc.bh, loc.br]))
        S = float(np.hypot(*center)) + size + 2.0 * W + float(finite.max(initial=0.0))
        xi_c, m_c = float(center @ n_c), float(center @ m)
        lo = np.concatenate([[xi_c - W], bps])
        hi = np.concatenate([bps, [xi_c + W]])
        A = loc.A  # (2, 2, K): A[0, :, k] = n_h,k, A[1, :, k] = n_r,k
        bh, br = loc.bh, loc.br
        n_rows = 4 + 2 * cm1
        ncode = (nslab * K) << cm1
        Ctab = np.zeros((n_rows, ncode), np.complex128)
        Btab = np.full((n_rows, ncode), -np.inf)  # (slab, k) never chosen: always re-locate

        def row(N: np.ndarray, off: float) -> tuple[complex, float]:
            """Normalized, shifted row for Nᵀp + off > 0."""
            tol = self.ABS_TOL + self.REL_TOL * (S + abs(off))
            nn = float(np.hypot(*N))
            if nn == 0.0:
                return 0j, (math.inf if off > tol else -math.inf)
            return complex(N[0], -N[1]) / nn, (off - tol) / nn

        for s in range(nslab):
            cs = np.flatnonzero(cand[s])
            for k in cs:
                others = [int(j) for j in cs if j != k]
                fixed = [row(n_c, -lo[s]), row(-n_c, hi[s]),
                         row(m, -(m_c - W)), row(-m, m_c + W)]
                for bits in range(1 << cm1):
                    code = ((s * K + int(k)) << cm1) | bits
                    rows = list(fixed)
                    for t in range(cm1):
                        if t >= len(others):
                            rows += [(0j, math.inf)] * 2
                            continue
                        j = others[t]
                        h = (bits >> t) & 1
                        a, beta = (A[0, :, j], bh[j]) if h else (A[1, :, j], br[j])
                        rows.append(row(A[0, :, k] - a, -(bh[k] - beta)))
                        rows.append(row(A[1, :, k] - a, -(br[k] - beta)))
                    Ctab[:, code] = [c for c, _ in rows]
                    Btab[:, code] = [b for _, b in rows]
        others_tab = np.full((nslab * K, max(cm1, 1)), -1, np.intp)
        for s in range(nslab):
            cs = np.flatnonzero(cand[s])
            for k in cs:
                oth = [int(j) for j in cs if j != k]
                others_tab[s * K + k, :len(oth)] = oth
        pw = (1 << np.arange(max(cm1, 1))).astype(np.intp) if cm1 else np.zeros(1, np.intp)
        return Ctab, Btab, others_tab, pw, cm1

    def _one_point_tables(self) -> tuple:
        """The locator's constants as Python floats and lists, for :meth:`_locate_one`."""
        loc = self._loc
        A = loc.A
        K = A.shape[2]
        cand = [[int(k) for k in np.flatnonzero(row)] for row in loc.cand]
        others = self._tables[2].tolist()
        return (float(loc.n_c[0]), float(loc.n_c[1]), loc.bps.tolist(), cand,
                A[0, 0].tolist(), A[0, 1].tolist(), A[1, 0].tolist(), A[1, 1].tolist(),
                loc.delta.tolist(), loc.bh.tolist(), K, others, self._tables[4])

    def _locate_one(self, x: float, y: float) -> tuple[int, int] | None:
        """(k, row code) of one point (x, y): the computation of :meth:`_locate_rows` in
        Python floats, whose rounding may differ from numpy's (the caller checks the rows
        at the point, and a point that fails them is located by :meth:`_full`). None when
        no candidate scores (NaN)."""
        nc0, nc1, bps, cand, a00, a01, a10, a11, delta, bh, K, others, cm1 = self._one
        s = bisect_right(bps, x * nc0 + y * nc1)  # the slab (searchsorted "right")
        best, kb = -math.inf, -1
        leg_h = {}
        for k in cand[s]:
            d0 = x * a00[k] + y * a01[k]
            d1 = x * a10[k] + y * a11[k] + delta[k]
            leg_h[k] = d0 <= d1
            v = (d0 if d0 < d1 else d1) - bh[k]
            if v > best:  # (the first maximum, as argmax)
                best, kb = v, k
        if kb < 0:
            return None
        sk = s * K + kb
        code = sk << cm1
        for t, j in enumerate(others[sk][:cm1]):
            if j >= 0 and leg_h[j]:
                code |= 1 << t
        return kb, code

    # --- the work ---------------------------------------------------------------------------
    def _locate_rows(self, p: np.ndarray, rowoff: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Locate the points p (the computation of :meth:`Partition.locate`) → (k, C, B):
        their sub-tubes and rows. ``rowoff``: (len(p), 1) row offsets i·K."""
        loc = self._loc
        D = p @ loc.A
        D[1] += loc.delta
        H = D[0] <= D[1]  # active leg of every tube: n_h (True) or n_r
        k, slab = loc.finish(D, p)
        Ctab, Btab, others_tab, pw, cm1 = self._tables
        sk = slab * loc.A.shape[2]
        sk += k
        code = sk << cm1
        if cm1:
            oth = others_tab.take(sk, axis=0)  # (M, cm1), −1 = none (any bit: same rows)
            oth += rowoff
            code += H.reshape(-1).take(oth) @ pw
        return k, Ctab.take(code, axis=1), Btab.take(code, axis=1)

    def _full(self, p: np.ndarray) -> None:
        """Full locate (the same computation as :meth:`Partition.locate`) and new rows."""
        self.locates += 1
        M = p.shape[0]
        if self._tables is None:  # pragma: no cover
            k = self._loc(p)
            self._M = M
        else:
            R = self._tables[0].shape[0]
            if M != self._M:
                K = self._loc.A.shape[2]
                self._rowoff = (np.arange(M) * K)[:, None]
                self._v = np.empty(R * M, np.complex128)
                self._vr = np.empty((R, M))
                self._zt = np.empty(R * M, np.complex128)
                self._tile = np.tile(np.arange(M), R)  # row r, point i → element r·M + i
                self._M = M
            k, self._C, self._B = self._locate_rows(p, self._rowoff)
            # update()'s row check as 1-D calls: the points gathered once per row
            self._check = (self._zt, self._tile, self._C.reshape(R * M), self._v,
                           self._v.real, self._B.reshape(R * M), self._vr.reshape(R * M)
                           ) if M else None
        self._shape = (M, 2)
        if self._k.shape != k.shape or (self._k != k).any():
            k.setflags(write=False)
            self._k = k
        self._slack = -math.inf

    def _partial(self, p: np.ndarray, vr: np.ndarray) -> None:
        """Locate again only the points with a failing row (the others keep k and rows).

        Locate's arithmetic is per point, but a matrix product may round differently for a
        subset than for all points: if a re-located point's fresh rows do not hold at the
        point itself (it lies within the rows' tolerance of a boundary), the full locate
        decides instead, so that the result always equals ``locate`` of all points.
        """
        M = vr.shape[1]
        fail = np.greater(vr, 0.0)
        fail = np.logical_not(fail, out=fail).reshape(-1).nonzero()[0]  # (NaN rows too)
        if fail.shape[0] <= 16 and self._one is not None:  # the common case: a point or two
            bad = sorted({i % M for i in fail.tolist()})
            if len(bad) <= 4:
                self._partial_few(p, bad)
                return
        ok = np.minimum.reduce(vr, axis=0) > 0.0
        bad = np.logical_not(ok, out=ok).nonzero()[0]
        if 4 * bad.shape[0] > p.shape[0]:  # many: the full locate costs about the same
            self._full(p)
            return
        ps = p.take(bad, axis=0)
        k, C, B = self._locate_rows(ps, self._rowoff[: bad.shape[0]])
        zs = ps.view(np.complex128).reshape(bad.shape[0])
        if not np.minimum.reduce((C * zs).real + B, axis=None) > 0.0:
            self._full(p)
            return
        self.partial += 1
        self._C[:, bad] = C
        self._B[:, bad] = B
        ne = self._k.take(bad) != k
        if ne[ne.argmax()]:
            knew = self._k.copy()
            knew[bad] = k
            knew.setflags(write=False)
            self._k = knew
        self._slack = -math.inf

    def _partial_few(self, p: np.ndarray, bad: list[int]) -> None:
        """:meth:`_partial` for the few points ``bad``, in Python floats (microseconds instead
        of ~30 numpy calls): their new rows must hold at the points, else :meth:`_full`."""
        rows = self._rows
        new = []
        for i in bad:
            x, y = p[i].tolist()
            got = self._locate_one(x, y)
            if got is None:
                self._full(p)
                return
            k, code = got
            row = rows.get(code)
            if row is None:  # (the table's column as numbers: (Re C, Im C, B) per row)
                Ctab, Btab = self._tables[0], self._tables[1]
                row = rows[code] = (Ctab[:, code], Btab[:, code], [
                    (c.real, c.imag, b) for c, b in zip(Ctab[:, code].tolist(),
                                                       Btab[:, code].tolist(), strict=True)])
            C, B, cb = row
            for cr, ci, b in cb:
                if not cr * x - ci * y + b > 0.0:  # Re(C z) + B, as update's rows
                    self._full(p)
                    return
            new.append((i, k, C, B))
        self.partial += 1
        knew = None
        for i, k, C, B in new:
            self._C[:, i] = C
            self._B[:, i] = B
            if int(self._k[i]) != k:
                if knew is None:
                    knew = self._k.copy()
                knew[i] = k
        if knew is not None:
            knew.setflags(write=False)
            self._k = knew
        self._slack = -math.inf

    def update(self, p: np.ndarray, max_move: float | None = None) -> np.ndarray:
        """Sub-tube index of each point (M, 2) → (M,) int, equal to ``locate(p)``.

        The returned array is read-only and is the same object as the previous call's when
        no point changed its sub-tube. ``max_move``: see the class docstring.
        """
        if max_move is not None and type(p) is np.ndarray and p.shape == self._shape:
            self._slack -= max_move * (1.0 + 1e-9) + 1e-9
            if self._slack > 0.0:
                return self._k
            ck = self._check
            if ck is not None and p.dtype is _F64 and p.flags.c_contiguous:
                # the rows at the same points as at the last locate (the common call)
                self.checks += 1
                zt, tile, Cf, v, vre, Bf, vrf = ck
                p.view(_C128).take(tile, None, zt, "clip")
                _mul(Cf, zt, v)
                _add(vre, Bf, vrf)
                vmin = float(vrf[vrf.argmin()])  # (NaN if any: argmin returns the first NaN)
                if vmin > 0.0:
                    self._slack = vmin
                else:
                    self._partial(p, self._vr)
                return self._k
        if not (type(p) is np.ndarray and p.dtype == np.float64 and p.ndim == 2
                and p.shape[1] == 2 and p.flags.c_contiguous):
            p = np.ascontiguousarray(p, dtype=np.float64)
            if p.ndim != 2 or p.shape[1] != 2:
                raise ValueError(f"positions must have shape (M, 2), got {p.shape}")
        M = p.shape[0]
        if M != self._M or self._C is None:
            self._full(p)
            return self._k
        self.checks += 1
        vr = self._vr
        if M:
            v = np.multiply(self._C, p.view(np.complex128).reshape(M),
                            self._v.reshape(vr.shape))
            np.add(v.real, self._B, vr)
            vf = vr.reshape(-1)  # min(vr) (NaN if any, as argmin returns the first NaN)
            vmin = float(vf[vf.argmin()])
        else:
            vmin = math.inf
        if vmin > 0.0:
            self._slack = vmin
        else:  # some row fails (or NaN): those points may have changed sub-tube
            self._partial(p, vr)
        return self._k


@dataclass
class SubTubeNode:
    """A sub-tube under construction (also the apex planner's, ``core/plan.py``)."""

    tube: Trapezoid
    xs: float  # −inf when the start base is T's
    xe: float  # +inf when the finishing line is T's
    origin: str  # for messages: "the tube before obstacle #2"
    obstacle: int | None  # 0-based index of the obstacle that created it


def _dist_to_polygon(p: np.ndarray, poly: np.ndarray) -> float:
    """Distance from ``p`` to the boundary of the polygon (a repeated vertex, as clipping may
    leave, is an edge of length 0)."""
    best = math.inf
    for i in range(len(poly)):
        a, e = poly[i], poly[(i + 1) % len(poly)] - poly[i]
        ee = float(e @ e)
        t = 0.0 if ee < 1e-24 else min(1.0, max(0.0, float((p - a) @ e) / ee))
        best = min(best, float(np.hypot(*(p - (a + t * e)))))
    return best


@dataclass(frozen=True, eq=False)
class ApexZone:
    """Where the switching rule looks ahead of a triangle's apex (:func:`apex_lookahead`).

    ``before`` is the index of the sub-tube that ends at the apex line, ``left``/``right`` the
    side tubes that start there (one is None after Remark 5), ``apex`` p_oth, ``xi_apex`` its
    ξ, ``depth_m`` how far upstream of the apex line the zone reaches.
    """

    triangle: int
    before: int
    left: int | None
    right: int | None
    apex: np.ndarray
    xi_apex: float
    depth_m: float


def apex_zones(part: Partition, params: ControllerParams) -> tuple[ApexZone, ...]:
    """The look-ahead zone of every triangle for a vehicle with response lag.

    §5 switches a robot into a side tube only on the apex line: one heading straight at the
    apex then enters the side tube at distance ≈ 0 from its triangle side, inside r_s (NOTES
    item 7) — harmless for a single integrator integrated finely, not for a vehicle that needs
    τ_d + t63 to react. Ahead of each apex, down to ``depth = (r_s + r_a) / sin θ`` (θ the
    side's angle to n_c; so a robot on the apex's line enters at d = r_s + r_a, where the
    side's barrier starts to act), clipped to the before-tube, a robot of the before-tube is
    therefore controlled by the side tube on its side of the apex: the triangle side's line
    extended upstream is a wall for it already. Found geometrically: the side tubes start on
    the apex line with a leg through the apex; the before-tube ends on it and contains it.
    """
    tol = 1e-6
    tube = part.tube
    n_c = tube.n_c
    xi0 = float(n_c @ tube.p_h0)
    out = []
    for tri in part.triangles:
        apex = np.asarray(tri.p_oth, dtype=float)
        xi_a = float(n_c @ apex) - xi0
        left = right = before = None
        for k, t in enumerate(part.sub_tubes):
            xs, xe = float(part.xi_start[k]), float(part.xi_end[k])
            if abs(xs - xi_a) < tol:
                if float(np.hypot(*(t.p_r0 - apex))) < tol:
                    left = k
                elif float(np.hypot(*(t.p_h0 - apex))) < tol:
                    right = k
            if (abs(xe - xi_a) < tol and float(t.d_Th(apex)) >= -tol
                    and float(t.d_Tr(apex)) >= -tol):
                before = k
        if before is None or (left is None and right is None):
            continue
        sides = [part.sub_tubes[k].t_r for k in (left,) if k is not None] + \
                [part.sub_tubes[k].t_h for k in (right,) if k is not None]
        xs_b = float(part.xi_start[before])
        room = xi_a - (xs_b if math.isfinite(xs_b) else 0.0)
        out.append(ApexZone(tri.obstacle, before, left, right, apex, xi_a,
                            lookahead_depth(sides, n_c, params, room)))
    return tuple(out)


def lookahead_depth(sides: Sequence[np.ndarray], n_c: np.ndarray, params: ControllerParams,
                    room: float) -> float:
    """Depth of an apex look-ahead zone (:func:`apex_zones`): (r_s + r_a) / sin θ, θ the
    smallest angle of the triangle sides ``sides`` (unit directions) to n_c, within [0, room]
    (``room``: the before-tube's length up to the apex line)."""
    sin_t = min(math.sqrt(max(0.0, 1.0 - float(t @ n_c) ** 2)) for t in sides)
    depth = (params.r_s + params.r_a) / sin_t if sin_t > 1e-9 else room
    return float(max(0.0, min(depth, room)))


def apex_lookahead(part: Partition, zones: Sequence[ApexZone], p: np.ndarray,
                   k: np.ndarray) -> np.ndarray:
    """The switching rule with look-ahead (:func:`apex_zones`): ``k`` = ``part.locate(p)``,
    points of a zone's before-tube within its depth upstream of the apex line are moved to the
    side tube on their side of the apex (left on a tie, as at the apex itself)."""
    if not zones:
        return k
    p = np.asarray(p, dtype=float).reshape(-1, 2)
    k = np.array(k, dtype=np.intp).reshape(-1)
    tube = part.tube
    n_c = tube.n_c
    m = np.array([-n_c[1], n_c[0]]) * -1.0  # from the left leg towards the right leg
    if float(m @ (tube.p_r0 - tube.p_h0)) < 0:
        m = -m
    xi = p @ n_c - float(n_c @ tube.p_h0)
    for z in zones:
        hit = (k == z.before) & (xi >= z.xi_apex - z.depth_m) & (xi < z.xi_apex)
        if not hit.any():
            continue
        lat = (p[hit] - z.apex) @ m
        if z.left is not None and z.right is not None:
            k[hit] = np.where(lat <= 0.0, z.left, z.right)
        else:
            k[hit] = z.left if z.left is not None else z.right
    return k


def partition(
    tube: Trapezoid,
    obstacles: Sequence[Obstacle],
    params: ControllerParams,
    strict: bool = True,
    keep_out: np.ndarray | None = None,
    triangles_about: Literal["O'", "O"] = "O'",
) -> Partition:
    """Partition ``tube`` into obstacle-free sub trapezoid tubes (Section IV-A, docs/paper.md).

    Obstacles whose ``apex_distance`` is ``"auto"`` get their h_k from the planner
    (:func:`vtube_fleet.core.plan.plan_partition`: chosen jointly, deterministic), which keeps
    the points ``keep_out`` (M, 2; the robots' start positions) out of every triangle;
    ``keep_out`` is not used otherwise.

    ``params`` supplies r_s, r_a, k_t, v and v'_max. Raises :class:`PartitionError` (naming the
    obstacle and the numbers) when a triangle does not fit in its parent sub-tube, when an
    obstacle blocks the tube (both side tubes invalid), when the Remark 5 apex cannot be placed
    or its kept side tube violates Assumption 3', and when an obstacle's extended area O' lies
    entirely outside the tube. With ``strict=False`` the last case and Assumption 3' violations
    of the before/after tubes are recorded in :attr:`Partition.warnings` instead. Constraint3
    violations of sub-tubes are always recorded as warnings (the caller decides; see
    :mod:`vtube_fleet.core.validation`), and so is a sub-tube too narrow to contain one safety disc
    (Assumption 3' in words; not part of the construction's validity test, which follows the
    letter of the construction, docs/paper.md). With no obstacles the result is the main tube alone.

    ``triangles_about="O"`` circumscribes the triangles about the obstacle O itself (radius r_o)
    instead of O' (r_o + r_s), as the authors' published simulation does, and, like it, keeps
    side tubes that break Assumption 3' (recorded as warnings with ``strict=False``); the
    triangle no longer keeps the safety disc off the obstacle (an uncertified simulation only,
    never flown: docs/config.md). Not combined with ``"auto"`` apex distances.
    """
    if any(isinstance(ob.apex_distance, str) for ob in obstacles):
        from vtube_fleet.core.plan import plan_partition

        return plan_partition(tube, obstacles, params, strict=strict, keep_out=keep_out)
    if triangles_about not in ("O'", "O"):
        raise ValueError(f"triangles_about must be \"O'\" or \"O\", got {triangles_about!r}")
    return PartitionBuilder(tube, obstacles, params, strict, about=triangles_about).run()


class PartitionBuilder:
    """The recursive split of partition §3, one obstacle at a time (:func:`partition`; the
    apex planner of ``core/plan.py`` drives it split by split)."""

    def __init__(self, tube: Trapezoid, obstacles: Sequence[Obstacle],
                 params: ControllerParams, strict: bool, about: str = "O'") -> None:
        self.tube = tube
        self.about_obstacle = about == "O"  # triangles about O, not O' (uncertified sims)
        self.obstacles = obstacles
        self.params = params
        self.strict = strict
        self.n_c, self.m = tube.n_c, tube.m
        self.xi0 = float(tube.n_c @ tube.p_h0)
        self.L = tube.length
        self.a_max = alpha_max(params)
        self.warnings: list[Violation] = []
        self.nodes = [SubTubeNode(tube, -math.inf, math.inf, "the main tube", None)]
        self.triangles: dict[int, Triangle] = {}

    # --- helpers ------------------------------------------------------------------------
    def xi(self, x: np.ndarray) -> float:
        """Main-tube longitudinal coordinate ξ(x) = n_cᵀ(x − p_h0)."""
        return float(self.n_c @ x) - self.xi0

    def on_line(self, a: np.ndarray, t: np.ndarray, z: float) -> np.ndarray:
        """Point of the line through ``a`` with direction ``t`` at ξ = z."""
        return a + t * ((z - self.xi(a)) / float(t @ self.n_c))

    def side_tube(self, pts: tuple[np.ndarray, ...], gaps: tuple[float, float], side: str,
                  name: str) -> tuple[Trapezoid | None, str]:
        """A side tube and "" if it is valid (not inverted, Assumption 3'), else (None, why)."""
        if min(gaps) <= 0:
            return None, (f"inverted: the triangle crosses the parent's {side} leg by "
                          f"{_num(-min(gaps))} m")
        try:
            t = Trapezoid(*pts, name=name)
        except GeometryError as e:  # pragma: no cover - excluded by the gap test
            return None, f"degenerate ({e})"
        reasons = _assumption3_reasons(t, self.params)
        if reasons and not self.about_obstacle:  # (the authors' code never checks it: the
            # uncertified construction keeps the tube; finish() records the violation)
            return None, "Assumption 3' fails: " + "; ".join(reasons)
        return t, ""

    def order(self) -> list[int]:
        """Obstacle indices in the order of the construction: farthest from the finishing
        line first (smallest ξ), ties: more-left first."""
        m = self.m
        keyed = [(round(self.xi(ob.center), 9), round(float(m @ ob.center), 9), i)
                 for i, ob in enumerate(self.obstacles)]
        return [i for _, _, i in sorted(keyed)]

    # --- the construction ---------------------------------------------------------------
    def run(self) -> Partition:
        for i in self.order():
            self.split(i)
        return self.finish()

    def finish(self) -> Partition:
        """The partition of the obstacles split so far (final checks, names, order)."""
        m = self.m
        if not self.triangles:
            return Partition(self.tube, (self.tube,), np.array([-math.inf]),
                             np.array([math.inf]), (), tuple(self.warnings))
        nodes = sorted(self.nodes, key=lambda nd: (
            nd.xs, float(m @ (nd.tube.p_h0 + nd.tube.p_r0)) / 2.0))
        subs = tuple(dataclasses.replace(nd.tube, name=f"T_o{k + 1}")
                     for k, nd in enumerate(nodes))
        for nd, t in zip(nodes, subs, strict=True):
            label = f"{t.name} ({nd.origin})"
            a3 = [Violation("Assumption3'", f"Assumption3' violated in {label}: {r}")
                  for r in _assumption3_reasons(t, self.params)]
            if a3 and self.strict:
                i = nd.obstacle
                assert i is not None
                raise PartitionError(i, "; ".join(v.message for v in a3),
                                     obstacle_label(i, self.obstacles[i]))
            self.warnings += a3
            # Not part of the construction's validity test (docs/paper.md), hence a warning
            # even in strict mode: a passage narrower than one safety disc.
            self.warnings += [Violation("Assumption3'", f"Assumption3' violated in {label}: {r}")
                              for r in _width_reasons(t, self.params)]
            self.warnings += check_constraint2(t, self.params, "Constraint3", label)
        return Partition(
            self.tube, subs,
            np.array([nd.xs for nd in nodes]), np.array([nd.xe for nd in nodes]),
            tuple(self.triangles[k] for k in sorted(self.triangles)), tuple(self.warnings),
        )

    def parent_index(self, i: int) -> int:
        """Index in :attr:`nodes` of the current sub-tube that contains obstacle ``i``'s centre
        (the §5 rule)."""
        nodes = self.nodes
        loc = _Locator([nd.tube for nd in nodes], np.array([nd.xs for nd in nodes]),
                       np.array([nd.xe for nd in nodes]), self.n_c, self.xi0)
        return int(loc(self.obstacles[i].center))

    def split(self, i: int, k_par: int | None = None) -> None:
        """Insert the triangle of obstacle ``i`` into the sub-tube that contains its centre
        (``k_par``: its index in :attr:`nodes`, if the caller knows it)."""
        ob = self.obstacles[i]
        params, n_c, m = self.params, self.n_c, self.m
        where = obstacle_label(i, ob)

        def fail(reason: str) -> PartitionError:
            return PartitionError(i, reason, where)

        p_o = ob.center
        R = float(ob.radius) + (0.0 if self.about_obstacle else params.r_s)
        h_lo = h_min(float(ob.radius), params)
        if isinstance(ob.apex_distance, str):  # "auto" is resolved by core/plan.py first
            raise ValueError(f"{where}: apex_distance {ob.apex_distance!r} was not resolved")
        h = float(ob.apex_distance) if ob.apex_distance is not None else DEFAULT_APEX_FACTOR * h_lo
        if not h > R:
            raise fail(f"apex distance h = {_num(h)} m must exceed r_o + r_s = {_num(R)} m "
                       f"(the apex would lie inside the extended obstacle O')")

        # An obstacle whose O' does not meet T is not part of the problem.
        tube = self.tube
        dist_T = 0.0 if bool(tube.contains(p_o)) else _dist_to_polygon(p_o, tube.polygon())
        if dist_T >= R:
            msg = (f"lies outside the tube: O' (radius r_o + r_s = {_num(R)} m) is "
                   f"{_num(dist_T - R)} m away from T")
            if self.strict:
                raise fail(msg)
            self.warnings.append(Violation("Partition", f"Partition: {where} {msg}; ignored"))
            return

        # Isosceles triangle with incircle O' (partition §2).
        alpha = math.asin(R / h)
        x_o = self.xi(p_o)
        p_oth = p_o - h * n_c
        half = (h + R) * math.tan(alpha)
        p_otu = p_o + R * n_c - half * m
        p_otd = p_o + R * n_c + half * m
        xA, xB = x_o - h, x_o + R

        # Parent: the current sub-tube that contains p_o (§5 rule).
        nodes = self.nodes
        if k_par is None:
            k_par = self.parent_index(i)
        par = nodes[k_par]
        Q = par.tube
        xs_a = 0.0 if par.xs == -math.inf else par.xs
        xe_a = self.L if par.xe == math.inf else par.xe

        # Fit check.
        if not (xs_a < xA and xB < xe_a):
            raise fail(
                f"its circumscribed triangle (apex ξ_A = {_num(xA)}, base ξ_B = {_num(xB)}, "
                f"h = {_num(h)} m) does not fit in its parent sub-tube ({par.origin}, "
                f"ξ from {_num(xs_a)} to {_num(xe_a)}): need ξ_s < ξ_A and ξ_B < ξ_e; change "
                f"the obstacle's apex_distance or the obstacle positions"
            )

        def lh(z: float) -> np.ndarray:
            return self.on_line(Q.p_h0, Q.t_h, z)

        def lr(z: float) -> np.ndarray:
            return self.on_line(Q.p_r0, Q.t_r, z)

        hA, hB, rA, rB = lh(xA), lh(xB), lr(xA), lr(xB)
        num = i + 1
        left, why_l = self.side_tube(
            (hA, hB, p_oth, p_otu), (float(m @ (p_otu - hB)), float(m @ (p_oth - hA))),
            "left", f"left of obstacle #{num}")
        right, why_r = self.side_tube(
            (p_oth, p_otd, rA, rB), (float(m @ (rB - p_otd)), float(m @ (rA - p_oth))),
            "right", f"right of obstacle #{num}")

        if left is None and right is None:
            raise fail(f"the obstacle blocks the tube: neither side passage is valid "
                       f"(left: {why_l}; right: {why_r})")

        if left is not None and right is not None:
            x_apex = xA
            tri = Triangle(i, p_o, R, h, alpha, p_oth, p_otu, p_otd, None, alpha)
            sides = [(left, f"the tube left of obstacle #{num}"),
                     (right, f"the tube right of obstacle #{num}")]
        else:
            # Remark 5: drop the invalid side; keep the passage-side tangent of O' at angle β.
            dropped: Literal["left", "right"] = "right" if right is None else "left"
            kept_side = "left" if dropped == "right" else "right"
            s = 1.0 if dropped == "right" else -1.0  # +1: the left passage is kept
            leg_a, leg_t = (Q.p_r0, Q.t_r) if dropped == "right" else (Q.p_h0, Q.t_h)
            target = xs_a + 2.0 * params.r_a + 1e-6  # + 1 µm: before_k longer than 2 r_a

            def apex(b: float) -> tuple[float, np.ndarray | None]:
                """ξ of (tangent of O' at angle b to n_c) ∩ (dropped side's leg line);
                −inf when the wedge between the two lines does not open downstream."""
                nk = -(math.sin(b) * n_c + s * math.cos(b) * m)
                den = float(nk @ leg_t)
                if den >= -1e-12:
                    return -math.inf, None
                pt = leg_a + leg_t * ((R - float(nk @ (leg_a - p_o))) / den)
                return self.xi(pt), pt

            beta = alpha
            x_apex, p_apex = apex(alpha)
            if x_apex < target:
                x_hi = apex(self.a_max)[0] if self.a_max > alpha else -math.inf
                if x_hi < target:
                    raise fail(
                        f"Remark 5 (the {dropped} side tube is dropped: "
                        f"{why_r if dropped == 'right' else why_l}): the apex cannot be "
                        f"placed: even with β = α_max = {_num(math.degrees(self.a_max), 2)}° "
                        f"the apex is at ξ = {_num(x_hi)} < ξ_s + 2 r_a = {_num(target)}"
                    )
                lo_b, hi_b = alpha, self.a_max  # bisection: smallest β with apex ξ ≥ target
                for _ in range(60):
                    mid_b = 0.5 * (lo_b + hi_b)
                    if apex(mid_b)[0] >= target:
                        hi_b = mid_b
                    else:
                        lo_b = mid_b
                beta = hi_b
                x_apex, p_apex = apex(beta)
            if p_apex is None or not x_apex < xB:
                raise fail(f"Remark 5: the modified triangle is degenerate (apex ξ = "
                           f"{_num(x_apex)} is not upstream of the base ξ_B = {_num(xB)})")
            nk = -(math.sin(beta) * n_c + s * math.cos(beta) * m)
            tp = p_o + R * nk  # tangent point on O'
            d = math.cos(beta) * n_c - s * math.sin(beta) * m  # downstream direction
            p_base = tp + d * ((xB - self.xi(tp)) / math.cos(beta))
            if dropped == "right":
                pts = (lh(x_apex), hB, p_apex, p_base)
                gaps = (float(m @ (p_base - hB)), float(m @ (p_apex - lh(x_apex))))
                tri = Triangle(i, p_o, R, h, alpha, p_apex, p_base, rB, "right", beta)
            else:
                pts = (p_apex, p_base, lr(x_apex), rB)
                gaps = (float(m @ (rB - p_base)), float(m @ (lr(x_apex) - p_apex)))
                tri = Triangle(i, p_o, R, h, alpha, p_apex, hB, p_base, "left", beta)
            kept, why_k = self.side_tube(pts, gaps, kept_side, f"{kept_side} of obstacle #{num}")
            if kept is None:
                raise fail(f"Remark 5 (the {dropped} side tube is dropped): the modified "
                           f"{kept_side} side tube is not valid: {why_k}")
            sides = [(kept, f"the tube {kept_side} of obstacle #{num}")]

        before = Trapezoid(Q.p_h0, lh(x_apex), Q.p_r0, lr(x_apex), name=f"before #{num}")
        after = Trapezoid(hB, Q.p_h1, rB, Q.p_r1, name=f"after #{num}")
        new = [SubTubeNode(before, par.xs, x_apex, f"the tube before obstacle #{num}", i)]
        new += [SubTubeNode(t, x_apex, xB, origin, i) for t, origin in sides]
        new.append(SubTubeNode(after, xB, par.xe, f"the tube after obstacle #{num}", i))
        nodes[k_par:k_par + 1] = new
        self.triangles[i] = tri
