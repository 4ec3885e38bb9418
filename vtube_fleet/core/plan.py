"""Planning the partition (Remark 6): the apex distances h_k chosen jointly.

An obstacle whose ``apex_distance`` is ``"auto"`` (:data:`~vtube_fleet.core.tube.APEX_AUTO`)
gets its h_k from :func:`plan_apex`, together with every other ``"auto"`` obstacle:

* **constraints** — (pothk) h_k ≥ h_min,k; the triangle fits in its parent sub-tube; both side
  tubes, or the one Remark 5 keeps, are valid; Assumption 3/3' for every sub-tube (L ∩ R = ∅,
  M ≠ ∅, length > 2 r_a, room for one safety disc); no ``keep_out`` point (the robots' start
  positions) inside a triangle. They are the construction's own tests
  (:func:`vtube_fleet.core.partition.partition`): the planner only chooses the numbers.
* **objective** — maximise the smallest *margin* (metres): over all sub-tubes, the margins to
  Assumption 3' (:func:`tube_margins`): for a tube with both L and R, min over the tube of
  max(d_Th, d_Tr) − k_t r_a (how much k_t r_a could grow before L ∩ R ≠ ∅); for M, max over
  the tube of min(d_Th, d_Tr) − k_t r_a; the length minus 2 r_a; each base width minus the
  width one safety disc needs; and over all triangles, the distance of the nearest start
  position minus r_s (a robot must start clear of its sub-tube's legs, Assumption 1), and for
  a start position inside an apex look-ahead zone (:func:`~vtube_fleet.core.partition.
  apex_zones`, the side tube it is flown in) max(its distance upstream of the zone, its
  distance to that side tube's legs − r_s) (:meth:`_Planner._lookahead_margin`). Ties
  (the smallest margin not moved by an obstacle's h) go to the larger sum over the obstacles
  of each one's own smallest margin (its sub-tubes and triangle), so every h_k is placed, not
  only the binding one. A plan that builds beats one that does not, one without start
  positions inside a triangle one with.
* **search** — h_k ∈ [h_min,k, min(H_MAX_FACTOR·h_min,k, ξ(p_o,k))]; coordinate ascent in the
  construction's order (farthest obstacle first): for each ``"auto"`` obstacle a grid of
  ``GRID`` values, then a golden-section refinement of the best cell, the others fixed; sweeps
  repeat until nothing changes (at most ``SWEEPS``). Each trial rebuilds the construction only
  from that obstacle on (the state before it is kept), and a split whose parent sub-tube and
  h are unchanged is reused. No randomness: the same input gives the same h_k, bit for bit.

Obstacles given a number (or ``None``, the default 1.3 h_min) keep it. Pure numpy.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vtube_fleet.core.partition import (
    DEFAULT_APEX_FACTOR,
    LOCATE_TOL,
    Partition,
    PartitionBuilder,
    PartitionError,
    SubTubeNode,
    h_min,
    lookahead_depth,
)
from vtube_fleet.core.text import compact_number as _num
from vtube_fleet.core.tube import APEX_AUTO, Obstacle, Trapezoid

__all__ = [
    "GRID",
    "H_MAX_FACTOR",
    "REFINE",
    "SWEEPS",
    "ApexPlan",
    "Margin",
    "plan_apex",
    "plan_partition",
    "resolved_obstacles",
    "tube_margins",
]

#: h_k is searched up to this × h_min,k (longer triangles only shorten the tubes before them).
H_MAX_FACTOR = 4.0
#: grid points per obstacle and coordinate step
GRID = 9
#: golden-section iterations refining the best grid cell
REFINE = 12
#: at most this many sweeps over the obstacles
SWEEPS = 3

_GOLD = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass(frozen=True)
class Margin:
    """One sub-tube's margin to one part of Assumption 3' (metres, < 0: violated by that much).

    ``condition`` is ``"L ∩ R = ∅"``, ``"M ≠ ∅"``, ``"length > 2 r_a"`` or ``"room for one
    robot"``; ``tube`` names the sub-tube by its origin ("the tube right of obstacle #3");
    ``obstacle`` is the 0-based index of the obstacle that created it (None: the main tube).
    """

    value_m: float
    condition: str
    tube: str
    obstacle: int | None

    def describe(self) -> str:
        how = "margin" if self.value_m >= 0 else "violated by"
        which = "Assumption 1" if self.condition.startswith("start") else "Assumption 3'"
        return (f"{self.tube}: {which} {self.condition}, {how} "
                f"{_num(abs(self.value_m))} m")


@dataclass(frozen=True)
class ApexPlan:
    """The planner's choice (:func:`plan_apex`).

    ``h`` (per input obstacle): the apex distance used; ``auto``: which were chosen by the
    planner; ``margin_m``: the objective (the smallest margin, module docstring; −inf when no
    partition could be built); ``binding``: the sub-tube (or triangle) and condition attaining
    it; ``inside``: keep-out points inside a triangle; ``feasible``: built, nobody inside a
    triangle, margin > 0; ``error``: why the best choice cannot be built (else None) and
    ``failed_obstacle`` the obstacle it names; ``evaluations``: trial constructions.
    """

    h: tuple[float, ...]
    auto: tuple[bool, ...]
    margin_m: float
    binding: Margin | None
    inside: int
    feasible: bool
    error: str | None
    evaluations: int
    failed_obstacle: int | None = None

    def describe(self) -> str:
        """One line: the chosen h_k and the objective."""
        hs = ", ".join(f"#{i + 1} h = {_num(h)} m" for i, (h, a) in
                       enumerate(zip(self.h, self.auto, strict=True)) if a)
        m = (f"smallest margin {_num(self.margin_m)} m"
             if math.isfinite(self.margin_m) else "no partition")
        where = f" ({self.binding.tube}, {self.binding.condition})" if self.binding else ""
        return f"apex distances chosen (auto): {hs}; {m}{where}"


# ----------------------------------------------------------------------------------------------
# margins
# ----------------------------------------------------------------------------------------------
def _extreme(poly: list[tuple[float, float]], fs: list[tuple[float, float, float]],
             kind: str) -> float:
    """min over the convex polygon of max(f, g) (``kind="minmax"``) or max of min(f, g)
    (``"maxmin"``) for affine f(x) = a₀x + a₁y − b (one or two of them); attained at a vertex
    or where f = g meets an edge. Plain floats: the polygons have 4 vertices."""
    agg, best = (max, min) if kind == "minmax" else (min, max)
    vals = [[a0 * x + a1 * y - c for a0, a1, c in fs] for x, y in poly]
    cand = [agg(v) for v in vals]
    if len(fs) == 2:
        n = len(poly)
        for k in range(n):
            u, w = vals[k], vals[(k + 1) % n]
            du, dw = u[0] - u[1], w[0] - w[1]
            if du * dw < 0:
                t = du / (du - dw)
                cand.append(agg(u[0] + t * (w[0] - u[0]), u[1] + t * (w[1] - u[1])))
    return best(cand)


def tube_margins(tube: Trapezoid, k_t: float, r_a: float, r_s: float) -> list[tuple[str, float]]:
    """The margins (condition, metres) of one tube to the parts of Assumption 3/3' that
    :func:`vtube_fleet.core.partition.check_assumption3` tests (module docstring); ≥ 0 where
    that part holds (up to its area tolerance)."""
    d = k_t * r_a
    poly = [(float(v[0]), float(v[1])) for v in (tube.p_h0, tube.p_h1, tube.p_r1, tube.p_r0)]
    nh, nr, nc = tube.n_h, tube.n_r, tube.n_c
    fh = (float(nh[0]), float(nh[1]), float(nh @ tube.p_h1))
    fr = (float(nr[0]), float(nr[1]), float(nr @ tube.p_r1))
    has_l, has_r = tube.has_L, tube.has_R
    out = []
    if has_l and has_r:
        out.append(("L ∩ R = ∅", _extreme(poly, [fh, fr], "minmax") - d))
    fs = [f for f, has in ((fh, has_l), (fr, has_r)) if has]
    if fs:
        out.append(("M ≠ ∅", _extreme(poly, fs, "maxmin") - d))
    out.append(("length > 2 r_a", float(nc @ (tube.p_r1 - tube.p_r0)) - 2.0 * r_a))
    need = r_s * (1.0 / float(tube.t_h @ nc) + 1.0 / float(tube.t_r @ nc))
    w = min(math.dist(poly[0], poly[3]), math.dist(poly[1], poly[2]))
    out.append(("room for one robot", w - need))
    return out


# ----------------------------------------------------------------------------------------------
# the planner
# ----------------------------------------------------------------------------------------------
def _locate_among(nodes: Sequence[SubTubeNode], b: PartitionBuilder, p: np.ndarray) -> int:
    """The §5 rule (:meth:`Partition.locate`) for one point among a few sub-tubes: half-open
    slabs (a point within LOCATE_TOL upstream of a base counts as on it), the least violation
    max(−d_Th, −d_Tr), ties (up to LOCATE_TOL) to the first."""
    xi = b.xi(p)
    best, best_v = 0, math.inf
    n = len(nodes)
    for k, nd in enumerate(nodes):
        if not (nd.xs - LOCATE_TOL <= xi < nd.xe - LOCATE_TOL):
            continue
        t = nd.tube
        v = max(-float(t.d_Th(p)), -float(t.d_Tr(p))) - LOCATE_TOL * (n - k) / (n + 1)
        if v < best_v:
            best, best_v = k, v
    return best


def resolved_obstacles(obstacles: Sequence[Obstacle], plan: ApexPlan) -> tuple[Obstacle, ...]:
    """The obstacles with the planned h_k written in (``"auto"`` replaced by numbers)."""
    return tuple(dataclasses.replace(ob, apex_distance=h) if a else ob
                 for ob, h, a in zip(obstacles, plan.h, plan.auto, strict=True))


class _Planner:
    def __init__(self, tube: Trapezoid, obstacles: Sequence[Obstacle], params,
                 strict: bool, keep_out: np.ndarray | None) -> None:
        self.obstacles = list(obstacles)
        self.params = params
        self.auto = [isinstance(ob.apex_distance, str) for ob in obstacles]
        for ob in obstacles:
            if isinstance(ob.apex_distance, str) and ob.apex_distance != APEX_AUTO:
                raise ValueError(f"apex_distance {ob.apex_distance!r}")
        self.b = PartitionBuilder(tube, self.obstacles, params, strict)
        self.order = self.b.order()
        self.lo: dict[int, float] = {}
        self.hi: dict[int, float] = {}
        h0 = []
        for i, ob in enumerate(obstacles):
            hm = h_min(float(ob.radius), params)
            if not self.auto[i]:
                h0.append(float(ob.apex_distance) if ob.apex_distance is not None
                          else DEFAULT_APEX_FACTOR * hm)
                continue
            lo = hm * (1.0 + 1e-9)
            room = float(self.b.xi(ob.center)) - 1e-6  # apex inside the tube
            hi = max(lo, min(H_MAX_FACTOR * hm, room))
            self.lo[i], self.hi[i] = lo, hi
            h0.append(min(max(DEFAULT_APEX_FACTOR * hm, lo), hi))
        self.h = h0
        kp = np.zeros((0, 2)) if keep_out is None else np.asarray(keep_out, float).reshape(-1, 2)
        self.keep_out = kp[np.all(np.isfinite(kp), axis=1)]
        self.evaluations = 0
        self._memo: dict[tuple, tuple] = {}
        self._margin_memo: dict[int, tuple[float, Margin]] = {}
        self._tri_memo: dict[int, tuple[int, float]] = {}
        self._hold: list = []  # keeps memoised objects alive (ids are keys)
        self._descend: dict[tuple, SubTubeNode] = {}
        self._ob_memo: dict[tuple[int, float], Obstacle] = {}
        self._intern: dict[tuple, SubTubeNode] = {}
        self.kids: dict[int, tuple[SubTubeNode, ...]] = {}
        self.root_node = self.b.nodes[0]

    # --- one trial ----------------------------------------------------------------------
    def _obstacles(self, h: Sequence[float]) -> list[Obstacle]:
        out = []
        for i, ob in enumerate(self.obstacles):
            if self.auto[i]:
                key = (i, float(h[i]))
                ob = self._ob_memo.get(key)
                if ob is None:
                    ob = self._ob_memo[key] = dataclasses.replace(self.obstacles[i],
                                                                  apex_distance=key[1])
            out.append(ob)
        return out

    # --- the construction with reuse ----------------------------------------------------
    def _snap(self) -> tuple:
        b = self.b
        return list(b.nodes), dict(b.triangles), list(b.warnings), dict(self.kids)

    def _restore(self, st: tuple) -> None:
        b = self.b
        b.nodes, b.triangles, b.warnings = list(st[0]), dict(st[1]), list(st[2])
        self.kids = dict(st[3])

    def _parent(self, i: int) -> SubTubeNode:
        """The leaf sub-tube containing obstacle ``i``'s centre, found by descending the split
        tree (the §5 rule among the children of each split; cached per children tuple)."""
        node = self.root_node
        while True:
            ch = self.kids.get(id(node))
            if ch is None:
                return node
            key = (id(ch), i)
            nxt = self._descend.get(key)
            if nxt is None:
                nxt = ch[_locate_among(ch, self.b, self.obstacles[i].center)]
                self._descend[key] = nxt
            node = nxt

    def _split(self, i: int, obs: list[Obstacle]) -> None:
        """``PartitionBuilder.split`` of obstacle ``i``, reused when its parent sub-tube (the same
        object) and h are unchanged; the new sub-tubes are interned by geometry, so a tube
        that does not depend on h_i (the one after the triangle) stays the same object and
        what is built inside it is reused too."""
        b = self.b
        parent = self._parent(i)
        key = (i, obs[i].apex_distance, id(parent))
        hit = self._memo.get(key)
        k_par = next(k for k, nd in enumerate(b.nodes) if nd is parent)
        if hit is None:
            n0, w0 = len(b.nodes), len(b.warnings)
            try:
                b.split(i, k_par)
            except PartitionError as e:
                self._memo[key] = ("err", e)
                raise
            grown = len(b.nodes) - n0
            new = () if grown == 0 and b.nodes[k_par] is parent else \
                tuple(b.nodes[k_par:k_par + grown + 1])
            new = tuple(self._intern.setdefault(
                (id(parent), nd.origin, nd.xs, nd.xe,
                 *(float(x) for v in (nd.tube.p_h0, nd.tube.p_h1, nd.tube.p_r0, nd.tube.p_r1)
                   for x in v)), nd) for nd in new)
            hit = ("ok", new, b.triangles.get(i), tuple(b.warnings[w0:]))
            self._memo[key] = hit
            self._hold.append(parent)
            b.warnings = b.warnings[:w0]
            if new:  # undone here, re-applied below with the interned sub-tubes
                b.nodes[k_par:k_par + len(new)] = [parent]
        if hit[0] == "err":
            raise hit[1]
        _, new, tri, warns = hit
        if new:
            b.nodes[k_par:k_par + 1] = list(new)
            self.kids[id(parent)] = new
        if tri is not None:
            b.triangles[i] = tri
        b.warnings += list(warns)

    def _node_margin(self, nd: SubTubeNode) -> tuple[float, Margin]:
        got = self._margin_memo.get(id(nd))
        if got is None:
            p = self.params
            ms = tube_margins(nd.tube, p.k_t, p.r_a, p.r_s)
            cond, val = min(ms, key=lambda cv: cv[1])
            got = (val, Margin(val, cond, nd.origin, nd.obstacle))
            self._margin_memo[id(nd)] = got
            self._hold.append(nd)
        return got

    def _keep_out(self, tri) -> tuple[int, float]:
        """(keep-out points inside the triangle — validation's test —, the smallest distance
        of a keep-out point to it, 0 inside)."""
        got = self._tri_memo.get(id(tri))
        if got is None:
            q = self.keep_out
            inside = tri.contains(q, tol=-1e-9)
            n_in = int(np.count_nonzero(inside & (np.hypot(*(q - tri.center).T)
                                                  > tri.radius_ext)))
            poly = tri.polygon()
            d = np.full(len(q), np.inf)
            for a, c in ((poly[0], poly[1]), (poly[1], poly[2]), (poly[2], poly[0])):
                e = c - a
                t = np.clip(((q - a) @ e) / float(e @ e), 0.0, 1.0)
                d = np.minimum(d, np.hypot(*(q - (a + t[:, None] * e)).T))
            d[inside] = 0.0
            got = (n_in, float(d.min()))
            self._tri_memo[id(tri)] = got
            self._hold.append(tri)
        return got

    def trial(self, h: Sequence[float], start: int, state: tuple) -> tuple[tuple, str | None,
                                                                              Margin | None]:
        """Score of the apex distances ``h``, rebuilding from construction step ``start``
        (``state``: the builder's state before it). Higher is better."""
        self.evaluations += 1
        self.failed = None
        b = self.b
        self._restore(state)
        obs = self._obstacles(h)
        b.obstacles = obs
        for j in range(start, len(self.order)):
            try:
                self._split(self.order[j], obs)
            except PartitionError as e:
                self.failed = e.obstacle
                return (0, j, -math.inf, -math.inf), str(e), None
        worst, binding = math.inf, None
        own: dict[int | None, float] = {}
        for nd in b.nodes:
            v, mg = self._node_margin(nd)
            if v < worst:
                worst, binding = v, mg
            own[nd.obstacle] = min(own.get(nd.obstacle, math.inf), v)
        spread = sum(own.values())
        inside = 0
        if len(self.keep_out):
            for tri in b.triangles.values():
                n_in, clear = self._keep_out(tri)
                inside += n_in
                v = clear - self.params.r_s
                if v < worst:
                    worst = v
                    binding = Margin(v, "start positions ≥ r_s from the triangle",
                                     f"the triangle of obstacle #{tri.obstacle + 1}",
                                     tri.obstacle)
                own[tri.obstacle] = min(own.get(tri.obstacle, math.inf), v)
            spread = sum(own.values())
            for tri in b.triangles.values():
                v = self._lookahead_margin(tri)
                if v < worst:
                    worst = v
                    binding = Margin(v, "start positions clear of the apex look-ahead "
                                     "(Assumption 1)",
                                     f"ahead of the apex of obstacle #{tri.obstacle + 1}",
                                     tri.obstacle)
                own[tri.obstacle] = min(own.get(tri.obstacle, math.inf), v)
            spread = sum(own.values())
        return (2 if inside == 0 else 1, -inside, worst, spread), None, binding

    def _lookahead_margin(self, tri) -> float:
        """Smallest margin of the keep-out points to the apex look-ahead of ``tri``
        (:func:`~vtube_fleet.core.partition.apex_zones`): a start position of the tube before
        the apex, within the zone's depth upstream of the apex line, is flown in the side tube
        on its side and must be more than r_s from that tube's legs. Per point
        max(ξ_apex − depth − ξ, d − r_s): how far it is upstream of the zone, or clear of
        the legs (< 0: validation's look-ahead conflict)."""
        b, p = self.b, self.params
        apex = np.asarray(tri.p_oth, dtype=float)
        xi_a = b.xi(apex)
        before = None
        for nd in b.nodes:
            if (abs(nd.xe - xi_a) < 1e-6 and float(nd.tube.d_Th(apex)) >= -1e-6
                    and float(nd.tube.d_Tr(apex)) >= -1e-6):
                before = nd
                break
        q = self.keep_out
        if before is None or not len(q):
            return math.inf
        n_c = b.n_c
        sides = {"left": np.asarray(tri.p_otu, float) - apex,
                 "right": np.asarray(tri.p_otd, float) - apex}
        if tri.remark5 is not None:
            sides.pop(tri.remark5)
        xs = before.xs if math.isfinite(before.xs) else 0.0
        depth = lookahead_depth([t / float(np.hypot(*t)) for t in sides.values()], n_c, p,
                                xi_a - xs)
        xi = q @ n_c - b.xi0
        t = before.tube
        dh, dr = np.asarray(t.d_Th(q), float), np.asarray(t.d_Tr(q), float)
        hit = (xi >= xs) & (xi < xi_a) & (dh >= 0.0) & (dr >= 0.0)
        if not hit.any():
            return math.inf
        m = np.array([n_c[1], -n_c[0]])  # from the left leg towards the right leg
        if float(m @ (b.tube.p_r0 - b.tube.p_h0)) < 0:
            m = -m
        lat = (q - apex) @ m
        out = math.inf
        for j in np.flatnonzero(hit):
            side = ("left" if lat[j] <= 0.0 else "right") if len(sides) == 2 else next(
                iter(sides))
            e = sides[side] / float(np.hypot(*sides[side]))
            to_side = abs(float(e[0] * (q[j, 1] - apex[1]) - e[1] * (q[j, 0] - apex[0])))
            d = min(to_side, float(dh[j] if side == "left" else dr[j]))
            out = min(out, max(xi_a - depth - float(xi[j]), d - p.r_s))
        return out

    # --- the search ---------------------------------------------------------------------
    def run(self) -> ApexPlan:
        b = self.b
        root = self._snap()
        best_score, err, binding = self.trial(self.h, 0, root)
        auto_steps = [j for j, i in enumerate(self.order) if self.auto[i]]
        for _sweep in range(SWEEPS if len(auto_steps) > 1 else 1):
            changed = False
            state, j_done = root, 0
            for j in auto_steps:
                # advance the kept state to just before step j with the current choice
                self._restore(state)
                b.obstacles = self._obstacles(self.h)
                ok = True
                for jj in range(j_done, j):
                    try:
                        self._split(self.order[jj], b.obstacles)
                    except PartitionError:
                        ok = False
                        break
                if not ok:
                    break
                state, j_done = self._snap(), j
                i = self.order[j]
                res = self._coordinate(i, j, state, best_score)
                if res is not None:
                    self.h[i], best_score, err, binding = res
                    changed = True
            if not changed:
                break
        best_score, err, binding = self.trial(self.h, 0, root)
        tier, neg_inside, margin, _ = best_score
        return ApexPlan(
            h=tuple(float(x) for x in self.h), auto=tuple(self.auto),
            margin_m=float(margin) if tier else -math.inf, binding=binding,
            inside=-int(neg_inside) if tier else 0,
            feasible=tier == 2 and margin > 0.0, error=err, evaluations=self.evaluations,
            failed_obstacle=self.failed)

    def _coordinate(self, i: int, j: int, state: tuple, best: tuple
                    ) -> tuple[float, tuple, str | None, Margin | None] | None:
        """Best h_i with the others fixed; None if nothing beats ``best``."""
        lo, hi = self.lo[i], self.hi[i]
        h = list(self.h)

        def score(x: float) -> tuple:
            h[i] = x
            return self.trial(h, j, state)

        grid = [lo] if hi <= lo else [lo + (hi - lo) * k / (GRID - 1) for k in range(GRID)]
        results = [score(x) for x in grid]
        kbest = 0
        for k in range(1, len(grid)):
            if _better(results[k][0], results[kbest][0]):
                kbest = k
        xb, sb, eb, mb = grid[kbest], *results[kbest]
        if len(grid) > 1:  # golden section on the cell around the best grid point
            a = grid[max(kbest - 1, 0)]
            c = grid[min(kbest + 1, len(grid) - 1)]
            x1, x2 = c - _GOLD * (c - a), a + _GOLD * (c - a)
            r1, r2 = score(x1), score(x2)
            for _ in range(REFINE):
                if not _better(r2[0], r1[0]):
                    c, x2, r2 = x2, x1, r1
                    x1 = c - _GOLD * (c - a)
                    r1 = score(x1)
                else:
                    a, x1, r1 = x1, x2, r2
                    x2 = a + _GOLD * (c - a)
                    r2 = score(x2)
                for x, r in ((x1, r1), (x2, r2)):
                    if _better(r[0], sb):
                        xb, sb, eb, mb = x, *r
        if _better(sb, best):
            return xb, sb, eb, mb
        return None


def _better(a: tuple, b: tuple) -> bool:
    """Score ``a`` beats ``b``: (tier, −inside) higher, else the smallest margin higher by
    more than 1 nm, else (equal smallest margin) the sum of the obstacles' own smallest
    margins higher by more than 1 nm."""
    if a[:2] != b[:2]:
        return a[:2] > b[:2]
    if a[2] > b[2] + 1e-9:
        return True
    return a[2] >= b[2] - 1e-9 and a[3] > b[3] + 1e-9


def plan_apex(tube: Trapezoid, obstacles: Sequence[Obstacle], params,
              keep_out: np.ndarray | None = None, strict: bool = True) -> ApexPlan:
    """Choose every ``"auto"`` apex distance jointly (module docstring). ``keep_out``: points
    (M, 2) to keep out of the triangles (the robots' start positions)."""
    return _Planner(tube, obstacles, params, strict, keep_out).run()


def plan_partition(tube: Trapezoid, obstacles: Sequence[Obstacle], params, *,
                   strict: bool = True, keep_out: np.ndarray | None = None) -> Partition:
    """:func:`plan_apex`, then the partition with the chosen h_k (raises
    :class:`~vtube_fleet.core.partition.PartitionError` as :func:`~vtube_fleet.core.partition.
    partition` does, with the planner's best choice); :attr:`Partition.apex` holds the plan."""
    obstacles = tuple(obstacles)
    plan = plan_apex(tube, obstacles, params, keep_out, strict)
    part = PartitionBuilder(tube, resolved_obstacles(obstacles, plan), params, strict).run()
    return dataclasses.replace(part, apex=plan)
