"""The per-vehicle agent: pure decision logic, no I/O, no asyncio.

An :class:`Agent` is what one vehicle knows and decides:

* a **neighbour table** of the other vehicles' latest :class:`~vtube_fleet.state.NeighbourState`
  (time-stamped, newest ``seq`` wins). :func:`classify` sorts it at a given time:
  *live* entries (flying, younger than ``max_age_s``) are neighbours at their reported
  positions; a stale entry is never used as a live position: a flying vehicle heard from between
  ``max_age_s`` and ``lost_after_s`` ago is kept as a *static point* at its last position (so the
  pair barrier still keeps clear of where it was), and one silent for longer than
  ``lost_after_s``, or that says it is ``LOST``, is *lost*: a static obstacle at its last
  position. A vehicle that is airborne but stopped flying the controller (holding, landing)
  is treated like a lost one: inside the tube it becomes an obstacle for everyone, at once, by
  the same rule in every agent. Entries of vehicles on the ground (connecting, ready, arming,
  landed, failed) are ignored.
* its **phase** (:class:`~vtube_fleet.state.Phase`), advanced by the pilot; the agent itself moves
  IN_TUBE → EXITED when (TraCondition) holds on the main tube: −n_cᵀ(p − p_r1) ≤ ε_0
  (Assumption 2).
* its **horizontal setpoint** in the tube frame: the core controller
  :func:`vtube_fleet.core.controller.velocity_command` (ModifiedVectorField) evaluated for its own
  row only (``rows=[0]``) with the sub-tube index from :meth:`FlightPlan.locate` (the switching
  logic (ObstacleController)) and its neighbours within r_s + r_a, the same code the simulator runs.
  The supervisor computes many agents at once with :func:`fleet_setpoints`, which calls
  ``velocity_command`` once with ``rows`` = all those agents; row for row this equals each agent's
  own :meth:`Agent.setpoint` (``tests/test_fleet_agent.py``).

The flown radii come from the safety budget (:mod:`vtube_fleet.fleet.budget`): the plan's
``params`` are the configured ones inflated by δ.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from vtube_fleet.core.controller import TubeArrays, velocity_command
from vtube_fleet.core.loss import partition_around_lost
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
from vtube_fleet.state import AIRBORNE_PHASES, STOPPED_PHASES, NeighbourState, Phase

__all__ = [
    "LOST_APEX_FACTOR",
    "Agent",
    "FlightPlan",
    "NeighbourView",
    "Setpoint",
    "classify",
    "classify_arrays",
    "exit_velocity",
    "fleet_setpoints",
    "lost_obstacles",
]

_EMPTY_POS = np.zeros((0, 2))
_EMPTY_IDS = np.zeros(0, dtype=np.int64)


# ------------------------------------------------------------------------------------------
# the plan every agent shares
# ------------------------------------------------------------------------------------------
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

    def exited(self, p: np.ndarray) -> np.ndarray:
        """(TraCondition) on the MAIN tube: −n_cᵀ(p − p_r1) ≤ ε_0 → (…,) bool."""
        return self.tube.finished(p, self.flown.eps_0)

    def commands(self, p: np.ndarray, rows: Sequence[int] | np.ndarray) -> np.ndarray:
        """The controller's commands (len(rows), 2) for robots ``rows`` of the swarm ``p``
        (M, 2): sub-tubes by :meth:`Partition.locate`, then ``velocity_command``.

        One row (an agent) takes every other point as a pair candidate; several rows (the
        supervisor) take the pairs within r_s + r_a (:func:`pairs_within`, a k-d tree): the
        same nonzero terms (u2 is exactly 0 beyond, (Vmij)), summed in another order, so the
        commands agree to the last bits (1,000 vehicles: ~1 M candidate pairs → a few
        thousand)."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if rows.size == 0:
            return _EMPTY_POS.copy()
        k = np.asarray(self.locate(p), dtype=np.int64)
        extra: dict[str, Any] = {}
        if self.kind == "apf":
            extra["obstacles"] = self.all_obstacles
        if rows.size > 1:
            # + 1 nm: the k-d tree compares squared distances, so a pair 1 ulp inside the
            # barrier's support could be missed; pairs beyond add exactly 0
            extra["pairs"] = pairs_within(p, self.neighbour_radius_m + 1e-9)
        return np.asarray(
            velocity_command(p, k, self.arrays, self.flown, kind=self.kind,
                             rows=rows, **extra),
            dtype=float,
        ).reshape(-1, 2)


