"""The control tick: one implementation for one vehicle and for a thousand.

Every process that flies vehicles — the supervisor (its whole fleet) and an MQTT agent (its one
vehicle) — keeps their state in a :class:`~vtube_fleet.fleet.table.FleetTable` and runs the same
:class:`Tick` over it at the mission's rate (:class:`ControlClock`). A tick, in this order
(:meth:`Tick.__call__`):

1. **links** (:func:`read_links`): every link read ONCE; telemetry only arrives between ticks;
2. **sense** (:func:`sense`): new local positions into the tube frame (one vectorized frame
   conversion), the estimate compensator fed; then each vehicle's route segment
   (:func:`hand_over`: from its first position on, the hand-overs while it flies the tube);
3. **faults** (:func:`find_faults` over :data:`FAULT_RULES`): every rule evaluated for every
   vehicle; a vehicle that hits one is LOST (a static obstacle at its last position) or lands
   where it is (a low battery: stopped, an obstacle until it is down), or FAILED while arming;
   touch-downs of holding/landing vehicles are noticed;
4. **states** (:func:`own_states`): what each vehicle tells the others (published on the bus
   by an agent);
5. **classify** (:func:`~vtube_fleet.fleet.neighbour_view.classify`): the own states plus those
   heard from others (an agent's bus) sorted into live / static / lost;
6. **plan**: re-partition around lost and stopped vehicles, in whichever segment they stopped
   (:meth:`~vtube_fleet.fleet.flight_plan.FlightPlan.with_lost`, in the worker thread), a
   partition of its own for a vehicle it traps that has passed some obstacles
   (:meth:`~vtube_fleet.fleet.flight_plan.FlightPlan.past`; the others trapped wait or land;
   when no common partition exists, each vehicle in the tube flies one of its own or waits:
   :class:`NoCommonPartition`), exits
   (TraCondition on the route's LAST finishing line), then the controller's commands for every
   vehicle still in the tube in ONE call, each in its segment
   (:meth:`~vtube_fleet.fleet.flight_plan.FlightPlan.commands`, ModifiedVectorField; one call
   more per vehicle flying a partition of its own);
7. **actuate** (:func:`actuate`): each vehicle's setpoint for its phase (arming, the climb, the
   tube plus the estimate compensation d̂ — with reference tracking plus the position loop to
   each vehicle's reference, :func:`track_references` after step 2 —, the exit behaviour,
   standing still), all sent in one
   batch (:func:`~vtube_fleet.link.base.send_velocities_ned`);
8. **measure** is the caller's: the supervisor judges the fleet
   (:mod:`vtube_fleet.fleet.measure`), an agent records what it heard; both feed the budget
   watch with :func:`watch_budget`.

Transitions a tick decides (lost, exited, hold, land, failed, landed) go through the vehicles'
:class:`~vtube_fleet.fleet.pilot.VehiclePilot` (its events and waiters); the pilot keeps the
flight procedure (arm, climb, hold, land) and no tick step of its own.
"""

from __future__ import annotations

import asyncio
import gc
import inspect
import math
import sys
import time
from collections.abc import Awaitable, Callable, Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from vtube_fleet.config.mission import Mission
from vtube_fleet.core.partition import PartitionError
from vtube_fleet.core.text import point_text
from vtube_fleet.fleet.budget import BudgetWatch
from vtube_fleet.fleet.compensation import RESIDUAL_WINDOW_S
from vtube_fleet.fleet.flight_plan import (
    FlightPlan,
    exit_room_of,
    exit_stop_m,
    exit_velocities,
    lost_obstacles,
)
from vtube_fleet.fleet.neighbour_view import NeighbourView, States, classify
from vtube_fleet.fleet.table import PHASE_CODE, FleetTable, phase_mask
from vtube_fleet.frames import TubeFrame
from vtube_fleet.link.base import LinkError, VehicleLink, VehicleState, send_velocities_ned
from vtube_fleet.state import (
    AIRBORNE_PHASES,
    OFFBOARD_PHASES,
    STOPPED_PHASES,
    TUBE_PHASES,
    Phase,
)

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.core.tube import Obstacle
    from vtube_fleet.fleet.pilot import VehiclePilot

__all__ = [
    "FAULT_RULES",
    "ControlClock",
    "Fault",
    "FaultContext",
    "FaultRule",
    "LinkColumns",
    "NeighbourSource",
    "NoCommonPartition",
    "Tick",
    "TickResult",
    "actuate",
    "find_faults",
    "hand_over",
    "own_states",
    "read_links",
    "sense",
    "slow_m_s",
    "stop_anchor_m",
    "toward_m_s",
    "unresponsive_s",
    "used_ages",
    "vertical_down_m_s",
    "watch_budget",
]

_ARMING = PHASE_CODE[Phase.ARMING]
_TAKEOFF = PHASE_CODE[Phase.TAKEOFF]
_IN_TUBE = PHASE_CODE[Phase.IN_TUBE]
_EXITED = PHASE_CODE[Phase.EXITED]
_HOLDING = PHASE_CODE[Phase.HOLDING]
_LANDING = PHASE_CODE[Phase.LANDING]
_LOST = PHASE_CODE[Phase.LOST]
_WAITING = PHASE_CODE[Phase.WAITING]
_STEPPING = PHASE_CODE[Phase.STEPPING]
_OFFBOARD_MASK = phase_mask(OFFBOARD_PHASES)
_CHECKED_MASK = phase_mask(AIRBORNE_PHASES | {Phase.ARMING})
#: who may be trapped by a re-partition (the climb and the tube)
_TRAPPABLE_MASK = phase_mask({Phase.IN_TUBE, Phase.TAKEOFF})
#: who needs the plan around the stopped vehicles (those, and those waiting or stepping aside
#: in the tube: a failed re-plan aborts them too)
_FLYING_TUBE_MASK = phase_mask(TUBE_PHASES | {Phase.TAKEOFF})
#: who flies among the others: while anyone does, no waiting vehicle is released
_BUSY_MASK = phase_mask({Phase.ARMING, Phase.TAKEOFF, Phase.IN_TUBE, Phase.STEPPING})
_IN_TUBE_MASK = phase_mask(TUBE_PHASES)
_STOPPED_MASK = phase_mask(STOPPED_PHASES)

#: Gain (1/s) and limit (m/s) of the horizontal position hold during the climb (on top of the
#: estimate-disturbance compensation, which cancels most of the take-off drift).
TAKEOFF_XY_GAIN_1_S = 0.5
TAKEOFF_XY_MAX_M_S = 0.5
#: Height (m) above which a climbing vehicle counts as airborne without PX4 saying IN_AIR.
AIRBORNE_UP_M = 0.5
#: The floor of :func:`slow_m_s`: below this a vehicle is still whatever v_min is.
STILL_M_S = 0.05
#: Estimate jitter (m) a still vehicle's position may show without counting as moving.
STILL_POS_TOL_M = 0.1
#: Stepping aside (docs/fleet.md, "Waiting for a way"): the gain (1/s) and the speed cap (m/s)
#: of the move to the point across n_c, and how near (m) counts as there.
STEP_GAIN_1_S = 1.0
STEP_MAX_M_S = 0.5
STEP_ARRIVED_M = 0.1
#: Reference tracking: the cap (m/s) of the position loop's correction K (r − p̂) added to the
#: command (a vehicle further off than this correction can close is held by the watch anyway).
TRACKING_CORRECTION_MAX_M_S = 1.0
#: … and the start ramp (s): a reference (re)started from the hover flies its commands scaled
#: up from 0 to 1 over this time (:func:`reference_velocities`). PX4's velocity response to a
#: 1 m/s step from the hover leaves a vehicle ~0.6 m behind its reference; ramped over 3 s,
#: ~0.3 m (docs/fleet.md, reference tracking).
TRACKING_RAMP_S = 3.0


# ----------------------------------------------------------------------------------------------
# 1. the links, read once a tick
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class LinkColumns:
    """What a tick reads from the links, gathered in ONE pass (:func:`read_links`), row k from
    ``links[k]``: each link's ``states`` (its :class:`VehicleState`), the arrival of its latest
    local position ``position_s`` (NaN: none), whether its GPS origin is known
    (``origin_known``), whether it reports OFFBOARD (``offboard``), armed (``armed``: True) and
    disarmed (``disarmed``: False; unknown is neither), on the ground (``on_ground``) or in the
    air (``in_air``), its one-way latency ``latency_s`` (NaN: not measured yet), whether it
    is ``closed`` and its remaining battery charge ``battery_pct`` (%, NaN: not reported). The
    links only change between ticks (their telemetry arrives in the event
    loop), so one snapshot serves every step of a tick."""

    states: list[VehicleState]
    position_s: np.ndarray
    origin_known: np.ndarray
    offboard: np.ndarray
    armed: np.ndarray
    disarmed: np.ndarray
    on_ground: np.ndarray
    in_air: np.ndarray
    latency_s: np.ndarray
    closed: np.ndarray
    battery_pct: np.ndarray


def read_links(links: Sequence[VehicleLink]) -> LinkColumns:
    """The links as :class:`LinkColumns`, in their order."""
    n = len(links)
    states = [lk.state for lk in links]
    nan = math.nan
    cols = np.array([(nan if (t := s.last_position_s) is None else t, s.origin is not None,
                      s.flight_mode == "OFFBOARD", s.armed is True, s.armed is False,
                      s.landed_state == "ON_GROUND", s.landed_state == "IN_AIR",
                      nan if (x := lk.latency_s) is None else x, lk.closed,
                      s.battery_remaining)
                     for lk, s in zip(links, states, strict=True)], dtype=float).reshape(n, 10)
    flag = cols[:, 1:7] == 1.0
    return LinkColumns(states, cols[:, 0], flag[:, 0], flag[:, 1], flag[:, 2], flag[:, 3],
                       flag[:, 4], flag[:, 5], cols[:, 7], cols[:, 8] == 1.0, 100.0 * cols[:, 9])


