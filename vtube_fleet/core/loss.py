"""Re-partitioning the tube around lost (stopped) vehicles (docs/fleet.md, "Losing a vehicle").

A vehicle that stops flying the controller inside the tube is an obstacle: a disc of radius
r_lost at its last known position, extended by r_s like any other (ExtObstacle).
:func:`partition_around_lost` partitions the tube around the configured obstacles and those
discs, trying in order:

1. **as given** — the configured obstacles with the apex distances they are flown with, each
   lost disc with its own (the fleet: 1.05 h_min, (pothk));
2. **planned** — the lost discs' h_k chosen by the planner (``"auto"``, :mod:`~vtube_fleet.core.
   plan`), the configured obstacles unchanged;
   A partition of steps 1-2 with a sub-tube too narrow for one robot (a warning of the
   construction, docs/paper.md) is kept only if the fallback finds nothing better;
3. **grouped** — the fallback (:func:`_grouped`). Steps 1-2 fail when a lost disc is too close
   to another obstacle (their triangles overlap in ξ, so neither fits in one parent sub-tube,
   or the tube between them is not longer than 2 r_a), too close to the start base (no room
   for its apex and a tube before it longer than 2 r_a) or too close to the finishing line:

   * **one circle**: the lost disc and the obstacles (configured or lost) nearest to it are
     replaced by the incircle of the smallest isosceles triangle with its axis along n_c and
     half apex angle α ≤ α_max that contains all their extended discs
     (:func:`group_obstacle`). That triangle is the circle's circumscribed triangle I_k of
     partition §2 with h = R_in / sin α ≥ h_min (pothk): the paper's construction, unchanged.
     Groups grow by single linkage on the gap between extended discs, one level at a time
     (level 0: every lost disc alone; at most :data:`MAX_LEVELS`);
   * **its width**: the same triangle clipped to the lateral extent of the discs
     (:class:`ClippedTriangle`: each side at α until it reaches the strip the discs span,
     then parallel to n_c), when both parts of a side are longer than 2 r_a. A side is then
     two sub trapezoid tubes (narrowing at α, then parallel), and a group that is long along
     n_c (a vehicle lost beside another obstacle) no longer closes the passage beside it;
   * **one passage**: if no shape keeps both passages, the triangle's far side is put on T's
     leg (Remark 5's one-sided triangle: ``passage="left"``/``"right"``);
   * **extension**: when an apex or a base leaves less than 2 r_a to T's start base or
     finishing line, the construction runs in T extended along its own legs beyond that base
     (:func:`extended_tube`); the sub-tubes that touch it are longer than 2 r_a as
     Assumption 3' asks, and inside T their legs, hence every command, are the same. The
     vehicles fly only inside T and exit at T's finishing line (TraCondition).

   At each level the shapes with both passages are tried first, each with the steepest
   sides that build (half apex angles :data:`ALPHA_FACTORS`, from α_max down); of those, the
   one with the smallest area inside T taken from the vehicles wins (ties: the larger
   Assumption-3' margin); the one-sided shapes only when neither builds.

**The guarantee.** The partition treats every obstacle as a circle inside its circumscribed
triangle; a group's circle is such an obstacle. Every sub-tube is built and checked by the
construction's own tests (Assumption 3' strictly, room for one robot, Constraint 3: every
narrowing side at α ≤ α_max; a clipped side turns parallel to n_c, so a vehicle crossing
the kink is farther from its new leg than from the old one, Assumption 1 holds on). Each
candidate is certified before it is accepted: no extended disc O' — of the configured
obstacles and of every lost vehicle, whatever was merged — meets a sub-tube inside T. So a
robot centre inside its sub-tube is outside every O' (Theorem 2's argument).

**Who can use it.** :func:`wall_clearance` and :func:`cannot_pass`: a vehicle whose centre
is inside a new triangle has no sub-tube it is inside of, so none can be given to it safely;
the runtime holds only those.

**A partition of its own** (:func:`partition_past`): such a vehicle may have passed some of
the obstacles already (their O' entirely behind it along n_c). When it always advances
along n_c (:func:`moves_forward`: n_cᵀ v_c ≥ v cos α_max − v'_max, more than the estimate
compensation's residual D), it never comes back to them, so they need no triangle in *its*
partition: the re-partition around the others often leaves it outside every region (a
vehicle following the lost one past an obstacle).
Obstacle safety is per vehicle (it keeps out of every O' it can still reach through its own
sub-tube) and the pair barrier is partition-free, so the others keep the common partition.

**Stepping aside** (:func:`step_aside`): a vehicle that cannot pass waits where it is (the
runtime stops it: an obstacle for the others). Once nobody else flies the tube, it is
released: a multicopter at rest can move sideways, across n_c, or back, which no command of
the controller does (its speed never drops below v_min). The shortest path — straight back
along the tube (often no distance at all), then straight across it — to a point inside a
sub-tube of the partition without it, that keeps out of every O' and r_s inside the tube's
legs, is where it goes before it flies the controller again from there.

Everything here is deterministic and independent of where the other vehicles are, so every
agent that sees the same lost discs builds the same partition. Pure numpy.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.partition import (
    DEFAULT_APEX_FACTOR,
    ApexZone,
    Partition,
    PartitionBuilder,
    PartitionError,
    SubTubeNode,
    Triangle,
    _area,
    _clip,
    _dist_to_polygon,
    alpha_max,
    apex_lookahead,
    h_min,
    partition,
)
from vtube_fleet.core.plan import tube_margins
from vtube_fleet.core.text import compact_number as _num
from vtube_fleet.core.text import obstacle_label, point_text
from vtube_fleet.core.tube import APEX_AUTO, GeometryError, Obstacle, Trapezoid

__all__ = [
    "ALPHA_FACTORS",
    "MAX_LEVELS",
    "ClippedTriangle",
    "Grouping",
    "Repartition",
    "cannot_pass",
    "extended_tube",
    "group_obstacle",
    "left_out",
    "moves_forward",
    "partition_around_lost",
    "partition_past",
    "passed",
    "repartition_around_lost",
    "step_aside",
    "wall_clearance",
]

#: The half apex angles a group's (or a lost disc's) triangle is tried with in the fallback:
#: sin α = sin α_max / f (f = 1: α_max, the shortest triangle allowed by (pothk)).
ALPHA_FACTORS = (1.0, 1.05, 1.15, 1.3, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0)
#: The shapes tried at each merge level, (passage, clipped) (:func:`group_obstacle`,
#: :class:`ClippedTriangle`): both passages first (they leave the vehicles beside the lost one
#: their sides); only if neither builds, the one-sided ones (they take one whole side of the
#: tube from the apex to the base).
_TIERS: tuple[tuple[tuple[str, bool], ...], ...] = (
    (("both", True), ("both", False)),
    (("left", True), ("right", True), ("left", False), ("right", False)),
)
#: At most this many merge levels of the fallback (the first: every lost disc on its own).
MAX_LEVELS = 6

_DISC_TOL = 1e-6  # m: a sub-tube may touch an O' (tangent sides), not enter it
_EXT_TOL = 1e-3  # m: extension beyond what 2 r_a needs
_MARGIN_TOL = 1e-9  # m: margins are computed in floats


@dataclass(frozen=True)
class Grouping:
    """How the fallback (step 3 of :func:`partition_around_lost`) built a partition:
    ``groups`` one tuple per merged circle, of the discs it holds (``("obstacle", i)`` a
    configured obstacle, ``("lost", j)`` a lost disc), ``alpha`` the half apex angle (rad),
    ``passage`` the side passages kept (:func:`group_obstacle`), ``clipped``: the
    triangle is clipped to the discs' width (:class:`ClippedTriangle`), ``extension_m``
    (upstream, downstream) how far the tube was extended for the construction, ``margin_m``
    the smallest Assumption-3' margin of the sub-tubes."""

    groups: tuple[tuple[tuple[str, int], ...], ...]
    alpha: float
    passage: str
    clipped: bool
    extension_m: tuple[float, float]
    margin_m: float

    def describe(self) -> str:
        parts = []
        for g in self.groups:
            names = [f"obstacle #{i + 1}" if kind == "obstacle" else f"lost #{i + 1}"
                     for kind, i in g]
            parts.append(" + ".join(names) if len(names) > 1 else names[0])
        ext = ""
        if any(self.extension_m):
            ext = (f"; tube extended {_num(self.extension_m[0])} m upstream, "
                   f"{_num(self.extension_m[1])} m downstream for the construction")
        side = "" if self.passage == "both" else f", only the {self.passage} passage"
        side += ", clipped to the discs' width" if self.clipped else ""
        return (f"grouped: {', '.join(parts)} in one circle{'s' if len(parts) > 1 else ''} (α = "
                f"{_num(math.degrees(self.alpha), 2)}°{side}); smallest margin "
                f"{_num(self.margin_m)} m{ext}")


