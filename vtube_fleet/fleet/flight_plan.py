"""The flight plan every vehicle of a mission shares: the planned route (each segment
partitioned into sub-tubes around its obstacles, with the flown radii), re-planned around
vehicles that stopped in it.

:class:`FlightPlan` wraps one :class:`~vtube_fleet.core.route.Route` (a ``[tube]`` is a route of
one segment: the same partition, switching, commands and exits as before routes, bit for bit)
and answers the tick's geometric questions (:mod:`vtube_fleet.fleet.tick`) for any rows of the
swarm, each with its segment — the hand-over state the caller keeps (the table's ``segment``
column) and passes back: the hand-over (:meth:`FlightPlan.advance`), the switching rule
(ObstacleController) with the apex look-ahead (:meth:`FlightPlan.locate`), the controller's
commands (:meth:`FlightPlan.commands`, ModifiedVectorField), (TraCondition) on the route's
LAST finishing line (:meth:`FlightPlan.exited`), and the route with lost-vehicle obstacles
(:meth:`FlightPlan.with_lost`, :func:`lost_obstacles`: each in whichever segment it stopped).
:func:`exit_velocities` is what a vehicle past the finishing line flies (Assumption 2: it no
longer follows the controller; straight on along the last segment's n_c).

The flown radii come from the safety budget (:mod:`vtube_fleet.fleet.budget`): the plan's
``flown`` parameters are the configured ones inflated by δ.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from vtube_fleet.core.controller import TubeArrays, velocity_command
from vtube_fleet.core.loss import (
    cannot_pass,
    left_out,
    partition_around_lost,
    partition_past,
    step_aside,
)
from vtube_fleet.core.neighbours import pairs_within
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.partition import Partition, PartitionError, h_min
from vtube_fleet.core.route import Corridor, ReplanFn, Route, disc_meets, replan_segment
from vtube_fleet.core.tube import Obstacle, Trapezoid

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.config.mission import Mission, MissionConfig
    from vtube_fleet.fleet.neighbour_view import NeighbourView

__all__ = ["LOST_APEX_FACTOR", "FlightPlan", "exit_queue", "exit_room_of", "exit_stop_m",
           "exit_velocities", "lost_obstacles"]

_EMPTY_POS = np.zeros((0, 2))


@dataclass(frozen=True, eq=False)
class FlightPlan:
    """What all agents share: the planned ``route`` (its corridor — segments and configured
    obstacles —, the controller parameters ``flown`` (r_s', r_a': the physical radii inflated
    by the safety budget) it was planned with, each segment's partition, the obstacles left by
    LOST vehicles) and the controller ``kind``.

    :meth:`with_lost` re-plans the segments a lost vehicle's obstacle meets
    (:meth:`Route.with_lost <vtube_fleet.core.route.Route.with_lost>`, each segment by
    ``replan``; None: its default rule); results are cached per set of lost obstacles and
    shared by every plan derived from the same root, so N agents reacting to the same loss
    re-plan once.
    """

    route: Route
    kind: str = "new"
    _cache: dict[tuple, FlightPlan] = field(default_factory=dict, repr=False)
    #: the re-plan of one segment around lost vehicles (``Route.with_lost``'s ``replan``):
    #: today's rules, then the grouping fallback (:func:`~vtube_fleet.core.loss.
    #: partition_around_lost`)
    replan: ReplanFn | None = partition_around_lost

    @classmethod
    def build(
        cls,
        corridor: Corridor,
        params: ControllerParams,
        *,
        kind: str = "new",
        route: Route | None = None,
        lookahead: bool = True,
        keep_out: np.ndarray | None = None,
        replan: ReplanFn | None = partition_around_lost,
    ) -> FlightPlan:
        """Plan ``corridor`` with ``params`` (raises
        :class:`~vtube_fleet.core.partition.PartitionError` naming the segment and the
        obstacle) and wrap; ``route``: already planned (not planned again). ``lookahead``:
        switch sub-tubes ahead of apexes (vehicles with response lag); ``keep_out``: the points
        ``"auto"`` apex distances keep out of the triangles (the mission's start slots, the
        same in every process)."""
        if route is None:
            route = Route.plan(corridor, params, keep_out=keep_out, lookahead=lookahead)
        plan = cls(route, kind, replan=replan)
        plan._cache[()] = plan
        return plan

    @classmethod
    def for_mission(cls, mission: Mission, flown: ControllerParams, **kw: Any) -> FlightPlan:
        """The plan of ``mission`` flown with ``flown``: its corridor, ``"auto"`` apex
        distances planned on its start slots (every process of a run plans the same)."""
        return cls.build(mission.scenario.corridor, flown, keep_out=mission.slots, **kw)

    # -- what the plan is ----------------------------------------------------------------
    @property
    def flown(self) -> ControllerParams:
        """The controller parameters flown (r_s', r_a')."""
        return self.route.params

    @property
    def corridor(self) -> Corridor:
        return self.route.corridor

    @property
    def lost(self) -> tuple[Obstacle, ...]:
        """The obstacles left by lost vehicles (route-numbered after the configured ones)."""
        return self.route.lost

    @property
    def lookahead(self) -> bool:
        return self.route.lookahead

    @property
    def arrays(self) -> TubeArrays:
        """Every segment's sub-tubes stacked for the controller (built once per route)."""
        return self.route.arrays

    @property
    def neighbour_radius_m(self) -> float:
        """r_s + r_a (flown): the range of the pair barrier u2 (Vmij)."""
        return float(self.flown.r_s + self.flown.r_a)

    @property
    def all_obstacles(self) -> tuple[Obstacle, ...]:
        return self.route.obstacles

    # -- the hand-over and the switching rule ---------------------------------------------
    def advance(self, p: np.ndarray, segment: np.ndarray) -> np.ndarray:
        """The segments (M,) after points p (M, 2) flying ``segment`` (−1: not yet assigned:
        the segment its position starts in) were seen here: the hand-over
        (:meth:`Route.advance <vtube_fleet.core.route.Route.advance>`)."""
        return self.route.advance(p, segment)

    def locate(self, p: np.ndarray, segment: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """(segment (M,), global sub-tube (M,)) of points (M, 2) flying ``segment`` (None:
        the segments they start in): the hand-over, then the switching rule
        (ObstacleController) of each one's segment, with the apex look-ahead of the flown
        plan."""
        return self.route.locate(p, segment)

    def exited(self, p: np.ndarray, segment: np.ndarray | None = None) -> np.ndarray:
        """(TraCondition) on the route's LAST finishing line, for points flying the last
        segment: −n_cᵀ(p − p_r1) ≤ ε_0 → (M,) bool (``segment`` None: a one-segment route)."""
        return self.route.finished(p, segment)

    def commands(self, p: np.ndarray, rows: Sequence[int] | np.ndarray,
                 segment: np.ndarray | None = None) -> np.ndarray:
        """The controller's commands (len(rows), 2) for robots ``rows`` of the swarm ``p``
        (M, 2), each flying ``segment[k]`` (len(rows),; None: the segment it starts in):
        sub-tubes by :meth:`locate`, then ``velocity_command`` over the route's stacked
        sub-tubes (pairs do not care about segments, paper note 6).

        The pair candidates are the pairs within r_s + r_a (:func:`pairs_within`, a k-d tree;
        u2 is exactly 0 beyond, (Vmij)): the same for one row (an MQTT agent) and for many (a
        supervisor), so a row's command does not depend on which other rows are asked for."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if rows.size == 0:
            return _EMPTY_POS.copy()
        seg = None if segment is None else np.asarray(segment, dtype=np.intp).reshape(-1)
        _, k = self.locate(p[rows], seg)
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

    # -- lost vehicles ---------------------------------------------------------------------
    def with_lost(self, lost: Sequence[Obstacle]) -> FlightPlan:
        """The plan with these lost-vehicle obstacles (replacing any previous ones): every
        segment the obstacle's O' meets is re-partitioned (one stopped in a junction's overlap
        belongs to both), by ``replan`` (default: :func:`~vtube_fleet.core.loss.
        partition_around_lost`: the configured obstacles keep the apex distances of this plan
        — ``"auto"`` ones are not re-planned under flying vehicles —, a lost-vehicle obstacle
        gets ``LOST_APEX_FACTOR`` × h_min; if that partition fails, h_k chosen by the planner,
        core/plan.py; if that fails too, the lost vehicle grouped with the obstacles near it:
        all deterministic, so every agent gets the same partition)."""
        lost = tuple(lost)
        key = self.lost_key(lost)
        hit = self._cache.get(key)
        if hit is None:
            route = self.route.with_lost(lost, replan=self.replan)
            hit = FlightPlan(route, self.kind, self._cache, self.replan)
            self._cache[key] = hit
        return hit

    @staticmethod
    def lost_key(lost: Sequence[Obstacle]) -> tuple[tuple[float, float, float], ...]:
        """What tells one set of lost-vehicle obstacles from another (centres and radii to the
        micrometre): the key of :meth:`with_lost`'s plans."""
        return tuple((round(float(o.center[0]), 6), round(float(o.center[1]), 6),
                      round(float(o.radius), 6)) for o in lost)

    def holds(self, lost: Sequence[Obstacle], body_m: float) -> bool:
        """Whether this plan's lost-vehicle obstacles (:attr:`lost`) still hold the stopped
        vehicles ``lost`` describes: each one's body (a disc of radius ``body_m`` around its
        centre) inside one of them — it moved less than its obstacle's margin (radius −
        ``body_m``) since this plan was built. This plan then keeps the paper's guarantee
        for them as it is (every sub-tube and O' is built on those discs)."""
        new = np.array([o.center for o in lost], dtype=float).reshape(-1, 2)
        if not new.shape[0]:
            return True
        mine = self.lost
        if not mine:
            return False
        old = np.array([o.center for o in mine], dtype=float).reshape(-1, 2)
        r_old = np.array([float(o.radius) for o in mine])
        d = np.hypot(new[:, None, 0] - old[None, :, 0], new[:, None, 1] - old[None, :, 1])
        return bool((d + float(body_m) <= r_old[None, :] + 1e-9).any(axis=1).all())

    def planned_with_lost(self, lost: Sequence[Obstacle]) -> FlightPlan | None:
        """The plan :meth:`with_lost` has already built for these obstacles, else None (no
        work done)."""
        return self._cache.get(self.lost_key(tuple(lost)))

    def cannot_pass(self, p: np.ndarray, segment: np.ndarray | None = None) -> np.ndarray:
        """Points (M, 2) flying ``segment`` (M,) (None or −1: the segments they start in) inside the
        region their segment's partition takes around its obstacles
        (:func:`~vtube_fleet.core.loss.cannot_pass`): no safe sub-tube for a vehicle there."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        out = np.zeros(p.shape[0], bool)
        if not p.shape[0]:
            return out
        seg = (np.full(p.shape[0], -1, np.intp) if segment is None
               else np.asarray(segment, dtype=np.intp).reshape(-1).copy())
        if (seg < 0).any():  # not yet assigned: the segment its position starts in
            seg[seg < 0] = self.route.start_segments(p[seg < 0])
        zones = self.route.zones
        for s in np.unique(seg).tolist():
            rows = np.flatnonzero(seg == s)
            part = self.route.segments[int(s)].partition
            out[rows] = cannot_pass(part, p[rows], zones[int(s)] if self.lookahead else ())
        return out

    def step_aside(self, p: np.ndarray, segment: int = -1, *, back: bool = True
                   ) -> tuple[np.ndarray, np.ndarray] | None:
        """The path (via, q) a vehicle at rest at ``p`` (2,) flying ``segment`` (−1: the one
        it starts in) steps aside on — back along its segment's n_c to ``via`` (not with
        ``back`` False: straight across only), then across it to ``q`` inside a sub-tube of
        this plan (:func:`~vtube_fleet.core.loss.step_aside`, every obstacle of the route,
        configured and lost, kept out of) — or None."""
        p = np.asarray(p, dtype=float).reshape(2)
        seg = int(segment) if segment >= 0 else int(self.route.start_segments(p[None])[0])
        s = self.route.segments[seg]
        zones = self.route.zones[seg] if self.lookahead else ()
        extra = {} if back else {"max_back_m": 0.0}
        return step_aside(s.tube, s.partition, self.all_obstacles, self.flown, p, zones=zones,
                          **extra)

    def past(self, lost: Sequence[Obstacle], p: np.ndarray, segment: int = -1, *,
             residual_m_s: float = 0.0, outside: bool = True
             ) -> tuple[FlightPlan, np.ndarray] | None:
        """A plan of its own for one vehicle at ``p`` (2,) flying ``segment`` (−1: the one it
        starts in) that :meth:`cannot_pass` under ``with_lost(lost)``: in its segment
        the obstacles it has passed are left out (:func:`~vtube_fleet.core.loss.
        partition_past`, ``residual_m_s``: the budget's D; the others re-planned as
        :meth:`with_lost` does) → (the plan, the centres (P, 2) of the obstacles left out).
        An obstacle whose O' also meets a later segment is kept (the hand-over into that
        segment must not meet its region). None for a controller other than the paper's
        ("new": the bound on its commands is what makes this sound), when it passed none,
        when the rest cannot be partitioned, or when ``p`` is inside a region of that plan
        too (unless ``outside`` is False: a vehicle about to step aside into one of its
        sub-tubes). Called on the root plan (no lost obstacles yet)."""
        if self.kind != "new":
            return None
        p = np.asarray(p, dtype=float).reshape(2)
        seg = int(segment) if segment >= 0 else int(self.route.start_segments(p[None])[0])
        mine = self.route.segments[seg].tube
        later = [s.tube for s in self.route.segments[seg + 1:]]
        common = self.replan or replan_segment
        gone: list[np.ndarray] = []

        def replan(tube: Trapezoid, fixed: Sequence[Obstacle], here: Sequence[Obstacle],
                   params: ControllerParams) -> Partition:
            if tube is mine:
                obs = (*fixed, *here)
                keep = np.array([any(disc_meets(t, o, params.r_s) for t in later) for o in obs],
                                bool)
                own = partition_past(tube, fixed, here, params, p,
                                     residual_m_s=residual_m_s, keep=keep)
                if own is not None:
                    out = left_out(tube, obs, params, p, residual_m_s=residual_m_s, keep=keep)
                    gone.extend(obs[i].center for i in np.flatnonzero(out).tolist())
                    return own
            return common(tube, fixed, here, params)

        try:
            route = self.route.with_lost(tuple(lost), replan=replan)
        except PartitionError:
            return None
        if not gone:
            return None
        plan = FlightPlan(route, self.kind, {}, self.replan)
        if outside and plan.cannot_pass(p[None], np.array([seg]))[0]:
            return None
        return plan, np.array(gone, dtype=float).reshape(-1, 2)

    def segments_of_lost(self, i: int) -> list[str]:
        """The segments (``S2`` …) whose partition holds lost obstacle ``i`` (0-based among
        :attr:`lost`)."""
        gid = len(self.corridor.obstacles) + i
        return [s.name for s in self.route.segments if gid in s.obstacle_ids]


#: Apex distance of a lost vehicle's triangle: this × h_min (pothk). Smaller than the default
#: 1.3 for configured obstacles so that the triangle fits more often between a vehicle lost
#: mid-tube and the others (and swallows fewer of them); when even that partition fails,
#: :meth:`FlightPlan.with_lost` lets the planner choose (``"auto"``).
LOST_APEX_FACTOR = 1.05


def lost_obstacles(
    view: NeighbourView, corridor: Corridor, radius_m: float, params: ControllerParams
) -> tuple[Obstacle, ...]:
    """Obstacles (radius ``radius_m``, apex distance ``LOST_APEX_FACTOR`` × h_min under
    ``params``) for the lost vehicles inside the route (sorted by vehicle id; any segment:
    :meth:`FlightPlan.with_lost` gives each to the segments it meets), and for those stopped
    just past the last finishing line whose extended disc O' (``radius_m`` + r_s) reaches
    back across it; the others outside (farther past the line) stay static points only.

    Assumption 2 lets a robot that has exited vanish; ours do not: with ``after_exit =
    "continue"`` an exited vehicle holds when a stopped one is ahead in its lane, so when every
    vehicle leaves through one passage the queue can grow back to the finishing line, and a
    vehicle still in the tube, which the controller cannot stop (v_min), would fly into its
    tail (a mock flight after a loss: 0.12 m true). As an obstacle, the tail is partitioned
    around, or the vehicle behind it waits."""
    pts = np.asarray(view.lost_pos, dtype=float).reshape(-1, 2)
    if not pts.shape[0]:
        return ()
    apex = LOST_APEX_FACTOR * h_min(float(radius_m), params)
    keep = corridor.inside(pts, params.eps_0)
    last = corridor.last
    past = np.asarray(last.xi(pts), float) - last.length
    reach = float(radius_m) + float(params.r_s)
    near = ~keep & (past >= 0.0) & (past < reach)
    if near.any():  # (its foot on the finishing line inside the legs)
        foot = pts - (past[:, None] + 1e-9) * last.n_c
        near &= np.asarray(last.contains(foot), bool).reshape(-1)
    keep = keep | near
    return tuple(Obstacle(center=np.array(p, dtype=float), radius=float(radius_m),
                          apex_distance=apex) for p in pts[keep])


def exit_stop_m(plan: FlightPlan, config: MissionConfig) -> float:
    """The stopping distance (m) of an exited vehicle — how far behind a stopped vehicle
    ahead it holds, and before the fence's exit: 2 r_s' + v (τ_d + t63 + T), flown values."""
    return 2.0 * float(plan.flown.r_s) + float(plan.flown.v) * (
        config.tracking_dead_time_s + config.tracking_t63_s + config.period_s)


def exit_room_of(plan: FlightPlan, config: MissionConfig) -> float:
    """How far past the route's last finishing line the fence's exit is (m): its length plus
    ``exit_clear_m`` (:func:`~vtube_fleet.core.fence.exit_room_m`)."""
    from vtube_fleet.core.fence import exit_room_m

    return exit_room_m(plan.route.segments[-1].tube.length, config.exit_clear_m)


def exit_queue(plan: FlightPlan, config: MissionConfig, lost_radius_m: float, count: int
               ) -> tuple[int, float, float]:
    """With ``after_exit = "continue"``: how many exited vehicles can hold in one lane, the
    first a stopping distance before the fence's exit (:func:`exit_room_of`) and each one
    :func:`exit_stop_m` behind the one ahead, before the queue's tail is within reach of the
    line (r_lost + r_s': then it is an obstacle for the vehicles in the tube,
    :func:`lost_obstacles`) → (that number, the ``exit_clear_m`` that holds ``count``, the
    stopping distance)."""
    stop = exit_stop_m(plan, config)
    reach = float(lost_radius_m) + float(plan.flown.r_s)
    fits = max(0, int((exit_room_of(plan, config) - reach) // stop))
    need = max(0.0, count * stop + reach - plan.route.segments[-1].tube.length)
    return fits, need, stop


def exit_velocities(
    plan: FlightPlan,
    own_xy: np.ndarray,
    view: NeighbourView | None,
    *,
    stop_distance_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """What vehicles past the finishing line fly (Assumption 2: they no longer follow the
    tube's controller): straight on at v along the LAST segment's n_c, so vehicles that exited
    keep their spacing. ``own_xy`` (E, 2) the exited vehicles' positions; returns their
    velocities (E, 2) and ``blocked`` (E,): stop and hold instead, because a vehicle that is
    not flying on (static, lost or stopped — by its phase, not by its reported speed: PX4's
    velocity estimate can be 0.5 m/s off) lies ahead within ``stop_distance_m`` along n_c and
    within 2 r_s (flown) across, so a vehicle never runs into one that stopped ahead of it."""
    own = np.asarray(own_xy, dtype=float).reshape(-1, 2)
    n_c = plan.route.exit_heading
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