# ----------------------------------------------------------------------------------------------
# 2. sense
# ----------------------------------------------------------------------------------------------
def sense(tab: FleetTable, links: LinkColumns, frame: TubeFrame, mission: Mission
          ) -> tuple[np.ndarray, np.ndarray]:
    """Take every link's latest local position, if newer than the one in use (and its origin
    known), into the tube frame: one vectorized conversion of positions (pymap3d on arrays) and
    velocities (the frame's rotation), written into the table's columns, and one compensator
    update for them all. Returns the rows with a new sample and the climbing rows that reached
    the mission altitude (± tolerance) with it."""
    last = links.position_s
    rows = np.flatnonzero(np.isfinite(last) & links.origin_known & (last != tab.sample_s))
    if not rows.size:
        return rows, rows
    st = [links.states[i] for i in rows.tolist()]
    k = len(st)
    cols = np.array([(s.north_m, s.east_m, s.down_m, s.origin.lat_deg,  # type: ignore[union-attr]
                      s.origin.lon_deg, s.origin.alt_m,  # type: ignore[union-attr]
                      s.vn_m_s, s.ve_m_s) for s in st], dtype=float).reshape(k, 8).T
    x, y, up = (np.atleast_1d(v).astype(float) for v in frame.local_ned_to_tube(*cols[:6]))
    a, b, c, d = tab.to_tube
    vn, ve, t = cols[6], cols[7], last[rows]
    vx, vy = a * vn + b * ve, c * vn + d * ve
    tab.xy[rows, 0], tab.xy[rows, 1] = x, y
    tab.vel[rows, 0], tab.vel[rows, 1] = vx, vy
    tab.up[rows] = up
    tab.sample_s[rows] = t
    tab.has[rows] = np.isfinite(x) & np.isfinite(y)
    cfg = mission.config
    up_ok = np.abs(up - cfg.altitude_m) <= cfg.altitude_tolerance_m
    if tab.compensator is not None:
        tab.compensator.add(rows, t, x, y, vx, vy)
    return rows, rows[(tab.phase[rows] == _TAKEOFF) & up_ok]


def hand_over(tab: FleetTable, plan: FlightPlan) -> None:
    """The route segment of every vehicle (the table's ``segment`` column, the hand-over state
    :meth:`FlightPlan.locate` is given back every tick): a vehicle's first position assigns the
    segment it starts in, and while it flies the tube (IN_TUBE) it hands over to the next one
    where the route says (:meth:`~vtube_fleet.core.route.Route.advance`). A one-segment
    route: 0."""
    rows = np.flatnonzero(tab.has & ((tab.segment < 0) | (tab.phase == _IN_TUBE)))
    if rows.size:
        tab.segment[rows] = plan.advance(tab.xy[rows], tab.segment[rows])


def track_references(tab: FleetTable, links: LinkColumns, now_mono: float) -> None:
    """Reference tracking (``tracking = "reference"``, docs/fleet.md): each in-tube vehicle's
    reference r advances by the velocity it was sent to fly since the last tick (``ref_vel``:
    the controller's command on the start ramp, :func:`reference_velocities`), so r is the
    integral of the controller's commands: the paper's single integrator. A vehicle that did
    not fly the controller's command last tick (entering the tube, standing still, back from
    waiting) starts again from its estimate (``ref_since_s`` now); others have none. Then the
    offset r − p̂ at the sample's time (r then: :func:`reference_at`) ``track_off`` and its
    norm ``track_err_m``."""
    dt = now_mono - tab.ref_s if math.isfinite(tab.ref_s) else 0.0
    tab.ref_s = now_mono
    flew = tab.cmd_in_tube & np.isfinite(tab.ref_xy[:, 0]) & np.isfinite(tab.ref_vel[:, 0])
    tab.ref_xy[flew] += tab.ref_vel[flew] * dt
    go = (tab.phase == _IN_TUBE) & tab.has & ~tab.standstill
    start = go & ~flew
    tab.ref_xy[start] = tab.xy[start]
    tab.ref_vel[start] = 0.0
    tab.ref_since_s[start] = now_mono
    tab.ref_xy[~go] = np.nan
    tab.ref_vel[~go] = np.nan
    tab.ref_since_s[~go] = np.nan
    tab.ref_hist.append((now_mono, tab.ref_xy.copy()))
    tab.track_off[:] = np.nan
    keep = np.flatnonzero(go & flew)
    if keep.size:
        age = (now_mono - tab.sample_s[keep]) + np.nan_to_num(links.latency_s[keep], nan=0.0)
        # (a sample older than the reference's restart: against r at the restart)
        then = reference_at(tab, keep, np.maximum(now_mono - age, tab.ref_since_s[keep]))
        late = ~np.isfinite(then[:, 0])  # older than the history: r moved back at ref_vel
        then[late] = tab.ref_xy[keep[late]] - tab.ref_vel[keep[late]] * age[late, None]
        tab.track_off[keep] = then - tab.xy[keep]
    tab.track_err_m = np.hypot(tab.track_off[:, 0], tab.track_off[:, 1])