# ------------------------------------------------------------------------------------------
# neighbour classification
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class NeighbourView:
    """The neighbour table sorted at one time (all positions tube frame, (n, 2)).

    ``live``: airborne and fresh (``live_vel`` their measured velocities); ``static``:
    airborne, stale but not yet lost (kept at the last position); ``lost``: said LOST, silent
    for longer than ``lost_after_s``, or stopped (:data:`STOPPED_PHASES`: holding or landing):
    inside the tube these become obstacles.
    """

    live_ids: np.ndarray = field(default_factory=lambda: _EMPTY_IDS)
    live_pos: np.ndarray = field(default_factory=lambda: _EMPTY_POS)
    live_vel: np.ndarray = field(default_factory=lambda: _EMPTY_POS)
    static_ids: np.ndarray = field(default_factory=lambda: _EMPTY_IDS)
    static_pos: np.ndarray = field(default_factory=lambda: _EMPTY_POS)
    lost_ids: np.ndarray = field(default_factory=lambda: _EMPTY_IDS)
    lost_pos: np.ndarray = field(default_factory=lambda: _EMPTY_POS)

    def points(self) -> np.ndarray:
        """Every position the pair barrier must respect: live, static and lost (n, 2)."""
        return np.concatenate([self.live_pos, self.static_pos, self.lost_pos])

    def ids(self) -> np.ndarray:
        return np.concatenate([self.live_ids, self.static_ids, self.lost_ids])


def classify(
    states: Iterable[NeighbourState],
    now_s: float,
    *,
    max_age_s: float,
    lost_after_s: float,
    exclude: int | None = None,
    heard_since_s: float | None = None,
) -> NeighbourView:
    """Sort neighbour states at wall-clock time ``now_s`` (see the module docstring).

    ``heard_since_s`` (wall clock): when our own loop resumed after a stall; a state cannot be
    *lost* by silence before ``lost_after_s`` has passed since then (the backlog of a stalled
    process is not the neighbours' silence); it is still not used as a live position.
    """
    st = [s for s in states if s.vehicle_id != exclude]
    n = len(st)
    return classify_arrays(
        np.fromiter((s.vehicle_id for s in st), np.int64, n),
        np.array([(s.x_m, s.y_m) for s in st], dtype=float).reshape(n, 2),
        np.array([(s.vx_m_s, s.vy_m_s) for s in st], dtype=float).reshape(n, 2),
        [s.phase for s in st], np.fromiter((s.stamp_s for s in st), float, n), now_s,
        max_age_s=max_age_s, lost_after_s=lost_after_s, heard_since_s=heard_since_s)


#: :func:`classify_arrays`' sorting of a phase: 0 lost (said LOST, or stopped), 1 airborne
#: (live, static or lost by age), 2 on the ground (ignored).
_PHASE_CLASS = {ph: 0 if ph == Phase.LOST or ph in STOPPED_PHASES
                else 1 if ph in AIRBORNE_PHASES else 2 for ph in Phase}


