"""The fleet supervisor: one asyncio process flies every vehicle of a mission.

It orchestrates; each job has its own module:

* the **preflight** stages (:mod:`vtube_fleet.fleet.preflight`): connect, ready, the PX4
  parameter audit, the safety budget (δ from the measured link latency, position age and
  reported accuracy; the inflated scenario validated with the vehicles' actual positions), the
  fence, the control loop's health — any failure and nothing arms;
* the **control tick** (:mod:`vtube_fleet.fleet.tick`), run by a
  :class:`~vtube_fleet.fleet.tick.ControlClock` at ``rate_hz`` over the fleet's
  :class:`~vtube_fleet.fleet.table.FleetTable` from "ready" to the end;
* the **in-flight measurement** (:mod:`vtube_fleet.fleet.measure`) after every tick;
* the **summary** (:mod:`vtube_fleet.fleet.summary`), written on every exit path.

Procedure (:meth:`Supervisor.run`): preflight; **take-off**: all vehicles together (each over
its own slot, which Assumption 1 keeps 2 r_s' apart), Assumption 1 checked again at altitude;
**tube**: every vehicle becomes IN_TUBE on the same tick; **end**: when every vehicle has exited
(or is lost), ``on_complete`` (land / hold).

The mission flies its route (a ``[tube]`` is a route of one segment): each vehicle hands over
from segment to segment (the table's ``segment``), exits at the route's last finishing line.

Faults: a LOST vehicle (the tick's fault rules) becomes a static obstacle of radius r_s +
``lost_obstacle_margin_m`` at its last position and the segments it meets are re-partitioned
online; if no valid partition exists the others hold (OFFBOARD → Hold) and the mission aborts
(:class:`MissionAborted`, exit code 3). SIGINT / SIGTERM: every vehicle holds, then lands; the
summary and the recording are complete (exit code 130).
"""

from __future__ import annotations

import asyncio
import gc
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
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
from vtube_fleet.config.mission import Mission
from vtube_fleet.core.metrics import SafetyMonitor, verdict
from vtube_fleet.core.partition import PartitionError
from vtube_fleet.errors import UserError, bug_text
from vtube_fleet.fleet.budget import (
    LinkMeasurement,
    ResponseModel,
    SafetyBudget,
    achieved_rate_hz,
    mission_budget,
)
from vtube_fleet.fleet.flight_plan import FlightPlan, exit_queue
from vtube_fleet.fleet.measure import FlightMeasurement, TickTrace
from vtube_fleet.fleet.neighbour_view import NeighbourView
from vtube_fleet.fleet.pilot import VehiclePilot
from vtube_fleet.fleet.preflight import (
    FleetError,
    Preflight,
    PreflightError,
    measure_budget_links,
    preflight_report,
    wait_accuracy,
)
from vtube_fleet.fleet.response_check import ResponseProbe, ResponseReport, run_response_check
from vtube_fleet.fleet.summary import fleet_summary, telemetry_summary
from vtube_fleet.fleet.table import PHASE_CODE, FleetTable
from vtube_fleet.fleet.tick import ControlClock, Tick, TickResult
from vtube_fleet.fleet.view import FleetStatus, FleetView
from vtube_fleet.link.base import VehicleLink
from vtube_fleet.outcome import EXIT_INCOMPLETE, exit_code
from vtube_fleet.state import AIRBORNE_PHASES, COUNTED_AIRBORNE_PHASES, TUBE_PHASES, Phase

__all__ = [
    "FleetError",
    "FleetResult",
    "MissionAborted",
    "PreflightError",
    "Supervisor",
    "TickTrace",
]

log = logging.getLogger(__name__)