# ----------------------------------------------------------------------------------------------
# geometry
# ----------------------------------------------------------------------------------------------
def group_obstacle(tube: Trapezoid, centers: np.ndarray, radii_ext: np.ndarray, alpha: float,
                   r_s: float, passage: str = "both") -> Obstacle:
    """The circle whose circumscribed triangle (partition §2, half apex angle ``alpha``)
    contains the discs ``centers`` (N, 2) of radii ``radii_ext`` (N,) (extended radii
    r_o + r_s), as an obstacle of radius R_in − r_s with apex distance h = R_in / sin α.

    In the frame ξ = n_cᵀ(x − p_h0), w = mᵀ(x − p_h0) (m from the left leg to the right one)
    a disc is inside the left side iff ξ_j sin α + w_j cos α − R_j ≥ q and inside the right
    side iff ξ_j sin α − w_j cos α − R_j ≥ p, with q = ξ_A sin α + w_c cos α and
    p = ξ_A sin α − w_c cos α for the apex (ξ_A, w_c); the base is ξ_B = max_j(ξ_j + R_j).

    * ``passage="both"``: the smallest such triangle: q = Q = min_j(ξ_j sin α + w_j cos α −
      R_j), p = P (likewise), so ξ_A = (P + Q) / (2 sin α), w_c = (Q − P) / (2 cos α);
    * ``"left"``: only the passage left of it is kept: the left side is the tight one
      (q = Q) and the apex lies on it just beyond T's right leg, so the right side crosses
      that leg and the construction drops the right side tube (Remark 5): the triangle flown
      is the left side, the right leg and the base; ``"right"`` mirrors it.

    The incircle of the triangle (apex ξ_A, base ξ_B, H = ξ_B − ξ_A) has R_in = H sin α /
    (1 + sin α) and its centre at ξ_A + h, h = H / (1 + sin α). With ``"both"`` one disc
    gives itself back, with h = R / sin α.
    """
    c = np.asarray(centers, dtype=float).reshape(-1, 2)
    R = np.asarray(radii_ext, dtype=float).reshape(-1)
    n_c, m = tube.n_c, tube.m
    xi = (c - tube.p_h0) @ n_c
    w = (c - tube.p_h0) @ m
    sa, ca = math.sin(alpha), math.cos(alpha)
    P = float(np.min(xi * sa - w * ca - R))
    Q = float(np.min(xi * sa + w * ca - R))
    xi_b = float(np.max(xi + R))
    if passage == "both":
        if len(R) == 1:  # exactly the disc (no rounding drift)
            return Obstacle(center=c[0], radius=max(float(R[0]) - r_s, 1e-9),
                            apex_distance=float(R[0]) / sa)
        xi_a = (P + Q) / (2.0 * sa)
        w_c = (Q - P) / (2.0 * ca)
    elif passage in ("left", "right"):
        # the kept side: normal n (into the triangle) and offset, in (ξ, w)
        sgn = 1.0 if passage == "left" else -1.0
        off = Q if passage == "left" else P
        nrm = sa * n_c + sgn * ca * m  # nᵀ(x − p_h0) = off on the kept side
        leg_a, leg_t = (tube.p_r0, tube.t_r) if passage == "left" else (tube.p_h0, tube.t_h)
        den = float(nrm @ leg_t)
        if abs(den) < 1e-12:
            raise GeometryError("the kept side is parallel to the leg")
        at = leg_a + leg_t * ((off - float(nrm @ (leg_a - tube.p_h0))) / den)
        # upstream along the kept side, 1 % of the triangle's length beyond the leg
        up = -(ca * n_c - sgn * sa * m)
        at = at + up * (0.01 * max(1.0, xi_b - float((at - tube.p_h0) @ n_c)))
        xi_a = float((at - tube.p_h0) @ n_c)
        w_c = float((at - tube.p_h0) @ m)
    else:
        raise ValueError(f"passage must be 'both', 'left' or 'right', got {passage!r}")
    H = xi_b - xi_a
    if not H > 0.0:
        raise GeometryError("the triangle's apex is not upstream of its base")
    R_in = H * sa / (1.0 + sa)
    h = H / (1.0 + sa)
    center = tube.p_h0 + (xi_a + h) * n_c + w_c * m
    return Obstacle(center=center, radius=max(R_in - r_s, 1e-9), apex_distance=h)


