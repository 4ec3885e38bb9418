"""The fleet supervisor: one asyncio process flies every vehicle of a mission.

Procedure (:meth:`Supervisor.run`):

1. **connect** every endpoint concurrently (``connect_timeout_s``); the error names every
   vehicle that did not answer;
2. **ready**: heartbeat, local + global position, home, GPS origin, health
   (``ready_timeout_s``); the control clock starts (sensing only);
3. **safety budget**: the link latency and the age of the position samples are measured for
   about a second; δ = v'_max·(T + L + τ_d + t63) (:class:`~vtube_fleet.fleet.agent.
   SafetyBudget`) inflates r_s and r_a; the inflated scenario is validated (Assumption 1 with
   the vehicles' actual positions in the tube frame, Assumption 3/3', (pothk), the partition);
   if anything fails nothing arms and the report names each offending vehicle, its position and
   the numbers;
4. **take-off**: all vehicles together (each stays over its own slot, which Assumption 1 keeps
   2 r_s' apart): setpoints stream, OFFBOARD, ARM, offboard climb; all must reach the mission
   altitude, then Assumption 1 is checked again at altitude;
5. **tube**: every vehicle becomes IN_TUBE on the same tick; each tick (``rate_hz``) senses all
   vehicles (one vectorized frame conversion), publishes their states on the in-process bus,
   detects faults, re-partitions around LOST vehicles, detects exits (TraCondition), computes
   all in-tube setpoints in one ``velocity_command`` call and sends them;
6. **end**: when every vehicle has exited (or is lost), ``on_complete`` (land / hold); a
   summary is written on every exit path.

Faults: a LOST vehicle (silent for ``lost_after_s``, or out of OFFBOARD) becomes a static
obstacle of radius r_s + ``lost_obstacle_margin_m`` at its last position and the tube is
re-partitioned online; if no valid partition exists the others hold (OFFBOARD → Hold) and the
mission aborts (:class:`MissionAborted`, exit code 3). SIGINT / SIGTERM: every vehicle holds,
then lands; the summary and the recording are complete (exit code 130).

The summary (``summary.json``) is built by :class:`vtube_fleet.core.metrics.SummaryAccumulator`, the
simulator's own accumulator, fed every tick from **telemetry** positions: the ``""`` stream holds
the vehicles in the tube (and lost vehicles at their frozen positions) with the *commanded*
horizontal velocities, so ``min_speed_m_s``/``max_speed_m_s`` are the commanded speeds in the
tube; the measured speeds are ``min_measured_speed_m_s``/``max_measured_speed_m_s``;
``min_pair_distance_airborne_m`` also counts vehicles that have exited.
"""

from __future__ import annotations

import asyncio
import gc
import inspect
import logging
import math
import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vtube_fleet.artifacts import (
    SUMMARY_EVERY_S,
    SummaryPacer,
    write_interim_summary,
    write_summary,
)
from vtube_fleet.bus.base import InProcessBus
from vtube_fleet.config.mission import Mission
from vtube_fleet.core.metrics import (
    SafetyMonitor,
    SummaryAccumulator,
    ViolationLog,
    finite_or_none,
    percentile_or_none,
    truth_keys,
    verdict,
)
from vtube_fleet.core.neighbours import pairs_within
from vtube_fleet.core.partition import PartitionError
from vtube_fleet.core.validation import flown_symbols, validate_scenario
from vtube_fleet.errors import PROBLEMS_SHOWN, UserError, join_problems
from vtube_fleet.fleet.agent import (
    Agent,
    FlightPlan,
    NeighbourView,
    classify_arrays,
    fleet_setpoints,
    lost_obstacles,
)
from vtube_fleet.fleet.budget import (
    LOOP_CHECK_S,
    LOOP_MIN_S,
    BudgetWatch,
    LinkMeasurement,
    SafetyBudget,
    achieved_rate_hz,
    loop_problem,
    mission_budget,
    on_time_share,
)
from vtube_fleet.fleet.compensation import CompensatorBank, ResidualTracker
from vtube_fleet.fleet.pilot import (
    PilotError,
    VehiclePilot,
    actuate_all,
    check_faults_all,
    fleet_states,
    link_columns,
    measure_budget_links,
    sense_all,
    wait_accuracy,
)
from vtube_fleet.fleet.table import PHASE_CODE, PHASES, PilotTable, phase_mask
from vtube_fleet.fleet.view import FleetStatus, FleetView, vehicle_rows
from vtube_fleet.link.base import LinkTimeout, VehicleLink
from vtube_fleet.outcome import EXIT_INCOMPLETE, exit_code
from vtube_fleet.state import AIRBORNE_PHASES, COUNTED_AIRBORNE_PHASES, STOPPED_PHASES, Phase

__all__ = [
    "CONNECT_WINDOW",
    "FleetError",
    "FleetResult",
    "MissionAborted",
    "PreflightError",
    "Supervisor",
    "TickTrace",
    "preflight_report",
]

log = logging.getLogger(__name__)
_NO_CMDS = np.zeros((0, 2))
_PHASE_VALUES = tuple(ph.value for ph in PHASES)  # by phase code (fleet/table.py)
_IN_TUBE = PHASE_CODE[Phase.IN_TUBE]
_LOST = PHASE_CODE[Phase.LOST]
_AIRBORNE_MASK = phase_mask(AIRBORNE_PHASES)
_COUNTED_AIRBORNE_MASK = phase_mask(COUNTED_AIRBORNE_PHASES)
_STOPPED_OR_LOST_MASK = phase_mask(STOPPED_PHASES | {Phase.LOST})


#: Rate of the ground-truth stream asked for with ``truth=True`` (HIL_STATE_QUATERNION).
TRUTH_RATE_HZ = 20.0

#: Minimum height of the mission altitude above every vehicle before take-off.
MIN_CLIMB_M = 1.0

#: Links connecting at once (:meth:`Supervisor._connect`).
CONNECT_WINDOW = 64


async def _raise(result: object) -> None:
    """Re-raise a result of ``gather(..., return_exceptions=True)`` inside a coroutine."""
    if isinstance(result, BaseException):
        raise result


class FleetError(UserError):
    """The fleet could not start (connect / ready / preflight); nothing armed."""


class PreflightError(FleetError):
    """The vehicles' positions or the safety budget break the paper's conditions."""


class MissionAborted(UserError):
    """The mission was aborted in flight (no valid partition, take-off failure, timeout)."""

    exit_code = EXIT_INCOMPLETE


@dataclass
class FleetResult:
    """What :meth:`Supervisor.run` returns: the outcome, why, the summary dict and its path."""

    outcome: str
    reason: str
    summary: dict[str, Any]
    summary_path: Path | None

    @property
    def exit_code(self) -> int:
        """The process exit code of :attr:`outcome` (:func:`vtube_fleet.outcome.exit_code`)."""
        return exit_code(self.outcome)


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


def preflight_report(
    mission: Mission,
    flown: Any,
    positions: np.ndarray,
    names: Sequence[str],
    *,
    where: str = "on the ground",
) -> tuple[Any, list[str]]:
    """Validate the (inflated) scenario with the vehicles' actual positions; ``flown``: the
    parameters with the flown radii r_s', r_a' (the plan's ``flown``).

    Returns (partition or None, problems). Each problem is one line naming the vehicles
    (``robot i`` of :func:`vtube_fleet.core.validation.validate_scenario` becomes ``vehicle i
    (endpoint)``) with the numbers.
    """
    sc = mission.scenario
    part, violations = validate_scenario(sc.tube, sc.obstacles, flown, positions,
                                         keep_out=mission.slots)  # "auto": plan on the slots

    def one(text: str) -> str:
        i = int(text)
        return names[i] if 0 <= i < len(names) else f"robot {i}"

    problems = []
    for v in violations:
        msg = re.sub(r"\brobots (\d+) and (\d+)",
                     lambda m: f"{one(m.group(1))} and {one(m.group(2))}", v.message)
        msg = re.sub(r"\brobot (\d+)", lambda m: one(m.group(1)), msg)
        problems.append(f"{flown_symbols(msg)} ({where}, r_s' = {flown.r_s:.3f} m: the "
                        f"physical r_s = {sc.robots.r_s:g} m + δ)")
    return part, problems