def reference_at(tab: FleetTable, rows: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """The references of ``rows`` (k, 2) at monotonic times ``t_s`` (k,), interpolated in the
    history the ticks kept (``ref_hist``); NaN where ``t_s`` is older than it or a row had no
    reference then."""
    out = np.full((rows.size, 2), np.nan)
    hist = tab.ref_hist
    if len(hist) < 2:
        return out
    ts = np.fromiter((t for t, _ in hist), float, len(hist))
    refs = np.stack([r[rows] for _, r in hist])  # (H, k, 2)
    j = np.clip(np.searchsorted(ts, t_s), 1, ts.size - 1)
    t0, t1 = ts[j - 1], ts[j]
    w = np.clip((t_s - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0, 1.0)[:, None]
    k = np.arange(rows.size)
    got = refs[j - 1, k] * (1.0 - w) + refs[j, k] * w
    return np.where((t_s >= ts[0])[:, None], got, np.nan)


def reference_velocities(tab: FleetTable, rows: np.ndarray, cmds: np.ndarray, now_mono: float
                         ) -> np.ndarray:
    """What ``rows`` fly along their references (k, 2): the controller's commands ``cmds``
    scaled by the start ramp s = min(1, time since the reference started /
    :data:`TRACKING_RAMP_S`), kept in ``ref_vel`` for the next :func:`track_references`.
    Vehicles that start together share s(t): the same paths as the paper's, flown slower at
    first (a common time scale), so that no vehicle is asked for a step from the hover."""
    s = np.clip((now_mono - tab.ref_since_s[rows]) / TRACKING_RAMP_S, 0.0, 1.0)
    v = np.where(np.isfinite(s)[:, None], np.nan_to_num(s)[:, None] * cmds, 0.0)
    tab.ref_vel[rows] = v
    return v


def tracking_corrections(tab: FleetTable, rows: np.ndarray, gain_1_s: float) -> np.ndarray:
    """The position loop of reference tracking for ``rows`` (k, 2): K (r − p̂) at the sample's
    time (:func:`track_references`), at most :data:`TRACKING_CORRECTION_MAX_M_S`; zero where
    a row has no reference."""
    off = tab.track_off[rows]
    return toward_m_s(tab.xy[rows] + off, tab.xy[rows], np.isfinite(off).all(axis=1),
                      gain_1_s, TRACKING_CORRECTION_MAX_M_S)


# ----------------------------------------------------------------------------------------------
# 3. faults
# ----------------------------------------------------------------------------------------------
def slow_m_s(mission: Mission) -> float:
    """max(v_min / 2, :data:`STILL_M_S`): a vehicle in the tube is always commanded at least
    v_min (> 0, paper note 9) and PX4's steady shortfall is 10–20 %, so one whose estimated
    position moves slower than half of v_min for :func:`unresponsive_s` has slowed below v_min
    in the tube (issue 9): it is declared lost, an obstacle for everyone."""
    return max(0.5 * mission.scenario.robots.v_min, STILL_M_S)


def unresponsive_s(mission: Mission) -> float:
    """τ_d + 3 t63 + 1 s: longer than PX4 needs to follow any command change."""
    cfg = mission.config
    return cfg.tracking_dead_time_s + 3.0 * cfg.tracking_t63_s + 1.0


@dataclass(frozen=True)
class FaultContext:
    """What a fault rule reads: the table, this tick's links, the mission, the monotonic time
    ``now_s``, ``listening_since_s`` (our own loop resumed after a stall then: silence counts
    from then on; None: no stall) and ``checked`` (the rows under watch: airborne or arming)."""

    tab: FleetTable
    links: LinkColumns
    mission: Mission
    now_s: float
    listening_since_s: float | None
    checked: np.ndarray


#: A fault rule: ``find(ctx)`` → (rows hit (bool, n), the reason of one row).
FaultFind = Callable[[FaultContext], tuple[np.ndarray, Callable[[int], str]]]


@dataclass(frozen=True)
class FaultRule:
    """One in-flight fault rule, evaluated every tick for every vehicle (:func:`find_faults`):
    ``name``, ``find`` and the ``action`` on a vehicle that hits it: ``"lost"`` (stop commanding
    it; a static obstacle for everyone at its last position), ``"land"`` (it lands in place and,
    stopped, becomes an obstacle) or ``"hold"`` (PX4 Hold where it is: an obstacle too)."""

    name: str
    find: FaultFind
    action: str = "lost"  # "lost", "land" or "hold"


@dataclass(frozen=True)
class Fault:
    """A vehicle (table ``row``) that hit ``rule`` this tick, and why (``reason``)."""

    row: int
    rule: FaultRule
    reason: str


def _no_telemetry(ctx: FaultContext) -> tuple[np.ndarray, Callable[[int], str]]:
    last = ctx.links.position_s
    cfg = ctx.mission.config
    since = ctx.listening_since_s
    heard = last if since is None else np.maximum(last, since)
    hit = ~np.isfinite(last) | (ctx.now_s - heard > cfg.lost_after_s)

    def why(r: int) -> str:
        t = float(last[r])
        age = "never" if math.isnan(t) else f"{ctx.now_s - t:.2f} s ago"
        return (f"no telemetry for more than lost_after_s = {cfg.lost_after_s:g} s (last "
                f"position {age})")

    return hit, why


def _left_offboard(ctx: FaultContext) -> tuple[np.ndarray, Callable[[int], str]]:
    tab = ctx.tab
    hit = (_OFFBOARD_MASK[tab.phase] & tab.offboard_seen & ~tab.in_transition
           & ~ctx.links.offboard)

    def why(r: int) -> str:
        s = ctx.links.states[r]
        reason = f"left OFFBOARD unexpectedly (mode {s.flight_mode}, status {s.system_status})"
        texts = [t.text for t in s.statustexts
                 if 0 <= t.severity <= 2 and ctx.now_s - t.time_s <= 3.0]
        if texts:  # e.g. PX4's geofence or offboard-loss failsafe: "Failsafe activated"
            reason += f"; vehicle says \"{texts[-1]}\""
        return reason

    return hit, why


def _disarmed_in_air(ctx: FaultContext) -> tuple[np.ndarray, Callable[[int], str]]:
    ph = ctx.tab.phase
    return (_IN_TUBE_MASK[ph] | (ph == _EXITED)) & ctx.links.disarmed, \
        lambda r: "disarmed in the air"


def _unresponsive(ctx: FaultContext) -> tuple[np.ndarray, Callable[[int], str]]:
    """In the tube and commanded, its estimated position moved less than :func:`slow_m_s` ×
    the time for :func:`unresponsive_s`: not following its setpoints. Judged on the position,
    not on the reported speed: PX4's velocity estimate can be 0.8 m/s off (a probe flight froze
    a vehicle whose estimate kept saying 0.3 m/s: never caught, the others flew on to the
    fence). A spell starts afresh whenever the position moved more than that (plus
    :data:`STILL_POS_TOL_M` of estimate jitter). Keeps the spells in the table
    (``still_since_s``, ``still_xy``)."""
    tab, now = ctx.tab, ctx.now_s
    wait_s = unresponsive_s(ctx.mission)
    slow = slow_m_s(ctx.mission)
    since = ctx.listening_since_s
    hit = np.zeros(tab.n, bool)
    if since is not None and now - since <= wait_s:
        return hit, str
    watched = ctx.checked & (tab.phase == _IN_TUBE)
    speed = np.hypot(tab.vel[:, 0], tab.vel[:, 1])
    cmd_speed = np.where(tab.cmd_set, np.hypot(tab.cmd[:, 0], tab.cmd[:, 1]), 0.0)
    # on the start ramp of reference tracking it flies less than its command: not yet judged
    ramping = (now - tab.ref_since_s) < TRACKING_RAMP_S  # (NaN: no reference, False)
    commanded = watched & (cmd_speed > 0.0) & ~ramping
    tab.still_since_s[~commanded] = np.nan
    start = commanded & np.isnan(tab.still_since_s)
    tab.still_since_s[start] = now
    tab.still_xy[start] = tab.xy[start]
    timing = commanded & ~start
    still = now - tab.still_since_s
    moved = np.hypot(tab.xy[:, 0] - tab.still_xy[:, 0], tab.xy[:, 1] - tab.still_xy[:, 1])
    # it moves (as fast as half of v_min, at least): count afresh from here
    again = timing & (moved >= slow * still + STILL_POS_TOL_M)
    tab.still_since_s[again] = now
    tab.still_xy[again] = tab.xy[again]
    hit = timing & ~again & (still >= wait_s)
    what = "v_min / 2" if slow > STILL_M_S else "still"

    def why(r: int) -> str:
        return (f"not following its setpoints: moved {float(moved[r]):.2f} m in "
                f"{float(still[r]):.1f} s (< {slow:g} m/s ({what}) × the time), while "
                f"commanded {float(cmd_speed[r]):.2f} m/s (reported speed "
                f"{float(speed[r]):.2f} m/s)")

    return hit, why


#: The phases a low battery lands from (landing already, nothing to change).
_LANDS_MASK = phase_mask({Phase.ARMING, Phase.TAKEOFF, Phase.EXITED, Phase.HOLDING}
                         | TUBE_PHASES)


def _battery_low(ctx: FaultContext) -> tuple[np.ndarray, Callable[[int], str]]:
    """Reports less charge than ``battery_reserve_pct`` (0: off): it lands where it is, and
    while it comes down it is a stopped vehicle, an obstacle in the tube for everyone
    (:data:`~vtube_fleet.state.STOPPED_PHASES`). The check before arming
    (:meth:`~vtube_fleet.fleet.preflight.Preflight.check_batteries`) makes this rare: the
    mission's drain or duration was underestimated, or the pack is failing."""
    reserve = ctx.mission.config.battery_reserve_pct
    pct = ctx.links.battery_pct
    if reserve <= 0.0:
        return np.zeros(ctx.tab.n, bool), str
    hit = _LANDS_MASK[ctx.tab.phase] & (pct < reserve)  # NaN (not reported) is never below

    def why(r: int) -> str:
        return (f"battery {float(pct[r]):.0f} % < battery_reserve_pct = {reserve:g} %: lands "
                f"where it is, an obstacle for the others until it is on the ground")

    return hit, why


#: The in-flight fault rules, in order of precedence (a vehicle takes the first it hits). A
#: rule added here acts for every vehicle of every process (supervisor and agents alike).
def _untrusted_telemetry(ctx: FaultContext) -> tuple[np.ndarray, Callable[[int], str]]:
    """The link refused this vehicle's telemetry for longer than its window (forged, from two
    sources, physically impossible: ``VehicleState.telemetry_fault``, docs/security.md): its
    positions cannot be trusted, so it holds where it is and is an obstacle for everyone."""
    states = ctx.links.states
    faulted = np.fromiter((s.telemetry_fault is not None for s in states), bool, len(states))
    flying = _OFFBOARD_MASK[ctx.tab.phase]  # on our setpoints (arming … past the line)
    return faulted & flying, lambda r: f"telemetry not trustworthy: {states[r].telemetry_fault}"


FAULT_RULES: tuple[FaultRule, ...] = (
    FaultRule("no_telemetry", _no_telemetry),
    FaultRule("untrusted_telemetry", _untrusted_telemetry, action="hold"),
    FaultRule("left_offboard", _left_offboard),
    FaultRule("disarmed_in_air", _disarmed_in_air),
    FaultRule("unresponsive", _unresponsive),
    FaultRule("battery_low", _battery_low, action="land"),
)


def find_faults(tab: FleetTable, links: LinkColumns, mission: Mission, now_s: float,
                listening_since_s: float | None = None,
                rules: Sequence[FaultRule] = FAULT_RULES) -> tuple[list[Fault], np.ndarray]:
    """Evaluate ``rules`` for every vehicle under watch (airborne or arming) at monotonic time
    ``now_s``. Returns the faults (one per vehicle: the first rule it hits) and the rows that
    touched down while holding or landing (on the ground and disarmed). Notes OFFBOARD as
    confirmed (``offboard_seen``) for the vehicles that fly offboard and report it."""
    ph = tab.phase
    down = ((ph == _LANDING) | (ph == _HOLDING)) & links.on_ground & links.disarmed
    checked = _CHECKED_MASK[ph] & ~down
    tab.offboard_seen |= checked & _OFFBOARD_MASK[ph] & links.offboard
    ctx = FaultContext(tab, links, mission, now_s, listening_since_s, checked)
    free = checked.copy()
    faults: list[Fault] = []
    for rule in rules:
        if not free.any():
            break
        hit, why = rule.find(ctx)
        hit = hit & free
        for r in np.flatnonzero(hit).tolist():
            faults.append(Fault(r, rule, why(r)))
        free &= ~hit
    return faults, np.flatnonzero(down)


# ----------------------------------------------------------------------------------------------
# 4. states
# ----------------------------------------------------------------------------------------------
def stop_anchor_m(mission: Mission) -> float:
    """How far a stopped vehicle (holding, landing) may move from the position it tells the
    others before that position follows it: half of ``lost_obstacle_margin_m`` (at least
    :data:`MIN_ANCHOR_M`), so it stays inside the obstacle it is for them."""
    return max(0.5 * mission.config.lost_obstacle_margin_m, MIN_ANCHOR_M)


#: The smallest step of a stopped vehicle's told position (m): :func:`stop_anchor_m`.
MIN_ANCHOR_M = 0.1


def own_states(tab: FleetTable, links: LinkColumns, now_mono: float, now_wall: float,
               anchor_m: float = MIN_ANCHOR_M) -> tuple[States, np.ndarray, np.ndarray]:
    """What each vehicle with a position sample tells the others now: a LOST vehicle at its
    frozen position with zero velocity; a stopped one (holding, landing: an obstacle for the
    others, re-partitioned around) at its *anchor* with zero velocity: where it stopped, moved
    to where it is only once it is more than ``anchor_m`` away (PX4 brakes, then holds or
    lands with a slow drift: the estimate's wander would otherwise make every process
    re-partition the tube every tick, each at a slightly different moment); the stamp the
    wall-clock time its position was measured (its age: since it arrived plus the one-way link
    latency). With reference tracking an in-tube vehicle is told at its reference r, moving
    at its command (:func:`track_references`). Returns the states, their table rows and their
    ages (s)."""
    stopped = _STOPPED_MASK[tab.phase] & tab.has
    tab.stop_set &= stopped
    if stopped.any():
        d = np.hypot(tab.xy[:, 0] - tab.stop_xy[:, 0], tab.xy[:, 1] - tab.stop_xy[:, 1])
        move = stopped & (~tab.stop_set | (d > anchor_m))  # (NaN > x is False: not set yet)
        tab.stop_xy[move] = tab.xy[move]
        tab.stop_set |= move
    rows = np.flatnonzero(np.isfinite(tab.sample_s))
    lost = tab.lost_set[rows, None]
    anchored = tab.stop_set[rows, None]
    here, moving = tab.xy[rows], tab.vel[rows]
    refd = np.isfinite(tab.ref_xy[rows, :1])
    if refd.any():  # reference tracking: an in-tube vehicle is told at r, moving at its command
        here = np.where(refd, tab.ref_xy[rows], here)
        moving = np.where(refd, np.nan_to_num(tab.ref_vel[rows]), moving)
    pos = np.where(lost, tab.lost[rows], np.where(anchored, tab.stop_xy[rows], here))
    vel = np.where(lost | anchored, 0.0, moving)
    ages = (now_mono - tab.sample_s[rows]) + np.nan_to_num(links.latency_s[rows], nan=0.0)
    return States(tab.ids[rows], pos, vel, tab.phase[rows], now_wall - ages), rows, ages


# ----------------------------------------------------------------------------------------------
# 7. actuate
# ----------------------------------------------------------------------------------------------
def vertical_down_m_s(tab: FleetTable, mission: Mission, rows: np.ndarray,
                      climb: np.ndarray) -> np.ndarray:
    """The altitude hold of ``rows`` (NED down velocity): v_up = clamp(k_z (altitude − up),
    ±max_vertical_speed), capped at ``climb_speed_m_s`` upwards where ``climb``; 0 without a
    height."""
    cfg = mission.config
    up = tab.up[rows]
    u = cfg.altitude_gain_1_s * (cfg.altitude_m - up)
    lo = -cfg.max_vertical_speed_m_s
    hi = np.where(climb, cfg.climb_speed_m_s, cfg.max_vertical_speed_m_s)
    return np.where(np.isfinite(up), -np.where(u < lo, lo, np.where(u > hi, hi, u)), 0.0)


def _progress(route: Any, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far along ``route`` points (k, 2) are: (segment they start in, ξ in it)."""
    seg = route.start_segments(p)
    return seg, route.xi(p, seg)


def toward_m_s(target: np.ndarray, xy: np.ndarray, ok: np.ndarray, gain_1_s: float,
               max_m_s: float) -> np.ndarray:
    """The velocities (k, 2) that bring points ``xy`` to ``target`` (k, 2): gain × the
    offset, at most ``max_m_s``; zero where not ``ok`` or not finite."""
    d = gain_1_s * (target - xy)
    d = np.where((np.isfinite(d).all(axis=1) & ok)[:, None], d, 0.0)
    norm = np.hypot(d[:, 0], d[:, 1])
    return d * np.where(norm > max_m_s, max_m_s / np.where(norm > 0, norm, 1), 1.0)[:, None]


@dataclass
class Actuation:
    """What :func:`actuate` decided beyond the setpoints: the rows whose setpoint failed (with
    the link's error), the rows that start sending, the exited rows that hold or land now
    (with why) and the rows whose compensation residual just exceeded the budget."""

    failed: list[tuple[int, LinkError]]
    first_sent: np.ndarray
    hold: list[tuple[int, str]]
    land: list[tuple[int, str]]
    residual_over: np.ndarray


def actuate(tab: FleetTable, links: LinkColumns, link_list: Sequence[VehicleLink],
            mission: Mission, plan: FlightPlan, now_mono: float, cmd_rows: np.ndarray,
            cmds: np.ndarray, view: NeighbourView | None) -> Actuation:
    """Every vehicle's setpoint for its phase, sent in one batch:

    * a mode change in flight, or arming: zero horizontal velocity (altitude hold; none while
      arming) — streaming before OFFBOARD / until PX4 confirms;
    * the climb: a weak hold of the take-off spot (or, during the response check, the step's
      velocity ``probe_vel``), the climb-capped altitude hold, plus d̂ once airborne;
    * in the tube: the controller's command (rows ``cmd_rows`` get ``cmds``; the others zero)
      plus d̂, the altitude hold; with reference tracking the command on its start ramp plus
      the position loop K (r − p̂) (:func:`reference_velocities`,
      :func:`tracking_corrections`; the table keeps the controller's command); a vehicle
      standing still (``standstill``) or waiting zero
      plus d̂; one stepping aside towards its point (``step_xy``, :data:`STEP_GAIN_1_S`,
      at most :data:`STEP_MAX_M_S`) plus d̂, zero until it has one;
    * past the (route's last) finishing line:
      :func:`~vtube_fleet.fleet.flight_plan.exit_velocities` plus d̂, or zero and hold when
      blocked, or hold / land once ``exit_clear_m`` past it (``after_exit``); with
      ``"continue"``, hold a stopping distance before the fence's exit
      (:func:`~vtube_fleet.core.fence.exit_room_m`);
    * otherwise nothing (the command column cleared).

    Vehicles behind a closed link are skipped. The setpoints go to the links together
    (:func:`~vtube_fleet.link.base.send_velocities_ned`); the compensation residual of the
    in-tube commands is tracked (:class:`~vtube_fleet.fleet.compensation.ResidualTracker`)."""
    cfg = mission.config
    n = tab.n
    ph = tab.phase
    tab.cmd_in_tube[:] = False
    open_ = ~links.closed
    zero = open_ & (tab.in_transition | (ph == _ARMING))
    climb = open_ & ~zero & (ph == _TAKEOFF)
    tube = open_ & ~zero & (ph == _IN_TUBE)
    aside = open_ & ~zero & ((ph == _WAITING) | (ph == _STEPPING))
    exited = open_ & ~zero & (ph == _EXITED)
    idle = open_ & ~(zero | climb | tube | aside | exited)
    tab.cmd_set[idle] = False
    tab.cmd[idle] = np.nan
    vx = np.zeros(n)
    vy = np.zeros(n)
    comp = np.zeros(n, bool)  # add d̂
    send = zero | climb | tube | aside | exited
    hold: list[tuple[int, str]] = []
    land: list[tuple[int, str]] = []
    # the climb: hold the take-off spot
    if climb.any():
        r = np.flatnonzero(climb)
        d = toward_m_s(tab.takeoff_xy[r], tab.xy[r], tab.has[r], TAKEOFF_XY_GAIN_1_S,
                    TAKEOFF_XY_MAX_M_S)
        probe = tab.probe_vel[r]
        d = np.where(np.isfinite(probe).all(axis=1)[:, None], probe, d)
        vx[r], vy[r] = d[:, 0], d[:, 1]
        comp[r] = links.in_air[r] | (np.nan_to_num(tab.up[r], nan=-math.inf) > AIRBORNE_UP_M)
    # the tube: the controller's commands
    cmd_at = np.full(n, -1, np.int64)
    cmd_at[cmd_rows] = np.arange(cmd_rows.size)
    controlled = tube & ~tab.standstill
    if tube.any():
        r = np.flatnonzero(tube)
        k = cmd_at[r]
        got = (k >= 0) & controlled[r]
        c = np.zeros((r.size, 2))
        c[got] = cmds[k[got]]
        vx[r], vy[r] = c[:, 0], c[:, 1]
        comp[r] = True
        tab.cmd_in_tube[r] = controlled[r]
    # waiting (zero) or stepping aside (to its point, once it has one)
    if aside.any():
        r = np.flatnonzero(aside)
        go = (ph[r] == _STEPPING) & tab.step_set[r] & tab.has[r] & ~tab.standstill[r]
        via = tab.step_via[r]
        to = np.where(np.isfinite(via).all(axis=1)[:, None], via, tab.step_xy[r])
        d = toward_m_s(to, tab.xy[r], go, STEP_GAIN_1_S, STEP_MAX_M_S)
        vx[r], vy[r] = d[:, 0], d[:, 1]
        comp[r] = True
    # past the finishing line
    if exited.any():
        r = np.flatnonzero(exited)
        still = tab.standstill[r]
        past = np.where(tab.has[r], plan.route.beyond_finish_m(tab.xy[r]), 0.0)
        stop = exit_stop_m(plan, cfg)
        v, blocked = exit_velocities(plan, tab.xy[r], view, stop_distance_m=stop)
        blocked &= tab.has[r]
        clear = (cfg.after_exit in ("hold", "land")) & (past >= cfg.exit_clear_m)
        # "continue" (until every vehicle has exited) ends at the fence: a vehicle holds a
        # stopping distance before the fence's exit (one stuck in the tube must not send the
        # others into PX4's fence failsafe)
        room = exit_room_of(plan, cfg)
        far = (cfg.after_exit == "continue") & (past >= room - stop) & ~clear
        v[clear | far | blocked | still] = 0.0
        vx[r], vy[r] = v[:, 0], v[:, 1]
        # standing still: zero for the ESTIMATED position
        comp[r] = still | ~(clear | far | blocked)
        for j in np.flatnonzero(clear & ~still).tolist():
            why = f"{float(past[j]):.1f} m past the finishing line"
            (hold if cfg.after_exit == "hold" else land).append((int(r[j]), why))
        for j in np.flatnonzero(far & ~still).tolist():
            hold.append((int(r[j]), f"{float(past[j]):.1f} m past the finishing line, a "
                                    f"stopping distance before the fence's exit "
                                    f"({room:.1f} m past it)"))
        for j in np.flatnonzero(blocked & ~clear & ~still).tolist():
            hold.append((int(r[j]), "a stopped vehicle ahead past the finishing line"))
    rows = np.flatnonzero(send)
    tab.cmd[rows, 0], tab.cmd[rows, 1] = vx[rows], vy[rows]
    tab.cmd_set[rows] = True
    if not rows.size:
        return Actuation([], rows, hold, land, rows)
    # the estimate compensation d̂ (the command stays as the controller's in the table)
    bank = tab.compensator
    sx, sy = vx[rows], vy[rows]
    corr = None
    if bank is not None:
        c_rows = comp[rows]
        corr = bank.d_hat_m_s(rows)
        sx = np.where(c_rows, sx + corr[:, 0], sx)
        sy = np.where(c_rows, sy + corr[:, 1], sy)
    if cfg.tracking == "reference":  # the ramp and the position loop (not in tab.cmd)
        fly = controlled[rows] & tube[rows]
        if fly.any():
            at = rows[fly]
            c = np.stack((vx[at], vy[at]), axis=1)
            v = reference_velocities(tab, at, c, now_mono)
            v += tracking_corrections(tab, at, cfg.tracking_gain_1_s) - c
            sx, sy = sx.copy(), sy.copy()
            sx[fly] += v[:, 0]
            sy[fly] += v[:, 1]
    down = vertical_down_m_s(tab, mission, rows, climb[rows])
    down[ph[rows] == _ARMING] = 0.0
    a, b, c, d = tab.to_ned
    result = send_velocities_ned([link_list[i] for i in rows.tolist()], a * sx + b * sy,
                                 c * sx + d * sy, down)
    sent = np.fromiter((e is None for e in result), bool, len(result))
    tab.setpoints_sent[rows[sent]] += 1
    first = rows[sent & ~tab.ever_sent[rows]]
    tab.ever_sent[first] = True
    failed = [(int(rows[j]), result[j]) for j in np.flatnonzero(~sent).tolist()]
    over = rows[:0]
    tracked = sent & controlled[rows]
    if corr is not None and tracked.any():
        at = np.flatnonzero(tracked)
        lag = (0.5 * bank.window_s + cfg.period_s) + np.nan_to_num(  # type: ignore[union-attr]
            links.latency_s[rows[at]], nan=0.0)
        over = tab.residuals.track(rows[at], now_mono, corr[at], lag)
    return Actuation(failed, first, hold, land, over)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------------------
# the tick
# ----------------------------------------------------------------------------------------------
class NeighbourSource(Protocol):
    """Where a process hears the vehicles it does not fly (an MQTT agent's bus)."""

    def states(self, now_wall: float) -> States:
        """The latest state of every other vehicle."""

    def problem(self, now_wall: float) -> str | None:
        """Why those states cannot be trusted now (None: they can)."""

    # (optional) ``tube_stages(now_wall) -> (bool, ids)``: whether a vehicle this source does
    # not hear may fly among the others, and the ids of those waiting in the tube, fleet-wide
    # (an agent's bus: the statuses every agent hears; states only reach nearby cells)


@dataclass
class TickResult:
    """What one tick saw and did, for the caller's measurement: the links, the own ``states``
    with their table ``rows`` and ``ages_s``, the neighbour ``view`` (None while the
    neighbours cannot be trusted: ``untrusted`` says why), the mission time ``t_s`` and the
    age ``max_age_s`` above which a position is stale."""

    links: LinkColumns
    states: States
    rows: np.ndarray
    ages_s: np.ndarray
    view: NeighbourView | None
    untrusted: str | None
    t_s: float
    max_age_s: float


#: A re-plan around lost vehicles: the common plan, and the plans of their own of the vehicles
#: it traps that have one (table row → (plan, centres of the obstacles it left out))
Replanned = tuple[FlightPlan, dict[int, tuple[FlightPlan, np.ndarray]]]


class NoCommonPartition(PartitionError):
    """The route cannot be re-partitioned around the stopped vehicles, with what each vehicle
    in the tube can fly instead (``on_trapped = "wait"``, docs/fleet.md "No common
    partition"): ``own`` (table row → (plan, centres left out)), the plan of its own
    (:meth:`FlightPlan.past`) of each that has one — for one stepping aside, even if it is
    still inside a region of it."""

    def __init__(self, error: PartitionError,
                 own: dict[int, tuple[FlightPlan, np.ndarray]]) -> None:
        super().__init__(error.obstacle, error.reason)
        self.args = error.args
        self.own = own


def replan_job(root: FlightPlan, lost: tuple[Obstacle, ...], rows: np.ndarray,
               xy: np.ndarray, segment: np.ndarray, residual_m_s: float,
               stepping: np.ndarray | None = None, apart: bool = False) -> Replanned:
    """``root.with_lost(lost)`` and, for each vehicle in the tube (table ``rows`` at ``xy``
    flying ``segment``, as the tick saw them) it traps, :meth:`FlightPlan.past` (``residual_m_s``:
    the budget's D): what :meth:`Tick._plan_with_lost` plans, in the worker thread or at once.
    When there is no common plan and ``apart``: :class:`NoCommonPartition` with the plan of
    its own of every row that has one (those ``stepping`` aside: even if inside a region of
    it). Reads only."""
    try:
        common = root.with_lost(lost)
    except PartitionError as exc:
        if not apart:
            raise
        steps = np.zeros(rows.size, bool) if stepping is None else stepping
        mine = {int(rows[k]): root.past(lost, xy[k], int(segment[k]),
                                        residual_m_s=residual_m_s, outside=not steps[k])
                for k in range(rows.size)}
        raise NoCommonPartition(exc, {r: m for r, m in mine.items() if m is not None}
                                ) from exc
    own: dict[int, tuple[FlightPlan, np.ndarray]] = {}
    if stepping is not None:  # (one stepping aside flies the common plan when there is one)
        rows, xy, segment = rows[~stepping], xy[~stepping], segment[~stepping]
    if rows.size:
        for k in np.flatnonzero(common.cannot_pass(xy, segment)).tolist():
            mine = root.past(lost, xy[k], int(segment[k]), residual_m_s=residual_m_s)
            if mine is not None:
                own[int(rows[k])] = mine
    return common, own


class Tick:
    """The control tick of the vehicles of one table (module docstring): ``pilots[k]`` flies
    table row k.

    ``plan``: the flight plan (the root of the re-plans around lost vehicles; :meth:`set_plan`
    replaces it); ``neighbours``: the other vehicles' states (None: the table is the whole
    fleet); ``publish``: where each vehicle's own state goes every tick (an agent's bus);
    ``on_exit(rows, t_s)``, ``on_replan(plan, t_s)``, ``on_replan_failed(error, view)``: the
    owner's part (the supervisor records exits and new partitions, and decides what a failed
    re-plan means); ``rules``: the fault rules; ``t0_s``: the monotonic time mission time counts
    from (default: the first tick)."""

    def __init__(
        self,
        table: FleetTable,
        pilots: Sequence[VehiclePilot],
        mission: Mission,
        plan: FlightPlan,
        *,
        frame: TubeFrame | None = None,
        neighbours: NeighbourSource | None = None,
        publish: Callable[[Any], None] | None = None,
        on_exit: Callable[[np.ndarray, float], None] | None = None,
        on_replan: Callable[[FlightPlan, float], None] | None = None,
        on_replan_failed: Callable[[PartitionError, NeighbourView], None] | None = None,
        rules: Sequence[FaultRule] = FAULT_RULES,
        t0_s: float | None = None,
        replan_worker: Executor | None = None,
    ) -> None:
        if len(pilots) != table.n:
            raise ValueError(f"{len(pilots)} pilots for a table of {table.n} rows")
        self.table = table
        self.pilots = list(pilots)
        self.links = [p.link for p in self.pilots]
        self.mission = mission
        self.cfg = mission.config
        self.frame = mission.frame if frame is None else frame
        self.root = self.plan = plan
        self.neighbours = neighbours
        self.publish = publish
        self.on_exit = on_exit
        self.on_replan = on_replan
        self.on_replan_failed = on_replan_failed
        self.rules = tuple(rules)
        self.t0_s = t0_s
        #: where re-partitions around lost vehicles are planned off the control loop (None:
        #: in the tick itself): :meth:`_plan_with_lost`
        self.replan_worker = replan_worker
        self._replan_pending: tuple[tuple[Any, ...], Future[Replanned]] | None = None
        #: table rows flying a plan of their own (:meth:`FlightPlan.past`): trapped in the
        #: common re-partition, clear in one without the obstacles they have passed
        self.own_plans: dict[int, FlightPlan] = {}
        self._replan_failed: tuple[tuple[Any, ...], PartitionError] | None = None
        #: the failed re-partition the vehicles here fly apart after (None: a common plan)
        self.apart: NoCommonPartition | None = None
        #: the radius of the obstacle a lost vehicle becomes: physical r_s + margin
        self.lost_radius_m = (mission.scenario.controller.r_s
                              + self.cfg.lost_obstacle_margin_m)
        #: a vehicle's physical radius r_s: what of a stopped one its obstacle must hold
        self.body_m = float(mission.scenario.controller.r_s)
        #: how far a stopped vehicle moves before the others see it move (:func:`own_states`)
        self.anchor_m = stop_anchor_m(mission)
        #: what the own vehicles published last (one message per row with a position)
        self.last_states: dict[int, Any] = {}

    def set_plan(self, plan: FlightPlan) -> None:
        """Fly ``plan`` from now on (the root of later re-plans; before the flight: the
        segments are assigned again from the positions, by its hand-over depths)."""
        self.root = self.plan = plan
        self.own_plans = {}
        self.table.segment[:] = -1

    def t_s(self, now_mono: float) -> float:
        """Mission time: seconds since :attr:`t0_s`."""
        if self.t0_s is None:
            self.t0_s = now_mono
        return now_mono - self.t0_s

    def __call__(self, now_mono: float, now_wall: float,
                 listening_since: float | None = None) -> TickResult:
        """One tick at monotonic ``now_mono`` / wall-clock ``now_wall`` (the module docstring's
        order). ``listening_since``: when our own loop resumed after its last stall."""
        tab, pilots, mission = self.table, self.pilots, self.mission
        t = self.t_s(now_mono)
        # 1. links, 2. sense
        links = read_links(self.links)
        new, up = sense(tab, links, self.frame, mission)
        hand_over(tab, self.plan)
        if self.cfg.tracking == "reference":
            track_references(tab, links, now_mono)
        for r in up.tolist():
            if not pilots[r].at_altitude.is_set():
                pilots[r].at_altitude.set()
        for r in new[tab.has[new]].tolist():  # ``has`` changes only with a new sample
            if not pilots[r].sensed.is_set():
                pilots[r].sensed.set()
        # 3. faults
        faults, down = find_faults(tab, links, mission, now_mono, listening_since, self.rules)
        for r in down.tolist():
            pilots[r].touched_down()
        for f in faults:
            pilots[f.row].fault(f.rule.action, f.reason)
        # 4. states
        states, rows, ages = own_states(tab, links, now_mono, now_wall, self.anchor_m)
        if self.publish is not None and len(states):
            tab.seq[rows] += 1
            for msg in states.messages(tab.seq[rows]):
                self.last_states[msg.vehicle_id] = msg
                self.publish(msg)
        # 5. classify (the neighbours heard, when they can be trusted)
        ph = tab.phase
        untrusted = None
        view: NeighbourView | None = None
        tab.standstill[:] = False
        if self.neighbours is not None and bool((_IN_TUBE_MASK[ph] | (ph == _EXITED)).any()):
            untrusted = self.neighbours.problem(now_wall)
        if untrusted is not None:
            tab.standstill[_IN_TUBE_MASK[ph] | (ph == _EXITED)] = True
        else:
            everyone = states
            lost_after: float | np.ndarray = math.inf  # own vehicles: lost by the fault rules
            heard = None
            if self.neighbours is not None:
                others = self.neighbours.states(now_wall)
                everyone = states.concat(others)
                lost_after = np.concatenate([np.full(len(states), math.inf),
                                             np.full(len(others), self.cfg.lost_after_s)])
                heard = (None if listening_since is None
                         else now_wall - (now_mono - listening_since))
            view = classify(everyone, now_wall, max_age_s=self.cfg.neighbour_max_age_s,
                            lost_after_s=lost_after, heard_since_s=heard)
            # 6. plan: re-partition around lost and stopped vehicles; waiting ones released
            current = self._replan(view, t)
            self._waiting(everyone, view, current, now_wall)
        cmd_rows, cmds = self._commands(view, t)
        # 7. actuate
        act = actuate(tab, links, self.links, mission, self.plan, now_mono, cmd_rows, cmds, view)
        for r in act.first_sent.tolist():
            pilots[r].sent_setpoint.set()
        for r, exc in act.failed:
            pilots[r].event(f"setpoint not sent: {exc}", "warning")
        for r, why in act.hold:
            pilots[r].begin_hold(why)
        for r, why in act.land:
            pilots[r].begin_land(why)
        for r in act.residual_over.tolist():
            self._warn_residual(r)
            if r in self.own_plans:  # it may no longer advance along n_c: lands
                why = ("flying a partition of its own, its estimate compensation's residual "
                       f"exceeds disturbance_residual_m_s = "
                       f"{self.cfg.disturbance_residual_m_s:g} m/s: it may move back "
                       "towards the obstacles it left out")
                del self.own_plans[r]
                pilots[r].reason = pilots[r].reason or why
                pilots[r].begin_land(why, "warning")
        return TickResult(links, states, rows, ages, view, untrusted, t,
                          self.cfg.neighbour_max_age_s)

    def _replan(self, view: NeighbourView, t: float) -> bool:
        """Re-partition if the set of lost-vehicle obstacles inside the route changed, while a
        vehicle here still flies (the climb or the tube, or steps aside). True when the plan
        flown is the one for this view's stopped vehicles, or still holds them when there is
        none around where they are now (:meth:`FlightPlan.holds`: each moved less than its
        obstacle's margin since it was built — a stopped multicopter still drifts)."""
        if not view.lost_ids.size and not self.plan.lost:
            return True
        if not _FLYING_TUBE_MASK[self.table.phase].any():
            return False  # nobody here left to fly the tube
        root = self.root
        lost = lost_obstacles(view, root.corridor, self.lost_radius_m, root.flown)
        try:
            got = self._plan_with_lost(root, lost)
        except PartitionError as exc:
            if self.apart is None and self.plan.holds(lost, self.body_m):
                return True  # (they moved less than their obstacles' margin: it still holds)
            return self._replan_failed_now(exc, view)
        if got is None:
            return False  # being planned in the worker: the current plan flies on meanwhile
        new, own = got
        if new is not self.plan or self.apart is not None:
            self.plan = new
            self.apart = None
            self.own_plans = {}
            self.table.step_set[self.table.phase == _STEPPING] = False  # (a new point)
            if self.on_replan is not None:
                self.on_replan(new, t)
            self._land_the_trapped(new, own)
        return True

    def _replan_failed_now(self, exc: PartitionError, view: NeighbourView) -> bool:
        """No plan around the stopped vehicles that the plan flown does not hold: with
        ``on_trapped = "wait"`` each flies apart (:meth:`_fly_apart`; True: that is current),
        else the owner decides (False)."""
        if isinstance(exc, NoCommonPartition):
            if self.cfg.on_trapped == "wait":
                self._fly_apart(exc)
                return True
        if self.on_replan_failed is not None:
            self.on_replan_failed(exc, view)
        return False

    def _plan_with_lost(self, root: FlightPlan, lost: tuple[Obstacle, ...]
                        ) -> Replanned | None:
        """``root.with_lost(lost)`` and the plans of their own of the vehicles it traps
        (:func:`replan_job`): at once without :attr:`replan_worker` (or when the plan is
        already flown); else planned in the worker thread (0.05-0.9 s that would stall the
        control loop: the vehicles would fly on stale setpoints and the budget watch would end
        the run) and None until it is done. Meanwhile the current plan flies on and the lost
        vehicles stay points of the pair barrier (:class:`NeighbourView`), which keeps
        everyone 2 r_s' from them, farther than their obstacle's O'. A failure is kept for its
        obstacles (raised again, not planned again)."""
        hit = root.planned_with_lost(lost)
        if hit is not None and hit is self.plan:
            return hit, {}  # flown already (with its plans of their own)
        tab = self.table
        # (the plans of their own: only for vehicles in the tube; a climbing one's command
        # is its take-off spot's, which may point back along n_c)
        rows = np.flatnonzero(((tab.phase == _IN_TUBE) | (tab.phase == _STEPPING)) & tab.has)
        stepping = tab.phase[rows] == _STEPPING
        residual = float(self.cfg.disturbance_residual_m_s)
        apart = self.cfg.on_trapped == "wait"
        key = root.lost_key(lost)
        if self._replan_failed is not None and self._replan_failed[0] == key:
            raise self._replan_failed[1]
        if self.replan_worker is None:
            try:
                return replan_job(root, lost, rows, tab.xy[rows], tab.segment[rows],
                                  residual, stepping, apart)
            except PartitionError as exc:
                self._replan_failed = (key, exc)
                raise
        pending = self._replan_pending
        if pending is not None and pending[0] == key:
            if not pending[1].done():
                return None
            self._replan_pending = None
            try:
                return pending[1].result()
            except PartitionError as exc:
                self._replan_failed = (key, exc)
                raise
        if pending is not None:
            pending[1].cancel()  # replaced (if it has not started)
        # planned even when the common plan is cached (a set of lost vehicles seen before):
        # the plans of their own depend on where the vehicles are now
        self._replan_pending = (key, self.replan_worker.submit(
            replan_job, root, lost, rows, tab.xy[rows].copy(), tab.segment[rows].copy(),
            residual, stepping, apart))
        return None

    def _land_the_trapped(self, plan: FlightPlan, own: dict[int, tuple[FlightPlan, np.ndarray]]
                          ) -> None:
        """A vehicle of this table still flying the climb or the tube whose position lies
        inside the region the new partition takes around its obstacles has no safe sub-tube
        (:meth:`FlightPlan.cannot_pass`). If the plan of its own planned with it (``own``:
        :meth:`FlightPlan.past`, without the obstacles it has passed) still has it outside
        every region, it flies that one (:attr:`own_plans`); else it lands where it is
        (stopped, it is an obstacle for everyone at the next tick). The others fly on.
        Vehicles already past the lost one are not in that region and finish."""
        tab = self.table
        rows = np.flatnonzero(_TRAPPABLE_MASK[tab.phase] & tab.has)
        if not rows.size:
            return
        trapped = rows[plan.cannot_pass(tab.xy[rows], tab.segment[rows])]
        for r in trapped.tolist():
            x, y = tab.xy[r]
            pilot = self.pilots[r]
            if tab.phase[r] == _IN_TUBE and self._fly_own(
                    r, own.get(r), lambda: "inside the region the new partition takes around "
                                           "the stopped vehicle(s)"):
                continue
            why = (f"cannot pass the stopped vehicle(s): at ({x:.2f}, {y:.2f}), inside the "
                   f"region the new partition takes around them (no safe sub-tube)")
            if tab.phase[r] == _IN_TUBE and self.cfg.on_trapped == "wait":
                pilot.begin_wait(why + "; waits there until nobody flies the tube behind it "
                                       "or within reach, then steps aside into a sub-tube")
                continue
            pilot.reason = pilot.reason or why
            pilot.begin_land(why, "warning")

    def _fly_apart(self, exc: NoCommonPartition) -> None:
        """No common plan around the stopped vehicles (docs/fleet.md, "No common partition";
        ``on_trapped = "wait"``): each vehicle here in the tube flies the plan of its own
        ``exc.own`` holds if it is outside every region of it (it has passed the obstacles
        left out, which it never comes back to); else it waits, a stopped vehicle, released
        as any waiting one; one stepping aside steps into its own plan's sub-tube; a
        climbing one lands (no plan to enter the tube by). Once per failure: its plans
        replace those of an earlier one."""
        tab = self.table
        before = set(self.own_plans) if self.apart is not None else set()
        if self.apart is not exc:
            self.apart = exc
            self.own_plans = {}
            tab.step_set[tab.phase == _STEPPING] = False  # (a new point, in its own plan)
            for r, (mine, _) in exc.own.items():
                if tab.phase[r] == _STEPPING:
                    self.own_plans[r] = mine
        def why() -> str:  # (built only for an event: the loop runs this every tick)
            return (f"the {'route' if self.root.route.S > 1 else 'tube'} cannot be "
                    f"re-partitioned around the stopped vehicle(s) ({exc})")

        for r in np.flatnonzero(_TRAPPABLE_MASK[tab.phase] & tab.has).tolist():
            if r in self.own_plans:
                continue
            pilot = self.pilots[r]
            if tab.phase[r] != _IN_TUBE:
                pilot.reason = pilot.reason or why()
                pilot.begin_land(why() + "; cannot enter it", "warning")
                continue
            # (flew one after the failure before: said already)
            if self._fly_own(r, exc.own.get(r), None if r in before else why):
                continue
            x, y = tab.xy[r]
            pilot.begin_wait(f"{why()}: at ({x:.2f}, {y:.2f}), with no partition of its own; "
                             "waits there until nobody flies the tube behind it or within "
                             "reach, then steps aside into a sub-tube")

    def _fly_own(self, r: int, mine: tuple[FlightPlan, np.ndarray] | None,
                 why: Callable[[], str] | None) -> bool:
        """Row ``r`` (in the tube, trapped) flies ``mine`` (:meth:`FlightPlan.past`: its plan
        of its own, the centres left out) if it is outside every region of it (True): it has
        passed the obstacles left out, which it never comes back to (it always advances
        along the tube). The event says so, after ``why()`` (None: said already)."""
        tab = self.table
        if mine is None or mine[0].cannot_pass(tab.xy[r:r + 1], tab.segment[r:r + 1])[0]:
            return False
        self.own_plans[r] = mine[0]
        if why is not None:
            x, y = tab.xy[r]
            passed = ", ".join(point_text(c) for c in mine[1])
            self.pilots[r].event(f"flies on with a partition of its own: {why()}, but at "
                                 f"({x:.2f}, {y:.2f}) it is past the obstacle(s) at {passed}, "
                                 f"which it never comes back to (it always advances along "
                                 f"the tube), so they are left out of its partition",
                                 "warning")
        return True

    def _waiting(self, everyone: States, view: NeighbourView, current: bool,
                 now_wall: float) -> None:
        """Waiting for a way (docs/fleet.md): a vehicle here stepping aside gets its path
        once the plan without it is flown (``current``) (:meth:`FlightPlan.step_aside`;
        none: it waits again, once, if others wait too, else it lands), and flies the
        controller again once there, outside every region; a waiting one is released
        (→ STEPPING) when no vehicle flies among the others — arming, climbing or stepping
        aside, or in the tube unless farther ahead than r_s' + r_a' along the route (it only
        moves away: :func:`~vtube_fleet.core.loss.moves_forward`): of those heard
        (``everyone``, the silent ones of ``view`` aside) and, from an agent's bus, of the
        whole fleet (``tube_stages``: any teammate in the tube) — and it is, of the
        waiting vehicles released fewest times before, the one farthest along the route
        (ties: the smallest id; it leaves the way free for those behind it); an agent that
        does not hear every such vehicle (states reach nearby cells only) takes the
        smallest id instead. Every process decides alike, so one moves at a time."""
        tab = self.table
        ph = tab.phase
        stepping = np.flatnonzero((ph == _STEPPING) & tab.has)
        if not stepping.size and not (ph == _WAITING).any():
            return
        # the fleet's waiting vehicles (id → how many times released without a path)
        w = np.flatnonzero((everyone.phase == _WAITING) & np.isfinite(everyone.pos).all(axis=1))
        tries = dict.fromkeys(everyone.ids[w].tolist(), 0)
        where = dict(zip(everyone.ids[w].tolist(), everyone.pos[w], strict=True))
        own = np.flatnonzero((ph == _WAITING) & tab.has)
        tries.update(zip(tab.ids[own].tolist(), tab.step_tries[own].tolist(), strict=True))
        where.update(zip(tab.ids[own].tolist(), tab.xy[own], strict=True))
        heard = ~np.isin(everyone.ids, view.lost_ids)
        flying = heard & (everyone.phase == _IN_TUBE)  # (may be far enough ahead: below)
        busy = bool(_BUSY_MASK[everyone.phase[heard & ~flying]].any())
        unheard: set[int] = set()
        fleet = getattr(self.neighbours, "tube_stages", None)
        if fleet is not None:
            far_busy, also = fleet(now_wall)
            busy = busy or far_busy
            for i, k in also.items():
                tries[i] = max(tries.get(i, 0), k)
            unheard = set(also) - set(where)
        if stepping.size and current:
            for r in stepping[~tab.step_set[stepping]].tolist():
                self._step_point(r, others_wait=bool(set(tries) - {int(tab.ids[r])}))
            passed = stepping[np.hypot(*(tab.step_via[stepping] - tab.xy[stepping]).T)
                              <= STEP_ARRIVED_M]  # (NaN: none, or passed)
            tab.step_via[passed] = np.nan
            there = stepping[tab.step_set[stepping] & ~np.isfinite(tab.step_via[stepping, 0])
                             & (np.hypot(*(tab.step_xy[stepping] - tab.xy[stepping]).T)
                                <= STEP_ARRIVED_M)]
            for r in there.tolist():
                if self._plan_of(r).cannot_pass(tab.xy[r:r + 1], tab.segment[r:r + 1])[0]:
                    continue
                x, y = tab.xy[r]
                self.pilots[r].resume_tube(f"at ({x:.2f}, {y:.2f}), inside a sub-tube: "
                                           "flies the tube again")
        if busy or not tries or not (tab.phase == _WAITING).any():
            return
        route = self.plan.route
        level = min(tries.values())
        cands = {i for i, k in tries.items() if k == level}
        if cands & unheard:  # (an agent that does not hear every waiting vehicle)
            first, how = min(cands), "it has the smallest id"
        else:
            ids = np.array(sorted(cands), np.int64)
            pos = np.array([where[i] for i in ids.tolist()]).reshape(-1, 2)
            seg, xi = _progress(route, pos)
            first = int(ids[np.lexsort((ids, -xi, -seg))[0]])
            how = "it is the farthest along the tube"
        for r in np.flatnonzero((tab.ids == first) & (tab.phase == _WAITING)).tolist():
            if flying.any():  # every vehicle flying the tube must be ahead, out of reach
                f = np.flatnonzero(flying)
                seg_f, xi_f = _progress(route, everyone.pos[f])
                seg_w, xi_w = _progress(route, tab.xy[r:r + 1])
                if not np.all((seg_f > seg_w) | ((seg_f == seg_w) & (
                        xi_f - xi_w > self.plan.neighbour_radius_m))):
                    return
            self.pilots[r].begin_step(f"released: nobody else flies the tube behind it or "
                                      f"within reach and {how} of those waiting"
                                      + (" (again)" if level else ""))

    def _plan_of(self, r: int) -> FlightPlan:
        """The plan row ``r`` flies: its own (:attr:`own_plans`) or the common one."""
        return self.own_plans.get(r, self.plan)

    def _step_point(self, r: int, others_wait: bool) -> None:
        """The path row ``r`` steps aside on under the current plan; without one it waits
        again (once, while ``others_wait``: they may leave the way free) or lands."""
        tab = self.table
        x, y = tab.xy[r]
        mine = self.own_plans.get(r)
        # (with a plan of its own: straight across only; backing away could bring what it
        # left out ahead of it again; with no plan at all: no path)
        path = (None if mine is None and self.apart is not None
                else (mine or self.plan).step_aside(tab.xy[r], int(tab.segment[r]),
                                                    back=mine is None))
        pilot = self.pilots[r]
        if path is None:
            why = (f"cannot step aside from ({x:.2f}, {y:.2f}) into a sub-tube: no path back "
                   f"along the tube and then across it (or straight there) keeps out of every "
                   f"obstacle's O' and r_s' inside the legs")
            if others_wait and tab.step_tries[r] == 0:
                tab.step_tries[r] = 1
                pilot.begin_wait(why + " now; waits again until the others waiting have gone")
                return
            pilot.reason = pilot.reason or why
            pilot.begin_land(why, "warning")
            return
        via, q = path
        back = float(np.hypot(via[0] - x, via[1] - y))
        tab.step_via[r] = via if back > STEP_ARRIVED_M else np.nan
        tab.step_xy[r] = q
        tab.step_set[r] = True
        pilot.event(f"steps aside from ({x:.2f}, {y:.2f})"
                    + (f" {back:.2f} m back along the tube to ({via[0]:.2f}, {via[1]:.2f}), "
                       f"then" if back > STEP_ARRIVED_M else "")
                    + f" {float(np.hypot(*(q - via))):.2f} m "
                    + ("across it" if back > STEP_ARRIVED_M else "in a straight line")
                    + f" to ({q[0]:.2f}, {q[1]:.2f}), inside a sub-tube of the partition "
                      "without it")

    def _commands(self, view: NeighbourView | None, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Exits (TraCondition on the route's last finishing line, for the vehicles flying the
        last segment), then the controller's commands of every vehicle still in the tube that
        the view holds, each in its segment: (rows, commands (k, 2))."""
        tab = self.table
        none = np.zeros(0, np.int64), np.zeros((0, 2))
        flying = np.flatnonzero((tab.phase == _IN_TUBE) & tab.has & ~tab.standstill)
        if not flying.size or view is None:
            return none
        done = np.asarray(self.plan.exited(tab.xy[flying], tab.segment[flying]),
                          bool).reshape(-1)
        if done.any():
            out = flying[done]
            for r in out.tolist():
                self.pilots[r].mark_exit(t)
            if self.on_exit is not None:
                self.on_exit(out, t)
        left = flying[~done]
        ids = view.ids()
        if not left.size or not ids.size:
            return none
        # each vehicle's index among the view's points (-1: not in it)
        order = np.argsort(ids, kind="stable")
        at = np.searchsorted(ids[order], tab.ids[left])
        at = np.minimum(at, ids.size - 1)
        seen = ids[order][at] == tab.ids[left]
        rows = left[seen]
        if not rows.size:
            return none
        idx, seg, points = order[at[seen]], tab.segment[rows], view.points()
        if not self.own_plans:  # (every tick: no per-row work unless someone flies its own)
            return rows, self.plan.commands(points, idx, seg)
        mine = np.isin(rows, np.fromiter(self.own_plans, np.int64, len(self.own_plans)))
        if not mine.any():
            return rows, self.plan.commands(points, idx, seg)
        out = np.empty((rows.size, 2))
        out[~mine] = self.plan.commands(points, idx[~mine], seg[~mine])
        for k in np.flatnonzero(mine).tolist():  # each with its own partition
            out[k] = self.own_plans[int(rows[k])].commands(points, idx[k:k + 1],
                                                           seg[k:k + 1])[0]
        return rows, out

    def _warn_residual(self, r: int) -> None:
        """WARN: a limit crossed — the safety budget's D no longer covers the estimate."""
        mean = float(self.table.residuals.mean_m_s[r])
        budget = self.cfg.disturbance_residual_m_s
        self.pilots[r].event(f"estimate compensation residual {mean:.2f} m/s (mean over "
                             f"{RESIDUAL_WINDOW_S:g} s) > the budgeted D = {budget:.2f} m/s: the "
                             f"flown radii may not cover the estimate error (mission key "
                             f"disturbance_residual_m_s)", "warning")


# ----------------------------------------------------------------------------------------------
# 8. the budget watch (supervisor and agents alike)
# ----------------------------------------------------------------------------------------------
_AIRBORNE_MASK = phase_mask(AIRBORNE_PHASES)


def used_ages(tab: FleetTable, result: TickResult) -> tuple[np.ndarray, np.ndarray]:
    """The table rows and ages (s) of the positions the tick used as live: airborne vehicles'
    samples younger than ``neighbour_max_age_s`` (older: a stale vehicle, handled as a
    fault, not as the link's latency)."""
    keep = (_AIRBORNE_MASK[tab.phase[result.rows]]
            & (result.ages_s <= result.max_age_s))
    return result.rows[keep], result.ages_s[keep]


def watch_budget(watch: BudgetWatch, tab: FleetTable, result: TickResult, tick_gap_s: float,
                 accuracy_m: Callable[[np.ndarray], Sequence[float]], *,
                 forgotten: set[int],
                 used: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> tuple[str | None, str | None]:
    """Feed the budget watch one tick (:class:`~vtube_fleet.fleet.budget.BudgetWatch`): the
    gap since the previous tick, the ages of the positions used (:func:`used_ages`), lost
    vehicles' ages dropped
    (``forgotten``: the rows already dropped); once a second judge L (worst uplink latency) and
    σ (``accuracy_m(rows in the tube)``); with reference tracking, every tick, each in-tube
    vehicle's |p̂ − r| against e (:meth:`~vtube_fleet.fleet.budget.BudgetWatch.check_tracking`);
    with velocity tracking, every tick, the velocities sent and the estimated paths of the
    in-tube vehicles flying the controller's command with a live sample (compared where it is
    no older than T + L), against the budget's response model
    (:meth:`~vtube_fleet.fleet.budget.BudgetWatch.check_response`).
    Does nothing while no vehicle is in the tube.
    ``used``: :func:`used_ages` of this tick if the caller has it already.
    Returns ``(warning, hold)``."""
    ph = tab.phase
    if not (ph == _IN_TUBE).any():
        return None, None
    rows, ages = used_ages(tab, result) if used is None else used
    if watch.budget.reference:  # every tick: |p̂ − r| against e
        tube = np.flatnonzero(ph == _IN_TUBE)
        hold = watch.check_tracking(tab.track_err_m[tube], tab.ids[tube], result.t_s)
    else:  # every tick: the estimated paths against the response model's
        b = watch.budget
        live = np.zeros(tab.n, bool)  # a sample the tick used as live …
        live[rows] = True
        fresh = np.zeros(tab.n, bool)  # … and no older than the budget's T + L
        fresh[rows[ages <= b.period_s + b.latency_s]] = True
        sent = np.where(tab.cmd_set[:, None], tab.cmd, np.nan)
        hold = watch.check_response(result.t_s, sent, tab.xy,
                                    (ph == _IN_TUBE) & tab.cmd_in_tube & live, tab.ids, fresh)
    if hold is not None:
        return None, hold
    watch.add_tick_gap(tick_gap_s)
    watch.add_ages(result.t_s, ages, rows, tab.sample_s[rows])
    lost = set(np.flatnonzero(ph == _LOST).tolist()) - forgotten
    if lost:
        watch.forget(sorted(lost))
        forgotten |= lost
    if not watch.due(result.t_s):
        return None, None
    lat = result.links.latency_s
    up = float(np.nanmax(lat)) if np.isfinite(lat).any() else 0.0
    acc = accuracy_m(np.flatnonzero(ph == _IN_TUBE))
    return watch.check(result.t_s, max(up, 0.0), acc, tab.sample_s.copy())


# ----------------------------------------------------------------------------------------------
# the control clock
# ----------------------------------------------------------------------------------------------
#: The interpreter's thread switch interval while a control clock runs (``sys.
#: setswitchinterval``; CPython's default is 5 ms). A re-partition planned in the worker thread
#: runs Python and holds the interpreter lock, and the event loop needs it back after every
#: wake-up (a datagram, the tick's timer): with 5 ms each wake-up could wait up to 5 ms and the
#: loop fell behind (`bench/bench_gil.py`: 72 of 200 ticks, late p99 190 ms; with 0.1 ms 200 of
#: 200, p99 6.7 ms, and the thread re-partitions as fast).
GIL_SWITCH_S = 0.0001
#: the switch interval before the first running clock of this process, then one entry per
#: running clock (several agents' clocks may share a process, e.g. in tests)
_RUNNING_CLOCKS: list[float | None] = []


class ControlClock:
    """Calls ``step(now_mono, now_wall, listening_since)`` every ``period_s`` until stopped
    (supervisor and agents alike). A tick more than a period late is not caught up. While it
    runs, the interpreter switches threads every :data:`GIL_SWITCH_S` at most (the re-partition
    worker does not hold the loop back).

    A gap of more than 2 T + 0.1 s between two ticks is a stall of our own loop:
    :attr:`listening_since` becomes the time it resumed (the links' backlog is not the vehicles'
    silence) and ``on_stall(gap_s)`` is told. The cyclic garbage collector waits while a tick
    runs (the setpoints go out first). ``guard(exc)``: a tick that raised (a bug must not leave
    vehicles without setpoints silently); ``after()``: called after each tick (it may return an
    awaitable, which the clock awaits: fault injection in tests); if it raises, ``guard`` is
    told and the ticks go on without it. Keeps every tick's start
    (loop time), lateness, duration and the gap to the previous one."""

    def __init__(self, period_s: float, step: Callable[[float, float, float | None], Any], *,
                 wall_clock: Callable[[], float] = time.time,
                 on_stall: Callable[[float], None] | None = None,
                 guard: Callable[[Exception], None] | None = None,
                 after: Callable[[], Awaitable[None] | None] | None = None) -> None:
        self.period_s = float(period_s)
        self.step = step
        self.wall_clock = wall_clock
        self.on_stall = on_stall
        self.guard = guard
        self.after = after
        self.listening_since: float | None = None
        self.ticks = 0
        self.starts_s: list[float] = []
        self.lateness_s: list[float] = []
        self.durations_s: list[float] = []
        self.gaps_s: list[float] = []
        self.recent_gap_s = 0.0  # the longest gap since :meth:`take_recent_gap`

    def take_recent_gap(self) -> float:
        """The longest gap between two ticks since the last call (the budget watch's)."""
        gap, self.recent_gap_s = self.recent_gap_s, 0.0
        return gap

    async def run(self, stop: asyncio.Event) -> None:
        if not _RUNNING_CLOCKS:
            _RUNNING_CLOCKS.append(sys.getswitchinterval())  # the interval to restore
            sys.setswitchinterval(min(_RUNNING_CLOCKS[0], GIL_SWITCH_S))
        _RUNNING_CLOCKS.append(None)
        try:
            await self._run(stop)
        finally:
            _RUNNING_CLOCKS.pop()
            if len(_RUNNING_CLOCKS) == 1:  # the last clock of this process ended
                sys.setswitchinterval(_RUNNING_CLOCKS.pop())

    async def _run(self, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        period = self.period_s
        next_t = loop.time()
        prev: float | None = None
        while not stop.is_set():
            start = loop.time()
            self.starts_s.append(start)
            self.lateness_s.append(start - next_t)
            if prev is not None:
                gap = start - prev
                self.gaps_s.append(gap)
                self.recent_gap_s = max(self.recent_gap_s, gap)
                if gap > 2.0 * period + 0.1:
                    self.listening_since = time.monotonic()
                    if self.on_stall is not None:
                        self.on_stall(gap)
            prev = start
            t0 = time.perf_counter()
            collecting = gc.isenabled()
            gc.disable()  # the cyclic collector waits until the setpoints are out
            try:
                self.step(time.monotonic(), self.wall_clock(), self.listening_since)
            except Exception as exc:
                if self.guard is None:
                    raise
                self.guard(exc)
            finally:
                if collecting:
                    gc.enable()
            self.durations_s.append(time.perf_counter() - t0)
            if self.after is not None:
                try:
                    pending = self.after()
                    if inspect.isawaitable(pending):
                        await pending
                except Exception as exc:
                    if self.guard is None:
                        raise
                    self.after = None  # the ticks go on without what failed after them
                    self.guard(exc)
            self.ticks += 1
            next_t += period
            now = loop.time()
            if next_t < now - period:  # more than a period behind: do not try to catch up
                next_t = now
            delay = next_t - now
            if delay > 0:
                try:
                    async with asyncio.timeout(delay):
                        await stop.wait()
                except TimeoutError:
                    pass
            else:
                await asyncio.sleep(0)
