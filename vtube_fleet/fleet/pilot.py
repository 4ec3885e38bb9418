"""One vehicle's flight procedure: ready → arm → take off → tube → hold or land.

A :class:`VehiclePilot` ties a :class:`~vtube_fleet.link.VehicleLink` (commands out, telemetry
in) to its row of a :class:`~vtube_fleet.fleet.table.FleetTable`. The control tick
(:mod:`vtube_fleet.fleet.tick`) reads and writes that row for every vehicle at once; the pilot
keeps what is one vehicle's alone: its phase changes with their events and waiters, and the
procedure's steps, which wait on the link (:meth:`wait_ready`, :meth:`arm_and_climb`,
:meth:`hold`, :meth:`land`) or run in the background (the mode changes :meth:`begin_hold`,
:meth:`begin_land`). The supervisor runs N pilots over one table and one tick; an MQTT agent runs
one pilot over a table of one row (:meth:`fly`: the whole procedure, its clock running the
tick).

**Frames.** Telemetry comes in as PX4's LOCAL_POSITION_NED about the vehicle's own
GPS_GLOBAL_ORIGIN; the tick turns it into the tube frame (x, y, up). Setpoints go out as
north/east velocity in that vehicle's LOCAL_NED plus a vertical term that holds the mission
altitude.

**Take-off** as in the PX4 SITL captures: velocity setpoints (0, 0, 0) stream first, then
OFFBOARD is selected, then ARM (retried while PX4 answers TEMPORARILY_REJECTED), then the
offboard climb; a weak horizontal term holds the take-off spot against drift. The vehicle then
hovers at the mission altitude until the tube flight starts.

**Faults** are found by the tick's rules (:data:`~vtube_fleet.fleet.tick.FAULT_RULES`) and
applied here (:meth:`fault`): phase LOST — the tick stops commanding the vehicle and the others
see a static obstacle at its last position (and re-partition around it); or LANDING (a low
battery) — PX4 lands it where it is, and the others see a stopped vehicle, an obstacle too.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

import numpy as np

from vtube_fleet.config.mission import Mission
from vtube_fleet.errors import UserError
from vtube_fleet.fleet.table import PHASE_CODE, PHASES, FleetTable
from vtube_fleet.frames import TubeFrame
from vtube_fleet.link.base import LinkError, VehicleLink
from vtube_fleet.state import AIRBORNE_PHASES, OFFBOARD_PHASES, TUBE_PHASES, Phase

__all__ = ["EventSink", "PilotError", "VehiclePilot"]

log = logging.getLogger(__name__)

#: ``sink(text, vehicle_id, level)``: where a pilot reports events (phase changes, faults).
EventSink = Callable[[str, int | None, str], None]


class PilotError(UserError):
    """A vehicle could not complete a step of its procedure (names the vehicle and why)."""


class VehiclePilot:
    """One vehicle's flight procedure (module docstring): row ``row`` of ``table``.

    ``on_event`` receives events (default: the log); background coroutines (mode changes) are
    kept by the pilot (:meth:`spawn`).
    """

    def __init__(
        self,
        link: VehicleLink,
        table: FleetTable,
        row: int,
        mission: Mission,
        *,
        frame: TubeFrame | None = None,
        on_event: EventSink | None = None,
    ) -> None:
        self.link = link
        self.table = table
        self.row = int(row)
        self.mission = mission
        self.cfg = mission.config
        self.frame = frame if frame is not None else mission.frame
        self.on_event = on_event
        self.vehicle_id = int(table.ids[self.row])
        #: the tube flight may begin: audit the PX4 parameters and upload the tube fence first
        #: in :meth:`fly` (the supervisor does both for all its pilots at once)
        self.fence = True
        self.at_altitude = asyncio.Event()
        self.landed = asyncio.Event()
        self.sent_setpoint = asyncio.Event()
        self.sensed = asyncio.Event()  # the tick has taken a position of this vehicle
        self.reason: str | None = None
        #: why the last LAND went unanswered (None: acknowledged, or none sent)
        self.unanswered: str | None = None
        self._phase_waiters: list[asyncio.Future[None]] = []
        self._transition: asyncio.Task[None] | None = None
        self._tasks: set[asyncio.Task[Any]] = set()

    # -- this vehicle's row ---------------------------------------------------------------------
    @property
    def phase(self) -> Phase:
        return PHASES[self.table.phase[self.row]]

    @property
    def xy(self) -> np.ndarray:
        """Tube-frame position of the sample in use (NaN before one; a copy)."""
        return self.table.xy[self.row].copy()

    @property
    def vel_xy(self) -> np.ndarray:
        """Tube-frame velocity of the sample in use (a copy)."""
        return self.table.vel[self.row].copy()

    @property
    def up_m(self) -> float:
        """Height of the sample in use (m above the tube frame's origin)."""
        return float(self.table.up[self.row])

    @property
    def sample_s(self) -> float | None:
        """Monotonic arrival time of the position sample in use; None before one."""
        t = float(self.table.sample_s[self.row])
        return None if math.isnan(t) else t

    def has_position(self) -> bool:
        return bool(self.table.has[self.row])

    @property
    def cmd_xy(self) -> np.ndarray | None:
        """The last horizontal tube-frame command (m/s), None if none (a copy)."""
        t, r = self.table, self.row
        return t.cmd[r].copy() if t.cmd_set[r] else None

    @property
    def cmd_in_tube(self) -> bool:
        """This tick's command is the tube controller's."""
        return bool(self.table.cmd_in_tube[self.row])

    @property
    def lost_xy(self) -> np.ndarray | None:
        """The position frozen when the vehicle was declared LOST (a copy), else None."""
        t, r = self.table, self.row
        return t.lost[r].copy() if t.lost_set[r] else None

    def position(self) -> np.ndarray:
        """The position others should see: the frozen last position once LOST."""
        lost = self.lost_xy
        return lost if lost is not None else self.xy

    @property
    def exit_time_s(self) -> float | None:
        """Mission time of the exit (TraCondition); None before it."""
        t = float(self.table.exit_s[self.row])
        return None if math.isnan(t) else t

    @property
    def setpoints_sent(self) -> int:
        """Setpoints sent so far."""
        return int(self.table.setpoints_sent[self.row])

    def position_accuracy_m(self, allow_gnss: bool = True) -> float:
        """The vehicle's reported horizontal position accuracy (1 σ): the estimator's
        (ESTIMATOR_STATUS) or, if it sends none and ``allow_gnss``, the GNSS receiver's
        (GPS_RAW_INT h_acc); NaN if neither."""
        return self.link.state.accuracy_m(allow_gnss)

    def sample_age_s(self, now_mono: float) -> float:
        """Age of the position in use: since it arrived plus the one-way link latency."""
        if self.sample_s is None:
            return math.inf
        return (now_mono - self.sample_s) + (self.link.latency_s or 0.0)

    # -- naming / events ------------------------------------------------------------------------
    @property
    def name(self) -> str:
        """``slot 3 (udpin://127.0.0.1:14543)``: the slot index (= vehicle id) and endpoint (the
        link's own messages name the MAVLink system id instead: ``vehicle 4 (…)``)."""
        return f"slot {self.vehicle_id} ({self.link.endpoint.url})"

    def event(self, text: str, level: str = "info") -> None:
        if self.on_event is not None:
            self.on_event(text, self.vehicle_id, level)
        else:
            getattr(log, "warning" if level in ("warning", "error") else "info")(
                "%s: %s", self.name, text)

    def set_phase(self, phase: Phase, why: str = "", level: str | None = None) -> bool:
        """Set the phase (the table's column), wake the waiters, tell the event sink (at
        ``level``; default: a warning for LOST and FAILED); True if it changed."""
        phase = Phase(phase)
        old = self.phase
        if phase == old:
            return False
        self.table.phase[self.row] = PHASE_CODE[phase]
        waiters, self._phase_waiters = self._phase_waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_result(None)
        if level is None:
            level = "warning" if phase in (Phase.LOST, Phase.FAILED) else "info"
        self.event(f"{old.value} → {phase.value}" + (f" ({why})" if why else ""), level)
        return True

    def spawn(self, coro: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def cancel_tasks(self) -> None:
        """Cancel the background mode changes still running (end of a run)."""
        for t in list(self._tasks):
            t.cancel()

    # -- transitions the tick decides ----------------------------------------------------------
    def fault(self, action: str, reason: str) -> None:
        """A fault rule hit (:class:`~vtube_fleet.fleet.tick.FaultRule`): FAILED while arming;
        else ``"lost"`` (:meth:`declare_lost`), ``"land"`` (land in place) or ``"hold"`` (PX4
        Hold in place): stopped, it is an obstacle for everyone."""
        if self.phase == Phase.ARMING:
            self.reason = reason
            self.set_phase(Phase.FAILED, reason)
        elif action == "land":
            self.reason = self.reason or reason
            self.begin_land(reason, level="warning")
        elif action == "hold":
            self.reason = self.reason or reason
            self.begin_hold(reason)
        else:
            self.declare_lost(reason)

    def touched_down(self) -> None:
        """On the ground and disarmed after holding or landing."""
        self.set_phase(Phase.LANDED, "on the ground, disarmed")
        self.landed.set()

    def declare_lost(self, reason: str) -> None:
        """Become a static obstacle at the last known position; stop commanding."""
        if self.phase == Phase.LOST:
            return
        self.reason = reason
        t, r = self.table, self.row
        if t.has[r]:
            t.lost[r], t.lost_set[r] = t.xy[r], True
        t.cmd_set[r] = False
        t.cmd[r] = np.nan
        t.cmd_in_tube[r] = False
        where = ("" if not t.lost_set[r] else
                 f"; static obstacle at ({t.lost[r, 0]:.2f}, {t.lost[r, 1]:.2f})")
        self.set_phase(Phase.LOST, reason + where)

    def mark_exit(self, t_s: float) -> None:
        """Crossed the finishing line at mission time ``t_s`` (TraCondition)."""
        self.table.exit_s[self.row] = t_s
        self.set_phase(Phase.EXITED, f"crossed the finishing line at t = {t_s:.2f} s")

    def enter_tube(self) -> None:
        if self.phase == Phase.TAKEOFF:
            self.set_phase(Phase.IN_TUBE)

    def begin_wait(self, why: str) -> None:
        """IN_TUBE (or STEPPING, with no path yet) → WAITING: stop where it is (still in
        OFFBOARD, zero velocity), an obstacle for the others, until :meth:`begin_step`
        (docs/fleet.md, "Waiting for a way")."""
        if self.phase in (Phase.IN_TUBE, Phase.STEPPING):
            self.table.step_set[self.row] = False
            self.set_phase(Phase.WAITING, why, "warning")

    def begin_step(self, why: str) -> None:
        """WAITING → STEPPING: released; it steps aside once the plan without it is known."""
        if self.phase == Phase.WAITING:
            self.table.step_set[self.row] = False
            self.table.step_via[self.row] = np.nan
            self.set_phase(Phase.STEPPING, why)

    def resume_tube(self, why: str) -> None:
        """STEPPING → IN_TUBE: outside every region again, it flies the controller."""
        if self.phase == Phase.STEPPING:
            self.table.step_set[self.row] = False
            self.set_phase(Phase.IN_TUBE, why)

    # -- mode changes (background) -------------------------------------------------------------
    def _run_transition(self, coro: Awaitable[None], what: str) -> None:
        async def run() -> None:
            try:
                await coro
            except (LinkError, UserError) as exc:
                self.event(f"{what} failed: {exc}", "warning")
            finally:
                self._transition = None
                self.table.in_transition[self.row] = False

        self._transition = self.spawn(run())
        self.table.in_transition[self.row] = True

    def begin_hold(self, why: str) -> None:
        """Leave OFFBOARD into Hold (keeps streaming zero velocity until PX4 confirms); a Hold
        that is not acknowledged (after the link's tries) is followed by LAND."""
        if self.phase in (Phase.HOLDING, Phase.LANDING, Phase.LANDED, Phase.LOST):
            return
        self.set_phase(Phase.HOLDING, why)
        self.table.offboard_seen[self.row] = False
        self._run_transition(self._hold_or_land(), "hold")

    def begin_land(self, why: str, level: str | None = None) -> None:
        """LAND in place (:meth:`land_command`: retried, reported by name if unanswered);
        ``level``: of the phase change's event (a fault's landing warns)."""
        if self.phase in (Phase.LANDING, Phase.LANDED, Phase.LOST):
            return
        self.set_phase(Phase.LANDING, why, level)
        self.table.offboard_seen[self.row] = False
        self._run_transition(self.land_command(), "land")

    async def _hold_or_land(self) -> None:
        try:
            await self.link.stop_offboard()
        except LinkError as exc:
            self.event(f"Hold not acknowledged ({exc}): LAND instead", "warning")
            self.set_phase(Phase.LANDING, "Hold was not acknowledged")
            await self.land_command()

    #: Rounds of the link's command tries for LAND before the vehicle is reported by name.
    LAND_ROUNDS = 3

    async def land_command(self) -> bool:
        """NAV_LAND, up to :attr:`LAND_ROUNDS` rounds of the link's own tries; True once
        acknowledged. Unanswered, the vehicle is reported by name (an error event) and
        :attr:`unanswered` says why."""
        last: Exception | None = None
        for _ in range(self.LAND_ROUNDS):
            if self.link.closed:
                break
            try:
                await self.link.land()
            except LinkError as exc:
                last = exc
                continue
            self.unanswered = None
            return True
        self.unanswered = (f"LAND not acknowledged after {self.LAND_ROUNDS} rounds"
                           + (f" ({last})" if last is not None else " (link closed)"))
        self.event(self.unanswered, "error")
        return False

    # -- the procedure -------------------------------------------------------------------------
    async def wait_ready(self) -> None:
        """Heartbeat, positions, home, GPS origin and health (``ready_timeout_s``), then a
        position taken by the control tick (which must be running); phase CONNECTING → READY
        (no-op when already past CONNECTING)."""
        if self.phase != Phase.CONNECTING:
            return
        timeout_s = self.cfg.ready_timeout_s
        await self.link.wait_ready(timeout_s)
        try:
            async with asyncio.timeout(timeout_s):
                await self.sensed.wait()
        except TimeoutError:
            raise PilotError(f"{self.name}: no local position in the tube frame within "
                             f"{timeout_s:g} s (control loop not running?)") from None
        self.set_phase(Phase.READY, f"at ({self.xy[0]:.2f}, {self.xy[1]:.2f}) "
                                    f"up {self.up_m:.2f} m")

    def check_altitude_margin(self, minimum_m: float = 1.0) -> str | None:
        """A problem if the mission altitude is less than ``minimum_m`` above the vehicle."""
        if not math.isfinite(self.up_m):
            return f"{self.name}: height unknown"
        if self.cfg.altitude_m - self.up_m < minimum_m:
            return (f"{self.name}: mission altitude {self.cfg.altitude_m:g} m above "
                    f"origin_alt_m is only {self.cfg.altitude_m - self.up_m:.2f} m above the "
                    f"vehicle (at {self.up_m:.2f} m), need >= {minimum_m:g} m")
        return None

    async def arm_and_climb(self) -> None:
        """OFFBOARD (setpoints streaming first), ARM, offboard climb to the mission altitude.

        Requires a control clock running the tick (the supervisor's or the agent's)."""
        cfg = self.cfg
        self.set_phase(Phase.ARMING)
        try:
            async with asyncio.timeout(cfg.arm_timeout_s):
                await self.sent_setpoint.wait()
        except TimeoutError:
            raise PilotError(f"{self.name}: no setpoint streamed within "
                             f"{cfg.arm_timeout_s:g} s (control loop not running?)") from None
        await self.link.start_offboard()
        await self.link.arm(timeout_s=cfg.arm_timeout_s)
        if self.has_position():
            self.table.takeoff_xy[self.row] = self.table.xy[self.row]
        self.set_phase(Phase.TAKEOFF, f"climbing to {cfg.altitude_m:g} m")
        try:
            async with asyncio.timeout(cfg.takeoff_timeout_s):
                await self.at_altitude.wait()
        except TimeoutError:
            raise PilotError(
                f"{self.name}: did not reach {cfg.altitude_m:g} m ± {cfg.altitude_tolerance_m:g}"
                f" within takeoff_timeout_s = {cfg.takeoff_timeout_s:g} s (at {self.up_m:.2f} m,"
                f" mode {self.link.state.flight_mode})") from None
        self.event(f"at altitude ({self.up_m:.2f} m)")

    #: Seconds to wait for the vehicle's telemetry to confirm a mode change (HEARTBEAT: 1 Hz).
    MODE_CONFIRM_S = 3.0

    async def hold(self) -> None:
        """Hold now (PX4 Hold) and wait until the vehicle reports it (warning if it does not
        within ``MODE_CONFIRM_S``); no-op on the ground or when landing/lost."""
        if self.phase in OFFBOARD_PHASES or self.phase == Phase.HOLDING:
            if self.phase != Phase.HOLDING:
                self.begin_hold("hold requested")
            t = self._transition
            if t is not None:
                await asyncio.shield(t)
            if self.phase == Phase.HOLDING and not self.link.closed:
                try:
                    await self.link.wait_until(lambda s: s.flight_mode == "HOLD",
                                               self.MODE_CONFIRM_S, "Hold reported")
                except LinkError as exc:
                    self.event(f"hold not confirmed: {exc}", "warning")

    async def land(self) -> None:
        """Land now; waits for the LAND command's acknowledgement (not for touch-down); a
        landing vehicle whose LAND went unanswered is sent LAND again."""
        if self.phase == Phase.LANDING and self.unanswered and self._transition is None:
            await self.land_command()
        elif self.phase in AIRBORNE_PHASES and self.phase != Phase.LANDING:
            t = self._transition
            if t is not None:
                await asyncio.shield(t)
            self.begin_land("land requested")
            t = self._transition
            if t is not None:
                await asyncio.shield(t)
        elif self.phase == Phase.LOST:
            # best effort: a lost vehicle that still answers (e.g. it left OFFBOARD) is told
            # to land; it stays LOST (a static obstacle) for the others
            s = self.link.state
            fresh = (s.last_position_s is not None
                     and time.monotonic() - s.last_position_s < self.cfg.lost_after_s)
            if fresh and s.armed and s.landed_state != "ON_GROUND" and not self.link.closed:
                try:
                    await self.link.land()
                    self.event("lost vehicle still answers: LAND sent", "warning")
                except LinkError as exc:
                    self.event(f"LAND to the lost vehicle failed: {exc}", "warning")
        elif self.phase in (Phase.ARMING, Phase.READY) and self.link.state.armed:
            try:
                await self.link.disarm()
            except LinkError as exc:
                self.event(f"disarm failed: {exc}", "warning")
            self.set_phase(Phase.LANDED, "disarmed on the ground")
            self.landed.set()
        elif self.phase in (Phase.ARMING, Phase.READY, Phase.CONNECTING):
            if self.phase != Phase.CONNECTING:
                self.set_phase(Phase.LANDED, "never took off")
            self.landed.set()

    async def wait_phase(self, predicate: Callable[[Phase], bool], timeout_s: float,
                         what: str) -> Phase:
        """Wait until ``predicate(phase)`` holds; :class:`PilotError` after ``timeout_s``."""
        try:
            async with asyncio.timeout(timeout_s):
                while not predicate(self.phase):
                    fut = asyncio.get_running_loop().create_future()
                    self._phase_waiters.append(fut)
                    await fut
        except TimeoutError:
            raise PilotError(f"{self.name}: {what} not reached within {timeout_s:g} s "
                             f"(phase {self.phase.value})") from None
        return self.phase

    async def fly(
        self,
        start: Callable[[], Awaitable[None]] | None = None,
        finish: Callable[[], Awaitable[None]] | None = None,
    ) -> Phase:
        """The whole procedure for this vehicle alone; the caller's control clock runs the
        tick meanwhile.

        ``start`` is awaited at altitude before entering the tube (e.g. the fleet's "start"
        command), ``finish`` after this vehicle exited (e.g. "all vehicles exited") before
        ``on_complete`` (land or hold). Returns the final phase once landed / holding / lost.
        """
        from vtube_fleet.fleet.preflight import audit_and_fence

        cfg = self.cfg
        await self.wait_ready()
        pre = await audit_and_fence([self], self.mission, fence=self.fence)
        await pre.check_batteries()
        await self.arm_and_climb()
        if start is not None:
            await start()
        self.enter_tube()
        await self.wait_phase(lambda ph: ph not in TUBE_PHASES, cfg.mission_timeout_s,
                              "the finishing line")
        if self.phase == Phase.EXITED and finish is not None:
            await finish()
        if self.phase in (Phase.EXITED, Phase.HOLDING):
            if cfg.on_complete == "land":
                await self.land()
            else:
                await self.hold()
        if self.phase == Phase.LANDING:
            await self.wait_phase(lambda ph: ph != Phase.LANDING, cfg.land_timeout_s,
                                  "touch-down")
        return self.phase
