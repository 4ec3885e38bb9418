"""The tube as a geofence: an inclusion polygon around the main tube and one exclusion circle
per obstacle, in the paper's 2-D tube frame (pure numpy; the runtime turns it into PX4 fence
items, ``docs/fleet.md`` "The fence on the vehicle").

Geometry (w = r_s + ``margin_m``, the vehicle radius r_s of the *physical* parameters plus a
margin):

* the left and right legs of T are moved outwards by w (their inward normals n_h, n_r);
* between ξ = 0 and ξ = L the polygon follows these moved legs; behind the start base it goes
  straight back along −n_c by ``back_m`` (at least w, and far enough to hold every start slot
  with w to spare), past the finishing line straight on along n_c by ``exit_m`` — the exit
  behaviour (Assumption 2: straight on along n_c) and the landing stay inside;
* each obstacle O_k gets an exclusion circle of radius r_o,k + r_s (the body touches the
  obstacle on PX4's estimate).

The controller keeps every vehicle's estimate r_s' = r_s + δ inside the legs and r_o + r_s'
from an obstacle centre, so in a correct flight the fence never fires; it is the vehicle's own
backstop when our process, its host or its link fails.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtube_fleet.core.text import compact_number, point_text
from vtube_fleet.core.tube import Obstacle, Trapezoid

__all__ = ["FENCE_MARGIN_M", "FenceGeometry", "RouteFence", "route_fence", "tube_fence"]

#: Default margin beyond r_s by which the legs are widened (metres).
FENCE_MARGIN_M = 1.0

_EPS = 1e-9


@dataclass(frozen=True, eq=False)
class FenceGeometry:
    """Inclusion polygon ``polygon`` (K, 2) (counter-clockwise, tube frame, no repeated
    vertex) and exclusion circles ``circle_centers`` (C, 2) / ``circle_radii`` (C,)."""

    polygon: np.ndarray
    circle_centers: np.ndarray
    circle_radii: np.ndarray
    widen_m: float
    back_m: float
    exit_m: float

    def inside_polygon(self, x: np.ndarray) -> np.ndarray:
        """Points (…, 2) inside the inclusion polygon (crossing-number test, as PX4's
        ``insidePolygon``; points on an edge may go either way)."""
        p = np.asarray(x, dtype=float)
        px, py = p[..., 0][..., None], p[..., 1][..., None]
        a = self.polygon
        b = np.roll(a, -1, axis=0)
        ax, ay, bx, by = a[:, 0], a[:, 1], b[:, 0], b[:, 1]
        straddle = (ay > py) != (by > py)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = (bx - ax) * (py - ay) / (by - ay) + ax
        hits = straddle & (px < x_cross)
        return (np.count_nonzero(hits, axis=-1) % 2) == 1

    def inside_exclusion(self, x: np.ndarray) -> np.ndarray:
        """Points (…, 2) strictly inside any exclusion circle."""
        p = np.asarray(x, dtype=float)
        if self.circle_radii.size == 0:
            return np.zeros(p.shape[:-1], dtype=bool)
        d = np.linalg.norm(p[..., None, :] - self.circle_centers, axis=-1)
        return np.any(d < self.circle_radii, axis=-1)

    def contains(self, x: np.ndarray) -> np.ndarray:
        """Points (…, 2) the fence allows: inside the polygon, outside every circle."""
        return self.inside_polygon(x) & ~self.inside_exclusion(x)

    def problems(self, x: np.ndarray, names: Sequence[str]) -> list[str]:
        """One line per point of ``x`` (M, 2) the fence would not allow (vehicles before
        arming: PX4 would breach at once)."""
        pts = np.asarray(x, dtype=float).reshape(-1, 2)
        return _problems(pts, names, self.inside_polygon(pts), self.inside_exclusion(pts),
                         f"the fence polygon (legs widened by {compact_number(self.widen_m)} m, "
                         f"{compact_number(self.back_m)} m behind the start base, "
                         f"{compact_number(self.exit_m)} m past the finishing line)")


def _leg_point(p0: np.ndarray, t: np.ndarray, n_in: np.ndarray, n_c: np.ndarray,
               origin: np.ndarray, w: float, xi: float) -> np.ndarray:
    """Point at longitudinal coordinate ``xi`` of the leg line through ``p0`` (direction t)
    moved outwards by ``w`` (against its inward normal)."""
    q0 = p0 - w * n_in
    s = (xi - float(n_c @ (q0 - origin))) / float(t @ n_c)
    return q0 + s * t


def _drop_collinear(poly: np.ndarray) -> np.ndarray:
    keep = []
    n = len(poly)
    for i in range(n):
        a, b, c = poly[i - 1], poly[i], poly[(i + 1) % n]
        u, v = b - a, c - b
        if np.hypot(*u) < _EPS:
            continue
        cross = u[0] * v[1] - u[1] * v[0]
        if abs(cross) > _EPS * max(1.0, np.hypot(*u) * np.hypot(*v)):
            keep.append(b)
    return np.array(keep)


def exit_room_m(tube_length_m: float, exit_clear_m: float = 0.0) -> float:
    """How far past the finishing line the fence's exit reaches inside its margin w (the
    default ``exit_m`` of :func:`tube_fence` is this + w): the tube's length L plus
    ``exit_clear_m``. A vehicle that flies on past the line must stop within it."""
    return float(tube_length_m) + float(exit_clear_m)


def tube_fence(tube: Trapezoid, obstacles: Sequence[Obstacle], r_s: float, *,
               slots: np.ndarray | None = None, margin_m: float = FENCE_MARGIN_M,
               exit_m: float | None = None, exit_clear_m: float = 0.0) -> FenceGeometry:
    """The fence of ``tube`` (module docstring). ``slots`` (M, 2): start positions that must
    be inside with w to spare (they set ``back_m``). ``exit_m`` (default: L + ``exit_clear_m``
    + w): how far past the finishing line the polygon reaches.

    Raises ``ValueError`` for a negative margin or exit length.
    """
    if not (np.isfinite(margin_m) and margin_m >= 0):
        raise ValueError(f"fence margin must be >= 0 m, got {margin_m}")
    w = float(r_s) + float(margin_m)
    L = tube.length
    if exit_m is None:
        exit_m = exit_room_m(L, exit_clear_m) + w
    if not (np.isfinite(exit_m) and exit_m >= 0):
        raise ValueError(f"fence exit length must be >= 0 m, got {exit_m}")
    back_m = w
    if slots is not None and len(slots):
        behind = -float(np.min(tube.xi(np.asarray(slots, dtype=float))))
        back_m = max(back_m, behind + w)
    n_c, o = tube.n_c, tube.p_h0
    left = [_leg_point(tube.p_h0, tube.t_h, tube.n_h, n_c, o, w, xi) for xi in (0.0, L)]
    right = [_leg_point(tube.p_r0, tube.t_r, tube.n_r, n_c, o, w, xi) for xi in (0.0, L)]
    # left side from the back to the front, then the right side from the front to the back
    poly = np.array([left[0] - back_m * n_c, left[0], left[1], left[1] + exit_m * n_c,
                     right[1] + exit_m * n_c, right[1], right[0], right[0] - back_m * n_c])
    poly = _drop_collinear(poly)
    x, y = poly[:, 0], poly[:, 1]
    area2 = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    if area2 < 0:
        poly = poly[::-1].copy()
    centers = np.array([ob.center for ob in obstacles], dtype=float).reshape(-1, 2)
    radii = np.array([ob.radius + float(r_s) for ob in obstacles], dtype=float)
    for a in (poly, centers, radii):
        a.setflags(write=False)
    return FenceGeometry(poly, centers, radii, w, back_m, float(exit_m))


@dataclass(frozen=True, eq=False)
class RouteFence:
    """The fence of a route: one inclusion polygon per segment (PX4 takes several inclusion
    polygons as their union: a point is allowed if it is inside any of them) and the
    exclusion circles of every obstacle."""

    segments: tuple[FenceGeometry, ...]

    @property
    def polygons(self) -> tuple[np.ndarray, ...]:
        return tuple(f.polygon for f in self.segments)

    @property
    def circle_centers(self) -> np.ndarray:
        return self.segments[0].circle_centers

    @property
    def circle_radii(self) -> np.ndarray:
        return self.segments[0].circle_radii

    @property
    def widen_m(self) -> float:
        """w = r_s + margin: how far every leg is moved outwards."""
        return self.segments[0].widen_m

    @property
    def back_m(self) -> float:
        """How far the first polygon reaches behind the route's start base."""
        return self.segments[0].back_m

    @property
    def exit_m(self) -> float:
        """How far the last polygon reaches past the route's finishing line."""
        return self.segments[-1].exit_m

    @property
    def vertices(self) -> int:
        """Vertices of all inclusion polygons (PX4 stores each as one fence item)."""
        return sum(len(f.polygon) for f in self.segments)

    def inside_polygon(self, x: np.ndarray) -> np.ndarray:
        """Points (…, 2) inside some inclusion polygon (their union, as PX4 judges them)."""
        inside = np.zeros(np.asarray(x).shape[:-1], dtype=bool)
        for f in self.segments:
            inside |= f.inside_polygon(x)
        return inside

    def contains(self, x: np.ndarray) -> np.ndarray:
        """Points (…, 2) the fence allows: inside some polygon, outside every circle."""
        return self.inside_polygon(x) & ~self.segments[0].inside_exclusion(x)

    def problems(self, x: np.ndarray, names: Sequence[str]) -> list[str]:
        """One line per point of ``x`` (M, 2) the fence would not allow (vehicles before
        arming: PX4 would breach at once); one segment: :meth:`FenceGeometry.problems`."""
        if len(self.segments) == 1:
            return self.segments[0].problems(x, names)
        pts = np.asarray(x, dtype=float).reshape(-1, 2)
        return _problems(pts, names, self.inside_polygon(pts),
                         self.segments[0].inside_exclusion(pts),
                         f"every segment's fence polygon (legs widened by "
                         f"{compact_number(self.widen_m)} m, {compact_number(self.back_m)} m "
                         f"behind the route's start base, {compact_number(self.exit_m)} m past "
                         f"its finishing line)")


