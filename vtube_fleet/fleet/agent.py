"""The per-vehicle agent: pure decision logic, no I/O, no asyncio.

An :class:`Agent` is what one vehicle knows and decides:

* a **neighbour table** of the other vehicles' latest :class:`~vtube_fleet.bus.NeighbourState`
  (time-stamped, newest ``seq`` wins). :func:`classify` sorts it at a given time:
  *live* entries (flying, younger than ``max_age_s``) are neighbours at their reported
  positions; a stale entry is never used as a live position: a flying vehicle heard from between
  ``max_age_s`` and ``lost_after_s`` ago is kept as a *static point* at its last position (so the
  pair barrier still keeps clear of where it was), and one silent for longer than
  ``lost_after_s``, or that says it is ``LOST``, is *lost*: a static obstacle at its last
  position. Entries of vehicles on the ground (connecting, ready, arming, landed, failed) are
  ignored.
* its **phase** (:class:`~vtube_fleet.bus.Phase`), advanced by the pilot; the agent itself moves
  IN_TUBE → EXITED when (TraCondition) holds on the main tube: −n_cᵀ(p − p_r1) ≤ ε_0
  (Assumption 2).
* its **horizontal setpoint** in the tube frame: the core controller
  :func:`vtube_fleet.controller.velocity_command` (ModifiedVectorField) evaluated for its own row
  only (``rows=[0]``) with the sub-tube index from :meth:`Partition.locate` (the switching logic
  (ObstacleController)) and its neighbours within r_s + r_a, the same code the simulator runs.
  The supervisor computes many agents at once with :func:`fleet_setpoints`, which calls
  ``velocity_command`` once with ``rows`` = all those agents; row for row this equals each
  agent's own :meth:`Agent.setpoint` (``tests/test_fleet_agent.py``).

**The safety budget** (:class:`SafetyBudget`). The paper's guarantee (Theorems 1, 2) is for
continuous time and a vehicle whose velocity *is* the command. A fleet samples positions that
are already ``L`` old (link latency), holds each command for a control period ``T`` and flies
multicopters that follow a velocity step only after a dead time τ_d and then with a first-order
lag t63 (PX4 SITL captures: τ_d ≈ 0.3 s, t63 ≈ 1 s). After a command changes by Δv the position
of such a vehicle lags the ideal single integrator (Single) by at most Δv·(T + L + τ_d + t63).
Only the saturated part of (ModifiedVectorField), sat(u2 + u3' + u4', v'_max), reacts to
neighbours, walls and sub-tube sides; u1'' is common to all robots of a sub-tube and its
differences are themselves bounded by v'_max (Constraint2/Constraint3). So one robot's
unmodelled excursion towards anything is at most v'_max·(T + L + τ_d + t63), and the runtime
flies the controller with the radii inflated by

    δ = v'_max · (T + L + τ_d + t63),     r_s' = r_s + δ,     r_a' = r_a + δ,

so the continuous-time clearance 2 r_s' between two vehicles leaves 2 r_s after both lag, the
leg clearance r_s' leaves r_s and the obstacle clearance r_o + r_s' leaves r_o + r_s. The
inflated scenario must itself satisfy the paper's conditions (Assumption 1/3/3', (pothk)); the
supervisor validates it before arming and reports when the budget makes the mission infeasible.
The clearance actually flown is measured from telemetry and reported.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vtube_fleet.bus.base import NeighbourState, Phase
from vtube_fleet.controller import ControllerParams, velocity_command
from vtube_fleet.partition import Partition, h_min, partition
from vtube_fleet.tube import Obstacle, Trapezoid

__all__ = [
    "AIRBORNE_PHASES",
    "LOST_APEX_FACTOR",
    "Agent",
    "FlightPlan",
    "NeighbourView",
    "SafetyBudget",
    "Setpoint",
    "classify",
    "exit_velocity",
    "fleet_setpoints",
    "lost_obstacles",
]

#: Phases in which a vehicle is (or may be) in the air and so matters to the others.
AIRBORNE_PHASES: frozenset[Phase] = frozenset(
    {Phase.TAKEOFF, Phase.IN_TUBE, Phase.EXITED, Phase.HOLDING, Phase.LANDING}
)

_EMPTY_POS = np.zeros((0, 2))
_EMPTY_IDS = np.zeros(0, dtype=np.int64)


# ------------------------------------------------------------------------------------------
# the safety budget
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SafetyBudget:
    """δ = v'_max·(T + L + τ_d + t63) (module docstring), or a fixed override.

    ``period_s`` T, ``latency_s`` L (one-way link latency plus the age of the position sample),
    ``dead_time_s`` τ_d and ``t63_s`` of the vehicles' velocity tracking, ``v_max_prime`` of the
    controller; ``delta_m`` the inflation used (``overridden`` when set by the mission file).
    """

    period_s: float
    latency_s: float
    dead_time_s: float
    t63_s: float
    v_max_prime: float
    delta_m: float
    overridden: bool = False

    @property
    def delay_s(self) -> float:
        """The effective delay T + L + τ_d + t63."""
        return self.period_s + self.latency_s + self.dead_time_s + self.t63_s

    @classmethod
    def compute(
        cls,
        params: ControllerParams,
        *,
        period_s: float,
        latency_s: float,
        dead_time_s: float,
        t63_s: float,
        override_m: float | None = None,
    ) -> SafetyBudget:
        for name, value in (("period_s", period_s), ("latency_s", latency_s),
                            ("dead_time_s", dead_time_s), ("t63_s", t63_s)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"safety budget: {name} must be finite and >= 0, got {value}")
        delay = period_s + latency_s + dead_time_s + t63_s
        delta = float(params.v_max_prime) * delay if override_m is None else float(override_m)
        return cls(period_s, latency_s, dead_time_s, t63_s, float(params.v_max_prime), delta,
                   override_m is not None)

    def inflate(self, params: ControllerParams) -> ControllerParams:
        """The controller parameters actually flown: r_s' = r_s + δ, r_a' = r_a + δ."""
        return dataclasses.replace(params, r_s=params.r_s + self.delta_m,
                                   r_a=params.r_a + self.delta_m)

    def describe(self, params: ControllerParams | None = None) -> str:
        """One line with the formula and the numbers."""
        if self.overridden:
            text = f"δ = {self.delta_m:.3f} m (safety_margin_m from the mission file)"
        else:
            text = (
                f"δ = v'_max·(T + L + τ_d + t63) = {self.v_max_prime:g}·({self.period_s:.3f} + "
                f"{self.latency_s:.3f} + {self.dead_time_s:.3f} + {self.t63_s:.3f}) = "
                f"{self.delta_m:.3f} m"
            )
        if params is not None:
            text += (f" → r_s' = {params.r_s + self.delta_m:.3f} m, "
                     f"r_a' = {params.r_a + self.delta_m:.3f} m")
        return text

    def as_dict(self) -> dict[str, Any]:
        return {
            "delta_m": self.delta_m,
            "period_s": self.period_s,
            "latency_s": self.latency_s,
            "dead_time_s": self.dead_time_s,
            "t63_s": self.t63_s,
            "v_max_prime": self.v_max_prime,
            "overridden": self.overridden,
        }


# ------------------------------------------------------------------------------------------
# the plan every agent shares
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class FlightPlan:
    """What all agents share: the main tube, the configured obstacles, the obstacles left by
    LOST vehicles, the controller parameters flown (inflated by the safety budget) and the
    partition of the tube around all obstacles (Section IV-A).

    :meth:`with_lost` recomputes the partition online; results are cached per set of lost
    obstacles and shared by every plan derived from the same root, so N agents reacting to the
    same loss partition once.
    """

    tube: Trapezoid
    obstacles: tuple[Obstacle, ...]
    params: ControllerParams
    partition: Partition
    lost: tuple[Obstacle, ...] = ()
    kind: str = "new"
    _cache: dict[tuple, FlightPlan] = field(default_factory=dict, repr=False)

    @classmethod
    def build(
        cls,
        tube: Trapezoid,
        obstacles: Sequence[Obstacle],
        params: ControllerParams,
        *,
        kind: str = "new",
        part: Partition | None = None,
    ) -> FlightPlan:
        """Partition (raises :class:`~vtube_fleet.partition.PartitionError`) and wrap."""
        obstacles = tuple(obstacles)
        if part is None:
            part = partition(tube, obstacles, params)
        plan = cls(tube, obstacles, params, part, (), kind)
        plan._cache[()] = plan
        return plan

    @property
    def neighbour_radius_m(self) -> float:
        """r_s + r_a (flown): the range of the pair barrier u2 (Vmij)."""
        return float(self.params.r_s + self.params.r_a)

    @property
    def all_obstacles(self) -> tuple[Obstacle, ...]:
        return self.obstacles + self.lost

    def with_lost(self, lost: Sequence[Obstacle]) -> FlightPlan:
        """The plan with these lost-vehicle obstacles (replacing any previous ones)."""
        lost = tuple(lost)
        key = tuple((round(float(o.center[0]), 6), round(float(o.center[1]), 6),
                     round(float(o.radius), 6)) for o in lost)
        hit = self._cache.get(key)
        if hit is None:
            part = partition(self.tube, self.obstacles + lost, self.params)
            hit = FlightPlan(self.tube, self.obstacles, self.params, part, lost, self.kind,
                             self._cache)
            self._cache[key] = hit
        return hit

    def exited(self, p: np.ndarray) -> np.ndarray:
        """(TraCondition) on the MAIN tube: −n_cᵀ(p − p_r1) ≤ ε_0 → (…,) bool."""
        p = np.asarray(p, dtype=float)
        return -((p - self.tube.p_r1) @ self.tube.n_c) <= float(self.params.eps_0)

    def commands(self, p: np.ndarray, rows: Sequence[int] | np.ndarray) -> np.ndarray:
        """The controller's commands (len(rows), 2) for robots ``rows`` of the swarm ``p``
        (M, 2): sub-tubes by :meth:`Partition.locate`, then ``velocity_command``."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if rows.size == 0:
            return _EMPTY_POS.copy()
        k = np.asarray(self.partition.locate(p), dtype=np.int64)
        extra: dict[str, Any] = {}
        if self.kind == "apf":
            extra["obstacles"] = self.all_obstacles
        return np.asarray(
            velocity_command(p, k, self.partition.arrays, self.params, kind=self.kind,
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
    airborne, stale but not yet lost (kept at the last position); ``lost``: said LOST or silent
    for longer than ``lost_after_s``.
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
    buckets: dict[str, tuple[list[int], list[tuple[float, float]]]] = {
        "live": ([], []), "static": ([], []), "lost": ([], [])}
    live_vel: list[tuple[float, float]] = []
    for st in states:
        if st.vehicle_id == exclude:
            continue
        if not (math.isfinite(st.x_m) and math.isfinite(st.y_m)):
            continue
        age = now_s - st.stamp_s
        silence = age if heard_since_s is None else min(age, now_s - heard_since_s)
        if st.phase == Phase.LOST:
            which = "lost"
        elif st.phase not in AIRBORNE_PHASES:
            continue
        elif silence > lost_after_s:
            which = "lost"
        elif age > max_age_s:
            which = "static"
        else:
            which = "live"
        ids, pos = buckets[which]
        ids.append(st.vehicle_id)
        pos.append((st.x_m, st.y_m))
        if which == "live":
            live_vel.append((st.vx_m_s, st.vy_m_s))

    def arr(which: str) -> tuple[np.ndarray, np.ndarray]:
        ids, pos = buckets[which]
        if not ids:
            return _EMPTY_IDS, _EMPTY_POS
        order = np.argsort(ids, kind="stable")
        return (np.asarray(ids, dtype=np.int64)[order],
                np.asarray(pos, dtype=float).reshape(-1, 2)[order])

    li, lp = arr("live")
    lv = _EMPTY_POS
    if live_vel:
        lv = np.nan_to_num(np.asarray(live_vel, dtype=float).reshape(-1, 2))[
            np.argsort(buckets["live"][0], kind="stable")]
    si, sp = arr("static")
    oi, op = arr("lost")
    return NeighbourView(li, lp, lv, si, sp, oi, op)


#: Apex distance of a lost vehicle's triangle: this × h_min (pothk). Smaller than the default
#: 1.3 for configured obstacles so that the triangle fits more often between a vehicle lost
#: mid-tube and the others.
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
        if bool(tube.contains(p)):
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
        self.lost_radius_m = float(plan.params.r_s if lost_radius_m is None else lost_radius_m)
        self.phase = Phase.CONNECTING
        self.table: dict[int, NeighbourState] = {}

    # -- phase ---------------------------------------------------------------------------
    def set_phase(self, phase: Phase) -> bool:
        """Set the phase; True if it changed."""
        phase = Phase(phase)
        if phase == self.phase:
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

        Raises :class:`~vtube_fleet.partition.PartitionError` when no valid partition exists
        (the caller holds and aborts).
        """
        lost = lost_obstacles(view, self.root_plan.tube, self.lost_radius_m, self.plan.params)
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
        k = int(np.asarray(self.plan.partition.locate(own)).reshape(-1)[0])
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
    (static, lost, or live but slower than ``slow_m_s``, default v/2) lies ahead within
    ``stop_distance_m`` along n_c and within 2 r_s (flown) across, so a vehicle never runs
    into one that stopped ahead of it.
    """
    own = np.asarray(own_xy, dtype=float).reshape(2)
    n_c = plan.tube.n_c
    v = float(plan.params.v)
    slow = 0.5 * v if slow_m_s is None else float(slow_m_s)
    pts = [view.static_pos, view.lost_pos]
    if view.live_pos.shape[0]:
        sp = np.hypot(view.live_vel[:, 0], view.live_vel[:, 1])
        pts.append(view.live_pos[sp < slow])
    pts_all = np.concatenate(pts)
    if pts_all.shape[0]:
        rel = pts_all - own
        ahead = rel @ n_c
        across = np.abs(rel @ np.array([-n_c[1], n_c[0]]))
        blocked = (ahead > 0) & (ahead <= stop_distance_m) & (across < 2.0 * plan.params.r_s)
        if bool(blocked.any()):
            return None
    return v * n_c


def fleet_setpoints(plan: FlightPlan, p: np.ndarray, rows: Sequence[int] | np.ndarray
                    ) -> np.ndarray:
    """Commands of many agents at once (the supervisor's path).

    ``p`` (M, 2) is every point an agent would see (the agents' own positions plus the static
    and lost points), ``rows`` the agents to compute. Identical, row for row, to each agent's
    :meth:`Agent.setpoint` with the same view: ``velocity_command`` only couples a robot with
    neighbours within r_s + r_a.
    """
    return plan.commands(p, rows)
