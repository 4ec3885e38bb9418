"""The flight plan every vehicle of a mission shares: the tube, its obstacles, the flown radii
and the partition into sub-tubes, re-planned around vehicles that stopped in it.

:class:`FlightPlan` answers the tick's geometric questions (:mod:`vtube_fleet.fleet.tick`): the
switching rule (ObstacleController) with the apex look-ahead (:meth:`FlightPlan.locate`), the
controller's commands for any rows of the swarm (:meth:`FlightPlan.commands`, ModifiedVectorField),
(TraCondition) on the main tube (:meth:`FlightPlan.exited`), and the partition with lost-vehicle
obstacles (:meth:`FlightPlan.with_lost`, :func:`lost_obstacles`). :func:`exit_velocities` is what a
vehicle past the finishing line flies (Assumption 2: it no longer follows the controller).

The flown radii come from the safety budget (:mod:`vtube_fleet.fleet.budget`): the plan's
``flown`` parameters are the configured ones inflated by δ.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from vtube_fleet.core.controller import TubeArrays, velocity_command
from vtube_fleet.core.loss import cannot_pass, partition_around_lost
from vtube_fleet.core.neighbours import pairs_within
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.partition import (
    ApexZone,
    Partition,
    apex_lookahead,
    apex_zones,
    h_min,
    partition,
)
from vtube_fleet.core.tube import Obstacle, Trapezoid

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.fleet.neighbour_view import NeighbourView

__all__ = ["LOST_APEX_FACTOR", "FlightPlan", "exit_velocities", "lost_obstacles"]

_EMPTY_POS = np.zeros((0, 2))


@dataclass(frozen=True, eq=False)
class FlightPlan:
    """What all agents share: the main tube, the configured obstacles, the obstacles left by
    LOST vehicles, the controller parameters ``flown`` (r_s', r_a': the physical radii inflated
    by the safety budget) and the partition of the tube around all obstacles (Section IV-A).

    :meth:`with_lost` recomputes the partition online; results are cached per set of lost
    obstacles and shared by every plan derived from the same root, so N agents reacting to the
    same loss partition once.
    """

    tube: Trapezoid
    obstacles: tuple[Obstacle, ...]
    flown: ControllerParams
    partition: Partition
    lost: tuple[Obstacle, ...] = ()
    kind: str = "new"
    _cache: dict[tuple, FlightPlan] = field(default_factory=dict, repr=False)
    #: the apex look-ahead zones of the switching rule (:func:`~vtube_fleet.core.partition.
    #: apex_zones`; empty: the paper's §5 rule exactly)
    zones: tuple[ApexZone, ...] = ()
    lookahead: bool = True

    @classmethod
    def build(
        cls,
        tube: Trapezoid,
        obstacles: Sequence[Obstacle],
        params: ControllerParams,
        *,
        kind: str = "new",
        part: Partition | None = None,
        lookahead: bool = True,
        keep_out: np.ndarray | None = None,
    ) -> FlightPlan:
        """Partition (raises :class:`~vtube_fleet.core.partition.PartitionError`) and wrap.
        ``lookahead``: switch sub-tubes ahead of apexes (vehicles with response lag);
        ``keep_out``: the points ``"auto"`` apex distances keep out of the triangles (the
        mission's start slots, the same in every process)."""
        obstacles = tuple(obstacles)
        if part is None:
            part = partition(tube, obstacles, params, keep_out=keep_out)
        zones = apex_zones(part, params) if lookahead else ()
        plan = cls(tube, obstacles, params, part, (), kind, zones=zones, lookahead=lookahead)
        plan._cache[()] = plan
        return plan

    @cached_property
    def arrays(self) -> TubeArrays:
        """The partition's sub-tubes stacked for the controller (built once per plan)."""
        return TubeArrays.from_tubes(self.partition.sub_tubes)

    def locate(self, p: np.ndarray) -> np.ndarray:
        """The sub-tube of points (..., 2): the switching rule (ObstacleController), with the
        apex look-ahead of the flown plan."""
        p = np.asarray(p, dtype=float)
        k = np.asarray(self.partition.locate(p))
        if not self.zones:
            return k
        return apex_lookahead(self.partition, self.zones, p, k).reshape(k.shape)

    def lookahead_conflicts(self, p: np.ndarray) -> list[tuple[int, int, float]]:
        """Points (M, 2) that the apex look-ahead puts into a side tube at most r_s (flown)
        from its legs (they would start inside the barrier): (row, sub-tube, distance)."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        if not self.zones or not p.shape[0]:
            return []
        k0 = np.asarray(self.partition.locate(p)).reshape(-1)
        k1 = self.locate(p).reshape(-1)
        out = []
        for i in np.flatnonzero(k0 != k1):
            t = self.partition.sub_tubes[int(k1[i])]
            d = min(float(t.d_Th(p[i])), float(t.d_Tr(p[i])))
            if d <= self.flown.r_s:
                out.append((int(i), int(k1[i]), d))
        return out

    @property
    def neighbour_radius_m(self) -> float:
        """r_s + r_a (flown): the range of the pair barrier u2 (Vmij)."""
        return float(self.flown.r_s + self.flown.r_a)

    @property
    def all_obstacles(self) -> tuple[Obstacle, ...]:
        return self.obstacles + self.lost

    def with_lost(self, lost: Sequence[Obstacle]) -> FlightPlan:
        """The plan with these lost-vehicle obstacles (replacing any previous ones).

        The configured obstacles keep the apex distances of this plan (``"auto"`` ones are not
        re-planned under flying vehicles); a lost-vehicle obstacle gets
        ``LOST_APEX_FACTOR`` × h_min, and only if that partition fails, h_k chosen by the
        planner (core/plan.py), and only if that fails too, the lost vehicle grouped with the
        obstacles near it (:func:`~vtube_fleet.core.loss.partition_around_lost`; all
        deterministic, so every agent gets the same partition)."""
        lost = tuple(lost)
        key = tuple((round(float(o.center[0]), 6), round(float(o.center[1]), 6),
                     round(float(o.radius), 6)) for o in lost)
        hit = self._cache.get(key)
        if hit is None:
            tri_h = {t.obstacle: t.h for t in self.partition.triangles}
            fixed = tuple(dataclasses.replace(ob, apex_distance=tri_h[i])
                          if isinstance(ob.apex_distance, str) and i in tri_h else ob
                          for i, ob in enumerate(self.obstacles))
            part = partition_around_lost(self.tube, fixed, lost, self.flown)
            zones = apex_zones(part, self.flown) if self.lookahead else ()
            hit = FlightPlan(self.tube, self.obstacles, self.flown, part, lost, self.kind,
                             self._cache, zones, self.lookahead)
            self._cache[key] = hit
        return hit

    def cannot_pass(self, p: np.ndarray) -> np.ndarray:
        """Points (M, 2) inside the region this plan's partition takes around its obstacles
        (:func:`~vtube_fleet.core.loss.cannot_pass`): no safe sub-tube for a vehicle there."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        if not p.shape[0]:
            return np.zeros(0, bool)
        return cannot_pass(self.partition, p, self.zones)

    def exited(self, p: np.ndarray) -> np.ndarray:
        """(TraCondition) on the MAIN tube: −n_cᵀ(p − p_r1) ≤ ε_0 → (…,) bool."""
        return self.tube.finished(p, self.flown.eps_0)

    def commands(self, p: np.ndarray, rows: Sequence[int] | np.ndarray) -> np.ndarray:
        """The controller's commands (len(rows), 2) for robots ``rows`` of the swarm ``p``
        (M, 2): sub-tubes by :meth:`Partition.locate`, then ``velocity_command``.

        The pair candidates are the pairs within r_s + r_a (:func:`pairs_within`, a k-d tree;
        u2 is exactly 0 beyond, (Vmij)): the same for one row (an MQTT agent) and for many (a
        supervisor), so a row's command does not depend on which other rows are asked for."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if rows.size == 0:
            return _EMPTY_POS.copy()
        k = np.asarray(self.locate(p), dtype=np.int64)
        extra: dict[str, Any] = {}
        if self.kind == "apf":
            extra["obstacles"] = self.all_obstacles
        # + 1 nm: the k-d tree compares squared distances, so a pair 1 ulp inside the
        # barrier's support could be missed; pairs beyond add exactly 0
        extra["pairs"] = pairs_within(p, self.neighbour_radius_m + 1e-9)
        return np.asarray(
            velocity_command(p, k, self.arrays, self.flown, kind=self.kind,
                             rows=rows, **extra),
            dtype=float,
        ).reshape(-1, 2)


#: Apex distance of a lost vehicle's triangle: this × h_min (pothk). Smaller than the default
#: 1.3 for configured obstacles so that the triangle fits more often between a vehicle lost
#: mid-tube and the others (and swallows fewer of them); when even that partition fails,
#: :meth:`FlightPlan.with_lost` lets the planner choose (``"auto"``).
LOST_APEX_FACTOR = 1.05


def lost_obstacles(
    view: NeighbourView, tube: Trapezoid, radius_m: float, params: ControllerParams
) -> tuple[Obstacle, ...]:
    """Obstacles (radius ``radius_m``, apex distance ``LOST_APEX_FACTOR`` × h_min under
    ``params``) for the lost vehicles inside the main tube (sorted by vehicle id); lost
    vehicles outside it (e.g. past the finishing line) stay static points only."""
    out = []
    apex = LOST_APEX_FACTOR * h_min(float(radius_m), params)
    for p in view.lost_pos:
        # past the finishing line: Assumption 2, the vehicle no longer counts
        if bool(tube.contains(p)) and not bool(tube.finished(p, params.eps_0)):
            out.append(Obstacle(center=np.array(p, dtype=float), radius=float(radius_m),
                                apex_distance=apex))
    return tuple(out)


def exit_velocities(
    plan: FlightPlan,
    own_xy: np.ndarray,
    view: NeighbourView | None,
    *,
    stop_distance_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """What vehicles past the finishing line fly (Assumption 2: they no longer follow the
    tube's controller): straight on at v along the main tube's n_c, so vehicles that exited
    keep their spacing. ``own_xy`` (E, 2) the exited vehicles' positions; returns their
    velocities (E, 2) and ``blocked`` (E,): stop and hold instead, because a vehicle that is
    not flying on (static, lost or stopped — by its phase, not by its reported speed: PX4's
    velocity estimate can be 0.5 m/s off) lies ahead within ``stop_distance_m`` along n_c and
    within 2 r_s (flown) across, so a vehicle never runs into one that stopped ahead of it."""
    own = np.asarray(own_xy, dtype=float).reshape(-1, 2)
    n_c = plan.tube.n_c
    v = np.broadcast_to(float(plan.flown.v) * n_c, own.shape).copy()
    blocked = np.zeros(own.shape[0], bool)
    if view is None:
        return v, blocked
    pts = np.concatenate([view.static_pos, view.lost_pos])
    if pts.shape[0] and own.shape[0]:
        rel = pts[None, :, :] - own[:, None, :]  # (E, P, 2)
        ahead = rel @ n_c
        across = np.abs(rel @ np.array([-n_c[1], n_c[0]]))
        hit = (ahead > 0) & (ahead <= stop_distance_m) & (across < 2.0 * plan.flown.r_s)
        blocked = hit.any(axis=1)
    return v, blocked