def extended_tube(tube: Trapezoid, upstream_m: float, downstream_m: float) -> Trapezoid:
    """``tube`` with its start base moved ``upstream_m`` upstream and its finishing line
    ``downstream_m`` downstream, along its own legs (the same leg lines: inside ``tube`` every
    sub-tube built in the extended one has the same legs). Raises
    :class:`~vtube_fleet.core.tube.GeometryError` if the legs would cross."""
    if upstream_m == 0.0 and downstream_m == 0.0:
        return tube
    L = tube.length
    lh, lr = tube.lh, tube.lr
    return Trapezoid(lh(-upstream_m), lh(L + downstream_m), lr(-upstream_m),
                     lr(L + downstream_m), name=tube.name)


def _apex_and_base(tube: Trapezoid, ob: Obstacle, params: ControllerParams
                   ) -> tuple[float, float]:
    """ξ of the apex and the base of an obstacle's isosceles triangle (partition §2)."""
    R = float(ob.radius) + params.r_s
    h = (float(ob.apex_distance) if isinstance(ob.apex_distance, (int, float))
         else DEFAULT_APEX_FACTOR * h_min(float(ob.radius), params))
    x = float(tube.xi(ob.center))
    return x - h, x + R


def _clear_of_discs(part: Partition, tube: Trapezoid, centers: np.ndarray,
                    radii_ext: np.ndarray) -> str:
    """"" if no disc meets a sub-tube inside ``tube``, else which one does."""
    halves = [(tube.n_h, float(tube.n_h @ tube.p_h1)), (tube.n_r, float(tube.n_r @ tube.p_r1)),
              (tube.n_c, float(tube.n_c @ tube.p_h0)),
              (-tube.n_c, -float(tube.n_c @ tube.p_r1))]
    for t in part.sub_tubes:
        poly = t.polygon()
        for nrm, off in halves:
            poly = _clip(poly, nrm, off)
        if len(poly) < 3:
            continue
        sub = Trapezoid(t.p_h0, t.p_h1, t.p_r0, t.p_r1)
        for c, R in zip(centers, radii_ext, strict=True):
            inside = bool(sub.contains(c)) and bool(tube.contains(c))
            d = 0.0 if inside else _dist_to_polygon(c, poly)
            if d < R - _DISC_TOL:
                return (f"the disc at {point_text(c)} (radius {_num(float(R))} m) meets "
                        f"{t.name} ({_num(float(R) - d)} m inside)")
    return ""


def _footprint(part: Partition, tube: Trapezoid, n_obstacles: int) -> float:
    """Area (m²) inside ``tube`` of the triangles that are not a configured obstacle's own
    (the lost discs' and the groups'): where nobody may fly any more."""
    halves = [(tube.n_h, float(tube.n_h @ tube.p_h1)), (tube.n_r, float(tube.n_r @ tube.p_r1)),
              (tube.n_c, float(tube.n_c @ tube.p_h0)),
              (-tube.n_c, -float(tube.n_c @ tube.p_r1))]
    total = 0.0
    for t in part.triangles:
        if t.obstacle < n_obstacles:
            continue
        poly = t.polygon()
        for nrm, off in halves:
            poly = _clip(poly, nrm, off)
        total += _area(poly)
    return total


def _smallest_margin(part: Partition, params: ControllerParams) -> float:
    return min(v for t in part.sub_tubes
               for _, v in tube_margins(t, params.k_t, params.r_a, params.r_s))


# ----------------------------------------------------------------------------------------------
# the re-partition
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Repartition:
    """What :func:`repartition_around_lost` built: the ``partition``, the ``step`` that built
    it (``"as given"``, ``"planned"`` or ``"grouped"``: module docstring) and, for
    ``"grouped"``, the :class:`Grouping`."""

    partition: Partition
    step: str
    grouping: Grouping | None = None

    def describe(self) -> str:
        return self.grouping.describe() if self.grouping is not None else self.step


def partition_around_lost(tube: Trapezoid, obstacles: Sequence[Obstacle],
                          lost: Sequence[Obstacle], params: ControllerParams) -> Partition:
    """The partition of ``tube`` around the configured ``obstacles`` (with the apex distances
    they are flown with) and the ``lost`` discs (obstacles of radius r_lost; their apex
    distances are the first choice only), under the flown ``params``: steps 1-3 of the module
    docstring, the first that builds (:func:`repartition_around_lost`, which also says how).

    Raises :class:`~vtube_fleet.core.partition.PartitionError` with the reason of step 2 and
    what the fallback tried when nothing builds. Deterministic; pure."""
    return repartition_around_lost(tube, obstacles, lost, params).partition


