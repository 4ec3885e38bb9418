"""The supervisor's in-flight measurement: every tick judged, recorded and shown.

:class:`FlightMeasurement` takes each :class:`~vtube_fleet.fleet.tick.TickResult` and

* evaluates the safety conditions of Theorem 1 (:class:`~vtube_fleet.core.metrics.SafetyMonitor`
  with the PHYSICAL limits; on a route each vehicle's leg distances to the segment it flies,
  the table's ``segment``) on the vehicles in the tube — from telemetry (the ``""`` stream:
  positions as reported, the controller's commanded velocities) and, with ``truth``, from the
  vehicles' ground truth (the ``"_truth"`` stream) — into the run's
  :class:`~vtube_fleet.core.metrics.SummaryAccumulator` (the simulator's own), noting the first
  violation of each stream;
* keeps the figures the summary adds: commanded and measured speeds, the pair distance among all
  airborne vehicles (also those that exited), link latencies and position ages;
* feeds the budget watch (:func:`~vtube_fleet.fleet.tick.watch_budget`): a budget exceeded in
  flight holds the fleet (the supervisor's ``request_abort``);
* records the tick (:class:`~vtube_fleet.recording.api.Recorder`) and updates the live view.

"In the tube" means flying the controller this tick, or stopped inside the route (lost at its
last position, holding or landing while still in the air; judged against the segment it last
flew).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtube_fleet.config.mission import Mission
from vtube_fleet.core.metrics import (
    SafetyMonitor,
    SummaryAccumulator,
    ViolationLog,
    percentile_or_none,
)
from vtube_fleet.core.neighbours import pairs_within
from vtube_fleet.core.route import Route
from vtube_fleet.fleet.budget import BudgetWatch, SafetyBudget, on_time_share
from vtube_fleet.fleet.table import PHASE_CODE, PHASE_VALUES, FleetTable, phase_mask
from vtube_fleet.fleet.tick import AIRBORNE_UP_M, TickResult, used_ages, watch_budget
from vtube_fleet.fleet.view import FleetStatus, vehicle_rows
from vtube_fleet.frames import TubeFrame
from vtube_fleet.link.base import VehicleLink
from vtube_fleet.state import COUNTED_AIRBORNE_PHASES, STOPPED_PHASES, Phase

__all__ = ["FlightMeasurement", "TickTrace"]

_IN_TUBE = PHASE_CODE[Phase.IN_TUBE]
_LOST = PHASE_CODE[Phase.LOST]
_COUNTED_AIRBORNE_MASK = phase_mask(COUNTED_AIRBORNE_PHASES)
#: in the tube without the controller's command (judged there while inside it): stopped,
#: lost, or stepping aside out of a region (docs/fleet.md, "Waiting for a way")
_OFF_CONTROLLER_MASK = phase_mask(STOPPED_PHASES | {Phase.LOST, Phase.STEPPING})


@dataclass
class TickTrace:
    """One tick as flown (kept when ``keep_trace``): telemetry in the tube frame."""

    t_s: float
    pos: np.ndarray  # (M, 2) telemetry positions (frozen for LOST), NaN = unknown
    vel: np.ndarray  # (M, 2) measured velocities
    cmd: np.ndarray  # (M, 2) horizontal commands sent this tick, NaN = none
    in_tube: np.ndarray  # (M,) bool: commanded by the tube controller this tick
    phases: tuple[str, ...]
    truth: np.ndarray | None = None  # (M, 2) ground truth (truth=True), NaN = unknown
    segment: np.ndarray | None = None  # (M,) the route segment each vehicle flies (0: a tube)


class FlightMeasurement:
    """The in-flight measurement of a fleet (module docstring). ``monitor``: the safety
    monitor with the physical limits (pairs searched within the flown radii: :meth:`rebuild`
    once the budget is measured); ``recorder`` receives every tick; ``truth``: judge the
    ground truth too; ``keep_trace``: keep every tick in :attr:`trace` (tests); ``warn``: the
    budget watch's warnings."""

    def __init__(self, mission: Mission, table: FleetTable, links: Sequence[VehicleLink],
                 monitor: SafetyMonitor, *, frame: TubeFrame, recorder: Any,
                 truth: bool = False, keep_trace: bool = False,
                 warn: Callable[[str], None] | None = None) -> None:
        self.mission = mission
        #: where the budget watch's warnings go (the supervisor's events)
        self.warn: Callable[[str], None] = warn or (lambda text: None)
        self.cfg = mission.config
        self.table = table
        self.links = list(links)
        self.frame = frame
        self.monitor = monitor
        self.recorder = recorder
        self.truth = truth
        self.keep_trace = keep_trace
        self.trace: list[TickTrace] = []
        self.acc = SummaryAccumulator(table.n)
        self.violations = ViolationLog(monitor)
        self.latencies: list[float] = []
        self.sample_ages: list[float] = []
        self.measured_speed = [math.inf, -math.inf]
        self.settled_speed = [math.inf, -math.inf]
        self.settle_s = self.cfg.tracking_dead_time_s + 3.0 * self.cfg.tracking_t63_s
        self.cmd_speed = [math.inf, -math.inf]
        #: reference tracking on the mock: the largest |p − r| of the TRUE positions (the
        #: budget covers e + k σ of it)
        self.truth_reference_max_m = math.nan
        self.min_pair_airborne = math.inf
        self.min_pair_airborne_truth = math.inf
        self.watch: BudgetWatch | None = None  # the in-flight budget check, once flying
        self._forgotten: set[int] = set()  # lost vehicles whose ages the watch dropped

    def rebuild(self, monitor: SafetyMonitor) -> None:
        """Judge with ``monitor`` from now on (the flown radii once the budget is measured)."""
        self.monitor = self.violations.monitor = monitor

    # -- every tick --------------------------------------------------------------------------
    def measure(self, result: TickResult, *, tick: int, tube_start_s: float | None,
                flown_r_s: float, budget: SafetyBudget, tick_gap_s: float,
                tick_duration_s: float | None,
                note: Callable[[str, str, dict[str, Any]], None],
                request_hold: Callable[[str], None]) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                              list[str]]:
        """Judge, record and keep the figures of one tick (module docstring). ``note(source,
        message, entry)`` is told the first violation of a stream; ``request_hold(reason)``
        the budget watch's hold. Returns the logged positions, velocities, commands and
        phases (for the caller's view)."""
        tab = self.table
        t = result.t_s
        has = tab.has.copy()
        pos = tab.positions()
        vel = tab.vel.copy()
        pos[~has] = np.nan
        vel[~has] = np.nan
        cmd = np.where(tab.cmd_set[:, None], tab.cmd, np.nan)
        codes = tab.phase
        seg = np.maximum(tab.segment, 0)  # (a row that never had a position is absent)
        inside = tab.cmd_in_tube.copy()
        tube_rows = inside.copy()
        started = tube_start_s is not None
        if started:
            links = result.links
            stopped = ~inside & has & _OFF_CONTROLLER_MASK[codes]
            up = np.nan_to_num(tab.up, nan=-math.inf)
            stopped &= (codes == _LOST) | links.in_air | (up > AIRBORNE_UP_M)
            if stopped.any():
                rows = np.flatnonzero(stopped)
                tube_rows[rows] = self.mission.scenario.corridor.inside(pos[rows])
        airborne = _COUNTED_AIRBORNE_MASK[codes]
        lat = result.links.latency_s
        lat = lat[np.isfinite(lat)]
        latency = float(np.median(lat)) if lat.size else math.nan
        if lat.size:
            self.latencies.append(latency)
        truth = self.truth_positions() if self.truth else None
        metrics: dict[str, float] = {}
        safety = None
        if started:
            # the "" stream: in the tube (telemetry position, commanded velocity)
            p_tube = np.where(tube_rows[:, None], pos, np.nan)
            commanded = inside & np.isfinite(cmd[:, 0])
            v_tube = np.where(commanded[:, None], cmd, np.nan)  # speeds: the controller's
            sm = self.monitor.evaluate(p_tube, v_tube, segment=seg)
            self.acc.add(t, sm)
            self._note(t, "", sm, p_tube, v_tube, note, seg)
            safety = {"": (p_tube, v_tube)}
            for key in ("min_pair_distance_m", "min_obstacle_center_distance_m",
                        "min_left_leg_distance_m", "min_right_leg_distance_m",
                        "min_speed_m_s", "max_speed_m_s"):
                val = float(getattr(sm, key)[0])
                if math.isfinite(val):
                    metrics[key] = val
            if truth is not None:
                # the "_truth" stream: the same vehicles at their TRUE positions (no speeds:
                # the speed bounds are the controller's, judged on the commands)
                t_tube = np.where(tube_rows[:, None], truth, np.nan)
                smt = self.monitor.evaluate(t_tube, segment=seg)
                self.acc.add(t, smt, suffix="_truth")
                self._note(t, "_truth", smt, t_tube, None, note, seg)
                safety["_truth"] = (t_tube, np.full_like(t_tube, np.nan))
                for key in ("min_pair_distance_m", "min_obstacle_center_distance_m",
                            "min_left_leg_distance_m", "min_right_leg_distance_m"):
                    val = float(getattr(smt, key)[0])
                    if math.isfinite(val):
                        metrics[f"truth_{key}"] = val
            if truth is not None:  # reference tracking: how far the TRUTH is from r
                refd = inside & np.isfinite(tab.ref_xy[:, 0]) & np.isfinite(truth[:, 0])
                if refd.any():
                    off = np.hypot(*(truth[refd] - tab.ref_xy[refd]).T)
                    self.truth_reference_max_m = float(np.fmax(self.truth_reference_max_m,
                                                               off.max()))
            cs = np.hypot(*cmd[tube_rows & np.isfinite(cmd[:, 0])].T)
            if cs.size:
                self.cmd_speed[0] = min(self.cmd_speed[0], float(cs.min()))
                self.cmd_speed[1] = max(self.cmd_speed[1], float(cs.max()))
            ok = inside & np.isfinite(vel[:, 0])
            ms = np.hypot(*vel[ok].T)
            if ms.size:
                self.measured_speed[0] = min(self.measured_speed[0], float(ms.min()))
                self.measured_speed[1] = max(self.measured_speed[1], float(ms.max()))
                # after the vehicles had time to follow the first command (τ_d + 3 t63)
                if t - tube_start_s > self.settle_s:  # type: ignore[operator]
                    self.settled_speed[0] = min(self.settled_speed[0], float(ms.min()))
                    self.settled_speed[1] = max(self.settled_speed[1], float(ms.max()))
            self._watch(result, budget, tick_gap_s, request_hold)
        # every airborne pair from the take-off on (not only once the tube has started)
        self.min_pair_airborne = _min_pair(pos[airborne & np.isfinite(pos[:, 0])],
                                           flown_r_s, self.min_pair_airborne)
        if truth is not None:
            self.min_pair_airborne_truth = _min_pair(
                truth[airborne & np.isfinite(truth[:, 0])], flown_r_s,
                self.min_pair_airborne_truth)
        if tick_duration_s is not None:
            metrics["tick_duration_s"] = tick_duration_s
        if math.isfinite(latency):
            metrics["link_latency_s"] = latency
        # the phases as logged: after the budget watch, which may have made them hold
        logged = [PHASE_VALUES[c] for c in codes.tolist()]
        self.recorder.log_tick(t_s=t, tick=tick, ids=tab.ids.copy(), pos=pos, vel=vel,
                               phases=logged, cmd=cmd, metrics=metrics, safety=safety)
        if self.keep_trace:
            self.trace.append(TickTrace(t, pos, vel, cmd, tube_rows & np.isfinite(cmd[:, 0]),
                                        tuple(logged), truth, seg))
        return pos, vel, cmd, logged

    def _watch(self, result: TickResult, budget: SafetyBudget, tick_gap_s: float,
               request_hold: Callable[[str], None]) -> None:
        """The budget watch (:func:`~vtube_fleet.fleet.tick.watch_budget`) and the position
        ages the summary reports (airborne, younger than ``neighbour_max_age_s``)."""
        tab = self.table
        used = used_ages(tab, result)
        self.sample_ages.extend(used[1].tolist())
        if self.watch is None or self.watch.budget is not budget:
            self.watch = BudgetWatch(self.mission, budget)
            self._forgotten = set()
        links = self.links
        warning, hold = watch_budget(
            self.watch, tab, result, tick_gap_s,
            lambda rows: [links[r].state.accuracy_m() for r in rows.tolist()],
            forgotten=self._forgotten, used=used)
        if warning:
            self.warn(warning)
        if hold:
            request_hold(f"{hold}, so every vehicle in the tube holds")

    def _note(self, t: float, suffix: str, sm: Any, pos: np.ndarray, vel: np.ndarray | None,
              note: Callable[[str, str, dict[str, Any]], None], segment: np.ndarray) -> None:
        """On the first tick that breaks a limit (telemetry or truth): tell ``note``."""
        e = self.violations.note(t, suffix, sm, pos, vel, self.table.ids.tolist(), segment)
        if e is not None:
            note(suffix, e["source"], e)

    def truth_positions(self) -> np.ndarray:
        """(M, 2) ground truth in the tube frame (NaN where none arrived within lost_after_s);
        one vectorized frame conversion."""
        m = self.table.n
        out = np.full((m, 2), np.nan)
        now = time.monotonic()
        rows = [i for i, lk in enumerate(self.links)
                if lk.state.last_truth_s is not None
                and now - lk.state.last_truth_s <= self.cfg.lost_after_s]
        if rows:
            st = [self.links[i].state for i in rows]
            x, y, _ = self.frame.geodetic_to_tube(np.array([s.truth_lat_deg for s in st]),
                                                  np.array([s.truth_lon_deg for s in st]),
                                                  np.array([s.truth_alt_m for s in st]))
            out[rows, 0] = np.atleast_1d(x)
            out[rows, 1] = np.atleast_1d(y)
        return out

    # -- the live status -------------------------------------------------------------------------
    def status(self, status: FleetStatus, pilots: Sequence[Any], *, rows: bool,
               durations_s: Sequence[float], lateness_s: Sequence[float], period_s: float,
               rate_hz: float, delta_m: float, route: Route) -> FleetStatus:
        """Fill the live view's :class:`~vtube_fleet.fleet.view.FleetStatus`; ``rows``: with the
        per-vehicle rows, flying ``route`` (the flight plan's: its segments and sub-tubes)."""
        tab = self.table
        counts: dict[str, int] = {}
        for c in tab.phase.tolist():
            counts[PHASE_VALUES[c]] = counts.get(PHASE_VALUES[c], 0) + 1
        for lk in self.links:
            s = lk.state
            if s.last_heartbeat_s is not None and not lk.closed:
                status.connected += 1
            if s.armed:
                status.armed += 1
        status.phases = counts
        status.in_tube = counts.get("in_tube", 0)
        status.exited = int(np.isfinite(tab.exit_s).sum())
        status.lost = counts.get("lost", 0)
        status.landed = counts.get("landed", 0)
        summ = self.acc.summary()
        status.min_pair_m = min(summ.get("min_pair_distance_m") or math.inf,
                                self.min_pair_airborne)
        lim = self.monitor.limits
        status.pair_limit_m = lim.pair_m
        status.min_obstacle_m = summ.get("min_obstacle_center_distance_m") or math.inf
        obs = self.mission.scenario.obstacles
        status.obstacle_limit_m = (lim.obstacle_center_m(min(float(o.radius) for o in obs))
                                   if obs else math.nan)
        status.min_leg_m = min(summ.get("min_left_leg_distance_m") or math.inf,
                               summ.get("min_right_leg_distance_m") or math.inf)
        status.leg_limit_m = lim.leg_m
        status.delta_m = delta_m
        status.unsafe = self.violations.first is not None
        if self.truth:
            status.truth_pair_m = min(summ.get("min_pair_distance_m_truth") or math.inf,
                                      self.min_pair_airborne_truth)
            status.truth_obstacle_m = summ.get("min_obstacle_center_distance_m_truth") or math.inf
            status.truth_leg_m = min(summ.get("min_left_leg_distance_m_truth") or math.inf,
                                     summ.get("min_right_leg_distance_m_truth") or math.inf)
        d = list(durations_s[-400:])
        p50, p99 = percentile_or_none(d, 50), percentile_or_none(d, 99)
        status.tick_p50_ms = math.nan if p50 is None else 1000 * p50
        status.tick_p99_ms = math.nan if p99 is None else 1000 * p99
        status.rate_hz = rate_hz
        on_time = on_time_share(list(lateness_s[-400:]), period_s)
        if on_time is not None:
            status.on_time = on_time
        status.latency_ms = 1000 * (self.latencies[-1] if self.latencies else math.nan)
        if rows:  # the per-vehicle table / the worst vehicle per limit (the view wants them)
            status.rows = vehicle_rows(pilots, route, lim, tab.segment)
        return status


def _min_pair(q: np.ndarray, flown_r_s: float, current: float) -> float:
    """min(current, the smallest distance among the points ``q``) (pairs within 4 r_s' + 1 m)."""
    if q.shape[0] > 1:
        i_idx, j_idx = pairs_within(q, 4.0 * flown_r_s + 1.0)
        if len(i_idx):
            return min(current, float(np.hypot(*(q[i_idx] - q[j_idx]).T).min()))
    return current