class Supervisor:
    """Fly ``mission`` with one pilot per link (link i flies slot i). See the module docstring.

    ``recorder``: a :class:`vtube_fleet.recording.api.Recorder` (default: records nothing);
    ``view``: the live terminal view (default: none); ``out_dir``: where ``summary.json`` goes;
    ``keep_trace``: keep every tick's telemetry in :attr:`trace` (tests);
    ``tick_hook(tick, supervisor)``: called at the end of every tick (fault injection in tests;
    if it returns an awaitable, the control clock awaits it: a stalled control loop).
    :meth:`interrupt` stops the mission as a signal would (the command installs the handlers).
    """

    def __init__(
        self,
        mission: Mission,
        links: Sequence[VehicleLink],
        *,
        backend: str = "mavlink",
        recorder: Any = None,
        view: FleetView | None = None,
        out_dir: str | os.PathLike[str] | None = None,
        keep_trace: bool = False,
        tick_hook: Callable[[int, Supervisor], None] | None = None,
        truth: bool = False,
        fence: bool = True,
        fix_params: bool = False,
    ) -> None:
        if not links:
            raise FleetError("no vehicles to fly")
        if len(links) > mission.count:
            raise FleetError(f"{len(links)} endpoints but the mission has only "
                             f"{mission.count} slots ([robots] of {mission.source})")
        if len(links) < mission.count:
            mission = mission.with_vehicles(len(links))
        self.mission = mission
        self.cfg = mission.config
        self.frame = mission.frame
        self.links = list(links)
        self.backend = backend
        if recorder is None:
            from vtube_fleet.recording.api import NullRecorder

            recorder = NullRecorder()
        self.recorder = recorder
        self.view = view
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.keep_trace = keep_trace
        self.trace: list[TickTrace] = []
        self.tick_hook = tick_hook
        self.truth = truth
        self.fence = fence  # upload the tube as PX4's geofence before arming (fleet/onboard.py)
        self.fix_params = fix_params  # --fix-params: set the audited PX4 parameters, restore
        self._param_restore: list[dict[str, float]] = []
        #: summary "onboard": fence ("uploaded" / "off" / "unsupported" / None = not reached),
        #: fence_items, gf_action, px4_params (per vehicle, as read), params_fixed
        self.onboard: dict[str, Any] = {"fence": None, "fence_items": 0, "gf_action": None,
                                        "px4_params": [], "params_fixed": {}}

        sc = mission.scenario
        self.physical = sc.controller  # as configured: the PHYSICAL r_s, r_a (flown: plan.flown)
        # the plan before the budget is measured: latency 0 (replaced in _measure_budget())
        self.measured: LinkMeasurement | None = None
        self.budget = self._make_budget(None)
        flown = self.budget.inflate(self.physical)
        try:
            self.plan = FlightPlan.build(sc.tube, sc.obstacles, flown, keep_out=mission.slots)
        except PartitionError as exc:
            raise PreflightError(
                f"{mission.source}: with the safety budget {self.budget.describe(self.physical)}"
                f" the tube cannot be partitioned: {exc}") from None
        self.bus = InProcessBus()
        self.pilots: list[VehiclePilot] = []
        for i, link in enumerate(self.links):
            agent = Agent(i, self.plan, max_age_s=self.cfg.neighbour_max_age_s,
                          lost_after_s=self.cfg.lost_after_s,
                          lost_radius_m=self.physical.r_s + self.cfg.lost_obstacle_margin_m)
            self.pilots.append(VehiclePilot(link, agent, self.bus, mission, frame=self.frame,
                                            on_event=self._on_pilot_event))
        self.names = [p.name for p in self.pilots]
        # the fleet's estimate compensation and its residuals: one vectorized update a tick
        self.compensators = CompensatorBank(len(self.pilots))
        self.residuals = ResidualTracker(len(self.pilots), self.cfg.period_s,
                                         self.cfg.disturbance_residual_m_s)
        #: the pilots' tick state as columns, pilot i in row i (fleet/table.py)
        self.table = PilotTable(len(self.pilots))
        for i, p in enumerate(self.pilots):
            p.join_fleet(i, self.compensators, self.residuals, self.table)
        # limits of the PHYSICAL r_s; pairs searched within r_s' + r_a' + 1 m
        self.monitor = SafetyMonitor.for_run(sc.tube, sc.obstacles, self.physical, flown)
        self.acc = SummaryAccumulator(len(self.pilots))
        self.t0 = time.monotonic()
        self.tube_start_s: float | None = None
        self.stage = "connecting"
        self.tick = 0
        self.tick_durations: list[float] = []
        self.tick_lateness: list[float] = []
        self.tick_starts_s: list[float] = []  # loop time at the start of each tick
        self.latencies: list[float] = []
        self.sample_ages: list[float] = []
        self._sample_ages_window: list[float] = []
        self._sample_ids_window: list[int] = []  # the vehicle of each age in the window
        self._sample_at_window: list[float] = []  # and the arrival time of its sample
        self.measured_speed = [math.inf, -math.inf]
        self.settled_speed = [math.inf, -math.inf]
        self.settle_s = self.cfg.tracking_dead_time_s + 3.0 * self.cfg.tracking_t63_s
        self.cmd_speed = [math.inf, -math.inf]
        self.min_pair_airborne = math.inf
        self.events: list[dict[str, Any]] = []
        self.partitions = 1
        self._abort_reason: str | None = None
        self._abort_event = asyncio.Event()
        self._progress = asyncio.Event()
        self._interrupted: str | None = None
        self._clock_task: asyncio.Task[None] | None = None
        self._clock_stop = asyncio.Event()
        self._main: asyncio.Task[None] | None = None
        self.watch: BudgetWatch | None = None  # the in-flight budget check, once flying
        self._forgotten: set[int] = set()  # lost vehicles whose ages the watch dropped
        self._recent_tick_gap_s = 0.0  # the longest gap between control ticks, for the watch
        self.violations = ViolationLog(self.monitor)
        self.not_landed: list[str] = []
        self.truth_xy: np.ndarray | None = None  # (M, 2) ground truth, tube frame (truth=True)
        self.min_pair_airborne_truth = math.inf
        self.listening_since: float | None = None
        self._heap_frozen = False  # _freeze_heap
        self.outcome = "failed"
        self.reason = ""

    # -- small helpers -------------------------------------------------------------------------
    def _make_budget(self, measured: LinkMeasurement | None) -> SafetyBudget:
        return mission_budget(self.mission, measured)

    def t_s(self) -> float:
        return time.monotonic() - self.t0

    def event(self, text: str, *, vehicle_id: int | None = None, level: str = "info",
              echo: bool = True) -> None:
        """Record an event (events, recording) and show it; ``echo=False`` keeps it out of the
        terminal (logged at debug), for long lists whose summary is shown instead."""
        t = self.t_s()
        self.events.append({"t_s": round(t, 3), "vehicle": vehicle_id, "level": level,
                            "text": text})
        self.recorder.log_event(t, text, vehicle_id=vehicle_id, level=level)
        line = text if vehicle_id is None else f"{self.names[vehicle_id]}: {text}"
        if not echo:
            log.debug("%s", line)
        elif level in ("warning", "error") and self.view is None:
            log.warning("%s", line)
        else:
            log.info("%s", line)
        if echo and self.view is not None and (level != "info" or vehicle_id is None):
            self.view.message(f"[{t:7.1f}s] {level.upper() if level != 'info' else ''}"
                              f"{' ' if level != 'info' else ''}{line}")
        self._progress.set()

    def _listed(self, problems: Sequence[str]) -> str:
        """The problems for a one-line error (:func:`~vtube_fleet.errors.join_problems`); when
        some are left out of it, every one is recorded as an event first (not echoed: the
        error line is what the terminal shows)."""
        if len(problems) > PROBLEMS_SHOWN:
            for text in problems:
                self.event(text, level="error", echo=False)
        return join_problems(problems)

    def _on_pilot_event(self, text: str, vehicle_id: int | None, level: str) -> None:
        self.event(text, vehicle_id=vehicle_id, level=level)

    def _set_stage(self, stage: str) -> None:
        self.stage = stage
        self.event(f"stage: {stage}")

    # -- the control clock ---------------------------------------------------------------------
    async def _clock(self) -> None:
        loop = asyncio.get_running_loop()
        period = self.cfg.period_s
        next_t = loop.time()
        pacer = SummaryPacer(next_t + SUMMARY_EVERY_S)
        prev: float | None = None
        while not self._clock_stop.is_set():
            start = loop.time()
            self.tick_starts_s.append(start)
            self.tick_lateness.append(start - next_t)
            if prev is not None and start - prev > 2.0 * period + 0.1:
                # our own loop stalled: silence is counted from now on (pilot.check_faults)
                self.listening_since = time.monotonic()
                self.event(f"control loop stalled for {start - prev:.2f} s", level="warning")
            if prev is not None:
                self._recent_tick_gap_s = max(self._recent_tick_gap_s, start - prev)
            prev = start
            t0 = time.perf_counter()
            collecting = gc.isenabled()
            gc.disable()  # the cyclic collector waits until the setpoints are out
            try:
                self._tick()
            except Exception as exc:  # a bug must not leave vehicles without setpoints silently
                log.exception("control tick failed")
                self.request_abort(f"control tick failed: {type(exc).__name__}: {exc}")
            finally:
                if collecting:
                    gc.enable()
            self.tick_durations.append(time.perf_counter() - t0)
            if self.tick_hook is not None:
                stall = self.tick_hook(self.tick, self)
                if inspect.isawaitable(stall):
                    await stall  # fault injection: the control loop stalls (event loop alive)
            self.tick += 1
            next_t += period
            if pacer.due(loop.time()):  # in the slack after a tick, not before one
                t_c = loop.time()
                self._checkpoint()
                pacer.written(t_c, loop.time())
            now = loop.time()
            if next_t < now - period:  # more than a period behind: do not try to catch up
                next_t = now
            delay = next_t - now
            if delay > 0:
                try:
                    async with asyncio.timeout(delay):
                        await self._clock_stop.wait()
                except TimeoutError:
                    pass
            else:
                await asyncio.sleep(0)

    def _tick(self) -> None:
        now = time.monotonic()
        wall = time.time()
        t = now - self.t0
        pilots = self.pilots
        tab = self.table
        cfg = self.cfg
        links = link_columns(pilots)  # (the links change only between ticks)
        sense_all(pilots, self.frame, links)
        check_faults_all(pilots, now, self.listening_since, links)
        # every pilot's state (what each would publish) as one table: the budget's sample
        # ages (airborne; older: a stale vehicle, handled as a fault) and the neighbour view
        fs = fleet_states(pilots, now, wall, links)
        have = np.isfinite(tab.sample_s)
        keep = _AIRBORNE_MASK[tab.phase[have]]
        keep &= fs.ages_s <= cfg.neighbour_max_age_s
        self._sample_ages_window.extend(fs.ages_s[keep].tolist())
        self._sample_ids_window.extend(fs.ids[keep].tolist())
        self._sample_at_window.extend(fs.sample_s[keep].tolist())
        # in-process, a vehicle is lost when its pilot says so (pilot.check_faults, which knows
        # about stalls of this loop); stale states are static points until then
        view = classify_arrays(fs.ids, fs.pos, fs.vel, fs.phases, fs.stamps_s, wall,
                               max_age_s=cfg.neighbour_max_age_s, lost_after_s=math.inf)
        self._update_partition(view, t)
        in_tube = self.tube_start_s is not None
        # exits (TraCondition), then the controller for everyone still in the tube
        rows: list[int] = []
        row_pilots: list[VehiclePilot] = []
        if in_tube:
            flying = np.flatnonzero((tab.phase == _IN_TUBE) & tab.has)
            if flying.size:
                done = self.plan.exited(tab.xy[flying])
                for i in flying[done].tolist():
                    p = pilots[i]
                    p.mark_exit(t)
                    self.acc.add_exits(t, [p.vehicle_id])
                    self.recorder.log_exits(t, self.tick, [p.vehicle_id])
                # each flying vehicle's row of the view (pilot i is vehicle i), -1: not in it
                at = np.full(len(pilots), -1, np.int64)
                ids = view.ids()
                at[ids] = np.arange(ids.size)
                left = flying[~done]
                seen = at[left] >= 0
                rows = at[left[seen]].tolist()
                row_pilots = [pilots[i] for i in left[seen].tolist()]
        out = fleet_setpoints(self.plan, view.points(), rows) if rows else _NO_CMDS
        actuate_all(pilots, now, row_pilots, out, view, links)
        self._measure(t, now, view, links.latency_s)

    def _unreachable(self, now: float) -> str | None:
        """Link loss, told apart from a lost vehicle: once a vehicle is LOST for silence during
        take-off or the tube, if no other vehicle's telemetry has arrived within
        ``neighbour_max_age_s`` either, nobody can be commanded — "cannot reach anyone", not a
        geometry problem (whichever tick notices first gives this same reason). Vehicles lost
        otherwise (left OFFBOARD, disarmed, unresponsive) still talk: they are not link loss."""
        if self.stage not in ("takeoff", "tube"):
            return None
        silent = [p for p in self.pilots if p.phase == Phase.LOST
                  and (p.reason or "").startswith("no telemetry")]
        if not silent:
            return None
        others = [p for p in self.pilots if p not in silent
                  and p.phase in COUNTED_AIRBORNE_PHASES]
        max_age = self.cfg.neighbour_max_age_s
        since = -math.inf if self.listening_since is None else self.listening_since
        # (after a stall of our own loop, silence is counted from when it resumed)
        for p in others:
            last = p.link.state.last_position_s
            if last is not None and now - max(last, since) <= max_age:
                return None  # someone still answers: a lost vehicle, not a dead fleet link
        return (f"link loss: cannot reach anyone: {len(silent)} of {len(self.pilots)} vehicles "
                f"silent for more than lost_after_s = {self.cfg.lost_after_s:g} s"
                + (f" and the other {len(others)} not heard for more than "
                   f"neighbour_max_age_s = {max_age:g} s" if others else "")
                + "; no vehicle can be commanded (PX4's offboard-loss failsafe takes over); "
                "check the links and the vehicles' processes, not the tube")

    def _update_partition(self, view: NeighbourView, t: float) -> None:
        if not view.lost_ids.size:
            return
        if self._abort_reason is None:
            dead = self._unreachable(time.monotonic())
            if dead is not None:
                self.request_abort(dead)
                return
        if not any(p.phase in (Phase.IN_TUBE, Phase.TAKEOFF) for p in self.pilots):
            return  # nobody left to fly the tube
        root = self.pilots[0].agent.root_plan
        lost = lost_obstacles(view, root.tube, self.physical.r_s + self.cfg.lost_obstacle_margin_m,
                              root.flown)
        try:
            new = root.with_lost(lost)
        except PartitionError as exc:
            if self._abort_reason is None:
                ids = [int(i) for i in view.lost_ids]
                why = "; ".join(f"vehicle {p.vehicle_id}: {p.reason}" for p in self.pilots
                                if p.vehicle_id in ids and p.reason)
                self.request_abort(
                    f"cannot re-partition the tube around the lost vehicle(s) "
                    f"{', '.join(map(str, ids))} (in the air at their last known positions, "
                    f"each an obstacle of radius r_s + lost_obstacle_margin_m"
                    f"{'; ' + why if why else ''}): {exc}")
            return
        if new is not self.plan:
            self.plan = new
            for p in self.pilots:
                p.agent.plan = new
            self.partitions += 1
            where = ", ".join(f"({o.center[0]:.2f}, {o.center[1]:.2f}) r={o.radius:.2f}"
                              for o in new.lost)
            self.event(f"re-partitioned around lost vehicle(s): {len(new.partition.sub_tubes)} "
                       f"sub-tubes; lost obstacles {where or 'none inside the tube'}",
                       level="warning")
            self.recorder.log_partition(new.partition, t)

    def request_abort(self, reason: str) -> None:
        """Abort the mission: vehicles in the tube hold now; the main procedure ends."""
        if self._abort_reason is not None:
            return
        self._abort_reason = reason
        self.event(f"ABORT: {reason}", level="error")
        for p in self.pilots:
            if p.phase in (Phase.IN_TUBE, Phase.EXITED, Phase.ARMING, Phase.TAKEOFF):
                p.reason = p.reason or f"mission aborted: {reason}"
            if p.phase in (Phase.IN_TUBE, Phase.EXITED):
                p.begin_hold("mission aborted")
        self._abort_event.set()
        self._progress.set()

    # -- per-tick measurements -----------------------------------------------------------------
    def _measure(self, t: float, now: float, view: NeighbourView,
                 latencies_s: np.ndarray | None = None) -> None:
        pilots = self.pilots
        tab = self.table
        m = len(pilots)
        has = tab.has.copy()
        pos = np.where(tab.lost_set[:, None], tab.lost, tab.xy)  # VehiclePilot.position
        vel = tab.vel.copy()
        pos[~has] = np.nan
        vel[~has] = np.nan
        cmd = np.where(tab.cmd_set[:, None], tab.cmd, np.nan)
        codes = tab.phase
        inside = tab.cmd_in_tube.copy()
        # judged in the tube: flying the controller, or stopped inside it (lost at its last
        # position, holding, landing while still in the air)
        tube_rows = inside.copy()
        if self.tube_start_s is not None:
            tube = self.mission.scenario.tube
            for i in np.flatnonzero(~inside & has & _STOPPED_OR_LOST_MASK[codes]).tolist():
                if ((codes[i] == _LOST or pilots[i].airborne())
                        and bool(tube.contains(pos[i]))):
                    tube_rows[i] = True
        # the mission monitor's rule too
        airborne = _COUNTED_AIRBORNE_MASK[codes]
        lat = link_columns(pilots).latency_s if latencies_s is None else latencies_s
        lat = lat[np.isfinite(lat)]
        latency = float(np.median(lat)) if lat.size else math.nan
        if lat.size:
            self.latencies.append(latency)
        truth = self._truth_positions() if self.truth else None
        metrics: dict[str, float] = {}
        safety = None
        if self.tube_start_s is not None:
            # the "" stream: in the tube (telemetry position, commanded velocity)
            p_tube = np.where(tube_rows[:, None], pos, np.nan)
            commanded = inside & np.isfinite(cmd[:, 0])
            v_tube = np.where(commanded[:, None], cmd, np.nan)  # speeds: the controller's
            sm = self.monitor.evaluate(p_tube, v_tube)
            self.acc.add(t, sm)
            self._note_violation(t, "", sm, p_tube, v_tube)
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
                smt = self.monitor.evaluate(t_tube)
                self.acc.add(t, smt, suffix="_truth")
                self._note_violation(t, "_truth", smt, t_tube, None)
                safety["_truth"] = (t_tube, np.full_like(t_tube, np.nan))
                for key in ("min_pair_distance_m", "min_obstacle_center_distance_m",
                            "min_left_leg_distance_m", "min_right_leg_distance_m"):
                    val = float(getattr(smt, key)[0])
                    if math.isfinite(val):
                        metrics[f"truth_{key}"] = val
                qt = truth[airborne & np.isfinite(truth[:, 0])]
                if qt.shape[0] > 1:
                    i_idx, j_idx = pairs_within(qt, 4.0 * self.plan.flown.r_s + 1.0)
                    if len(i_idx):
                        self.min_pair_airborne_truth = min(
                            self.min_pair_airborne_truth,
                            float(np.hypot(*(qt[i_idx] - qt[j_idx]).T).min()))
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
                if t - self.tube_start_s > self.settle_s:
                    self.settled_speed[0] = min(self.settled_speed[0], float(ms.min()))
                    self.settled_speed[1] = max(self.settled_speed[1], float(ms.max()))
            q = pos[airborne & np.isfinite(pos[:, 0])]
            if q.shape[0] > 1:
                i_idx, j_idx = pairs_within(q, 4.0 * self.plan.flown.r_s + 1.0)
                if len(i_idx):
                    d = float(np.hypot(*(q[i_idx] - q[j_idx]).T).min())
                    self.min_pair_airborne = min(self.min_pair_airborne, d)
            self.sample_ages.extend(self._sample_ages_window)
            self._watch_budget(t, self._sample_ages_window, self._sample_ids_window,
                               self._sample_at_window)
        self._sample_ages_window.clear()
        self._sample_ids_window.clear()
        self._sample_at_window.clear()
        if self.tick_durations:
            metrics["tick_duration_s"] = self.tick_durations[-1]
        if math.isfinite(latency):
            metrics["link_latency_s"] = latency
        # the phases as logged: after the budget watch, which may have made them hold
        logged = [_PHASE_VALUES[c] for c in codes.tolist()]
        self.recorder.log_tick(
            t_s=t, tick=self.tick, ids=np.arange(m), pos=pos, vel=vel,
            phases=logged, cmd=cmd, metrics=metrics,
            safety=safety)
        if self.keep_trace:
            self.trace.append(TickTrace(t, pos, vel, cmd, tube_rows & np.isfinite(cmd[:, 0]),
                                        tuple(logged), truth))
        if self.view is not None:
            self.view.update(self.status())

    def _truth_positions(self) -> np.ndarray:
        """(M, 2) ground truth in the tube frame (NaN where none arrived within lost_after_s);
        one vectorized frame conversion."""
        m = len(self.pilots)
        out = np.full((m, 2), np.nan)
        now = time.monotonic()
        rows = [i for i, p in enumerate(self.pilots)
                if p.link.state.last_truth_s is not None
                and now - p.link.state.last_truth_s <= self.cfg.lost_after_s]
        if rows:
            st = [self.pilots[i].link.state for i in rows]
            x, y, _ = self.frame.geodetic_to_tube(np.array([s.truth_lat_deg for s in st]),
                                                  np.array([s.truth_lon_deg for s in st]),
                                                  np.array([s.truth_alt_m for s in st]))
            out[rows, 0] = np.atleast_1d(x)
            out[rows, 1] = np.atleast_1d(y)
        self.truth_xy = out
        return out

    def _note_violation(self, t: float, suffix: str, sm: Any, pos: np.ndarray,
                        vel: np.ndarray | None) -> None:
        """On the first tick that breaks a limit (telemetry or truth): say what, who and by
        how much (kept for the summary's ``first_violation``)."""
        e = self.violations.note(t, suffix, sm, pos, vel, [p.vehicle_id for p in self.pilots])
        if e is None:
            return
        who = " and ".join(self.names[v] for v in e["vehicles"])
        self.event(f"LIMIT BROKEN ({e['source']}): {e['condition']} {e['value']:.3f} m, limit "
                   f"{e['limit']:.3f} m: {who}", level="error")

    def _watch_budget(self, t: float, ages_s: list[float], vehicle_ids: list[int],
                      sample_s: list[float]) -> None:
        """Once a second in the tube (:class:`~vtube_fleet.fleet.budget.BudgetWatch`): L and σ
        over what the budget was built for, for 2 s → every vehicle in the tube holds. The
        ages of this tick's positions (``ages_s``, of ``vehicle_ids``, on samples that arrived
        at ``sample_s``) go in every tick; they count once superseded, and a vehicle declared
        lost has its ages dropped (its silence is a fault, not latency)."""
        gap, self._recent_tick_gap_s = self._recent_tick_gap_s, 0.0
        codes = self.table.phase
        if not (codes == _IN_TUBE).any():
            return
        if self.watch is None or self.watch.budget is not self.budget:
            self.watch = BudgetWatch(self.mission, self.budget)
            self._forgotten = set()
        self.watch.add_tick_gap(gap)
        self.watch.add_ages(t, ages_s, vehicle_ids, sample_s)
        lost = set(np.flatnonzero(codes == _LOST).tolist()) - self._forgotten  # (vehicle i: row i)
        if lost:
            self.watch.forget(sorted(lost))
            self._forgotten |= lost
        if not self.watch.due(t):
            return  # (the fleet-wide uplink and accuracy below: once a second, not per tick)
        up = max((p.link.latency_s or 0.0 for p in self.pilots), default=0.0)
        acc = [self.pilots[i].position_accuracy_m()
               for i in np.flatnonzero(codes == _IN_TUBE).tolist()]
        newest = self.table.sample_s.copy()  # NaN: none yet (vehicle i: row i)
        warning, hold = self.watch.check(t, up, acc, newest)
        if warning:
            self.event(warning, level="warning")
        if hold:
            self.request_abort(f"{hold}, so every vehicle in the tube holds")

    def status(self) -> FleetStatus:
        st = FleetStatus(t_s=self.t_s(), stage=self.stage, vehicles=len(self.pilots))
        counts: dict[str, int] = {}
        for p in self.pilots:
            value = _PHASE_VALUES[PHASE_CODE[p.agent.phase]]
            counts[value] = counts.get(value, 0) + 1
            s = p.link.state
            if s.last_heartbeat_s is not None and not p.link.closed:
                st.connected += 1
            if s.armed:
                st.armed += 1
        st.phases = counts
        st.in_tube = counts.get("in_tube", 0)
        st.exited = int(sum(p.exit_time_s is not None for p in self.pilots))
        st.lost = counts.get("lost", 0)
        st.landed = counts.get("landed", 0)
        summ = self.acc.summary()
        st.min_pair_m = min(summ.get("min_pair_distance_m") or math.inf, self.min_pair_airborne)
        lim = self.monitor.limits
        st.pair_limit_m = lim.pair_m
        st.min_obstacle_m = summ.get("min_obstacle_center_distance_m") or math.inf
        obs = self.mission.scenario.obstacles
        st.obstacle_limit_m = (lim.obstacle_center_m(min(float(o.radius) for o in obs))
                               if obs else math.nan)
        st.min_leg_m = min(summ.get("min_left_leg_distance_m") or math.inf,
                           summ.get("min_right_leg_distance_m") or math.inf)
        st.leg_limit_m = lim.leg_m
        st.delta_m = self.budget.delta_m
        st.unsafe = self.violations.first is not None
        if self.truth:
            st.truth_pair_m = min(summ.get("min_pair_distance_m_truth") or math.inf,
                                  self.min_pair_airborne_truth)
            st.truth_obstacle_m = summ.get("min_obstacle_center_distance_m_truth") or math.inf
            st.truth_leg_m = min(summ.get("min_left_leg_distance_m_truth") or math.inf,
                                 summ.get("min_right_leg_distance_m_truth") or math.inf)
        d = self.tick_durations[-400:]
        p50, p99 = percentile_or_none(d, 50), percentile_or_none(d, 99)
        st.tick_p50_ms = math.nan if p50 is None else 1000 * p50
        st.tick_p99_ms = math.nan if p99 is None else 1000 * p99
        st.rate_hz = self._achieved_rate(window=40)
        on_time = on_time_share(self.tick_lateness[-400:], self.cfg.period_s)
        if on_time is not None:
            st.on_time = on_time
        st.latency_ms = 1000 * (self.latencies[-1] if self.latencies else math.nan)
        if self.view is not None and self.view.wants_rows():  # the table / the worst vehicles
            sc = self.mission.scenario
            st.rows = vehicle_rows(self.pilots, sc.tube, sc.obstacles, self.monitor.limits,
                                   partition=self.plan.partition)
        return st

    def _achieved_rate(self, window: int | None = None) -> float:
        starts = self.tick_starts_s if window is None else self.tick_starts_s[-window:]
        return achieved_rate_hz(starts)

    # -- the procedure -------------------------------------------------------------------------
    async def _gather_named(self, what: str, coros: Sequence[Any], limit: int | None = None
                            ) -> list[str]:
        """One problem line per pilot whose coroutine failed; ``limit``: at most that many
        running at once (:func:`~vtube_fleet.fleet.onboard.gather_bounded`)."""
        if limit is None:
            results = await asyncio.gather(*coros, return_exceptions=True)
        else:
            from vtube_fleet.fleet.onboard import gather_bounded

            results = await gather_bounded(coros, limit)
        problems = []
        for p, r in zip(self.pilots, results, strict=True):
            if isinstance(r, asyncio.CancelledError):
                raise r
            if isinstance(r, BaseException):
                if not isinstance(r, UserError | OSError):
                    log.error("%s: %s failed", p.name, what, exc_info=r)
                msg = str(r)
                problems.append(msg if p.link.endpoint.url in msg else f"{p.name}: {msg}")
        return problems

    async def _connect(self) -> None:
        """Connect every link within ``connect_timeout_s``, at most :data:`CONNECT_WINDOW` at
        a time: a link binds its socket only when its turn comes, so the vehicles not reached
        yet are not heard (their default streams, ATTITUDE at 100 Hz among them, would
        otherwise flood this process before the first links have turned them off)."""
        self._set_stage("connecting")
        cfg = self.cfg
        loop = asyncio.get_running_loop()
        deadline = loop.time() + cfg.connect_timeout_s

        async def one(link: VehicleLink) -> None:  # runs when its turn in the window comes
            left = deadline - loop.time()
            if left <= 0:
                raise LinkTimeout(f"not tried: connect_timeout_s = "
                                  f"{cfg.connect_timeout_s:g} s ran out while connecting "
                                  f"the others (at most {CONNECT_WINDOW} at a time)")
            await link.connect(timeout_s=left)

        problems = await self._gather_named("connect", [one(p.link) for p in self.pilots],
                                            limit=CONNECT_WINDOW)
        if problems:
            raise FleetError(f"{len(problems)} of {len(self.pilots)} vehicles did not connect "
                             f"within connect_timeout_s = {cfg.connect_timeout_s:g} s: "
                             + self._listed(problems))
        self.event(f"connected {len(self.pilots)} vehicles ({self.backend})")

    async def _ready(self) -> None:
        self._set_stage("ready")
        problems = await self._gather_named("ready", [p.wait_ready() for p in self.pilots])
        if problems:
            raise FleetError(f"{len(problems)} of {len(self.pilots)} vehicles not ready: "
                             + self._listed(problems))

    async def _measure_budget(self) -> None:
        """Wait for the estimates to settle, measure the links (:func:`measure_budget_links`: round
        trip, position age, reported accuracy), fix δ (:func:`mission_budget`), validate the
        inflated scenario with the vehicles' positions, rebuild the plan."""
        self._set_stage("preflight")
        cfg = self.cfg
        if cfg.position_accuracy_m is None:
            try:
                await wait_accuracy(self.pilots, cfg.max_position_accuracy_m,
                                    cfg.ready_timeout_s, on_wait=self.event)
            except PilotError as exc:
                raise PreflightError(f"preflight failed, nothing armed: {exc}") from None
        measured, problems = await measure_budget_links(
            self.pilots, self.mission, on_wait=lambda text: self.event(text, level="warning"))
        self.measured = measured
        self.measured_latency_s = measured.latency_s
        if problems:
            raise PreflightError("preflight failed, nothing armed: " + self._listed(problems))
        self.budget = self._make_budget(measured)
        flown = self.budget.inflate(self.physical)
        sc = self.mission.scenario
        self.monitor = self.violations.monitor = SafetyMonitor.for_run(
            sc.tube, sc.obstacles, self.physical, flown)  # pairs searched within the flown radii
        acc = (f"worst reported position accuracy σ = {measured.accuracy_m:.2f} m"
               if math.isfinite(measured.accuracy_m) else "no accuracy reported")
        self.event(f"safety budget: {self.budget.describe(self.physical)} (measured: position "
                   f"age p95 {measured.position_age_s * 1000:.1f} ms + setpoint delay "
                   f"{measured.setpoint_delay_s * 1000:.1f} ms; {acc})")
        if self.truth:
            await self._request_truth()
        positions = np.array([p.xy for p in self.pilots])
        part, problems = preflight_report(self.mission, flown, positions, self.names)
        for i, p in enumerate(self.pilots):
            slot = self.mission.slots[i]
            off = float(np.hypot(*(p.xy - slot)))
            if off > 1.0:
                self.event(f"at ({p.xy[0]:.2f}, {p.xy[1]:.2f}), {off:.2f} m from its slot "
                           f"({slot[0]:.2f}, {slot[1]:.2f})", vehicle_id=i, level="warning")
            prob = p.check_altitude_margin(MIN_CLIMB_M)
            if prob:
                problems.append(prob)
        if problems or part is None:
            raise PreflightError(
                f"preflight failed, nothing armed ({len(problems)} problem"
                f"{'s' if len(problems) != 1 else ''}; {acc} → safety budget "
                f"{self.budget.describe(self.physical)}): " + self._listed(problems))
        self.plan = FlightPlan.build(self.mission.scenario.tube, self.mission.scenario.obstacles,
                                     flown, part=part)
        problems = self._lookahead_problems(positions, "on the ground")
        if problems:
            raise PreflightError("preflight failed, nothing armed: " + self._listed(problems))
        for p in self.pilots:
            p.agent.root_plan = p.agent.plan = self.plan
        self.recorder.log_scene(self.mission.scenario, self.plan.partition,
                                mission=self.mission.config, meta={
            "kind": "fleet", "rate_hz": cfg.rate_hz, "backend": self.backend,
            "safety_budget": self.budget.as_dict(), "r_s_flown": flown.r_s,
            "r_a_flown": flown.r_a, "endpoints": [p.link.endpoint.url for p in self.pilots],
            "fence": self.fence})

    def _lookahead_problems(self, positions: np.ndarray, where: str) -> list[str]:
        """Vehicles that the apex look-ahead would start inside a triangle side's barrier."""
        out = []
        for i, k, d in self.plan.lookahead_conflicts(positions):
            out.append(f"{self.names[i]} at ({positions[i, 0]:.2f}, {positions[i, 1]:.2f}) is "
                       f"in the look-ahead zone of an apex: it would fly "
                       f"{self.plan.partition.sub_tubes[k].name} with {d:.2f} m to its legs ≤ "
                       f"r_s' = {self.plan.flown.r_s:.2f} m ({where}; move the slot upstream "
                       f"or the obstacle downstream)")
        return out

    async def _request_truth(self) -> None:
        """Ask every vehicle for its SITL ground truth (``--truth``); refusals are errors."""
        problems = await self._gather_named(
            "ground truth", [p.link.request_truth(TRUTH_RATE_HZ) for p in self.pilots])
        if problems:
            raise PreflightError(f"--truth: {len(problems)} vehicle(s) do not send their "
                                 f"ground truth (HIL_STATE_QUATERNION; PX4 SITL and the mock "
                                 f"do, real vehicles do not): " + self._listed(problems))
        self.event(f"ground truth (HIL_STATE_QUATERNION) requested at {TRUTH_RATE_HZ:g} Hz")

    async def _audit_params(self) -> None:
        """The PX4 parameter audit on connect (:func:`~vtube_fleet.fleet.onboard.audit_fleet`):
        hard mismatches refuse to arm with the numbers, soft ones warn; ``fix_params`` sets
        them (the old values are restored by :meth:`_shutdown`)."""
        from vtube_fleet.fleet.onboard import audit_fleet

        res = await audit_fleet([p.link for p in self.pilots], self.mission, fix=self.fix_params)
        self._param_restore = res.changed
        self.onboard["px4_params"] = res.values
        self.onboard["params_fixed"] = {self.names[i]: old for i, old in enumerate(res.changed)
                                        if old}
        if res.unsupported:
            self.event(f"PX4 parameter audit skipped: the {self.backend} backend cannot read "
                       f"PX4 parameters (use --backend mavlink)", level="warning")
        for w in res.warnings:  # what --fix-params set is routine (info), the rest warns
            self.event(w, level="info" if "; --fix-params set " in w else "warning")
        if res.problems:
            raise PreflightError("preflight failed, nothing armed: PX4 parameters: "
                                 + self._listed(res.problems)
                                 + " (vtube-fleet run --fix-params sets them for the flight)")
        if not res.unsupported:
            self.event(f"PX4 parameters checked on {len(self.pilots)} vehicles"
                       + (" (--fix-params)" if self.fix_params else ""))

    async def _install_fences(self) -> None:
        """The tube as every vehicle's geofence (GF_ACTION, upload, read back, compare);
        a vehicle that refuses it keeps the fleet on the ground."""
        from vtube_fleet.fleet.onboard import (
            GF_ACTION_VALUES,
            NO_FENCE_WARNING,
            fence_geometry,
            fence_items,
            gather_bounded,
            install_fence,
        )
        from vtube_fleet.link.base import LinkUnsupported

        if not self.fence:
            self.onboard["fence"] = "off"
            self.event(NO_FENCE_WARNING, level="warning")  # a safety layer turned off
            return
        geom = fence_geometry(self.mission)
        positions = np.array([p.xy for p in self.pilots])
        problems = geom.problems(positions, self.names)
        if problems:
            raise PreflightError("preflight failed, nothing armed: the fence would be breached "
                                 "at once: " + self._listed(problems))
        items = fence_items(self.mission, geom)
        action = self.cfg.fence_action
        results = await gather_bounded(
            [install_fence(p.link, items, GF_ACTION_VALUES[action]) for p in self.pilots])
        if any(isinstance(r, LinkUnsupported) for r in results):
            self.onboard["fence"] = "unsupported"
            self.event(f"fence NOT uploaded: the {self.backend} backend cannot upload PX4 "
                       f"fences (use --backend mavlink, or --no-fence to silence this)",
                       level="warning")
            return
        problems = await self._gather_named("fence", [_raise(r) for r in results])
        if problems:
            raise PreflightError(f"preflight failed, nothing armed: {len(problems)} of "
                                 f"{len(self.pilots)} vehicles refused the fence: "
                                 + self._listed(problems))
        self.onboard.update(fence="uploaded", fence_items=len(items), gf_action=action)
        self.event(f"fence on {len(self.pilots)} vehicles: {len(geom.polygon)}-vertex polygon "
                   f"(legs + {geom.widen_m:.2f} m, {geom.back_m:.2f} m behind the start, "
                   f"{geom.exit_m:.2f} m past the finish), {geom.circle_radii.size} exclusion "
                   f"circle(s); GF_ACTION = {GF_ACTION_VALUES[action]} ({action})")

    async def _restore_params(self) -> None:
        """Set back what ``fix_params`` changed (every exit path: called by _shutdown)."""
        if not any(self._param_restore):
            return
        from vtube_fleet.fleet.onboard import restore_params

        fails = await restore_params([p.link for p in self.pilots], self._param_restore)
        for line in fails:
            self.event(line, level="error")
        if not fails:
            self.event("--fix-params: the PX4 parameters are restored")
        self._param_restore = []

    async def _check_loop(self) -> None:
        """Before arming: :func:`~vtube_fleet.fleet.budget.loop_problem` over the last
        LOOP_CHECK_S of clock time (at least LOOP_MIN_S: waits for it); a failure is judged
        once more on the next LOOP_CHECK_S (one stall, e.g. a GC pause, is not a slow loop),
        and a second one refuses to arm."""
        loop = asyncio.get_running_loop()
        started = self.tick_starts_s[0] if self.tick_starts_s else loop.time()
        if (wait := started + LOOP_MIN_S - loop.time()) > 0:
            await asyncio.sleep(wait)  # the clock must have run LOOP_MIN_S to be judged

        def judged() -> str | None:
            now = loop.time()
            return loop_problem(self.tick_starts_s, self.tick_lateness, self.tick_durations,
                                self.cfg.period_s, len(self.pilots), now_s=now,
                                window_s=min(LOOP_CHECK_S, now - started))

        if (problem := judged()) is None:
            return
        self.event(f"{problem}; judging the next {LOOP_CHECK_S:g} s once more", level="warning")
        await asyncio.sleep(LOOP_CHECK_S)  # a fresh window of ticks, not a synchronisation
        if (problem := judged()) is not None:
            raise PreflightError(f"preflight failed, nothing armed: {problem}")

    async def _takeoff(self) -> None:
        await self._check_loop()
        self._set_stage("takeoff")
        problems = await self._gather_named("take-off",
                                            [p.arm_and_climb() for p in self.pilots])
        if problems:
            raise MissionAborted(f"take-off failed for {len(problems)} of {len(self.pilots)} "
                                 f"vehicles: " + self._listed(problems))
        positions = np.array([p.xy for p in self.pilots])
        _, problems = preflight_report(self.mission, self.plan.flown, positions, self.names,
                                       where=f"at {self.cfg.altitude_m:g} m")
        problems += self._lookahead_problems(positions, f"at {self.cfg.altitude_m:g} m")
        if problems:
            raise MissionAborted("Assumption 1 broken at altitude: " + self._listed(problems))

    async def _fly_tube(self) -> None:
        self._set_stage("tube")
        self.tube_start_s = self.t_s()
        for p in self.pilots:
            p.enter_tube()
        deadline = asyncio.get_running_loop().time() + self.cfg.mission_timeout_s
        while True:
            if self._abort_reason is not None:
                raise MissionAborted(self._abort_reason)
            if not any(p.phase == Phase.IN_TUBE for p in self.pilots):
                return
            self._progress.clear()
            remaining = deadline - asyncio.get_running_loop().time()
            if remaining <= 0:
                left = [p.name for p in self.pilots if p.phase == Phase.IN_TUBE]
                raise MissionAborted(f"mission_timeout_s = {self.cfg.mission_timeout_s:g} s "
                                     f"reached with {len(left)} vehicle(s) still in the tube: "
                                     + ", ".join(left))
            try:
                async with asyncio.timeout(min(remaining, 1.0)):
                    await self._progress.wait()
            except TimeoutError:
                pass

    async def _finish(self, action: str) -> None:
        """Hold or land every airborne vehicle; wait for touch-down when landing."""
        self._set_stage("landing" if action == "land" else "holding")
        if action == "hold":
            await self._gather_named("hold", [p.hold() for p in self.pilots])
            await self._wait_landed()  # those that landed after exiting (after_exit = "land")
            return
        await self._gather_named("land", [p.land() for p in self.pilots])
        await self._wait_landed()

    async def _wait_landed(self) -> None:
        cfg = self.cfg
        waiting = [p for p in self.pilots if p.phase == Phase.LANDING]
        if not waiting:
            return
        try:
            async with asyncio.timeout(cfg.land_timeout_s):
                await asyncio.gather(*(p.landed.wait() for p in waiting))
        except TimeoutError:
            left = [p.name for p in waiting if p.phase == Phase.LANDING]
            self.not_landed = left
            self.event(f"{len(left)} vehicle(s) not on the ground after land_timeout_s = "
                       f"{cfg.land_timeout_s:g} s: {', '.join(left)}", level="warning")
            return
        self.event("all vehicles on the ground")

    async def _emergency(self, why: str) -> None:
        """Everyone holds, then lands (Ctrl-C / SIGTERM)."""
        self.event(f"{why}: every vehicle holds, then lands", level="warning")
        for p in self.pilots:
            if p.exit_time_s is None and p.phase in AIRBORNE_PHASES:
                p.reason = p.reason or f"{why}: held, then landed"
        self._set_stage("interrupted")
        await self._gather_named("hold", [p.hold() for p in self.pilots])
        await self._gather_named("land", [p.land() for p in self.pilots])
        await self._wait_landed()

    async def _mission(self) -> None:
        await self._connect()
        self._clock_task = asyncio.get_running_loop().create_task(self._clock())
        await self._ready()
        await self._audit_params()
        await self._measure_budget()
        await self._install_fences()
        self._freeze_heap()
        await self._takeoff()
        await self._fly_tube()
        lost = [p for p in self.pilots if p.phase == Phase.LOST]
        exited = sum(p.exit_time_s is not None for p in self.pilots)
        self.event(f"all vehicles out of the tube: {exited} exited, {len(lost)} lost")
        await self._finish(self.cfg.on_complete)

    def _freeze_heap(self) -> None:
        """Before take-off, every object the set-up made (links, pilots, plans: millions at
        1,000 vehicles) goes to the cyclic collector's permanent generation (``gc.freeze``):
        a full collection over them took ~70 ms, longer than the slack of a 50 ms tick, and
        ran a few times a minute. Reference counting still frees them; :meth:`run` gives them
        back to the collector at its end. A heap someone else froze (another supervisor in
        this process, the embedding program) is left as it is, and not given back here."""
        if not self._heap_frozen and gc.get_freeze_count() == 0:
            gc.freeze()
            self._heap_frozen = True

    # -- run -------------------------------------------------------------------------------------
    def interrupt(self, name: str) -> None:
        """Stop the mission (``name``: what asked, e.g. ``SIGINT``): vehicles hold, then land;
        the outcome is ``interrupted``. A second call stops waiting for touch-down."""
        if self._interrupted is None:
            self._interrupted = name
            self.event(f"{name} received", level="warning")
            if self._main is not None:
                self._main.cancel()
        else:
            self.event(f"second {name}: not waiting for touch-down", level="warning")
            self._abort_event.set()
            if self._main is not None:
                self._main.cancel()

    async def run(self) -> FleetResult:
        """Fly the mission; always writes ``summary.json`` (when ``out_dir`` is set)."""
        loop = asyncio.get_running_loop()
        error: BaseException | None = None
        self._checkpoint()  # from the first moment on, a summary.json exists
        try:
            self._main = loop.create_task(self._mission())
            try:
                await self._main
                self.outcome = "completed"
                n_exit = sum(p.exit_time_s is not None for p in self.pilots)
                if n_exit < len(self.pilots):
                    self.outcome = "incomplete"
                    self.reason = (f"{len(self.pilots) - n_exit} of {len(self.pilots)} vehicles "
                                   f"did not exit: " + ", ".join(
                                       f"{p.name} {p.phase.value}"
                                       + (f" ({p.reason})" if p.reason else "")
                                       for p in self.pilots if p.exit_time_s is None))
                elif self.not_landed:
                    self.outcome = "incomplete"
                    self.reason = (f"{len(self.not_landed)} vehicle(s) still airborne after "
                                   f"land_timeout_s = {self.cfg.land_timeout_s:g} s: "
                                   + ", ".join(self.not_landed))
            except asyncio.CancelledError:
                if self._interrupted is None:
                    raise
                self.outcome = "interrupted"
                self.reason = f"{self._interrupted}: held, then landed"
                self._main = loop.create_task(self._emergency(self._interrupted))
                try:
                    await self._main
                except asyncio.CancelledError:
                    pass
            except MissionAborted as exc:
                self.outcome = "aborted"
                self.reason = str(exc)
                error = exc
                await self._after_abort(exc)
            except UserError as exc:
                self.outcome = "failed"
                self.reason = str(exc)
                error = exc
                await self._after_abort(exc)
        finally:
            if self._heap_frozen:
                gc.unfreeze()
                self._heap_frozen = False
            self._judge()
            summary, path = await self._shutdown()
        if error is not None or self.outcome == "unsafe":
            self.event(f"{self.outcome}: {self.reason}", level="error")
        return FleetResult(self.outcome, self.reason, summary, path)

    def _judge(self) -> None:
        """The verdict (:func:`vtube_fleet.core.metrics.verdict`, the one place that decides):
        a run whose telemetry — or ground truth, with ``truth`` — broke a limit in the tube
        is ``unsafe`` whatever else happened; the reason keeps what happened too."""
        v = verdict(self._summary_core(), streams=("", "_truth") if self.truth else ("",))
        if v.safe:
            return
        before = f"{self.outcome}" + (f": {self.reason}" if self.reason else "")
        self.outcome = "unsafe"
        self.reason = f"{v.summary_line} (the mission itself ended {before})"

    async def _after_abort(self, exc: BaseException) -> None:
        """After an abort: in-tube vehicles already hold; vehicles still climbing or hovering
        over their slots (take-off phase) land; a partition failure leaves the others holding.
        """
        if self._abort_reason is None:
            self.request_abort(str(exc))
        try:
            climbing = [p for p in self.pilots if p.phase in (Phase.ARMING, Phase.TAKEOFF)]
            if climbing:
                await asyncio.gather(*(p.land() for p in climbing), return_exceptions=True)
                await self._wait_landed()
            holding = [p for p in self.pilots if p.phase == Phase.HOLDING]
            if holding:
                await asyncio.gather(*(p.hold() for p in holding), return_exceptions=True)
        except asyncio.CancelledError:
            pass

    def _checkpoint(self) -> None:
        """The summary so far, written atomically (``complete: false``): a run killed without
        a chance to clean up (SIGKILL, power loss) still leaves its last summary."""
        if self.out_dir is None:
            return
        try:
            summary = self.summary()
        except Exception as exc:  # noqa: BLE001 - a checkpoint never stops the flight
            log.warning("cannot build the interim summary: %s", exc)
            return
        write_interim_summary(self.out_dir, summary, f"the run was still in flight (stage "
                                                     f"{self.stage}, {self.t_s():.1f} s)")

    async def _shutdown(self) -> tuple[dict[str, Any], Path | None]:
        self._clock_stop.set()
        if self._clock_task is not None:
            try:
                await self._clock_task
            except BaseException as exc:  # noqa: BLE001 - report, never lose the summary
                log.warning("control clock ended with %r", exc)
        for p in self.pilots:
            for t in list(p._tasks):
                t.cancel()
        await self._restore_params()
        summary = self.summary()
        summary["complete"] = True
        path = None
        self.recorder.log_summary(summary)
        if self.out_dir is not None:
            try:
                path = write_summary(self.out_dir, summary)
            except (OSError, ValueError) as exc:
                log.error("cannot write summary.json in %s: %s", self.out_dir, exc)
                path = None
        self.recorder.close()
        await asyncio.gather(*(p.link.close() for p in self.pilots), return_exceptions=True)
        if self.view is not None:
            self.view.close()
        return summary, path

    # -- the summary -------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        cfg = self.cfg
        dur = np.asarray(self.tick_durations)
        on_time = on_time_share(self.tick_lateness, cfg.period_s)
        flown = self.plan.flown
        vehicles = []
        for p in self.pilots:
            vehicles.append({
                "id": p.vehicle_id, "endpoint": p.link.endpoint.url, "phase": p.phase.value,
                "exit_s": finite_or_none(p.exit_time_s), "reason": p.reason,
                "last_position": None if not p.has_position() else [
                    round(float(p.xy[0]), 3), round(float(p.xy[1]), 3)],
                "setpoints_sent": p.setpoints_sent,
            })
        last_exit = [p.exit_time_s for p in self.pilots if p.exit_time_s is not None]
        extra: dict[str, Any] = {
            "kind": "fleet",
            "source": self.mission.source,
            "backend": self.backend,
            "outcome": self.outcome,
            "reason": self.reason,
            "onboard": dict(self.onboard),  # the fence and the PX4 parameter audit
            "mavlink_signing": self._signing_summary(),
            "vehicles": len(self.pilots),
            "lost": [p.vehicle_id for p in self.pilots if p.phase == Phase.LOST],
            "r_s": self.physical.r_s,
            "r_a": self.physical.r_a,
            "r_s_flown": flown.r_s,
            "r_a_flown": flown.r_a,
            "apex_distances_m": [  # h_k of the configured obstacles flown ("auto": core/plan.py)
                next((t.h for t in self.plan.partition.triangles if t.obstacle == i), None)
                for i in range(len(self.mission.scenario.obstacles))],
            "pair_limit_m": self.monitor.limits.pair_m,
            "safety_budget": self.budget.as_dict(),
            "min_pair_distance_airborne_m": finite_or_none(self.min_pair_airborne),
            "min_commanded_speed_m_s": finite_or_none(self.cmd_speed[0]),
            "max_commanded_speed_m_s": finite_or_none(self.cmd_speed[1]),
            "min_measured_speed_m_s": finite_or_none(self.measured_speed[0]),
            "max_measured_speed_m_s": finite_or_none(self.measured_speed[1]),
            "settle_s": self.settle_s,
            "min_measured_speed_settled_m_s": finite_or_none(self.settled_speed[0]),
            "max_measured_speed_settled_m_s": finite_or_none(self.settled_speed[1]),
            "rate_hz": cfg.rate_hz,
            "achieved_rate_hz": finite_or_none(self._achieved_rate()),
            "ticks": int(dur.size),
            "ticks_on_time_share": on_time,
            "tick_duration_p50_s": finite_or_none(percentile_or_none(dur, 50)),
            "tick_duration_p99_s": finite_or_none(percentile_or_none(dur, 99)),
            "tick_duration_max_s": finite_or_none(float(dur.max()) if dur.size else math.nan),
            "link_latency_p50_s": finite_or_none(percentile_or_none(self.latencies, 50)),
            "link_latency_p99_s": finite_or_none(percentile_or_none(self.latencies, 99)),
            "position_age_p50_s": finite_or_none(percentile_or_none(self.sample_ages, 50)),
            "position_age_p99_s": finite_or_none(percentile_or_none(self.sample_ages, 99)),
            "tube_start_s": finite_or_none(self.tube_start_s),
            "flight_time_s": (finite_or_none(max(last_exit) - self.tube_start_s)
                              if last_exit and self.tube_start_s is not None else None),
            "partitions": self.partitions,
            "wall_s": round(self.t_s(), 3),
            "vehicle_states": vehicles,
            "events": self.events[-200:],
        }
        extra["first_violation"] = self.violations.first
        if self.truth:
            extra["truth"] = True
            extra["min_pair_distance_airborne_m_truth"] = finite_or_none(
                self.min_pair_airborne_truth)
            # (→ truth_min_pair_distance_airborne_m, like every *_truth key)
        if self.measured is not None:
            extra["measured"] = {
                "position_age_p95_s": self.measured.position_age_s,
                "setpoint_delay_s": self.measured.setpoint_delay_s,
                "accuracy_m": finite_or_none(self.measured.accuracy_m),
                "accuracies_m": [finite_or_none(a) for a in self.measured.accuracies_m]}
        comp = [p.compensator for p in self.pilots if p.compensator is not None]
        if comp:
            res = self.residuals.residuals().tolist()
            extra["estimate_compensation"] = {
                "max_correction_m_s": max(c.max_m_s for c in comp),
                "clipped": sum(c.clipped for c in comp),
                "residual_p50_m_s": finite_or_none(percentile_or_none(res, 50)),
                "residual_p99_m_s": finite_or_none(percentile_or_none(res, 99)),
                "residual_max_m_s": finite_or_none(max(res) if res else math.nan),
                "budgeted_m_s": self.budget.disturbance_m_s}
        try:
            out = self.acc.summary(**extra)
        except Exception as exc:  # never lose the summary
            log.error("summary accumulator failed: %s", exc)
            return extra
        return truth_keys(out)

    def _signing_summary(self) -> dict[str, Any]:
        """Whether the links signed (docs/security.md) and what they refused, by reason."""
        refused: dict[str, int] = {}
        for p in self.pilots:
            for why, n in getattr(p.link, "signing_refused", {}).items():
                refused[why] = refused.get(why, 0) + int(n)
        return {"enabled": bool(self.cfg.signing_key_file), "refused": refused}

    def _summary_core(self) -> dict[str, Any]:
        """The accumulator's figures only (what the verdict reads)."""
        try:
            return self.acc.summary(first_violation=self.violations.first)
        except Exception:  # pragma: no cover - never block the verdict
            return {"violations": 0}