def repartition_around_lost(tube: Trapezoid, obstacles: Sequence[Obstacle],
                            lost: Sequence[Obstacle], params: ControllerParams) -> Repartition:
    """:func:`partition_around_lost` with the step that built it.

    The triangles of a grouped partition are numbered so that configured obstacle i keeps
    ``i`` and lost disc j is ``len(obstacles) + j`` (as in steps 1-2); the circle of the g-th
    group is ``len(obstacles) + len(lost) + g``, and a merged obstacle has no triangle of its
    own."""
    obstacles, lost = tuple(obstacles), tuple(lost)
    if not lost:
        return Repartition(partition(tube, obstacles, params), "as given")
    floor = _floor(tube, obstacles, params)
    narrow: Repartition | None = None  # a partition of steps 1-2 with a passage too narrow
    err: PartitionError | None = None
    tries = [(lost, "as given")]
    if any(not isinstance(o.apex_distance, str) for o in lost):
        tries.append((tuple(dataclasses.replace(o, apex_distance=APEX_AUTO) for o in lost),
                      "planned"))
    for discs, step in tries:
        try:
            part = partition(tube, obstacles + discs, params)
        except PartitionError as e:
            err = e
            continue
        if _smallest_margin(part, params) >= floor - _MARGIN_TOL:
            return Repartition(part, step)
        narrow = narrow or Repartition(part, step)
    got, tried = _grouped(tube, obstacles, lost, params, floor)
    if got is not None:
        return got
    if narrow is not None:  # (as before the fallback existed: the warnings say why)
        return narrow
    assert err is not None
    s = str(err)
    where = s[: len(s) - len(err.reason) - 2] if s.endswith(": " + err.reason) else ""
    raise PartitionError(
        err.obstacle,
        f"{err.reason}; nor with the fallback (the lost vehicle(s) and the obstacles nearest "
        f"to them in one circle: {tried} partitions tried)", where)


def moves_forward(params: ControllerParams, residual_m_s: float = 0.0) -> bool:
    """Whether a vehicle flying the tube controller always advances along n_c:
    ‖u1''‖ = v at most α_max from n_c (Constraint 3: every narrowing leg, and u1'' turns
    between n_c and a leg's direction), the saturated rest ≤ v'_max (paper note 9), so
    n_cᵀ v_c ≥ v cos α_max − v'_max; the vehicle's (estimated) velocity differs from v_c by the
    estimate compensation's residual, at most ``residual_m_s`` (the budget's D). True when
    v cos α_max − v'_max > D: then ξ only grows along its path."""
    return (float(params.v) * math.cos(alpha_max(params))
            > float(params.v_max_prime) + float(residual_m_s))


def passed(tube: Trapezoid, obstacles: Sequence[Obstacle], params: ControllerParams,
           p: np.ndarray) -> np.ndarray:
    """(K,) bool: the obstacles whose extended disc O' (r_o + r_s) lies entirely behind the
    point ``p`` along ``tube``'s n_c: ξ(p_o) + r_o + r_s < ξ(p). With the flown r_s' (the
    safety budget: r_s plus the estimate and lag terms δ) a vehicle's true centre is then past
    r_o + r_s of it too."""
    if not len(obstacles):
        return np.zeros(0, bool)
    c = np.array([o.center for o in obstacles], dtype=float).reshape(-1, 2)
    R = np.array([float(o.radius) for o in obstacles]) + float(params.r_s)
    xi_p = float((np.asarray(p, dtype=float).reshape(2) - tube.p_h0) @ tube.n_c)
    return (c - tube.p_h0) @ tube.n_c + R < xi_p


def left_out(tube: Trapezoid, obstacles: Sequence[Obstacle], params: ControllerParams,
             p: np.ndarray, *, residual_m_s: float = 0.0, keep: np.ndarray | None = None
             ) -> np.ndarray:
    """(K,) bool: what a partition of its own for a vehicle at ``p`` leaves out
    (:func:`partition_past`): the obstacles it has :func:`passed`, except those in ``keep``;
    none when it may move backwards (:func:`moves_forward` with ``residual_m_s``)."""
    if not moves_forward(params, residual_m_s):
        return np.zeros(len(obstacles), bool)
    gone = passed(tube, obstacles, params, p)
    if keep is not None:
        gone &= ~np.asarray(keep, dtype=bool).reshape(-1)
    return gone


def partition_past(tube: Trapezoid, obstacles: Sequence[Obstacle], lost: Sequence[Obstacle],
                   params: ControllerParams, p: np.ndarray, *, residual_m_s: float = 0.0,
                   keep: np.ndarray | None = None) -> Partition | None:
    """The partition of ``tube`` for one vehicle at ``p`` (module docstring, "a partition of
    its own"): :func:`repartition_around_lost` around the configured ``obstacles`` and the
    ``lost`` discs it has not :func:`passed`, numbered as the full re-partition numbers them
    (configured i keeps i, lost j is len(obstacles) + j, the g-th group's circle after all).
    ``keep`` (len(obstacles) + len(lost),) bool: never left out (a route's caller: those
    that also meet a later segment). None when it passed none of the others or when it may
    move backwards (:func:`moves_forward` with the residual ``residual_m_s``): it has
    nothing of its own. Raises :class:`~vtube_fleet.core.partition.PartitionError` when the
    rest cannot be partitioned. Pure."""
    obstacles, lost = tuple(obstacles), tuple(lost)
    gone = left_out(tube, obstacles + lost, params, p, residual_m_s=residual_m_s, keep=keep)
    if not gone.any():
        return None
    n_o, n_l = len(obstacles), len(lost)
    keep_o = [i for i in range(n_o) if not gone[i]]
    keep_l = [j for j in range(n_l) if not gone[n_o + j]]
    rp = repartition_around_lost(tube, [obstacles[i] for i in keep_o],
                                 [lost[j] for j in keep_l], params)
    k_o, k_l = len(keep_o), len(keep_l)
    index = [*keep_o, *(n_o + j for j in keep_l)]

    def renumber(k: int) -> int:
        return index[k] if k < k_o + k_l else n_o + n_l + (k - k_o - k_l)

    part = rp.partition
    tris = tuple(sorted((dataclasses.replace(t, obstacle=renumber(t.obstacle))
                         for t in part.triangles), key=lambda t: t.obstacle))
    return dataclasses.replace(part, triangles=tris)