#: Minimum height of the mission altitude above every vehicle before take-off.
MIN_CLIMB_M = 1.0


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
        tick_hook: Callable[[int, Supervisor], Any] | None = None,
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
        self.backend = backend
        if recorder is None:
            from vtube_fleet.recording.api import NullRecorder

            recorder = NullRecorder()
        self.recorder = recorder
        self.view = view
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.tick_hook = tick_hook
        self.truth = truth
        self.fence = fence  # upload the tube as PX4's geofence before arming (fleet/onboard.py)
        self.fix_params = fix_params  # --fix-params: set the audited PX4 parameters, restore

        sc = mission.scenario
        self.physical = sc.controller  # as configured: the PHYSICAL r_s, r_a (flown: plan.flown)
        # the plan before the budget is measured: latency 0 (replaced in _measure_budget())
        self.measured: LinkMeasurement | None = None
        self.budget: SafetyBudget = mission_budget(mission, None)
        flown = self.budget.inflate(self.physical)
        try:
            plan = FlightPlan.for_mission(mission, flown)
        except PartitionError as exc:
            raise PreflightError(
                f"{mission.source}: with the safety budget {self.budget.describe(self.physical)}"
                f" the {'route' if sc.is_route else 'tube'} cannot be partitioned: {exc}"
            ) from None
        #: the fleet's tick state, vehicle i in row i (fleet/table.py)
        self.table = FleetTable(range(len(links)), mission, self.frame)
        self.pilots = [VehiclePilot(link, self.table, i, mission, frame=self.frame,
                                    on_event=self._on_pilot_event)
                       for i, link in enumerate(links)]
        self.names = [p.name for p in self.pilots]
        self.t0 = time.monotonic()
        self._replan_worker = ThreadPoolExecutor(1, thread_name_prefix="replan")
        self.ticker = Tick(self.table, self.pilots, mission, plan, frame=self.frame,
                           on_exit=self._on_exit, on_replan=self._on_replan,
                           on_replan_failed=self._on_replan_failed, t0_s=self.t0,
                           replan_worker=self._replan_worker)
        self.clock = ControlClock(self.cfg.period_s, self._step, on_stall=self._on_stall,
                                  guard=self._tick_failed, after=self._after_tick)
        #: summary "onboard": the fence and the PX4 parameter audit (fleet/preflight.py)
        self.onboard: dict[str, Any] = {"fence": None, "fence_items": 0, "gf_action": None,
                                        "px4_params": [], "params_fixed": {}}
        self.preflight = Preflight(self.pilots, mission, event=self.event, backend=backend,
                                   onboard=self.onboard)
        # limits of the PHYSICAL r_s; pairs searched within r_s' + r_a' + 1 m
        self.measurement = FlightMeasurement(
            mission, self.table, [p.link for p in self.pilots],
            SafetyMonitor.for_corridor(sc.corridor, self.physical, flown),
            frame=self.frame, recorder=recorder, truth=truth, keep_trace=keep_trace,
            warn=lambda text: self.event(text, level="warning"))
        self.tube_start_s: float | None = None
        self.stage = "connecting"
        self.events: list[dict[str, Any]] = []
        self.partitions = 1
        self.not_landed: list[str] = []
        #: with ``on_abort = "hold"``: the vehicles left holding in the air for an operator
        self.held_for_operator: list[str] = []
        #: lost vehicles silent at the end: nothing can be sent to them (PX4's failsafe decides)
        self.unreachable: list[str] = []
        #: after a second interrupt: the vehicles still in the air when the run stopped waiting
        self.not_waited: list[str] = []
        self._landing_all = False  # _bring_down runs (a first interrupt does not cancel it)
        self.outcome = "failed"
        self.reason = ""
        self._abort_reason: str | None = None
        self._abort_event = asyncio.Event()
        self._progress = asyncio.Event()
        self._interrupted: str | None = None
        self._clock_task: asyncio.Task[None] | None = None
        self._clock_restarted = False
        self._clock_stop = asyncio.Event()
        self._main: asyncio.Task[None] | None = None
        self._pacer = SummaryPacer(SUMMARY_EVERY_S)
        self._heap_frozen = False  # _freeze_heap
        #: the response check's report (fleet/response_check.py); None: not run
        self.response: ResponseReport | None = None
        self._probe: ResponseProbe | None = None

    # -- what the others read --------------------------------------------------------------------
    @property
    def plan(self) -> FlightPlan:
        """The plan flown now (re-planned around lost vehicles by the tick)."""
        return self.ticker.plan

    @property
    def monitor(self) -> SafetyMonitor:
        return self.measurement.monitor

    @property
    def trace(self) -> list[TickTrace]:
        return self.measurement.trace

    @property
    def min_pair_airborne(self) -> float:
        return self.measurement.min_pair_airborne

    @property
    def tick(self) -> int:
        """Ticks run so far."""
        return self.clock.ticks

    @property
    def tick_durations(self) -> list[float]:
        return self.clock.durations_s

    @property
    def tick_lateness(self) -> list[float]:
        return self.clock.lateness_s

    @property
    def tick_starts_s(self) -> list[float]:
        return self.clock.starts_s

    def t_s(self) -> float:
        return time.monotonic() - self.t0

    # -- events ----------------------------------------------------------------------------------
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

    def _on_pilot_event(self, text: str, vehicle_id: int | None, level: str) -> None:
        self.event(text, vehicle_id=vehicle_id, level=level)

    def _set_stage(self, stage: str) -> None:
        self.stage = stage
        self.event(f"stage: {stage}")

    # -- the control clock's tick ----------------------------------------------------------------
    def _step(self, now_mono: float, now_wall: float, listening_since: float | None
              ) -> TickResult:
        """One tick (:class:`~vtube_fleet.fleet.tick.Tick`), then its measurement."""
        result = self.ticker(now_mono, now_wall, listening_since)
        if self._probe is not None:
            self._probe.on_tick(now_mono)
        self._after_replan_check(now_mono, result)
        self._measure(result)
        return result

    def _tick(self) -> TickResult:
        """One tick now, as the clock runs it (benchmarks, tests)."""
        return self._step(time.monotonic(), time.time(), self.clock.listening_since)

    def _measure(self, result: TickResult) -> None:
        durations = self.clock.durations_s
        self.measurement.measure(
            result, tick=self.clock.ticks, tube_start_s=self.tube_start_s,
            flown_r_s=self.plan.flown.r_s, budget=self.budget,
            tick_gap_s=self.clock.take_recent_gap(),
            tick_duration_s=durations[-1] if durations else None,
            note=self._note_violation, request_hold=self.request_abort)
        if self.view is not None:
            self.view.update(self.status())

    def _on_stall(self, gap_s: float) -> None:
        self.event(f"control loop stalled for {gap_s:.2f} s", level="warning")

    def _clock_ended(self, task: asyncio.Task[None]) -> None:
        """The control clock ended before the run stopped it (a bug outside the guarded tick):
        the mission aborts at once and every vehicle is brought down; the clock is started
        again once, since the ticks are what see the vehicles touch down."""
        if task.cancelled() or self._clock_stop.is_set():
            return
        exc = task.exception()
        if exc is not None:
            log.error("the control loop ended", exc_info=exc)
        self.request_abort("the control loop ended" + (
            f": {bug_text(exc)}" if exc is not None else ""))
        if not self._clock_restarted:
            self._clock_restarted = True
            self._clock_task = asyncio.get_running_loop().create_task(
                self.clock.run(self._clock_stop))
            self._clock_task.add_done_callback(self._clock_ended)

    def _tick_failed(self, exc: Exception) -> None:
        log.exception("control tick failed", exc_info=exc)
        self.request_abort(f"control tick failed: {type(exc).__name__}: {exc}")

    def _after_tick(self) -> Any:
        """After each tick: the test hook (fault injection), the interim summary when due."""
        pending = None
        if self.tick_hook is not None:
            pending = self.tick_hook(self.clock.ticks, self)
        loop = asyncio.get_running_loop()
        if self._pacer.due(loop.time()):  # in the slack after a tick, not before one
            t_c = loop.time()
            self._checkpoint()
            self._pacer.written(t_c, loop.time())
        return pending

    def _note_violation(self, suffix: str, source: str, e: dict[str, Any]) -> None:
        """The first tick that breaks a limit (telemetry or truth): say what, who, how much."""
        who = " and ".join(self.names[v] for v in e["vehicles"])
        self.event(f"LIMIT BROKEN ({source}): {e['condition']} {e['value']:.3f} m, limit "
                   f"{e['limit']:.3f} m: {who}", level="error")

    # -- the tick's decisions that are the supervisor's ------------------------------------------
    def _on_exit(self, rows: np.ndarray, t: float) -> None:
        ids = self.table.ids[rows].tolist()
        self.measurement.acc.add_exits(t, ids)
        self.recorder.log_exits(t, self.clock.ticks, ids)

    def _on_replan(self, plan: FlightPlan, t: float) -> None:
        self.partitions += 1
        multi = plan.route.S > 1
        where = ", ".join(f"({o.center[0]:.2f}, {o.center[1]:.2f}) r={o.radius:.2f}"
                          + (f" in {'/'.join(plan.segments_of_lost(i))}" if multi else "")
                          for i, o in enumerate(plan.lost))
        self.event(f"re-partitioned around lost or stopped vehicle(s): {plan.route.K} sub-tubes"
                   + (f" in {plan.route.S} segments" if multi else "")
                   + f"; lost obstacles {where or 'none inside the tube'}", level="warning")
        self.recorder.log_partition(plan.route, t)

    def _on_replan_failed(self, exc: PartitionError, view: NeighbourView) -> None:
        if self._abort_reason is not None:
            return
        dead = self._unreachable(time.monotonic())
        if dead is not None:
            self.request_abort(dead)
            return
        ids = [int(i) for i in view.lost_ids]
        why = "; ".join(f"vehicle {p.vehicle_id}: {p.reason}" for p in self.pilots
                        if p.vehicle_id in ids and p.reason)
        self.request_abort(
            f"cannot re-partition the {'route' if self.plan.route.S > 1 else 'tube'} around "
            f"the lost or stopped vehicle(s) "
            f"{', '.join(map(str, ids))} (each an obstacle of radius r_s + "
            f"lost_obstacle_margin_m where it was last heard or stopped"
            f"{'; ' + why if why else ''}): {exc}")

    def _after_replan_check(self, now_mono: float, result: TickResult) -> None:
        """Link loss, told apart from a lost vehicle, every tick with a lost vehicle."""
        if self._abort_reason is None and result.view is not None and result.view.lost_ids.size:
            dead = self._unreachable(now_mono)
            if dead is not None:
                self.request_abort(dead)

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
        ls = self.clock.listening_since
        since = -math.inf if ls is None else ls
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

    def request_abort(self, reason: str) -> None:
        """Abort the mission: vehicles in the tube hold now; the main procedure ends."""
        if self._abort_reason is not None:
            return
        self._abort_reason = reason
        self.event(f"ABORT: {reason}", level="error")
        for p in self.pilots:
            if p.phase in TUBE_PHASES | {Phase.EXITED, Phase.ARMING, Phase.TAKEOFF}:
                p.reason = p.reason or f"mission aborted: {reason}"
            if p.phase in TUBE_PHASES | {Phase.EXITED}:
                p.begin_hold("mission aborted")
        self._abort_event.set()
        self._progress.set()

    # -- the live status ---------------------------------------------------------------------------
    def status(self) -> FleetStatus:
        st = FleetStatus(t_s=self.t_s(), stage=self.stage, vehicles=len(self.pilots))
        clock = self.clock
        return self.measurement.status(
            st, self.pilots, rows=self.view is not None and self.view.wants_rows(),
            durations_s=clock.durations_s, lateness_s=clock.lateness_s,
            period_s=self.cfg.period_s, rate_hz=achieved_rate_hz(clock.starts_s[-40:]),
            delta_m=self.budget.delta_m, route=self.plan.route)

    # -- the procedure -------------------------------------------------------------------------
    async def _mission(self) -> None:
        pre = self.preflight
        self._set_stage("connecting")
        await pre.connect()
        self._clock_task = asyncio.get_running_loop().create_task(
            self.clock.run(self._clock_stop))
        self._clock_task.add_done_callback(self._clock_ended)
        self._set_stage("ready")
        await pre.ready()
        await pre.audit_params(self.fix_params)
        await self._measure_budget()
        await pre.install_fences(self.fence)
        self._freeze_heap()
        await self._takeoff()
        await self._fly_tube()
        lost = [p for p in self.pilots if p.phase == Phase.LOST]
        exited = sum(p.exit_time_s is not None for p in self.pilots)
        self.event(f"all vehicles out of the tube: {exited} exited, {len(lost)} lost")
        await self._finish(self.cfg.on_complete)

    async def _measure_budget(self) -> None:
        """Wait for the estimates to settle, measure the links (:func:`measure_budget_links`:
        round trip, position age, reported accuracy), fix δ (:func:`mission_budget`), validate
        the inflated scenario with the vehicles' positions, rebuild the plan."""
        self._set_stage("preflight")
        cfg = self.cfg
        pre = self.preflight
        if cfg.position_accuracy_m is None:
            try:
                await wait_accuracy(self.pilots, cfg.max_position_accuracy_m,
                                    cfg.ready_timeout_s, on_wait=self.event)
            except PreflightError as exc:
                raise PreflightError(f"preflight failed, nothing armed: {exc}") from None
        measured, problems = await measure_budget_links(
            self.pilots, self.mission, on_wait=lambda text: self.event(text, level="warning"))
        self.measured = measured
        if problems:
            raise PreflightError("preflight failed, nothing armed: " + pre.listed(problems)
                                 + await self._margin_note(measured))
        self.budget = mission_budget(self.mission, measured)
        flown = self.budget.inflate(self.physical)
        sc = self.mission.scenario
        self.measurement.rebuild(SafetyMonitor.for_corridor(sc.corridor, self.physical, flown))
        acc = (f"worst reported position accuracy σ = {measured.accuracy_m:.2f} m"
               if math.isfinite(measured.accuracy_m) else "no accuracy reported")
        self.event(f"safety budget: {self.budget.describe(self.physical)} (measured: position "
                   f"age p95 {measured.position_age_s * 1000:.1f} ms + setpoint delay "
                   f"{measured.setpoint_delay_s * 1000:.1f} ms; {acc})")
        if self.truth:
            await pre.request_truth()
        positions = np.array([p.xy for p in self.pilots])
        # the route is planned here, before the climb ("auto" apex distances: a few
        # hundred ms), in a worker thread: the control clock keeps ticking meanwhile
        route, problems = await asyncio.to_thread(preflight_report, self.mission, flown,
                                                  positions, self.names)
        for i, p in enumerate(self.pilots):
            slot = self.mission.slots[i]
            off = float(np.hypot(*(p.xy - slot)))
            if off > 1.0:
                self.event(f"at ({p.xy[0]:.2f}, {p.xy[1]:.2f}), {off:.2f} m from its slot "
                           f"({slot[0]:.2f}, {slot[1]:.2f})", vehicle_id=i, level="warning")
            prob = p.check_altitude_margin(MIN_CLIMB_M)
            if prob:
                problems.append(prob)
        if problems or route is None:
            raise PreflightError(
                f"preflight failed, nothing armed ({len(problems)} problem"
                f"{'s' if len(problems) != 1 else ''}; {acc} → safety budget "
                f"{self.budget.describe(self.physical)}): " + pre.listed(problems)
                + await self._margin_note(measured))
        plan = FlightPlan.build(sc.corridor, flown, route=route)
        self.ticker.set_plan(plan)
        self._warn_exit_room(plan)
        self.recorder.log_scene(self.mission.scenario, plan.route,
                                mission=self.mission.config, meta={
            "kind": "fleet", "rate_hz": cfg.rate_hz, "backend": self.backend,
            "safety_budget": self.budget.as_dict(), "r_s_flown": flown.r_s,
            "r_a_flown": flown.r_a, "endpoints": [p.link.endpoint.url for p in self.pilots],
            "fence": self.fence})

    def _warn_exit_room(self, plan: FlightPlan) -> None:
        """With ``after_exit = "continue"``, say so when the exit area cannot hold the fleet in
        one lane (:func:`~vtube_fleet.fleet.flight_plan.exit_queue`): after a loss that
        leaves one passage every later vehicle exits there, and a queue's tail within reach
        of the finishing line is an obstacle that can strand vehicles still in the tube."""
        if self.cfg.after_exit != "continue":
            return
        queue = len(self.pilots) - 1
        fits, need_m, stop_m = exit_queue(plan, self.cfg, self.ticker.lost_radius_m, queue)
        if fits < queue:
            self.event(f"exit room: exit_clear_m = {self.cfg.exit_clear_m:g} m holds {fits} "
                       f"exited vehicle(s) in one lane, {stop_m:.1f} m "
                       f"apart, before the queue's tail is within reach of the finishing "
                       f"line; after a loss that leaves one passage up to {queue} may queue "
                       f"there, and the tail is then an obstacle that can strand vehicles "
                       f"still in the tube: exit_clear_m = {math.ceil(need_m)} m holds them",
                       level="warning")

    async def _margin_note(self, measured: LinkMeasurement) -> str:
        """"; " and which measured figure went past the margin ``check`` prints
        (:func:`~vtube_fleet.fleet.margin.refusal_note`: dozens of validations, so in a worker
        thread; nothing is armed at this point)."""
        from vtube_fleet.fleet.margin import refusal_note

        try:
            return "; " + await asyncio.to_thread(refusal_note, self.mission, measured)
        except Exception as exc:  # noqa: BLE001 - the refusal itself must not be lost
            log.warning("cannot compute check's margin: %s", exc)
            return ""

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

    async def _takeoff(self) -> None:
        await self.preflight.check_batteries()
        await self.preflight.check_loop(self.clock)
        self._set_stage("takeoff")
        problems = await self.preflight.gather_named(
            "take-off", [p.arm_and_climb() for p in self.pilots])
        if problems:
            raise MissionAborted(f"take-off failed for {len(problems)} of {len(self.pilots)} "
                                 f"vehicles: " + self.preflight.listed(problems))
        await self._check_response()
        positions = np.array([p.xy for p in self.pilots])
        where = f"at {self.cfg.altitude_m:g} m"
        # the positions against the partition planned on the ground: nothing is planned
        # while the vehicles fly (a plan would stall the loop at the worst moment)
        _, problems = preflight_report(self.mission, self.plan.flown, positions, self.names,
                                       where=where, route=self.ticker.root.route)
        if problems:
            raise MissionAborted("Assumption 1 broken at altitude: "
                                 + self.preflight.listed(problems))

    async def _check_response(self) -> None:
        """The response check (:mod:`~vtube_fleet.fleet.response_check`): every hovering
        vehicle flies a step of the cruise speed along the first segment and back to zero; one
        that lags behind it more than the budget's model aborts the mission (every vehicle
        lands).
        Skipped, and said, when ``response_check = false`` or when the room ahead does not
        hold the fleet."""
        budget = self.budget
        step = float(self.physical.v)
        rows = np.flatnonzero(self.table.phase == PHASE_CODE[Phase.TAKEOFF])
        model = ResponseModel.of(budget, self.cfg)
        report = ResponseReport(step, model, self.table.ids[rows].tolist())
        self.response = report
        if not self.cfg.response_check or rows.size == 0:
            report.skipped = ("response_check = false in the mission"
                              if not self.cfg.response_check else "no vehicle hovers")
            self.event(report.describe(), level="warning")
            return
        u = np.asarray(self.ticker.root.route.segments[0].tube.n_c, float)
        reach = model.reach_m(step)
        ahead = np.array([p.xy for p in self.pilots]) + reach * u
        _, problems = await asyncio.to_thread(
            preflight_report, self.mission, self.plan.flown, ahead, self.names,
            where=f"{reach:.1f} m ahead", route=self.ticker.root.route)
        if problems:
            report.skipped = (f"the fleet moved {reach:.1f} m ahead (the step's reach) breaks "
                              f"the partition: " + self.preflight.listed(problems))
            self.event(report.describe(), level="warning")
            return
        self._set_stage("response check")

        def attach(probe: ResponseProbe | None) -> None:
            self._probe = probe

        await run_response_check(ResponseProbe(self.table, rows, u), report, attach,
                                 lambda: self._abort_reason is not None)
        if self._abort_reason is not None:
            raise MissionAborted(self._abort_reason)
        self.event(report.describe(), level="info" if report.skipped is None else "warning")
        if report.skipped is None and report.refused():
            raise MissionAborted(report.refusal(self.names))

    async def _fly_tube(self) -> None:
        self._set_stage("tube")
        self.tube_start_s = self.t_s()
        for p in self.pilots:
            p.enter_tube()
        deadline = asyncio.get_running_loop().time() + self.cfg.mission_timeout_s
        while True:
            if self._abort_reason is not None:
                raise MissionAborted(self._abort_reason)
            if not any(p.phase in TUBE_PHASES for p in self.pilots):
                return
            self._progress.clear()
            remaining = deadline - asyncio.get_running_loop().time()
            if remaining <= 0:
                left = [p.name for p in self.pilots if p.phase in TUBE_PHASES]
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
        gather = self.preflight.gather_named
        if action == "hold":
            await gather("hold", [p.hold() for p in self.pilots])
            await self._wait_landed()  # those that landed after exiting (after_exit = "land")
            return
        await gather("land", [p.land() for p in self.pilots])
        await self._wait_landed()
        await self._land_again()  # e.g. a lost vehicle that answers but stays in the air

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
        # only the landing ones were waited for: a lost vehicle (silent, or not answering)
        # may still be in the air, so "all vehicles" would be untrue
        lost = [p.name for p in self.pilots if p.phase == Phase.LOST
                and not _seen_down(p, cfg.lost_after_s)]
        self.event("all vehicles on the ground" if not lost else
                   f"the {len(waiting)} landing vehicle(s) on the ground; not known to be "
                   f"down: {len(lost)} lost: {', '.join(lost)}",
                   level="info" if not lost else "warning")

    async def _emergency(self, why: str) -> None:
        """Everyone holds, then lands (Ctrl-C / SIGTERM)."""
        self._set_stage("interrupted")
        await self._bring_down(why)

    async def _bring_down(self, why: str) -> None:
        """Every airborne vehicle holds (its Hold not acknowledged: LAND at once), then lands
        in place, and the run waits for touch-down (``land_timeout_s``); a vehicle whose LAND
        is not acknowledged is sent LAND again (:meth:`VehiclePilot.land`) and reported by
        name. Holding positions keep the separation the tube flight had (≥ 2 r_s' apart by the
        controller, minus PX4's braking) and a vertical descent keeps it: all land at once."""
        self._landing_all = True
        airborne = [p for p in self.pilots if p.phase in AIRBORNE_PHASES]
        self.event(f"{why}: every vehicle holds, then lands in place ({len(airborne)} airborne)"
                   if airborne else f"{why}: no vehicle is airborne", level="warning")
        for p in self.pilots:
            if p.exit_time_s is None and p.phase in AIRBORNE_PHASES:
                p.reason = p.reason or f"{why}: held, then landed"
        gather = self.preflight.gather_named
        await gather("hold", [p.hold() for p in self.pilots])
        await gather("land", [p.land() for p in self.pilots])
        await self._wait_landed()
        await self._land_again()

    async def _land_again(self) -> None:
        """After the wait for touch-down: a vehicle still in OFFBOARD and airborne, or still
        landing with its LAND unanswered, is sent LAND again until ``land_timeout_s``; the
        ones left are reported by name (:attr:`not_landed`). A second interrupt stops this."""
        cfg = self.cfg
        loop = asyncio.get_running_loop()
        deadline = loop.time() + cfg.land_timeout_s

        def heard(p: VehiclePilot) -> bool:
            last = p.link.state.last_packet_s
            return (not p.link.closed and last is not None
                    and time.monotonic() - last <= cfg.lost_after_s)

        def lost_up(p: VehiclePilot) -> bool:  # lost, still answering, in the air
            s = p.link.state
            return p.phase == Phase.LOST and s.armed is True and s.landed_state != "ON_GROUND"

        def stuck() -> list[VehiclePilot]:
            return [p for p in self.pilots if heard(p) and (
                _offboard_airborne(p) or (p.phase == Phase.LANDING and p.unanswered)
                or (lost_up(p) and p.link.state.flight_mode != "LAND"))]

        silent = [p.name for p in self.pilots if not heard(p) and p.phase == Phase.LOST
                  and p.link.state.landed_state != "ON_GROUND"]
        if silent:
            self.unreachable = silent
            self.event(f"{len(silent)} lost vehicle(s) cannot be reached (silent for more than "
                       f"lost_after_s): PX4's own failsafe decides what they do (COM_OF_LOSS_T, "
                       f"NAV_DLL_ACT): " + ", ".join(silent), level="error")
        left = stuck()
        while left and loop.time() < deadline:
            self.event(f"{len(left)} vehicle(s) still airborne in OFFBOARD or without an "
                       f"acknowledged LAND: LAND again: "
                       + ", ".join(p.name for p in left), level="warning")
            await self.preflight.gather_named("land", [p.land_command() for p in left],
                                              pilots=left)
            # PX4 reports its mode once a second (HEARTBEAT): wait for the reports of LAND
            # (what was sent; any other mode, e.g. a failsafe's POSCTL, is still "stuck" and
            # must not be answered by another LAND at once: that spammed the vehicle)
            await asyncio.gather(*(p.link.wait_until(
                lambda st: (st.flight_mode == "LAND" or st.armed is not True
                            or st.landed_state == "ON_GROUND"),
                1.5, "LAND, or on the ground") for p in left),
                return_exceptions=True)
            left = stuck()
        # the lost ones that took LAND: their touch-down, in what is left of land_timeout_s
        coming = [p for p in self.pilots if heard(p) and lost_up(p) and p not in left]
        if coming:
            await asyncio.gather(*(p.link.wait_until(
                lambda st: st.landed_state == "ON_GROUND" or st.armed is False,
                max(deadline - loop.time(), 0.0), "on the ground") for p in coming),
                return_exceptions=True)
            left += [p for p in coming if lost_up(p)]
        if left:
            names = [p.name + (f" ({p.unanswered})" if p.unanswered else
                               f" (lost, in {p.link.state.flight_mode})" if lost_up(p) else "")
                     for p in left]
            self.not_landed = sorted(set(self.not_landed) | {p.name for p in left})
            self.event(f"NOT BROUGHT DOWN: {len(left)} vehicle(s) still airborne after "
                       f"land_timeout_s = {cfg.land_timeout_s:g} s of LAND: "
                       + "; ".join(names), level="error")

    # -- run -------------------------------------------------------------------------------------
    def interrupt(self, name: str) -> None:
        """Stop the mission (``name``: what asked, e.g. ``SIGINT``): vehicles hold, then land;
        the outcome is ``interrupted``. A second call stops waiting for touch-down."""
        if self._interrupted is None:
            self._interrupted = name
            if self._landing_all:  # already bringing every vehicle down: go on
                self.event(f"{name} received: every vehicle is already being landed; a second "
                           f"{name} stops waiting for touch-down", level="warning")
                return
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
                    self._say_not_down()
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
                    await self._land_without_waiting()
                self._say_not_down()
            except Exception as exc:  # MissionAborted, UserError, or a bug of ours
                if not isinstance(exc, MissionAborted | UserError):
                    # a bug of ours: the vehicles are brought down all the same; the
                    # traceback is logged for the report
                    log.error("internal error, every vehicle is brought down", exc_info=exc)
                    exc = MissionAborted(f"internal error: {bug_text(exc)}")
                self.outcome = "aborted" if isinstance(exc, MissionAborted) else "failed"
                self.reason = str(exc)
                error = exc
                self._main = loop.create_task(self._after_abort(exc))
                try:
                    await self._main  # a second interrupt stops waiting for touch-down
                except asyncio.CancelledError:
                    await self._land_without_waiting()
                self._say_not_down()
        finally:
            if self._heap_frozen:
                gc.unfreeze()
                self._heap_frozen = False
            self._judge_telemetry()
            self._judge()
            summary, path = await self._shutdown()
        if error is not None or self.outcome == "unsafe":
            self.event(f"{self.outcome}: {self.reason}", level="error")
        return FleetResult(self.outcome, self.reason, summary, path)

    async def _land_without_waiting(self) -> None:
        """After an interrupt while landing (the bring-down cancelled wherever it was, maybe before
        any LAND went out): every vehicle still airborne is sent LAND now (a holding one once
        its Hold is answered; no wait for touch-down), and those still in the air are named
        (:attr:`not_waited`). A third interrupt stops this too."""
        name = self._interrupted or "interrupt"
        airborne = [p for p in self.pilots if p.phase in AIRBORNE_PHASES]
        self._main = asyncio.get_running_loop().create_task(self._gather_land(airborne))
        try:
            await self._main
        except asyncio.CancelledError:
            pass
        self.not_waited = [p.name for p in self.pilots if p.phase in AIRBORNE_PHASES]
        if self.not_waited:
            self.event(f"{name}: LAND sent, not waiting for the touch-down of "
                       f"{len(self.not_waited)} vehicle(s) still in the air: "
                       + ", ".join(self.not_waited), level="error")

    async def _gather_land(self, pilots: list[VehiclePilot]) -> None:
        await asyncio.gather(*(p.land() for p in pilots), return_exceptions=True)

    def _judge_telemetry(self) -> None:
        """A run whose vehicles' telemetry the links stopped trusting is not ``completed``
        (its positions were refused or in conflict: ``incomplete``, naming the vehicles and
        why); refusals that never reached a vehicle's state (another id, another address) are
        said in the reason of a completed run (docs/security.md)."""
        t = telemetry_summary(self)
        if t["faults"]:
            why = "; ".join(f"{self.names[f['vehicle']]}: {f['reason']}" for f in t["faults"])
            if self.outcome == "completed":
                self.outcome = "incomplete"
                self.reason = f"telemetry not trustworthy: {why}"
            else:
                self.reason += f"; telemetry not trustworthy: {why}"
        elif t["refused"] and self.outcome == "completed":
            self.reason = ("telemetry refused (not the vehicles'): " + ", ".join(
                f"{k} {v}" for k, v in sorted(t["refused"].items())))

    def _say_not_down(self) -> None:
        """The run's reason names the vehicles not brought down, the lost ones that cannot be
        reached (silent: maybe still in the air) and those left holding."""
        if self.not_landed:
            self.reason += (f"; NOT on the ground: {len(self.not_landed)} vehicle(s): "
                            + ", ".join(self.not_landed))
        if self.not_waited:
            self.reason += (f"; not waited for touch-down (interrupted while landing): "
                            f"{len(self.not_waited)} vehicle(s) still in the air: "
                            + ", ".join(self.not_waited))
        if self.unreachable:
            self.reason += (f"; NOT known to be down: {len(self.unreachable)} lost vehicle(s) "
                            f"silent, PX4's failsafe decides: " + ", ".join(self.unreachable))
        if self.held_for_operator:
            self.reason += ("; left holding in the air (on_abort = hold): "
                            + ", ".join(self.held_for_operator))

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
        """After an abort: every vehicle in the air comes down (``on_abort = "land"``, the
        default: :meth:`_bring_down`), or, with ``on_abort = "hold"``, vehicles still climbing
        land and the others hold for an operator — said in red, naming them."""
        if self._abort_reason is None:
            self.request_abort(str(exc))
        if self.cfg.on_abort == "land":
            await self._bring_down("mission aborted")
            return
        climbing = [p for p in self.pilots if p.phase in (Phase.ARMING, Phase.TAKEOFF)]
        if climbing:
            await asyncio.gather(*(p.land() for p in climbing), return_exceptions=True)
            await self._wait_landed()
        holding = [p for p in self.pilots if p.phase == Phase.HOLDING]
        if holding:
            await asyncio.gather(*(p.hold() for p in holding), return_exceptions=True)
        left = [p.name for p in self.pilots if p.phase in AIRBORNE_PHASES]
        if left:
            self.held_for_operator = left
            self.event(f"on_abort = hold: {len(left)} vehicle(s) LEFT HOLDING IN THE AIR for an "
                       f"operator (PX4 Hold; land them yourself): " + ", ".join(left),
                       level="error")

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
        self._replan_worker.shutdown(wait=False, cancel_futures=True)
        for p in self.pilots:
            p.cancel_tasks()
        await self.preflight.restore_params()
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
        await self._close_links()
        if self.view is not None:
            self.view.close()
        return summary, path

    async def _close_links(self) -> None:
        """Close every link (each gives PX4 its own stream rates back) and say once, for the
        whole fleet, which vehicles did not confirm that."""
        for p in self.pilots:
            if hasattr(p.link, "warn_unrestored"):
                p.link.warn_unrestored = False
        await asyncio.gather(*(p.link.close() for p in self.pilots), return_exceptions=True)
        left = [p for p in self.pilots if getattr(p.link, "unrestored_streams", None)]
        if left:
            names = sorted({n for p in left for n in p.link.unrestored_names})
            ids = [int(p.vehicle_id) for p in left]
            shown = ", ".join(map(str, ids[:12])) + (f" … ({len(ids)} in all)"
                                                    if len(ids) > 12 else "")
            log.warning("PX4's own stream rates not confirmed by %d of %d vehicle(s) (%s) for "
                        "%s: they keep our rates until they reboot or a ground station sets "
                        "them", len(left), len(self.pilots), shown, ", ".join(names))

    # -- the summary -------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """The run's summary so far (:func:`vtube_fleet.fleet.summary.fleet_summary`)."""
        return fleet_summary(self)

    def _summary_core(self) -> dict[str, Any]:
        """The accumulator's figures only (what the verdict reads)."""
        try:
            return self.measurement.acc.summary(
                first_violation=self.measurement.violations.first)
        except Exception:  # pragma: no cover - never block the verdict
            return {"violations": 0}


def _seen_down(p: VehiclePilot, fresh_s: float) -> bool:
    """The vehicle's telemetry, younger than ``fresh_s``, says disarmed on the ground."""
    s = p.link.state
    return (s.last_position_s is not None and time.monotonic() - s.last_position_s <= fresh_s
            and not s.armed and s.landed_state == "ON_GROUND")


def _offboard_airborne(p: VehiclePilot) -> bool:
    """PX4 reports OFFBOARD, armed, and not on the ground: flying on our setpoints."""
    s = p.link.state
    return s.flight_mode == "OFFBOARD" and s.armed is True and s.landed_state != "ON_GROUND"