def _problems(pts: np.ndarray, names: Sequence[str], poly_in: np.ndarray, excl: np.ndarray,
              polygon: str) -> list[str]:
    """The lines of ``problems``: a point outside ``polygon`` (its description), or inside an
    exclusion circle."""
    out = []
    for i, p in enumerate(pts):
        if not poly_in[i]:
            out.append(f"{names[i]} at {point_text(p)} is outside {polygon}")
        elif excl[i]:
            out.append(f"{names[i]} at {point_text(p)} is inside an obstacle's exclusion circle")
    return out


def route_fence(corridor: Any, r_s: float, *, slots: np.ndarray | None = None,
                margin_m: float = FENCE_MARGIN_M, exit_m: float | None = None,
                exit_clear_m: float = 0.0) -> RouteFence:
    """The fence of a route (:class:`~vtube_fleet.core.route.Corridor`): for each segment,
    :func:`tube_fence` of its trapezoid — the legs widened by w = r_s + ``margin_m``, the first
    segment's polygon reaching ``slots`` behind its start base, the last one's ``exit_m`` past
    the route's finishing line, every other end w past the segment's base (the junctions'
    overlap, so the union holds every vehicle body at a bend too); the obstacles' exclusion
    circles. One segment: the same polygon as :func:`tube_fence`."""
    segs = tuple(corridor.segments)
    w = float(r_s) + float(margin_m)
    out = []
    for k, t in enumerate(segs):
        first, last = k == 0, k == len(segs) - 1
        f = tube_fence(t, corridor.obstacles, r_s, slots=slots if first else None,
                       margin_m=margin_m, exit_m=exit_m if last else w,
                       exit_clear_m=exit_clear_m if last else 0.0)
        out.append(f)
    return RouteFence(tuple(out))