def _levels(centers: np.ndarray, radii: np.ndarray, is_lost: np.ndarray
            ) -> list[list[list[int]]]:
    """The merge levels of the fallback: level 0 every disc on its own, then single linkage
    on the gap ‖c_a − c_b‖ − R_a − R_b over pairs with a lost disc, one distinct gap at a
    time; per level the groups (sorted disc indices) that hold a lost disc."""
    n = len(radii)
    gaps = []
    for a in range(n):
        for b in range(a + 1, n):
            if is_lost[a] or is_lost[b]:
                g = float(np.hypot(*(centers[a] - centers[b]))) - radii[a] - radii[b]
                gaps.append((round(g, 9), a, b))
    gaps.sort()
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def groups() -> list[list[int]]:
        by: dict[int, list[int]] = {}
        for i in range(n):
            by.setdefault(root(i), []).append(i)
        return sorted((g for g in by.values() if any(is_lost[i] for i in g)),
                      key=lambda g: g[0])

    out = [groups()]
    k = 0
    while k < len(gaps) and len(out) < MAX_LEVELS:
        level = gaps[k][0]
        changed = False
        while k < len(gaps) and gaps[k][0] == level:
            _, a, b = gaps[k]
            ra, rb = root(a), root(b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
                changed = True
            k += 1
        if changed:
            out.append(groups())
    return out


def _floor(tube: Trapezoid, obstacles: tuple[Obstacle, ...], params: ControllerParams
           ) -> float:
    """The smallest Assumption-3' margin a re-partition must keep: 0 (every sub-tube valid
    and room for one robot at its bases), or less if the configured obstacles alone leave
    less (the mission was accepted with it)."""
    try:
        return min(0.0, _smallest_margin(partition(tube, obstacles, params), params))
    except PartitionError:
        return 0.0


def _grouped(tube: Trapezoid, obstacles: tuple[Obstacle, ...], lost: tuple[Obstacle, ...],
             params: ControllerParams, floor: float) -> tuple[Repartition | None, int]:
    """Step 3 (module docstring) → (the partition, or None; how many were tried)."""
    n_o = len(obstacles)
    allobs = obstacles + lost
    centers = np.array([o.center for o in allobs], dtype=float).reshape(-1, 2)
    radii = np.array([float(o.radius) + params.r_s for o in allobs])
    is_lost = np.arange(len(allobs)) >= n_o
    a_max = alpha_max(params)
    tried = 0
    for groups, tier in itertools.product(_levels(centers, radii, is_lost), _TIERS):
        in_group = {i for g in groups for i in g}
        fixed = [i for i in range(n_o) if i not in in_group]
        index = fixed + [len(allobs) + k if len(g) > 1 else g[0] for k, g in enumerate(groups)]
        best: tuple[tuple[float, float], Repartition] | None = None
        for shape, clipped in tier:
            for f in ALPHA_FACTORS:  # the steepest sides that build (the smallest triangle)
                alpha = math.asin(min(1.0, math.sin(a_max) / f))
                if clipped and not _can_clip(groups, radii, alpha, params):
                    continue
                tried += 1
                got = _candidate(tube, obstacles, fixed, index, centers, radii, groups,
                                 alpha, shape, clipped, params, floor)
                if got is None:
                    continue
                part, alpha, ext, margin = got
                cost = (_footprint(part, tube, n_o), -margin)
                if best is None or cost < best[0]:
                    names = tuple(tuple(("lost", i - n_o) if is_lost[i] else ("obstacle", i)
                                        for i in g) for g in groups)
                    best = (cost, Repartition(part, "grouped", Grouping(
                        names, alpha, shape, clipped, ext, margin)))
                break
        if best is not None:
            return best[1], tried
    return None, tried


def _can_clip(groups: list[list[int]], radii: np.ndarray, alpha: float,
              params: ControllerParams) -> bool:
    """Whether some group's triangle may have a side long enough to clip: a single disc's
    side reaches the disc's width R + h(1 − cos α) before the base (h = R / sin α), and both
    parts must be longer than 2 r_a; a group of several discs is tried."""
    need = 2.0 * params.r_a
    for g in groups:
        if len(g) > 1:
            return True
        R = float(radii[g[0]])
        if R + R / math.sin(alpha) * (1.0 - math.cos(alpha)) > need:
            return True
    return False


def _candidate(tube: Trapezoid, obstacles: tuple[Obstacle, ...], fixed: list[int],
               index: list[int], centers: np.ndarray, radii: np.ndarray,
               groups: list[list[int]], alpha: float, shape: str, clipped: bool,
               params: ControllerParams, floor: float
               ) -> tuple[Partition, float, tuple[float, float], float] | None:
    """One candidate of step 3: the groups as circles (or clipped triangles) of half apex
    angle ``alpha`` and passage ``shape``, the fixed obstacles as they are, in T or, if that
    fails, in T extended (:func:`_extensions`); certified (no O' meets a sub-tube) and with
    a smallest margin ≥ ``floor``. → (partition of T, α, extension, margin) or None."""
    try:
        circles = [group_obstacle(tube, centers[g], radii[g], alpha, params.r_s, shape)
                   for g in groups]
    except GeometryError:
        return None
    obs = [obstacles[i] for i in fixed] + circles
    for ext in _extensions(tube, obs, params):
        try:
            t_ext = extended_tube(tube, *ext)
            if clipped:
                part = _clipped_partition(t_ext, obs, len(fixed), [
                    (centers[g], radii[g]) for g in groups], alpha, shape, params)
            else:
                part = partition(t_ext, obs, params)
        except (PartitionError, GeometryError):
            continue
        part = _in_tube(part, tube, ext[0], index)
        if _clear_of_discs(part, tube, centers, radii):
            continue
        margin = _smallest_margin(part, params)
        if margin >= floor - _MARGIN_TOL:
            return part, alpha, ext, margin
    return None


def _extensions(tube: Trapezoid, obs: Sequence[Obstacle], params: ControllerParams
                ) -> list[tuple[float, float]]:
    """(0, 0), then, if a triangle leaves less than 2 r_a to the start base or the finishing
    line, the extension (upstream, downstream) that gives it 2 r_a."""
    if not obs:
        return [(0.0, 0.0)]
    ends = [_apex_and_base(tube, o, params) for o in obs]
    need = 2.0 * params.r_a + _EXT_TOL
    up = max(0.0, need - min(a for a, _ in ends))
    down = max(0.0, need - (tube.length - max(b for _, b in ends)))
    return [(0.0, 0.0)] + ([(up, down)] if up > 0.0 or down > 0.0 else [])


def _in_tube(part: Partition, tube: Trapezoid, upstream_m: float, index: Sequence[int]
             ) -> Partition:
    """A partition built in the extended tube (``upstream_m``) as a partition of ``tube``:
    ξ measured from ``tube``'s start base; triangles renumbered by ``index``."""
    tris = sorted((dataclasses.replace(t, obstacle=int(index[t.obstacle]))
                   for t in part.triangles), key=lambda t: t.obstacle)
    return Partition(tube, part.sub_tubes, part.xi_start - upstream_m,
                     part.xi_end - upstream_m, tuple(tris), part.warnings)


# ----------------------------------------------------------------------------------------------
# the circumscribed triangle clipped to the group's width
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ClippedTriangle(Triangle):
    """A group's circumscribed triangle clipped to the lateral extent of its discs: the sides
    at α from the apex (tangent to the discs, (pothk)) until they reach the strip
    w_L ≤ w ≤ w_R that the discs span, then walls parallel to n_c to the base (a kinked side:
    two sub-tubes, the first narrowing at α ≤ α_max, the second with parallel legs).

    ``p_oth`` the apex, ``p_otu``/``p_otd`` the base corners (left/right), ``kinks`` (left,
    right) where a side turns parallel to n_c (``None``: that side is straight to the base, or
    is the parent's leg, ``remark5``). :meth:`polygon` is the whole region."""

    kinks: tuple[np.ndarray | None, np.ndarray | None] = (None, None)

    def polygon(self) -> np.ndarray:
        """Vertices (N, 2): apex, left kink, left base corner, right base corner, right kink."""
        kl, kr = self.kinks
        pts = [self.p_oth] + ([kl] if kl is not None else []) + [self.p_otu, self.p_otd] + (
            [kr] if kr is not None else [])
        return np.stack(pts)

    def contains(self, x: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Closed membership of points (..., 2) in the (convex) region, tolerance in metres."""
        x = np.asarray(x, dtype=float)
        poly = self.polygon()
        area2 = sum(_cross2(poly[k], poly[(k + 1) % len(poly)]) for k in range(len(poly)))
        sgn = 1.0 if area2 > 0 else -1.0
        ok = np.ones(x.shape[:-1], dtype=bool)
        for k in range(len(poly)):
            a, b = poly[k], poly[(k + 1) % len(poly)]
            e = b - a
            ne = float(np.hypot(*e))
            if ne < 1e-12:
                continue
            d = sgn * (e[0] * (x[..., 1] - a[1]) - e[1] * (x[..., 0] - a[0])) / ne
            ok &= d >= -tol
        return ok


def _cross2(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _clipped_partition(tube: Trapezoid, obs: Sequence[Obstacle], n_fixed: int,
                      groups: Sequence[tuple[np.ndarray, np.ndarray]], alpha: float,
                      passage: str, params: ControllerParams) -> Partition:
    """The partition of ``tube`` with each group of discs in a :class:`ClippedTriangle`
    (inserted first, into the main tube, upstream first), then the fixed obstacles
    ``obs[:n_fixed]`` split as usual (:class:`~vtube_fleet.core.partition.PartitionBuilder`);
    ``obs[n_fixed:]`` are the groups' circles (names and numbers in messages). Every sub-tube
    is checked by the construction's own final checks (Assumption 3', strict)."""
    b = PartitionBuilder(tube, list(obs), params, True)
    order = sorted(range(len(groups)), key=lambda g: float(tube.xi(obs[n_fixed + g].center)))
    for g in order:
        c, R = groups[g]
        _insert_clipped(b, n_fixed + g, c, R, alpha, passage)
    for i in b.order():
        if i < n_fixed:
            b.split(i)
    return b.finish()


def _insert_clipped(b: PartitionBuilder, k: int, centers: np.ndarray, radii: np.ndarray,
                    alpha: float, passage: str) -> None:
    """Split the sub-tube that holds circle ``k``'s centre around the clipped triangle of the
    discs (:class:`ClippedTriangle`); raises PartitionError when it does not fit or a
    sub-tube is degenerate."""
    where = obstacle_label(k, b.obstacles[k])

    def fail(reason: str) -> PartitionError:
        return PartitionError(k, reason, where)

    n_c, m = b.n_c, b.m
    sa, ca = math.sin(alpha), math.cos(alpha)
    s_j = centers @ n_c
    u_j = centers @ m
    Q = float(np.min(s_j * sa + u_j * ca - radii))  # left side: s sin α + u cos α = Q
    P = float(np.min(s_j * sa - u_j * ca - radii))  # right side: s sin α − u cos α = P
    u_lo, u_hi = float(np.min(u_j - radii)), float(np.max(u_j + radii))
    s_b = float(np.max(s_j + radii))

    def pt(s: float, u: float) -> np.ndarray:
        return s * n_c + u * m

    k_par = b.parent_index(k)
    par = b.nodes[k_par]
    T = par.tube
    xi0 = b.xi0

    def lh(z: float) -> np.ndarray:
        return b.on_line(T.p_h0, T.t_h, z)

    def lr(z: float) -> np.ndarray:
        return b.on_line(T.p_r0, T.t_r, z)

    def meet(off: float, sgn: float, leg: str) -> float:
        """ξ where the side s sin α + sgn·u cos α = off meets the parent's ``leg`` line."""
        def f(z: float) -> float:
            x = lr(z) if leg == "right" else lh(z)
            return float(n_c @ x) * sa + sgn * float(m @ x) * ca - off

        f0, f1 = f(0.0), f(1.0)
        if abs(f1 - f0) < 1e-12:
            raise fail("a side of the clipped triangle is parallel to the parent's leg")
        return -f0 / (f1 - f0)

    apex = pt((P + Q) / (2.0 * sa), (Q - P) / (2.0 * ca))
    dropped: Literal["left", "right"] | None = None
    if passage != "both":  # the apex on the other leg (Remark 5's one-sided triangle)
        dropped = "right" if passage == "left" else "left"
        off, sgn = (Q, 1.0) if passage == "left" else (P, -1.0)
        z = meet(off, sgn, dropped)
        apex = lr(z) if dropped == "right" else lh(z)
    z_a = float(n_c @ apex) - xi0
    z_b = s_b - xi0
    # the kept sides: where each turns parallel to n_c (None: straight to the base, when a
    # part would not be longer than 2 r_a, Assumption 3')
    need = 2.0 * b.params.r_a + _EXT_TOL
    sides = {}
    for side, off, sgn, u_wall in (("left", Q, 1.0, u_lo), ("right", P, -1.0, u_hi)):
        if passage not in ("both", side):
            continue
        z_k = (off - sgn * u_wall * ca) / sa - xi0
        if z_k - z_a > need and z_b - z_k > need:
            kink, base = pt(z_k + xi0, u_wall), pt(s_b, u_wall)
        else:
            kink, base = None, pt(s_b, sgn * (off - s_b * sa) / ca)
        sides[side] = (kink, base)
    if all(k is None for k, _ in sides.values()):
        raise fail("no side of the triangle is long enough to clip (2 r_a before and after "
                   "the kink)")
    xs_a = 0.0 if par.xs == -math.inf else par.xs
    xe_a = b.L if par.xe == math.inf else par.xe
    if not (xs_a < z_a and z_b < xe_a):
        raise fail(f"its clipped triangle (apex ξ_A = {_num(z_a)}, base ξ_B = {_num(z_b)}) "
                   f"does not fit in its parent sub-tube ({par.origin}, ξ from {_num(xs_a)} "
                   f"to {_num(xe_a)})")
    label = f"obstacle #{k + 1}"
    new = [SubTubeNode(Trapezoid(T.p_h0, lh(z_a), T.p_r0, lr(z_a), name=f"before #{k + 1}"),
                       par.xs, z_a, f"the tube before {label}", k)]
    corners = {}
    try:
        for side, (kink, base) in sides.items():
            z_k = z_b if kink is None else float(n_c @ kink) - xi0
            end = base if kink is None else kink
            if side == "left":
                front = Trapezoid(lh(z_a), lh(z_k), apex, end, name=f"left of #{k + 1}")
            else:
                front = Trapezoid(apex, end, lr(z_a), lr(z_k), name=f"right of #{k + 1}")
            new.append(SubTubeNode(front, z_a, z_k, f"the tube {side} of {label}", k))
            if kink is not None:
                if side == "left":
                    tail = Trapezoid(lh(z_k), lh(z_b), kink, base, name=f"left of #{k + 1}")
                else:
                    tail = Trapezoid(kink, base, lr(z_k), lr(z_b), name=f"right of #{k + 1}")
                new.append(SubTubeNode(tail, z_k, z_b, f"the tube {side} of {label} (tail)",
                                       k))
            corners[side] = (kink, base)
            gap = float(m @ (base - lh(z_b))) if side == "left" else float(m @ (lr(z_b) - base))
            if gap <= 0.0:
                raise fail(f"the {side} passage is closed at its base ({_num(-gap)} m)")
    except GeometryError as e:
        raise fail(f"a sub-tube of its clipped triangle is degenerate ({e})") from None
    new.append(SubTubeNode(Trapezoid(lh(z_b), T.p_h1, lr(z_b), T.p_r1, name=f"after #{k + 1}"),
                           z_b, par.xe, f"the tube after {label}", k))
    b.nodes[k_par:k_par + 1] = new
    kl, bl = corners.get("left", (None, lh(z_b)))
    kr, br = corners.get("right", (None, lr(z_b)))
    ob = b.obstacles[k]
    b.triangles[k] = ClippedTriangle(
        k, ob.center, float(ob.radius) + b.params.r_s, float(ob.apex_distance), alpha, apex,
        bl, br, dropped, alpha, kinks=(kl, kr))


# ----------------------------------------------------------------------------------------------
# who can use it
# ----------------------------------------------------------------------------------------------
def wall_clearance(part: Partition, positions: np.ndarray,
                   zones: Sequence[ApexZone] = ()) -> np.ndarray:
    """For points (M, 2): the signed distance (M,) to the nearer leg of the sub-tube the
    switching rule gives each (:meth:`Partition.locate`, with the apex look-ahead ``zones``
    as flown: :func:`~vtube_fleet.core.partition.apex_zones`): min(d_Th, d_Tr) of that
    sub-tube. Negative: the point is outside the sub-tube it is given, i.e. inside a triangle
    (or outside T); NaN for a NaN point."""
    p = np.asarray(positions, dtype=float).reshape(-1, 2)
    out = np.full(p.shape[0], np.nan)
    ok = np.all(np.isfinite(p), axis=1)
    if not ok.any():
        return out
    q = p[ok]
    k = np.asarray(part.locate(q)).reshape(-1)
    if zones:
        k = apex_lookahead(part, zones, q, k)
    d = np.empty(q.shape[0])
    for kk in np.unique(k):
        t = part.sub_tubes[int(kk)]
        sel = k == kk
        d[sel] = np.minimum(t.d_Th(q[sel]), t.d_Tr(q[sel]))
    out[ok] = d
    return out


def cannot_pass(part: Partition, positions: np.ndarray, zones: Sequence[ApexZone] = (),
                clearance_m: float = 0.0) -> np.ndarray:
    """Which vehicles (positions (M, 2), tube frame, those still flying the tube) cannot be
    given a safe sub-tube under ``part``: :func:`wall_clearance` < ``clearance_m`` (M,) bool.

    With the default 0 that is a vehicle whose centre is inside a triangle: every sub-tube it
    could be given has it beyond a leg, and the region it is in may hold an obstacle's O'.
    A vehicle outside every triangle but closer than r_s to the new triangle side is given its
    side tube: the saturated barrier pushes it off the side while the triangle keeps it clear
    of O' (paper note 7, as at every apex); ``clearance_m = r_s`` counts those too (Assumption
    1 to the letter). NaN positions are not counted."""
    d = wall_clearance(part, positions, zones)
    return np.asarray(d < clearance_m, dtype=bool)


# ----------------------------------------------------------------------------------------------
# stepping aside
# ----------------------------------------------------------------------------------------------
#: Step of the search along the path across n_c (m).
STEP_ASIDE_RES_M = 0.05
#: How far inside its sub-tube a vehicle stepping aside stops (m), beyond the region's side:
#: the estimate's jitter must not put it back inside.
STEP_ASIDE_CLEARANCE_M = 0.3
#: The steps (m) of how far back along the tube a vehicle stepping aside may go first, and at
#: most how far (m).
STEP_ASIDE_BACK_STEP_M = 0.5
STEP_ASIDE_MAX_BACK_M = 15.0


def step_aside(tube: Trapezoid, part: Partition, obstacles: Sequence[Obstacle],
               params: ControllerParams, p: np.ndarray, *, zones: Sequence[ApexZone] = (),
               clearance_m: float = STEP_ASIDE_CLEARANCE_M,
               res_m: float = STEP_ASIDE_RES_M,
               back_step_m: float = STEP_ASIDE_BACK_STEP_M,
               max_back_m: float = STEP_ASIDE_MAX_BACK_M
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """Where a vehicle at rest at ``p`` (2,) inside a region of ``part`` steps to (module
    docstring, "stepping aside"), as (via, q): straight back along −n_c from ``p`` to
    ``via`` = p − b·n_c (b a multiple of ``back_step_m`` up to ``max_back_m``, ξ ≥ 0;
    b = 0 first), then straight across n_c to q = via + s·n_⊥ (either side, ties to the
    left), such that :func:`wall_clearance` (q) ≥ ``clearance_m`` (inside a sub-tube) and
    every point of both legs of the path (sampled every ``res_m``) is outside every O'
    (‖x − p_o‖ > r_o + r_s of ``obstacles``) and at least r_s inside ``tube``'s legs (no
    closer than ``p`` already is, by its estimate). The straight line p → q of such a q
    (via = ``p``: no corner) counts too when every point of it is so: the shortest path,
    b + |s| or ‖q − p‖. (``p``, ``p``) when it is already there; None when there is none.
    A region's apex is upstream, so backing away is how a vehicle beside an obstacle that
    closes one passage reaches the other. Pure."""
    p = np.asarray(p, dtype=float).reshape(2)
    side = np.array([-tube.n_c[1], tube.n_c[0]])  # n_⊥, to the left of n_c
    r_s = float(params.r_s)
    c = (np.array([o.center for o in obstacles], dtype=float).reshape(-1, 2)
         if len(obstacles) else np.zeros((0, 2)))
    R = np.array([float(o.radius) for o in obstacles]) + r_s
    leg_min = min(r_s, float(min(tube.d_Th(p), tube.d_Tr(p))))
    R = np.minimum(R, np.hypot(p[0] - c[:, 0], p[1] - c[:, 1]) - 1e-9) if c.shape[0] else R

    def good(x: np.ndarray) -> int:
        """How many of the path's samples ``x`` (k, 2), from its start, are good."""
        ok = np.minimum(tube.d_Th(x), tube.d_Tr(x)) >= leg_min
        if c.shape[0]:
            d = np.hypot(x[:, None, 0] - c[None, :, 0], x[:, None, 1] - c[None, :, 1])
            ok &= (d > R[None, :]).all(axis=1)
        bad = np.flatnonzero(~ok)
        return int(bad[0]) if bad.size else int(x.shape[0])

    xi_p = float(tube.xi(p))
    b_all = np.arange(0.0, min(max_back_m, max(xi_p, 0.0)) + res_m, res_m)
    n_back = good(p - b_all[:, None] * tube.n_c)  # how far back the way is clear
    best: tuple[np.ndarray, np.ndarray] | None = None
    best_len = math.inf
    for b in np.arange(0.0, b_all[n_back - 1] + 1e-9 if n_back else -1.0, back_step_m):
        if b >= best_len:
            break
        via = p - b * tube.n_c
        reach = abs(float(tube.width(float(tube.xi(via))))) + 2.0 * r_s
        s = np.arange(0.0, reach + res_m, res_m)
        for sign in (1.0, -1.0):
            x = via + (sign * s)[:, None] * side
            n_ok = good(x)
            if not n_ok:
                continue
            there = wall_clearance(part, x[:n_ok], zones) >= clearance_m
            if there.any():
                k = int(np.flatnonzero(there)[0])
                q = x[k]
                if b + s[k] < best_len:
                    best, best_len = (via, q), float(b + s[k])
                if b > 0.0:  # the diagonal p → q: shorter, and no corner, when it is clear
                    direct = float(np.hypot(*(q - p)))
                    t = np.append(np.arange(0.0, direct, res_m), direct) / direct
                    if direct < best_len and good(p + t[:, None] * (q - p)) == t.size:
                        best, best_len = (p.copy(), q), direct
    return best
