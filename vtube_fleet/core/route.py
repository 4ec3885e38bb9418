"""Routes: a corridor of chained trapezoid virtual tubes (docs/route.md).

The layout is **route → segment → partition → sub-tube**:

* :class:`RouteGeometry` — the segments' trapezoids and the junctions between them, built
  from waypoints (:meth:`RouteGeometry.from_waypoints`) or from one ``[tube]``
  (:meth:`RouteGeometry.single`);
* :class:`Corridor` — the geometry and the configured obstacles O_k (each owned by the segment
  that contains its centre): what a scenario file describes;
* :class:`Route` — a corridor planned with controller parameters: one :class:`Segment` per
  trapezoid, each with its obstacles and its own :class:`~vtube_fleet.core.partition.Partition`
  (Section IV-A; Remark 6's joint apex choice per segment), every sub-tube of every segment
  stacked into one :class:`~vtube_fleet.core.controller.TubeArrays` with a global sub-tube
  index, so :func:`~vtube_fleet.core.controller.velocity_command` is unchanged (the pair terms
  do not care about segments, paper note 6).

Waypoint i has a position c_i, a half-width w_i and optionally a heading; waypoints i and i + 1
make segment i: its bases are perpendicular to its heading n_i (waypoint i's ``heading``, else
the direction c_i → c_{i+1}), centred on c_i and c_{i+1}, w_i and w_{i+1} to each side. At a
waypoint j where the heading turns by θ_j the two segments' bases cross at c_j; both segments
are prolonged along their legs by the overlap e_j (default w_j tan(|θ_j|/2): the mitre, so the
prolonged segments meet at the outer corner and their union is the corridor with mitred
corners). A vehicle is controlled by exactly one segment; it hands over from segment s to
s + 1 (never back) once it is inside s + 1 with more than r_s to s + 1's legs, not past its
finishing line, and more than r_s from the legs of the sub-tube of s + 1 it would fly (so not
inside a triangle's barrier). The junction conditions (:func:`junction_checks`) prove that
every vehicle does so before it reaches the end of segment s. Pure numpy.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from vtube_fleet.core.controller import TubeArrays
from vtube_fleet.core.partition import (
    LOCATE_TOL,
    ApexZone,
    Partition,
    PartitionError,
    Triangle,
    Violation,
    _area,
    _clip,
    _dist_to_polygon,
    apex_lookahead,
    apex_zones,
    lookahead_depth,
    partition,
)
from vtube_fleet.core.text import compact_number as _num
from vtube_fleet.core.text import obstacle_label
from vtube_fleet.core.tube import APEX_AUTO, GeometryError, Obstacle, Trapezoid
from vtube_fleet.errors import UserError

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.core.params import ControllerParams

__all__ = [
    "MAX_BEND_DEG",
    "Corridor",
    "Junction",
    "JunctionCheck",
    "ReplanFn",
    "Route",
    "RouteError",
    "RouteGeometry",
    "RouteTracker",
    "Segment",
    "Waypoint",
    "disc_meets",
    "handover_line",
    "handover_region",
    "junction_checks",
    "obstacle_ownership",
    "progress_speed",
    "renumber_obstacles",
    "replan_segment",
    "segment_error",
    "segment_keep_out",
]

#: A bend of this or more (degrees) is refused when the geometry is built: the prolongation
#: w tan(θ/2) grows without bound towards a U-turn (the junction conditions refuse bends above
#: 90° already, docs/route.md; this only keeps the numbers finite).
MAX_BEND_DEG = 170.0

_TOL = 1e-9


class RouteError(UserError):
    """The waypoints do not make a route (too few, coincident, a segment going backwards …)."""


def _unit(a: float) -> np.ndarray:
    return np.array([math.cos(a), math.sin(a)])


def _left(n: np.ndarray) -> np.ndarray:
    """n rotated by +90°: the left of the direction of flight (the tube frame's y is left)."""
    return np.array([-n[1], n[0]])


def _deg(x: float) -> str:
    return _num(math.degrees(x), 1)


# ----------------------------------------------------------------------------------------------
# geometry
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Waypoint:
    """One waypoint: ``position`` c (2,) in metres (tube frame), ``half_width`` w (> 0),
    ``heading`` (radians counter-clockwise from the frame's x axis: the direction of flight
    across the base lines of the segment that starts here; ``None``: towards the next waypoint),
    ``overlap_m`` (the prolongation e of both segments at this waypoint's bend; ``None``: the
    mitre w tan(|θ|/2))."""

    position: np.ndarray
    half_width: float
    heading: float | None = None
    overlap_m: float | None = None

    def __post_init__(self) -> None:
        c = np.asarray(self.position, dtype=float).reshape(-1)
        if c.shape != (2,) or not np.all(np.isfinite(c)):
            raise RouteError(f"waypoint position must be two finite numbers, got {c}")
        c.setflags(write=False)
        object.__setattr__(self, "position", c)
        if not (math.isfinite(self.half_width) and self.half_width > 0):
            raise RouteError(f"waypoint half_width must be > 0, got {self.half_width}")
        if self.heading is not None and not math.isfinite(self.heading):
            raise RouteError(f"waypoint heading must be finite, got {self.heading}")
        if self.overlap_m is not None and not (math.isfinite(self.overlap_m)
                                               and self.overlap_m >= 0):
            raise RouteError(f"waypoint overlap_m must be >= 0, got {self.overlap_m}")


@dataclass(frozen=True, eq=False)
class Junction:
    """Where segment ``index`` hands over to segment ``index + 1``: at waypoint ``waypoint``
    (0-based; = index + 1), its position ``center``, the bend ``theta`` (radians, > 0: a left
    turn) and ``prolong_m`` (e_a, e_b): how far segment ``index`` is prolonged past the
    waypoint and segment ``index + 1`` before it (0, 0: a shared base)."""

    index: int
    waypoint: int
    center: np.ndarray
    theta: float
    prolong_m: tuple[float, float]

    @property
    def overlap_m(self) -> float:
        """The larger of the two prolongations."""
        return max(self.prolong_m)

    def overlap_text(self) -> str:
        a, b = self.prolong_m
        return (f"{_num(a, 3)} m" if abs(a - b) < 5e-4 else
                f"{_num(a, 3)} m / {_num(b, 3)} m")

    @property
    def theta_deg(self) -> float:
        return math.degrees(self.theta)

    @property
    def name(self) -> str:
        """``waypoint 3 (S2 → S3)``: how messages name it (1-based, as the config counts)."""
        return f"waypoint {self.waypoint + 1} (S{self.index + 1} → S{self.index + 2})"


@dataclass(frozen=True, eq=False)
class RouteGeometry:
    """The segments of a route (each a :class:`~vtube_fleet.core.tube.Trapezoid`, prolonged at
    its junctions; named ``S1``, ``S2`` …, or ``T`` for one ``[tube]``), the ``junctions``
    between consecutive ones and the ``waypoints`` they were built from (empty for a
    ``[tube]``)."""

    segments: tuple[Trapezoid, ...]
    junctions: tuple[Junction, ...] = ()
    waypoints: tuple[Waypoint, ...] = ()

    def __post_init__(self) -> None:
        if not self.segments:
            raise RouteError("a route needs at least one segment")
        if len(self.junctions) != len(self.segments) - 1:
            raise RouteError("a route of S segments has S - 1 junctions")

    @classmethod
    def single(cls, tube: Trapezoid) -> RouteGeometry:
        """The one-segment route of a ``[tube]`` (the trapezoid itself, unchanged)."""
        return cls((tube,))

    @classmethod
    def from_waypoints(cls, waypoints: Sequence[Waypoint]) -> RouteGeometry:
        """Segments and junctions of the waypoints (module docstring). Raises
        :class:`RouteError` naming the waypoint (1-based) when they make no route."""
        wps = tuple(waypoints)
        if len(wps) < 2:
            raise RouteError(f"a route needs at least 2 waypoints, got {len(wps)}")
        n_seg = len(wps) - 1
        heads = []
        for k in range(n_seg):
            c0, c1 = wps[k].position, wps[k + 1].position
            d = c1 - c0
            if float(np.hypot(*d)) < 1e-6:
                raise RouteError(f"waypoints {k + 1} and {k + 2} coincide")
            h = wps[k].heading
            n = _unit(h) if h is not None else d / float(np.hypot(*d))
            if float(n @ d) <= 1e-6:
                raise RouteError(
                    f"waypoint {k + 2} is not ahead of waypoint {k + 1} along segment "
                    f"S{k + 1}'s heading ({_deg(math.atan2(n[1], n[0]))}°): a segment's "
                    f"finishing base must lie ahead of its start base")
            heads.append(n)
        last = wps[-1].heading
        if last is not None:
            a = heads[-1]
            diff = math.atan2(a[0] * math.sin(last) - a[1] * math.cos(last),
                              a[0] * math.cos(last) + a[1] * math.sin(last))
            if abs(diff) > 1e-6:
                raise RouteError(
                    f"waypoint {len(wps)} (the finishing line): heading "
                    f"{_deg(last)}° differs from segment S{n_seg}'s "
                    f"{_deg(math.atan2(a[1], a[0]))}° (a trapezoid's bases are parallel; "
                    f"leave the last waypoint's heading out)")
        drawn = []  # each segment's legs between its waypoints' base lines (L0, L1, R0, R1)
        for k in range(n_seg):
            lft = _left(heads[k])
            c0, c1 = wps[k].position, wps[k + 1].position
            w0, w1 = wps[k].half_width, wps[k + 1].half_width
            drawn.append((c0 + w0 * lft, c1 + w1 * lft, c0 - w0 * lft, c1 - w1 * lft))
        junctions = []
        for j in range(1, n_seg):
            a, b = heads[j - 1], heads[j]
            theta = math.atan2(a[0] * b[1] - a[1] * b[0], float(a @ b))
            if abs(math.degrees(theta)) >= MAX_BEND_DEG:
                raise RouteError(f"waypoint {j + 1}: a bend of {_deg(theta)}° is refused "
                                 f"(at most {MAX_BEND_DEG:g}°; the junction conditions need "
                                 f"at most 90°, docs/route.md)")
            wp = wps[j]
            if wp.overlap_m is not None:
                e = (float(wp.overlap_m),) * 2
            elif abs(theta) <= 1e-12:
                e = (0.0, 0.0)
            else:  # the mitre: both prolonged to the outer corner of the two outer legs
                e = _mitre_prolongation(drawn[j - 1], drawn[j], a, b, wp, theta)
            junctions.append(Junction(j - 1, j, wp.position, theta, e))
        segs = []
        for k in range(n_seg):
            n = heads[k]
            L0, L1, R0, R1 = drawn[k]
            e_in = junctions[k - 1].prolong_m[1] if k >= 1 else 0.0
            e_out = junctions[k].prolong_m[0] if k < n_seg - 1 else 0.0
            pts = []
            for p0, p1 in ((L0, L1), (R0, R1)):
                t = p1 - p0
                adv = float(t @ n)
                if adv <= 1e-9:
                    raise RouteError(f"segment S{k + 1} (waypoints {k + 1} → {k + 2}): a leg "
                                     f"does not advance along the heading")
                pts.append((p0 - t * (e_in / adv), p1 + t * (e_out / adv)))
            (h0, h1), (r0, r1) = pts
            try:
                segs.append(Trapezoid(h0, h1, r0, r1, name=f"S{k + 1}"))
            except GeometryError as exc:
                raise RouteError(f"segment S{k + 1} (waypoints {k + 1} → {k + 2}): {exc}"
                                 ) from None
        geo = cls(tuple(segs), tuple(junctions), wps)
        geo._refuse_self_overlap()
        return geo

    def _refuse_self_overlap(self) -> None:
        """Raise :class:`RouteError` when two segments that are not neighbours share
        airspace: the corridor's pieces (:meth:`pieces`) of S_k and S_l, l ≥ k + 2, overlap
        (the route crosses or folds back onto itself). Each segment knows only its own
        obstacles and legs (Junction5), and the hand-over goes only to the next segment."""
        pieces = self.pieces()
        boxes = [(p.min(axis=0), p.max(axis=0)) if len(p) else None for p in pieces]
        for k in range(self.S):
            for m in range(k + 2, self.S):
                if boxes[k] is None or boxes[m] is None or \
                        np.any(boxes[k][0] > boxes[m][1]) or np.any(boxes[m][0] > boxes[k][1]):
                    continue
                both = _convex_intersection(pieces[k], pieces[m])
                area = _area(both)
                if area > _OVERLAP_AREA_M2:
                    c = both.mean(axis=0)
                    raise RouteError(
                        f"segments S{k + 1} (waypoints {k + 1} → {k + 2}) and S{m + 1} "
                        f"(waypoints {m + 1} → {m + 2}) overlap: {_num(area, 3)} m² of "
                        f"corridor around ({_num(float(c[0]), 2)}, {_num(float(c[1]), 2)}) "
                        f"belong to both; a route must not cross or fold back onto itself "
                        f"(a segment's vehicles know only its own legs and obstacles): move "
                        f"the waypoints so that the corridor does not meet itself")

    @property
    def S(self) -> int:
        """Number of segments."""
        return len(self.segments)

    @property
    def is_single(self) -> bool:
        return len(self.segments) == 1

    def mitre(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """The mitre line of junction ``j`` as (a point, unit normal pointing into segment
        j + 1's side): through the intersections of the two segments' left leg lines and of
        their right leg lines (the corridor's inner and outer corners); for parallel legs the
        base through the junction's waypoint."""
        p, q = self.mitre_corners(j)
        b = self.segments[j + 1]
        t = (q - p) / float(np.hypot(*(q - p)))
        nrm = np.array([-t[1], t[0]])
        if float(nrm @ (b.p_h1 + b.p_r1 - 2 * p)) < 0:
            nrm = -nrm
        return p, nrm

    def mitre_corners(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(left, right) end of junction ``j``'s mitre line: the corners where the two
        segments' left legs and their right legs meet (the waypoint's base for parallel
        legs)."""
        a, b = self.segments[j], self.segments[j + 1]
        c = self.junctions[j].center
        corners = []
        for pa, ta, pb, tb in ((a.p_h0, a.t_h, b.p_h0, b.t_h), (a.p_r0, a.t_r, b.p_r0, b.t_r)):
            den = ta[0] * tb[1] - ta[1] * tb[0]
            if abs(den) < 1e-9:
                corners.append(None)
                continue
            d = pb - pa
            u = (d[0] * tb[1] - d[1] * tb[0]) / den
            corners.append(pa + u * ta)
        if corners[0] is not None and corners[1] is not None and \
                float(np.hypot(*(corners[1] - corners[0]))) > 1e-9:
            return corners[0], corners[1]
        xi = float(a.xi(c))  # parallel legs: a's base through c_j
        return a.lh(xi), a.lr(xi)

    def pieces(self) -> list[np.ndarray]:
        """The corridor's convex pieces Q_k (polygons (n, 2)): segment k between the mitre
        lines of its two junctions (the route's start base and finishing line at the ends).
        Their union is the corridor the waypoints draw, with mitred corners."""
        out = []
        for k, t in enumerate(self.segments):
            poly = t.polygon()
            if k >= 1:
                p, nrm = self.mitre(k - 1)
                poly = _clip(poly, nrm, float(nrm @ p) - _TOL)
            if k < self.S - 1:
                p, nrm = self.mitre(k)
                poly = _clip(poly, -nrm, -float(nrm @ p) - _TOL)
            out.append(poly)
        return out


#: Two pieces of a route's corridor sharing more than this area (m²) overlap.
_OVERLAP_AREA_M2 = 1e-6


def _convex_intersection(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The intersection of the convex polygons ``p`` and ``q`` ((n, 2), either orientation):
    ``p`` clipped to the inner side of each edge of ``q``."""
    n = len(q)
    if len(p) < 3 or n < 3:
        return np.zeros((0, 2))
    sgn = 1.0 if float(q[:, 0] @ np.roll(q[:, 1], -1) - q[:, 1] @ np.roll(q[:, 0], -1)) > 0 \
        else -1.0
    out = p
    for i in range(n):
        a, e = q[i], q[(i + 1) % n] - q[i]
        nrm = sgn * np.array([-e[1], e[0]])
        out = _clip(out, nrm, float(nrm @ a))
        if len(out) < 3:
            return np.zeros((0, 2))
    return out


def _mitre_prolongation(da: tuple, db: tuple, n_a: np.ndarray, n_b: np.ndarray,
                        wp: Waypoint, theta: float) -> tuple[float, float]:
    """(e_a, e_b) of the mitre at a bend: a prolonged past the waypoint and b before it up to
    the corner where their outer legs meet (the right legs for a left turn), so their union is
    the corridor with a mitred corner; w tan(|θ|/2) each for parallel outer legs."""
    c = wp.position
    if theta > 0:  # a left turn: the outer legs are the right ones
        pa, qa, pb, qb = da[2], da[3], db[2], db[3]
    else:
        pa, qa, pb, qb = da[0], da[1], db[0], db[1]
    ta, tb = qa - pa, qb - pb
    den = ta[0] * tb[1] - ta[1] * tb[0]
    fallback = wp.half_width * math.tan(abs(theta) / 2.0)
    if abs(den) < 1e-12:
        return fallback, fallback
    d = pb - pa
    x = pa + ta * ((d[0] * tb[1] - d[1] * tb[0]) / den)
    return max(0.0, float(n_a @ (x - c))), max(0.0, float(n_b @ (c - x)))


def _inside_margin(pts: np.ndarray, tube: Trapezoid) -> np.ndarray:
    """Signed distance (m) of points (n, 2) inside the trapezoid: min of the legs' and bases'
    half-planes (< 0 outside)."""
    xi = tube.xi(pts)
    return np.minimum.reduce([tube.d_Th(pts), tube.d_Tr(pts), xi, tube.length - xi])


def disc_meets(tube: Trapezoid, ob: Obstacle, r_s: float) -> bool:
    """Whether the extended disc O' of ``ob`` (radius r_o + ``r_s``) meets the trapezoid
    ``tube``: the segments a lost obstacle belongs to (:meth:`Route.with_lost`)."""
    return (_contains(tube, ob.center)
            or _dist_to_polygon(ob.center, tube.polygon()) < float(ob.radius) + r_s)


def _contains(tube: Trapezoid, p: np.ndarray, tol: float = _TOL) -> bool:
    return bool(_inside_margin(np.asarray(p, float).reshape(1, 2), tube)[0] >= -tol)


# ----------------------------------------------------------------------------------------------
# the corridor: geometry + obstacles
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Corridor:
    """A route's geometry and its configured obstacles (config order).

    ``owner[i]`` is the segment obstacle i belongs to: the first segment whose (prolonged)
    trapezoid contains its centre, else the nearest one (its partition then reports the
    obstacle outside the tube, as for one tube); ``shared`` lists the obstacles whose centre
    lies in more than one segment (in a junction's overlap: refused by the validation,
    ``Junction5``). For one segment every obstacle is owned by it, in config order."""

    geometry: RouteGeometry
    obstacles: tuple[Obstacle, ...] = ()
    owner: tuple[int, ...] = field(init=False)
    shared: tuple[tuple[int, tuple[int, ...]], ...] = field(init=False)

    def __post_init__(self) -> None:
        obs = tuple(self.obstacles)
        object.__setattr__(self, "obstacles", obs)
        segs = self.geometry.segments
        owner, shared = [], []
        for i, ob in enumerate(obs):
            if len(segs) == 1:
                owner.append(0)
                continue
            inside = [s for s, t in enumerate(segs) if _contains(t, ob.center)]
            if inside:
                owner.append(inside[0])
                if len(inside) > 1:
                    shared.append((i, tuple(inside)))
            else:
                d = [_dist_to_polygon(ob.center, t.polygon()) for t in segs]
                owner.append(int(np.argmin(d)))
        object.__setattr__(self, "owner", tuple(owner))
        object.__setattr__(self, "shared", tuple(shared))

    @classmethod
    def single(cls, tube: Trapezoid, obstacles: Sequence[Obstacle] = ()) -> Corridor:
        """One ``[tube]`` and its obstacles: a one-segment route."""
        return cls(RouteGeometry.single(tube), tuple(obstacles))

    @property
    def segments(self) -> tuple[Trapezoid, ...]:
        return self.geometry.segments

    @property
    def junctions(self) -> tuple[Junction, ...]:
        return self.geometry.junctions

    @property
    def S(self) -> int:
        return self.geometry.S

    @property
    def is_single(self) -> bool:
        return self.geometry.is_single

    @property
    def tube(self) -> Trapezoid:
        """The trapezoid of a one-segment route; a route of several refuses (names them)."""
        if not self.is_single:
            raise RouteError(f"this is a route of {self.S} segments, not one trapezoid tube "
                             f"(this part of vtube_fleet does not fly routes yet)")
        return self.segments[0]

    @property
    def first(self) -> Trapezoid:
        return self.segments[0]

    @property
    def last(self) -> Trapezoid:
        return self.segments[-1]

    def segment_obstacles(self, s: int) -> tuple[tuple[int, ...], tuple[Obstacle, ...]]:
        """(config indices, obstacles) owned by segment ``s``, in config order."""
        ids = tuple(i for i, o in enumerate(self.owner) if o == s)
        return ids, tuple(self.obstacles[i] for i in ids)

    def start_segment_of(self, p: np.ndarray) -> np.ndarray:
        """(M,) the first segment whose trapezoid contains each point (M, 2), else the one
        it is least outside of (no hand-over: :meth:`Route.start_segments` adds them)."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        if self.is_single:
            return np.zeros(p.shape[0], dtype=np.intp)
        viol = np.stack([-_inside_margin(p, t) for t in self.segments], axis=1)  # (M, S)
        inside = viol <= _TOL
        return np.where(inside.any(axis=1), inside.argmax(axis=1),
                        viol.argmin(axis=1)).astype(np.intp)

    def inside(self, p: np.ndarray, eps_0: float | None = None) -> np.ndarray:
        """(M,) whether each point (M, 2) lies in some segment's trapezoid (closed): in the
        route. With ``eps_0``, a point of the last segment alone counts only before its
        finishing line ((TraCondition) not yet met): a point the route's controller still
        flies (a lost vehicle there is an obstacle; past the line, Assumption 2, it is not)."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        segs = self.segments
        before = np.zeros(p.shape[0], bool)
        for t in segs[:-1]:
            before |= np.asarray(t.contains(p), bool).reshape(-1)
        last = np.asarray(segs[-1].contains(p), bool).reshape(-1)
        if eps_0 is not None:
            last &= ~np.asarray(segs[-1].finished(p, eps_0), bool).reshape(-1)
        return before | last

    def past_finish(self, p: np.ndarray, eps_0: float) -> np.ndarray:
        """(M,) (TraCondition) of the LAST segment met by points (M, 2) that lie in no earlier
        segment: past the route's finishing line, by position alone (a judge that does not
        know the vehicles' segments: an exit seen from outside)."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        done = np.asarray(self.last.finished(p, eps_0), bool).reshape(-1)
        for t in self.segments[:-1]:
            done &= ~np.asarray(t.contains(p), bool).reshape(-1)
        return done

    def with_obstacles(self, obstacles: Sequence[Obstacle]) -> Corridor:
        return Corridor(self.geometry, tuple(obstacles))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corner of the box holding every segment."""
        pts = np.concatenate([t.polygon() for t in self.segments])
        return pts.min(axis=0), pts.max(axis=0)


# ----------------------------------------------------------------------------------------------
# the planned route
# ----------------------------------------------------------------------------------------------
def renumber_obstacles(text: str, ids: Sequence[int]) -> str:
    """A partition message of one segment (its obstacles numbered #1… among themselves) with
    the obstacles' route numbers (config order, #1 = the first configured obstacle)."""
    return re.sub(r"#(\d+)", lambda m: f"#{ids[int(m.group(1)) - 1] + 1}"
                  if 0 < int(m.group(1)) <= len(ids) else m.group(0), text)


def segment_error(s: int, ids: Sequence[int], exc: PartitionError, multi: bool
                  ) -> PartitionError:
    """A segment's :class:`PartitionError` in route terms (obstacle numbers, the segment)."""
    if not multi:
        return exc
    glob = None if exc.obstacle is None else ids[exc.obstacle]
    return PartitionError(glob, renumber_obstacles(exc.reason, ids),
                          f"segment S{s + 1}: " + renumber_obstacles(str(exc).removesuffix(
                              exc.reason).removesuffix(": "), ids))


def segment_keep_out(corridor: Corridor, s: int, params: ControllerParams,
                     keep_out: np.ndarray | None) -> np.ndarray | None:
    """The points Remark 6's planner keeps out of segment ``s``'s triangles (and their apex
    look-ahead zones): ``keep_out`` (the start positions) and, after a junction, the corners
    of its hand-over region (Junction2 wants the hand-over clear of the triangles). The same
    for every process that plans the route."""
    if s == 0 or corridor.is_single:
        return keep_out
    a, b = corridor.segments[s - 1], corridor.segments[s]
    r = float(params.r_s)
    line, _, _ = handover_line(a, b, r)
    if line is None:
        return keep_out
    H = handover_region(a, b, r, line)
    if not len(H):
        return keep_out
    base = np.zeros((0, 2)) if keep_out is None else np.asarray(keep_out, float).reshape(-1, 2)
    return np.concatenate([base, H])


def replan_segment(tube: Trapezoid, fixed: Sequence[Obstacle], lost: Sequence[Obstacle],
                   params: ControllerParams) -> Partition:
    """The default lost-vehicle re-plan of one segment: the partition around its configured
    obstacles (apex distances as flown) and the lost ones as given; if that fails, the lost
    ones' h_k chosen by the planner (core/plan.py; deterministic). The rule of the fleet's
    ``FlightPlan.with_lost``, per segment; a better one is passed to :meth:`Route.with_lost`."""
    try:
        return partition(tube, tuple(fixed) + tuple(lost), params)
    except PartitionError:
        if not lost:
            raise
        auto = tuple(dataclasses.replace(o, apex_distance=APEX_AUTO) for o in lost)
        return partition(tube, tuple(fixed) + auto, params)


ReplanFn = Callable[[Trapezoid, Sequence[Obstacle], Sequence[Obstacle], "ControllerParams"],
                    Partition]


@dataclass(frozen=True, eq=False)
class Segment:
    """One segment of a planned route: its trapezoid ``tube``, ``obstacle_ids`` (route indices
    of its obstacles: config order, then the lost ones), its ``partition`` (obstacles numbered
    among themselves, as :func:`~vtube_fleet.core.partition.partition` builds it) and
    ``offset``, the global index of its first sub-tube."""

    index: int
    tube: Trapezoid
    obstacle_ids: tuple[int, ...]
    partition: Partition
    offset: int

    @property
    def name(self) -> str:
        return f"S{self.index + 1}"

    @property
    def K(self) -> int:
        return self.partition.K


@dataclass(frozen=True, eq=False)
class Route:
    """A corridor planned with the parameters ``params`` (the flown ones in flight): one
    :class:`Segment` per trapezoid. Build with :meth:`plan` (or :meth:`from_partitions`).

    Global sub-tube k of segment s is ``segments[s].offset + k``; :attr:`arrays` stacks them
    all for :func:`~vtube_fleet.core.controller.velocity_command`. ``lost`` are the obstacles
    left by lost vehicles (:meth:`with_lost`), numbered after the configured ones.
    ``lookahead``: :meth:`locate` applies the apex look-ahead (vehicles with response lag,
    :func:`~vtube_fleet.core.partition.apex_zones`) in every segment.
    """

    corridor: Corridor
    params: ControllerParams
    segments: tuple[Segment, ...]
    lost: tuple[Obstacle, ...] = ()
    lookahead: bool = False

    # ----- construction -----------------------------------------------------------------
    @classmethod
    def plan(cls, corridor: Corridor, params: ControllerParams, *,
             keep_out: np.ndarray | None = None, strict: bool = True, lookahead: bool = False,
             triangles_about: str = "O'") -> Route:
        """Partition every segment around its obstacles (Remark 6's planner per segment for
        ``"auto"`` apex distances, ``keep_out`` the start positions). Raises
        :class:`~vtube_fleet.core.partition.PartitionError` naming the segment and the
        obstacle (route numbers)."""
        parts = []
        multi = not corridor.is_single
        for s, tube in enumerate(corridor.segments):
            ids, obs = corridor.segment_obstacles(s)
            try:
                parts.append(partition(tube, obs, params, strict=strict,
                                       keep_out=segment_keep_out(corridor, s, params, keep_out),
                                       triangles_about=triangles_about))  # type: ignore[arg-type]
            except PartitionError as e:
                raise segment_error(s, ids, e, multi) from None
        return cls.from_partitions(corridor, params, parts, lookahead=lookahead)

    @classmethod
    def from_partitions(cls, corridor: Corridor, params: ControllerParams,
                        partitions: Sequence[Partition], *, lost: Sequence[Obstacle] = (),
                        lost_ids: Sequence[Sequence[int]] | None = None,
                        lookahead: bool = False) -> Route:
        """A route of already built partitions (one per segment, in order; the configured
        obstacles of each segment first, then ``lost_ids[s]``: route indices of its lost
        ones)."""
        if len(partitions) != corridor.S:
            raise ValueError(f"{len(partitions)} partitions for {corridor.S} segments")
        segs, off = [], 0
        for s, (tube, part) in enumerate(zip(corridor.segments, partitions, strict=True)):
            ids = corridor.segment_obstacles(s)[0]
            if lost_ids is not None:
                ids = ids + tuple(lost_ids[s])
            segs.append(Segment(s, tube, ids, part, off))
            off += part.K
        return cls(corridor, params, tuple(segs), tuple(lost), lookahead)

    # ----- what the controller and the runtime read -------------------------------------
    @property
    def S(self) -> int:
        return len(self.segments)

    @property
    def K(self) -> int:
        """Number of sub-tubes of all segments."""
        return sum(s.K for s in self.segments)

    @property
    def obstacles(self) -> tuple[Obstacle, ...]:
        """Every obstacle, route-numbered: the configured ones, then the lost ones."""
        return self.corridor.obstacles + self.lost

    @cached_property
    def sub_tubes(self) -> tuple[Trapezoid, ...]:
        """Every sub-tube in global order (named ``S2.T_o3`` in a route of several segments;
        the partition's own objects for one)."""
        if self.S == 1:
            return self.segments[0].partition.sub_tubes
        return tuple(dataclasses.replace(t, name=seg.name if t.name == seg.name
                                         else f"{seg.name}.{t.name}")
                     for seg in self.segments for t in seg.partition.sub_tubes)

    @cached_property
    def segment_of(self) -> np.ndarray:
        """(K,) the segment of each global sub-tube."""
        return np.repeat(np.arange(self.S), [s.K for s in self.segments])

    @cached_property
    def triangles(self) -> tuple[Triangle, ...]:
        """Every circumscribed triangle, its ``obstacle`` the route index, in that order. The
        circle a re-partition drew around a lost vehicle and the obstacles nearest to it
        (:mod:`~vtube_fleet.core.loss`, "grouped") is no obstacle of the route: its triangle
        is numbered after them (``len(obstacles)`` on), one number per circle."""
        if self.S == 1 and not self.lost:
            return self.segments[0].partition.triangles
        out, extra = [], len(self.obstacles)
        for seg in self.segments:
            for t in seg.partition.triangles:
                if t.obstacle < len(seg.obstacle_ids):
                    out.append(dataclasses.replace(t, obstacle=seg.obstacle_ids[t.obstacle]))
                else:  # a grouped circle (its own number)
                    out.append(dataclasses.replace(t, obstacle=extra))
                    extra += 1
        return tuple(sorted(out, key=lambda t: t.obstacle))

    @cached_property
    def arrays(self) -> TubeArrays:
        """Every sub-tube stacked for the controller (global index)."""
        return TubeArrays.from_tubes(self.sub_tubes)

    @cached_property
    def zones(self) -> tuple[tuple[ApexZone, ...], ...]:
        """The apex look-ahead zones of each segment (local sub-tube indices); empty
        without ``lookahead``."""
        if not self.lookahead:
            return tuple(() for _ in self.segments)
        return tuple(apex_zones(s.partition, self.params) for s in self.segments)

    @cached_property
    def _table(self) -> dict[str, np.ndarray]:
        """Per-segment constants (S, …): leg normals and offsets, n_c, ξ origin, length."""
        tubes = [s.tube for s in self.segments]
        return {
            "n_h": np.stack([t.n_h for t in tubes]), "c_h": np.array([t.n_h @ t.p_h1
                                                                       for t in tubes]),
            "n_r": np.stack([t.n_r for t in tubes]), "c_r": np.array([t.n_r @ t.p_r1
                                                                       for t in tubes]),
            "n_c": np.stack([t.n_c for t in tubes]), "x0": np.array([t.n_c @ t.p_h0
                                                                      for t in tubes]),
            "L": np.array([t.length for t in tubes]),
            "off": np.array([s.offset for s in self.segments], dtype=np.intp),
            # the entry test of segment s + 1 as complex rows (entry_gap): for a point z,
            # Re(z·A[s]) + B[s] = (r_s − d_Th, r_s − d_Tr, −ξ − tol, ξ − L) of segment s + 1,
            # and +inf for the last segment
            "A": np.array([[complex(t.n_h[0], -t.n_h[1]) * -1, complex(t.n_r[0], -t.n_r[1]) * -1,
                            complex(t.n_c[0], -t.n_c[1]) * -1, complex(t.n_c[0], -t.n_c[1])]
                           for t in tubes[1:]] + [[0j] * 4]),
            "B": np.array([[float(self.params.r_s) + d + float(t.n_h @ t.p_h1),
                            float(self.params.r_s) + d + float(t.n_r @ t.p_r1),
                            float(t.n_c @ t.p_h0) - LOCATE_TOL,
                            -float(t.n_c @ t.p_h0) - t.length]
                           for t, d in zip(tubes[1:], self.handover_depths, strict=True)]
                          + [[math.inf] * 4]),
        }

    @cached_property
    def handover_depths(self) -> tuple[float, ...]:
        """How far beyond r_s inside the next segment's legs a vehicle hands over, per
        junction: half the Junction1 margin μ (0 when μ ≤ 0, e.g. a shared base). By the
        hand-over line every vehicle is μ beyond r_s, so it has handed over there at the
        latest, and it enters the next segment with μ/2 to spare (a body that lags its
        control point, a vehicle that lags its command)."""
        out = []
        r = float(self.params.r_s)
        for j in range(self.S - 1):
            line, mu, _ = handover_line(self.segments[j].tube, self.segments[j + 1].tube, r)
            out.append(0.5 * mu if line is not None and mu > 0.0 else 0.0)
        return tuple(out)

    def leg_distances(self, p: np.ndarray, segment: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dtl), (dtr) of each point (M, 2) to the MAIN legs of its own segment → (d_Th,
        d_Tr), each (M,): the leg distance the safety monitor judges."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        s = np.asarray(segment, dtype=np.intp).reshape(-1)
        tb = self._table
        return (np.einsum("ij,ij->i", p, tb["n_h"][s]) - tb["c_h"][s],
                np.einsum("ij,ij->i", p, tb["n_r"][s]) - tb["c_r"][s])

    def leg_table(self, segment: np.ndarray) -> tuple[np.ndarray, ...]:
        """(n_h (M, 2), n_hᵀp_h1 (M,), n_r (M, 2), n_rᵀp_r1 (M,)) of each point's segment: the
        main legs a robot flying it must keep r_s from."""
        s = np.asarray(segment, dtype=np.intp).reshape(-1)
        tb = self._table
        return tb["n_h"][s], tb["c_h"][s], tb["n_r"][s], tb["c_r"][s]

    def xi(self, p: np.ndarray, segment: np.ndarray) -> np.ndarray:
        """ξ of each point in its own segment (0 on that segment's start base)."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        s = np.asarray(segment, dtype=np.intp).reshape(-1)
        tb = self._table
        return np.einsum("ij,ij->i", p, tb["n_c"][s]) - tb["x0"][s]

    def finished(self, p: np.ndarray, segment: np.ndarray | None = None) -> np.ndarray:
        """(TraCondition) on the LAST segment's finishing line, for points flying the last
        segment (``segment``: each point's segment; ``None`` for a one-segment route)."""
        done = self.segments[-1].tube.finished(p, self.params.eps_0)
        if segment is None:
            if self.S != 1:
                raise ValueError("finished() of a route of several segments needs the "
                                 "points' segments")
            return done
        return done & (np.asarray(segment).reshape(np.shape(done)) == self.S - 1)

    @property
    def exit_heading(self) -> np.ndarray:
        """n_c of the LAST segment: the direction a vehicle past the route's finishing line
        flies on (Assumption 2)."""
        return self.segments[-1].tube.n_c

    def beyond_finish_m(self, p: np.ndarray) -> np.ndarray:
        """(M,) how far each point (M, 2) is past the LAST segment's finishing line along its
        n_c (ξ − L of the last segment; < 0 before it)."""
        last = self.segments[-1].tube
        return np.asarray(last.xi(np.asarray(p, dtype=float).reshape(-1, 2)), float) \
            - last.length

    # ----- the switching rule -----------------------------------------------------------
    def start_segments(self, p: np.ndarray) -> np.ndarray:
        """The segment each point (M, 2) starts in: the first segment whose trapezoid contains
        it, else the one it is least outside of; then the hand-overs it already qualifies for
        (:meth:`handover`)."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        if self.S == 1:
            return np.zeros(p.shape[0], dtype=np.intp)
        return self.handover(p, self.corridor.start_segment_of(p))

    def entry_gap(self, p: np.ndarray, segment: np.ndarray) -> np.ndarray:
        """How far (m) each point is from the entry region of the segment after its own:
        max(r − d_Th, r − d_Tr, −ξ, ξ − L) of segment + 1 with r = r_s + the junction's
        :attr:`handover_depths` (< 0: inside it by the main legs; +inf in the last segment).
        It shrinks by at most a point's move."""
        p = np.ascontiguousarray(p, dtype=float).reshape(-1, 2)
        s = np.asarray(segment, dtype=np.intp).reshape(-1)
        tb = self._table
        z = p.view(np.complex128)  # (M, 1)
        g = (z * tb["A"].take(s, axis=0)).real
        g += tb["B"].take(s, axis=0)
        return g.max(axis=1)

    def _enters(self, q: np.ndarray, nxt: np.ndarray) -> np.ndarray:
        """Whether points q may hand over to segments ``nxt``: more than r_s +
        :attr:`handover_depths` from nxt's main legs, 0 ≤ ξ ≤ L in it, and more than r_s from
        the legs of the sub-tube of nxt they would fly (the switching rule of its partition,
        with the look-ahead if any)."""
        gap = self.entry_gap(q, nxt - 1)
        ok = gap < 0.0
        rows = np.flatnonzero(ok)
        if rows.size:
            qs, ss = q[rows], nxt[rows]
            k = self._local(qs, ss)
            r_s = float(self.params.r_s)
            good = (self.arrays.d_Th(qs, k) > r_s) & (self.arrays.d_Tr(qs, k) > r_s)
            ok[rows[~good]] = False
        return ok

    def handover(self, p: np.ndarray, segment: np.ndarray) -> np.ndarray:
        """The segments after the hand-overs due at positions ``p`` (M, 2), from the current
        ``segment`` (M,): a point moves from s to s + 1 (and on, if it qualifies for the next
        too) when :meth:`_enters` holds. Returns a new array."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        seg = np.array(segment, dtype=np.intp).reshape(-1)
        for _ in range(self.S - 1):
            rows = np.flatnonzero(seg < self.S - 1)
            if not rows.size:
                break
            ok = self._enters(p[rows], seg[rows] + 1)
            if not ok.any():
                break
            seg[rows[ok]] += 1
        return seg

    def _local(self, p: np.ndarray, segment: np.ndarray) -> np.ndarray:
        """Global sub-tube of each point in its own segment's partition (§5 rule, with the
        look-ahead zones if any)."""
        k = np.empty(p.shape[0], dtype=np.intp)
        for s in np.unique(segment):
            rows = np.flatnonzero(segment == s)
            seg = self.segments[int(s)]
            q = p[rows]
            kl = np.asarray(seg.partition.locate(q), dtype=np.intp).reshape(-1)
            if self.zones[int(s)]:
                kl = apex_lookahead(seg.partition, self.zones[int(s)], q, kl)
            k[rows] = kl + seg.offset
        return k

    def locate(self, p: np.ndarray, segment: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """The switching rule over the route: (segment (M,), global sub-tube (M,)) of points
        p (M, 2) that were flying ``segment`` (M,) (``None``: :meth:`start_segments`). Pure:
        the caller keeps the segments (the hand-over needs them) and passes them back."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        if self.S == 1 and not self.lookahead:
            k = np.asarray(self.segments[0].partition.locate(p), dtype=np.intp).reshape(-1)
            return np.zeros(p.shape[0], dtype=np.intp), k
        seg = self.start_segments(p) if segment is None else self.handover(p, segment)
        return seg, self._local(p, seg)

    def follow(self, pos: np.ndarray) -> np.ndarray:
        """(T, M) the segment of every point of a trajectory ``pos`` (T, M, 2) (NaN rows:
        absent), the hand-overs replayed frame by frame (:meth:`advance`) from the segment each
        point starts in (:meth:`start_segments` at its first frame): what ``review`` judges
        each leg distance against."""
        pos = np.asarray(pos, dtype=float)
        T, M = pos.shape[:2]
        out = np.zeros((T, M), dtype=np.intp)
        if self.S == 1:
            return out
        seg = np.full(M, -1, dtype=np.intp)
        for t in range(T):
            seg = self.advance(pos[t], seg)
            out[t] = np.maximum(seg, 0)
        return out

    def advance(self, p: np.ndarray, segment: np.ndarray) -> np.ndarray:
        """One frame of :meth:`follow`: the segments (M,) after points p (M, 2) were seen
        flying ``segment`` (M,; −1: not seen yet): a point seen for the first time starts in
        :meth:`start_segments`, the others hand over (:meth:`handover`); absent points (NaN
        rows) keep theirs. Returns a new array. The runtime's hand-over state (the fleet's
        segment column, the coordinator's replay) advances by this."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        seg = np.array(segment, dtype=np.intp).reshape(-1)
        if self.S == 1:
            seg[np.isfinite(p).all(axis=1)] = 0
            return seg
        here = np.isfinite(p).all(axis=1)
        new = here & (seg < 0)
        if new.any():
            seg[new] = self.start_segments(p[new])
        old = here & ~new
        if old.any():
            seg[old] = self.handover(p[old], seg[old])
        return seg

    def tracker(self, p0: np.ndarray) -> RouteTracker:
        """A :class:`RouteTracker` (the simulator's incremental :meth:`locate`)."""
        return RouteTracker(self, p0)

    # ----- lost vehicles ----------------------------------------------------------------
    def with_lost(self, lost: Sequence[Obstacle], replan: ReplanFn | None = None) -> Route:
        """The route re-planned around obstacles left by lost (or stopped) vehicles,
        replacing any previous ones: each segment whose trapezoid the lost obstacle's O'
        (r_o + r_s) meets is re-partitioned by ``replan(tube, fixed, lost_here, params)``
        (default :func:`replan_segment`), ``fixed`` its configured obstacles with the apex
        distances they are flown with. One stopped in a junction's overlap belongs to both
        segments. A lost obstacle meeting no segment is nobody's. Raises
        :class:`~vtube_fleet.core.partition.PartitionError` (route numbers) when a segment
        cannot be partitioned."""
        replan = replan or replan_segment
        lost = tuple(lost)
        n_cfg = len(self.corridor.obstacles)
        R_s = float(self.params.r_s)
        parts, lost_ids = [], []
        for s, seg in enumerate(self.segments):
            here = [i for i, o in enumerate(lost) if disc_meets(seg.tube, o, R_s)]
            ids_cfg, obs_cfg = self.corridor.segment_obstacles(s)
            tri_h = {t.obstacle: t.h for t in seg.partition.triangles}
            fixed = tuple(dataclasses.replace(ob, apex_distance=tri_h[j])
                          if isinstance(ob.apex_distance, str) and j in tri_h else ob
                          for j, ob in enumerate(obs_cfg))
            ids = ids_cfg + tuple(n_cfg + i for i in here)
            if not here and not self.segments[s].obstacle_ids[len(ids_cfg):]:
                parts.append(seg.partition)  # nothing lost here, before or now: unchanged
            else:
                try:
                    parts.append(replan(seg.tube, fixed, [lost[i] for i in here],
                                        self.params))
                except PartitionError as e:
                    raise segment_error(s, ids, e, self.S > 1) from None
            lost_ids.append(tuple(n_cfg + i for i in here))
        return Route.from_partitions(self.corridor, self.params, parts, lost=lost,
                                     lost_ids=lost_ids, lookahead=self.lookahead)


# ----------------------------------------------------------------------------------------------
# incremental locate for the simulator
# ----------------------------------------------------------------------------------------------
class RouteTracker:
    """:meth:`Route.locate` for a swarm that moves a little between calls, exactly: per
    segment a :class:`~vtube_fleet.core.partition.SubTubeTracker` over all points (the §5
    rule of that segment's partition), the hand-over test only when some point may have come
    within reach of its next segment's entry region (:meth:`Route.entry_gap` shrinks by at
    most a point's move). :attr:`segment` (read-only) holds every point's segment;
    :attr:`handed` is set when a hand-over happened (the caller clears it)."""

    def __init__(self, route: Route, p0: np.ndarray) -> None:
        if route.lookahead:
            raise ValueError("RouteTracker follows the §5 rule (a route without look-ahead)")
        self.route = route
        p0 = np.asarray(p0, dtype=float).reshape(-1, 2)
        seg = route.start_segments(p0)
        seg.setflags(write=False)
        self.segment = seg
        self.handed = False
        self._trackers = [s.partition.tracker() for s in route.segments]
        self._off = route._table["off"]
        self._slack = -math.inf
        self._ks: list[np.ndarray] | None = None
        self._seg_k: np.ndarray | None = None
        self._k = np.zeros(0, np.intp)
        self.checks = 0

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the points ``mask`` (the others exited), in order."""
        seg = self.segment[np.asarray(mask, dtype=bool)]
        seg.setflags(write=False)
        self.segment = seg
        self._slack = -math.inf
        self._ks = None

    def quiet_calls(self, move: float) -> int:
        """Calls of :meth:`update` with ``move`` guaranteed not to test a hand-over."""
        dec = move * (1.0 + 1e-9) + 1e-9
        if not math.isfinite(self._slack):
            return 0 if self._slack < 0 else 1 << 40
        return max(0, int(self._slack / dec) - 1)

    def update(self, p: np.ndarray, max_move: float | None = None,
               handover: bool = True) -> np.ndarray:
        """Global sub-tube of each point (M, 2) → (M,) read-only (the same object while
        nothing changes), equal to ``route.locate(p, segment)[1]`` with the segments after
        the hand-overs due. ``handover=False``: do not test hand-overs in this call (an
        intermediate point of an integrator step)."""
        if max_move is None:
            self._slack = -math.inf
        else:
            self._slack -= max_move * (1.0 + 1e-9) + 1e-9
        if handover and not self._slack > 0.0:
            self.checks += 1
            seg = self.segment
            if seg.shape[0] != p.shape[0]:
                raise ValueError(f"{p.shape[0]} points for {seg.shape[0]} segments")
            gap = self.route.entry_gap(p, seg)
            if (gap < 0.0).any():  # only a point inside an entry region can hand over
                new = self.route.handover(p, seg)
                if (new != seg).any():
                    new.setflags(write=False)
                    self.segment = new
                    self.handed = True
                    gap = self.route.entry_gap(p, new)
            self._slack = float(gap.min()) if gap.shape[0] else math.inf
        ks = [t.update(p, max_move) for t in self._trackers]
        if (self._ks is not None and self._seg_k is self.segment
                and all(a is b for a, b in zip(ks, self._ks, strict=True))):
            return self._k
        seg = self.segment
        stack = np.stack(ks)
        k = stack[seg, np.arange(seg.shape[0])] + self._off[seg]
        k.setflags(write=False)
        if not (self._k.shape == k.shape and (self._k == k).all()):
            self._k = k
        self._ks, self._seg_k = ks, seg
        return self._k


# ----------------------------------------------------------------------------------------------
# the junction conditions (docs/route.md)
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class JunctionCheck:
    """The conditions of one junction with their margins (docs/route.md):

    * ``Junction1`` (hand-over line): ``handover_xi_m`` is ξ (in the first segment) of the
      line across it whose every vehicle position lies in the second segment's entry region,
      ``handover_margin_m`` the least clearance beyond r_s to the second segment's legs there
      (−inf when no such line exists);
    * ``Junction2`` (a clear junction): ``clear_margin_m``, how far the hand-over region stays
      upstream of the second segment's triangles and their look-ahead zones (inf: none);
    * ``Junction3`` (progress): ``progress_m_s`` = v cos β − v'_max, the least speed along
      the second segment's n_c in its first sub-tube (β its steepest narrowing leg);
    * ``Junction4`` (overlap inside the corridor): ``corridor_margin_m``, how far the
      prolonged segments stay inside the corridor's mitred outline (< 0: they leave it);

    ``command_jump_m_s`` = 2 v sin(|θ|/2): the change of u1'' at the hand-over (for the
    runtime's lag budget; not a condition of the single integrator)."""

    junction: Junction
    handover_xi_m: float | None
    handover_margin_m: float
    clear_margin_m: float
    progress_m_s: float
    corridor_margin_m: float
    command_jump_m_s: float
    violations: tuple[Violation, ...] = ()

    @property
    def ok(self) -> bool:
        return not self.violations

    def describe(self) -> str:
        j = self.junction
        xi = "none" if self.handover_xi_m is None else f"ξ = {_num(self.handover_xi_m, 2)} m"
        clear = ("no triangles" if not math.isfinite(self.clear_margin_m)
                 else f"{_num(self.clear_margin_m, 3)} m")
        corr = ("a shared base" if not math.isfinite(self.corridor_margin_m)
                else f"{_num(self.corridor_margin_m, 3)} m")
        return (f"{j.name}: bend {_num(j.theta_deg, 1)}°, overlap {j.overlap_text()}; "
                f"[Junction1] hand-over line {xi} of S{j.index + 1}, margin "
                f"{_num(self.handover_margin_m, 3)} m; [Junction2] clear of triangles: {clear}; "
                f"[Junction3] progress {_num(self.progress_m_s, 3)} m/s; [Junction4] overlap "
                f"inside the corridor, margin {corr}; command jump "
                f"{_num(self.command_jump_m_s, 3)} m/s")


def handover_line(a: Trapezoid, b: Trapezoid, r: float) -> tuple[float | None, float, str]:
    """Junction1: the best line ξ_a = s across a's vehicle region (r from a's legs) lying in
    b's entry region (0 ≤ ξ_b ≤ L_b): maximise the least d_b − r of its two end points → (s,
    margin, what binds); (None, shortfall, why) when no line reaches past b's start base."""
    # end points of the cross-section at ξ_a = s: P(s) = P0 + s D on the legs moved in by r
    ends = []
    for p0, t, n in ((a.p_h0, a.t_h, a.n_h), (a.p_r0, a.t_r, a.n_r)):
        A = p0 + r * n
        adv = float(t @ a.n_c)
        P0 = A - t * (float(a.xi(A)) / adv)
        ends.append((P0, t / adv))

    f_list: list[tuple[float, float, str]] = []  # margins h0 + h1 s (want max of the min)
    g_list: list[tuple[float, float, str]] = []  # constraints h0 + h1 s ≥ 0
    names = ("the lane r_s from its left leg", "the lane r_s from its right leg")
    for (P0, D), who in zip(ends, names, strict=True):
        for nrm, c, leg in ((b.n_h, float(b.n_h @ b.p_h1), "left"),
                            (b.n_r, float(b.n_r @ b.p_r1), "right")):
            f_list.append((float(nrm @ P0) - c - r, float(nrm @ D),
                           f"{who} comes within r_s of S_b's {leg} leg"))
        x0 = float(b.n_c @ b.p_h0)
        g_list.append((float(b.n_c @ P0) - x0, float(b.n_c @ D),
                       f"{who} is not yet past S_b's start base"))
        g_list.append((b.length - (float(b.n_c @ P0) - x0), -float(b.n_c @ D),
                       f"{who} is past S_b's finishing line"))
    (P0l, Dl), (P0r, Dr) = ends
    g_list.append((float(a.m @ (P0r - P0l)), float(a.m @ (Dr - Dl)), "the lanes cross"))
    lo, hi = 0.0, a.length

    def best(funcs: list[tuple[float, float, str]], lo: float, hi: float
             ) -> tuple[float, float, str]:
        cands = {lo, hi}
        for i in range(len(funcs)):
            for j in range(i + 1, len(funcs)):
                d = funcs[i][1] - funcs[j][1]
                if abs(d) > 1e-15:
                    s = (funcs[j][0] - funcs[i][0]) / d
                    if lo <= s <= hi:
                        cands.add(s)
        out = (lo, -math.inf, "")
        for s in sorted(cands):
            vals = [(h0 + h1 * s, why) for h0, h1, why in funcs]
            v, why = min(vals)
            if v > out[1]:
                out = (s, v, why)
        return out

    # the feasible interval of the constraints
    for h0, h1, _ in g_list:
        if abs(h1) < 1e-15:
            if h0 < -_TOL:
                lo, hi = 1.0, 0.0
            continue
        s0 = -h0 / h1
        if h1 > 0:
            lo = max(lo, s0)
        else:
            hi = min(hi, s0)
    if lo > hi + 1e-12:
        s, v, why = best(g_list, 0.0, a.length)
        return None, v, why
    s, v, why = best(f_list, lo, min(hi, a.length) if hi >= lo else lo)
    return s, v, why


def handover_region(a: Trapezoid, b: Trapezoid, r: float, s: float) -> np.ndarray:
    """H: a's vehicle region up to ξ_a = s, inside b's entry region (polygon (n, 2))."""
    poly = a.polygon()
    poly = _clip(poly, a.n_h, float(a.n_h @ a.p_h1) + r)
    poly = _clip(poly, a.n_r, float(a.n_r @ a.p_r1) + r)
    poly = _clip(poly, -a.n_c, -(float(a.n_c @ a.p_h0) + s) - _TOL)
    poly = _clip(poly, b.n_h, float(b.n_h @ b.p_h1) + r)
    poly = _clip(poly, b.n_r, float(b.n_r @ b.p_r1) + r)
    poly = _clip(poly, b.n_c, float(b.n_c @ b.p_h0) - _TOL)
    return _clip(poly, -b.n_c, -(float(b.n_c @ b.p_h0) + b.length))


def progress_speed(b: Trapezoid, params: ControllerParams) -> float:
    """v cos β − v'_max, β the steepest narrowing main leg of b (0 if none): the least speed
    along b's n_c of a robot in b's first sub-tube."""
    beta = 0.0
    for leg, has in ((b.t_h, b.has_L), (b.t_r, b.has_R)):
        if has:
            beta = max(beta, math.acos(max(-1.0, min(1.0, float(leg @ b.n_c)))))
    return params.v * math.cos(beta) - params.v_max_prime


def junction_checks(route: Route) -> list[JunctionCheck]:
    """The conditions Junction1–4 of every junction of a planned route, with their margins
    (:class:`JunctionCheck`; docs/route.md gives the reasoning)."""
    out = []
    geo = route.corridor.geometry
    pieces = geo.pieces() if geo.S > 1 else []
    r = float(route.params.r_s)
    p = route.params
    for j, jn in enumerate(geo.junctions):
        sa, sb = route.segments[j], route.segments[j + 1]
        a, b = sa.tube, sb.tube
        bad: list[Violation] = []
        where = jn.name
        # Junction1: the hand-over line
        s, mu, why = handover_line(a, b, r)
        why = why.replace("S_b", f"S{j + 2}")
        if s is None or mu < -1e-9:
            what = ("no line across S{a} reaches into S{b}'s entry region: {why} (by "
                    "{m} m)" if s is None else
                    "the best line across S{a} (ξ = {xi} m) leaves a vehicle position short of "
                    "S{b}'s entry region: {why} (by {m} m)").format(
                        a=j + 1, b=j + 2, why=why, m=_num(-mu, 3),
                        xi=_num(s if s is not None else 0.0, 2))
            bad.append(Violation("Junction1", f"Junction1 violated at {where}: {what}"))
        # Junction2: the hand-over region clear of triangles and look-ahead zones
        clear = math.inf
        if s is not None:
            H = handover_region(a, b, r, s)
            if len(H):
                zones = {z.triangle: z for z in route.zones[j + 1]}
                h_max = float(b.xi(H).max())
                for tri in sb.partition.triangles:
                    z = zones.get(tri.obstacle)
                    apex = float(b.xi(tri.p_oth))
                    m = apex - (0.0 if z is None else z.depth_m) - h_max
                    if m < clear:
                        # the zone is cut where its before-tube starts (b's start for the
                        # first triangle): how far it reaches in, uncut, is the move needed
                        full = 0.0 if z is None else _uncut_depth(sb.partition, z, route.params)
                        clear, who = m, (max(-m, h_max - (apex - full)),
                                         sb.obstacle_ids[tri.obstacle])
                if clear <= 0.0:
                    reach, ob = who
                    txt = (f"the triangle of obstacle #{ob + 1} (S{j + 2}) reaches into the "
                           f"hand-over region by {_num(reach, 3)} m (its apex"
                           f"{' and look-ahead zone' if route.lookahead else ''} must lie "
                           f"downstream of where vehicles enter S{j + 2})")
                    bad.append(Violation("Junction2", f"Junction2 violated at {where}: {txt}"))
        # Junction3: progress along n_c
        prog = progress_speed(b, p)
        if not prog > 0.0:
            bad.append(Violation("Junction3", (
                f"Junction3 violated at {where}: v cos β − v'_max = {_num(prog, 3)} m/s ≤ 0 "
                f"(β the steepest narrowing leg of S{j + 2}): a vehicle just handed over could "
                f"be pushed back out of S{j + 2}'s start")))
        # Junction4: the prolonged segments inside the corridor's mitred outline
        corr = math.inf
        pm, nrm = geo.mitre(j)
        for seg_t, piece, sign, who, other in ((a, pieces[j + 1], 1.0, j + 1, j + 2),
                                               (b, pieces[j], -1.0, j + 2, j + 1)):
            part = _clip(seg_t.polygon(), sign * nrm, sign * float(nrm @ pm) + 1e-9)
            if not len(part):
                continue
            m = _polygon_margin(part, piece)
            if m < corr:
                # how far the overlap reaches past the other piece's far end (its next mitre)
                far = j + 1 if sign > 0 else j - 1
                past = 0.0
                if 0 <= far < geo.S - 1:
                    pf, nf = geo.mitre(far)
                    past = float(np.max(sign * ((part - pf) @ nf)))
                corr, worst = m, (who, other, past)
        if corr < -1e-6:
            who, other, past = worst
            wp = geo.waypoints[jn.waypoint] if geo.waypoints else None
            if abs(jn.theta_deg) > 90.0:
                why = "beyond 90° the prolonged segments leave the corridor"
            elif wp is not None and wp.overlap_m is not None:
                why = "an overlap_m above the mitre takes the prolonged segments out of it"
            elif past > 1e-6:
                why = (f"S{other} is too short for the bends at both its ends: the overlap "
                       f"reaches {_num(past, 3)} m past its other end; lengthen S{other} or "
                       f"make the bends gentler")
            else:
                why = ("the legs meet at more than 90° where the corridor's width changes at "
                       "the bend: make the bend gentler or keep the width")
            bad.append(Violation("Junction4", (
                f"Junction4 violated at {where}: the overlap of S{who} reaches "
                f"{_num(-corr, 3)} m outside S{other}'s part of the corridor (bend "
                f"{_num(abs(jn.theta_deg), 1)}°, overlap {jn.overlap_text()}; {why})")))
        out.append(JunctionCheck(jn, s, mu, clear, prog, corr,
                                 2.0 * p.v * math.sin(abs(jn.theta) / 2.0), tuple(bad)))
    return out


def _uncut_depth(part: Partition, zone: ApexZone, params: ControllerParams) -> float:
    """The depth of an apex look-ahead zone before it is cut at its before-tube's start
    (:func:`~vtube_fleet.core.partition.lookahead_depth` with unlimited room)."""
    sides = [part.sub_tubes[k].t_r for k in (zone.left,) if k is not None] + \
            [part.sub_tubes[k].t_h for k in (zone.right,) if k is not None]
    if not sides:
        return zone.depth_m
    full = lookahead_depth(sides, part.tube.n_c, params, math.inf)
    return full if math.isfinite(full) else zone.depth_m


def _polygon_margin(pts: np.ndarray, piece: np.ndarray) -> float:
    """Least signed distance (m) of points inside the convex polygon ``piece`` (< 0: outside)."""
    n = len(piece)
    if n < 3:
        return -math.inf
    area2 = sum(piece[i][0] * piece[(i + 1) % n][1] - piece[(i + 1) % n][0] * piece[i][1]
                for i in range(n))
    sgn = 1.0 if area2 > 0 else -1.0
    best = math.inf
    for i in range(n):
        e = piece[(i + 1) % n] - piece[i]
        ln = float(np.hypot(*e))
        if ln < 1e-12:
            continue
        d = sgn * (e[0] * (pts[:, 1] - piece[i][1]) - e[1] * (pts[:, 0] - piece[i][0])) / ln
        best = min(best, float(d.min()))
    return best


def obstacle_ownership(corridor: Corridor, r_s: float) -> list[Violation]:
    """Junction5: every obstacle belongs to one segment. Its centre in two segments (a
    junction's overlap), or its O' (r_o + r_s) reaching into another segment's trapezoid, is
    refused: a vehicle flying that segment would not know the obstacle."""
    out: list[Violation] = []
    if corridor.is_single:
        return out
    for i, segs in corridor.shared:
        ob = corridor.obstacles[i]
        out.append(Violation("Junction5", (
            f"Junction5 violated: {obstacle_label(i, ob)} lies in the overlap of "
            f"{' and '.join(f'S{s + 1}' for s in segs)} (a junction): it would belong to two "
            f"segments; move it out of the junction")))
    shared = {i for i, _ in corridor.shared}
    for i, ob in enumerate(corridor.obstacles):
        if i in shared:
            continue
        R = float(ob.radius) + float(r_s)
        own = corridor.owner[i]
        for s, t in enumerate(corridor.segments):
            if s == own:
                continue
            if _contains(t, ob.center):
                d_in = -1.0
            else:
                d_in = _dist_to_polygon(ob.center, t.polygon())
            if d_in < R:
                reach = R - max(d_in, 0.0)
                out.append(Violation("Junction5", (
                    f"Junction5 violated: {obstacle_label(i, ob)} (segment S{own + 1}) "
                    f"reaches into S{s + 1}: its O' (r_o + r_s = {_num(R)} m) comes "
                    f"{_num(reach, 3)} m inside it; vehicles flying S{s + 1} do not avoid it "
                    f"(move it at least {_num(reach, 2)} m away from S{s + 1})")))
    return out