def classify_arrays(
    ids: np.ndarray,
    pos: np.ndarray,
    vel: np.ndarray,
    phases: Sequence[Phase],
    stamps_s: np.ndarray,
    now_s: float,
    *,
    max_age_s: float,
    lost_after_s: float,
    heard_since_s: float | None = None,
) -> NeighbourView:
    """:func:`classify` on a table of states given as arrays (``ids`` unique (n,), ``pos`` and
    ``vel`` (n, 2) tube frame, ``phases`` n, ``stamps_s`` (n,) wall clock): the supervisor's
    whole fleet in one vectorized pass, the same arithmetic as per state."""
    ok = np.isfinite(pos).all(axis=1)
    kind = np.fromiter((_PHASE_CLASS[ph] for ph in phases), np.int8, len(phases))
    age = now_s - stamps_s
    silence = age if heard_since_s is None else np.minimum(age, now_s - heard_since_s)
    flying = ok & (kind == 1)
    lost = (ok & (kind == 0)) | (flying & (silence > lost_after_s))
    static = flying & ~lost & (age > max_age_s)
    live = flying & ~lost & ~static

    def arr(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rows = np.flatnonzero(mask)
        if not rows.size:
            return _EMPTY_IDS, _EMPTY_POS, rows
        rows = rows[np.argsort(ids[rows], kind="stable")]
        return ids[rows].astype(np.int64, copy=False), pos[rows], rows

    li, lp, lr = arr(live)
    lv = np.nan_to_num(vel[lr]) if lr.size else _EMPTY_POS
    si, sp, _ = arr(static)
    oi, op, _ = arr(lost)
    return NeighbourView(li, lp, lv, si, sp, oi, op)


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


# ------------------------------------------------------------------------------------------
# the agent
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Setpoint:
    """An agent's decision for one tick: horizontal velocity in the tube frame (m/s), the
    sub-tube it is in (index into the plan's partition) and the neighbours it used."""

    vx_m_s: float
    vy_m_s: float
    sub_tube: int
    neighbours: int

    @property
    def speed_m_s(self) -> float:
        return math.hypot(self.vx_m_s, self.vy_m_s)


class Agent:
    """One vehicle's decision logic (module docstring). Pure: time is passed in.

    ``lost_radius_m`` is the radius of the obstacle a LOST neighbour becomes (r_s + margin).
    """

    def __init__(
        self,
        vehicle_id: int,
        plan: FlightPlan,
        *,
        max_age_s: float = 0.5,
        lost_after_s: float = 1.0,
        lost_radius_m: float | None = None,
    ) -> None:
        if not 0 < max_age_s <= lost_after_s:
            raise ValueError(f"need 0 < max_age_s <= lost_after_s, got {max_age_s}, "
                             f"{lost_after_s}")
        self.vehicle_id = int(vehicle_id)
        self.root_plan = plan
        self.plan = plan
        self.max_age_s = float(max_age_s)
        self.lost_after_s = float(lost_after_s)
        self.lost_radius_m = float(plan.flown.r_s if lost_radius_m is None else lost_radius_m)
        #: called with every new phase (the pilot keeps its fleet table's phase column so)
        self.on_phase: Callable[[Phase], None] | None = None
        self._phase = Phase.CONNECTING
        self.table: dict[int, NeighbourState] = {}

    # -- phase ---------------------------------------------------------------------------
    @property
    def phase(self) -> Phase:
        return self._phase

    @phase.setter
    def phase(self, phase: Phase) -> None:
        self._phase = Phase(phase)
        if self.on_phase is not None:
            self.on_phase(self._phase)

    def set_phase(self, phase: Phase) -> bool:
        """Set the phase; True if it changed."""
        phase = Phase(phase)
        if phase == self._phase:
            return False
        self.phase = phase
        return True

    # -- neighbour table -----------------------------------------------------------------
    def observe(self, states: Mapping[int, NeighbourState] | Iterable[NeighbourState]) -> None:
        """Merge neighbour states into the table (own id skipped; newest seq/stamp wins)."""
        values = states.values() if isinstance(states, Mapping) else states
        table = self.table
        for st in values:
            vid = st.vehicle_id
            if vid == self.vehicle_id:
                continue
            prev = table.get(vid)
            if prev is None or (st.seq, st.stamp_s) >= (prev.seq, prev.stamp_s):
                table[vid] = st

    def view(self, now_s: float, heard_since_s: float | None = None) -> NeighbourView:
        """The table sorted at ``now_s`` (:func:`classify`)."""
        return classify(self.table.values(), now_s, max_age_s=self.max_age_s,
                        lost_after_s=self.lost_after_s, exclude=self.vehicle_id,
                        heard_since_s=heard_since_s)

    def update_plan(self, view: NeighbourView) -> bool:
        """Re-partition if the set of lost obstacles changed; True if the plan changed.

        Raises :class:`~vtube_fleet.core.partition.PartitionError` when no valid partition exists
        (the caller holds and aborts).
        """
        lost = lost_obstacles(view, self.root_plan.tube, self.lost_radius_m, self.plan.flown)
        new = self.root_plan.with_lost(lost)
        if new is self.plan:
            return False
        self.plan = new
        return True

    # -- decisions -------------------------------------------------------------------------
    def has_exited(self, own_xy: np.ndarray) -> bool:
        """(TraCondition) for the own position."""
        return bool(self.plan.exited(np.asarray(own_xy, dtype=float)))

    def setpoint(self, own_xy: np.ndarray, view: NeighbourView) -> Setpoint:
        """The controller's command for this vehicle at ``own_xy`` given ``view``.

        Neighbours are every live, static or lost point within r_s + r_a (flown) of the own
        position; the command is ``velocity_command`` of the swarm [own, neighbours] for row 0.
        """
        own = np.asarray(own_xy, dtype=float).reshape(2)
        pts = view.points()
        if pts.shape[0]:
            d = np.hypot(*(pts - own).T)
            pts = pts[d <= self.plan.neighbour_radius_m]
        p = np.concatenate([own[None], pts])
        cmd = self.plan.commands(p, [0])[0]
        k = int(np.asarray(self.plan.locate(own)).reshape(-1)[0])
        return Setpoint(float(cmd[0]), float(cmd[1]), k, int(pts.shape[0]))


def exit_velocity(
    plan: FlightPlan,
    own_xy: np.ndarray,
    view: NeighbourView,
    *,
    stop_distance_m: float,
    slow_m_s: float | None = None,
) -> np.ndarray | None:
    """Velocity of a vehicle past the finishing line (Assumption 2: it no longer follows the
    tube's controller): straight on at v along the main tube's n_c, so vehicles that exited
    keep their spacing. Returns ``None`` (stop and hold) when a vehicle that is not flying on
    (static, lost or stopped — by its phase, not by its reported speed: PX4's velocity
    estimate can be 0.5 m/s off) lies ahead within ``stop_distance_m`` along n_c and within
    2 r_s (flown) across, so a vehicle never runs into one that stopped ahead of it.
    ``slow_m_s``: live vehicles slower than this count as stopped too (default: none).
    """
    own = np.asarray(own_xy, dtype=float).reshape(2)
    n_c = plan.tube.n_c
    v = float(plan.flown.v)
    pts = [view.static_pos, view.lost_pos]
    if slow_m_s is not None and view.live_pos.shape[0]:
        sp = np.hypot(view.live_vel[:, 0], view.live_vel[:, 1])
        pts.append(view.live_pos[sp < float(slow_m_s)])
    pts_all = np.concatenate(pts)
    if pts_all.shape[0]:
        rel = pts_all - own
        ahead = rel @ n_c
        across = np.abs(rel @ np.array([-n_c[1], n_c[0]]))
        blocked = (ahead > 0) & (ahead <= stop_distance_m) & (across < 2.0 * plan.flown.r_s)
        if bool(blocked.any()):
            return None
    return v * n_c


def fleet_setpoints(plan: FlightPlan, p: np.ndarray, rows: Sequence[int] | np.ndarray
                    ) -> np.ndarray:
    """Commands of many agents at once (the supervisor's path).

    ``p`` (M, 2) is every point an agent would see (the agents' own positions plus the static
    and lost points), ``rows`` the agents to compute. Row for row each agent's
    :meth:`Agent.setpoint` with the same view, to the last bits (``velocity_command`` only
    couples a robot with neighbours within r_s + r_a; the batch sums the same terms in
    another order, :meth:`FlightPlan.commands`).
    """
    return plan.commands(p, rows)
