"""One vehicle's whole flight: ready → arm → take off → tube → exit behaviour → land.

A :class:`VehiclePilot` ties a :class:`~vtube_fleet.link.VehicleLink` (telemetry in, setpoints
and commands out), an :class:`~vtube_fleet.fleet.agent.Agent` (the decisions), a
:class:`~vtube_fleet.bus.NeighbourBus` (own state out, neighbours in) and the mission's
:class:`~vtube_fleet.frames.TubeFrame`. It is used two ways:

* by the :class:`~vtube_fleet.fleet.supervisor.Supervisor`, which runs N pilots on one control
  clock and computes the in-tube setpoints of all of them in one controller call
  (:func:`~vtube_fleet.fleet.agent.fleet_setpoints`); the per-tick steps are the public methods
  :meth:`sense`, :meth:`publish`, :meth:`check_faults` and :meth:`actuate`;
* alone (one agent process per vehicle over MQTT): :meth:`fly` runs the procedure with its own
  control clock, :meth:`tick` doing the same per-tick steps for this one vehicle.

**Frames.** Telemetry comes in as PX4's LOCAL_POSITION_NED about the vehicle's own
GPS_GLOBAL_ORIGIN; :meth:`TubeFrame.local_ned_to_tube` turns it into the tube frame (x, y, up).
Setpoints go out as north/east velocity in that vehicle's LOCAL_NED
(:meth:`TubeFrame.tube_velocity_to_ned`) plus a vertical term that holds the mission altitude:
``v_up = clamp(k_z (altitude − up), ±max_vertical_speed)`` (during the climb capped at
``climb_speed_m_s``), ``down = −v_up``.

**Take-off** as in the PX4 SITL captures: velocity setpoints (0, 0, 0) stream first, then
OFFBOARD is selected, then ARM (retried while PX4 answers TEMPORARILY_REJECTED), then the
offboard climb; a weak horizontal term (gain 0.5 /s, at most 0.3 m/s) holds the take-off spot
against drift. The vehicle then hovers at the mission altitude until the tube flight starts.

**Faults** (:meth:`check_faults`): no local position for ``lost_after_s``, OFFBOARD left while
we fly offboard (after it was confirmed once), or a disarm in the air → phase LOST: the pilot
stops sending setpoints and publishes LOST at its last position, which the other agents turn
into a static obstacle (and a new partition).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable, Coroutine, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtube_fleet.bus.base import NeighbourBus
from vtube_fleet.config.mission import Mission
from vtube_fleet.core.loss import cannot_pass
from vtube_fleet.core.partition import PartitionError
from vtube_fleet.errors import UserError
from vtube_fleet.fleet.agent import Agent, NeighbourView, exit_velocity
from vtube_fleet.fleet.budget import (
    LinkMeasurement,
    budget_latency_s,
    budget_problems,
    latency_over,
)
from vtube_fleet.fleet.compensation import (
    RESIDUAL_WINDOW_S,
    CompensatorBank,
    EstimateCompensator,
    ResidualTracker,
)
from vtube_fleet.fleet.table import PHASE_CODE, PHASES, PilotTable, phase_mask
from vtube_fleet.frames import TubeFrame
from vtube_fleet.link.base import LinkError, VehicleLink, VehicleState, send_velocities_ned
from vtube_fleet.state import AIRBORNE_PHASES, OFFBOARD_PHASES, NeighbourState, Phase

__all__ = [
    "EventSink",
    "FleetStates",
    "MEASURE_TRIES",
    "PilotError",
    "VehiclePilot",
    "actuate_all",
    "check_faults_all",
    "fleet_states",
    "fleet_table",
    "LinkColumns",
    "link_columns",
    "measure_budget_links",
    "measure_links",
    "sense_all",
    "wait_accuracy",
]

log = logging.getLogger(__name__)

#: Seconds of sensing used to measure link latency + position-sample age before the safety
#: budget δ is fixed (supervisor and standalone agent alike).
MEASURE_S = 1.0


async def measure_links(pilots: Sequence[VehiclePilot], period_s: float,
                        duration_s: float = MEASURE_S) -> LinkMeasurement:
    """Round trips (every link at once), then ``duration_s`` of position-sample ages and
    accuracies sampled every ``period_s``."""
    trips = await asyncio.gather(*(p.link.measure_round_trip_s() for p in pilots),
                                 return_exceptions=True)
    rtts = [float(r) for r in trips if isinstance(r, int | float) and math.isfinite(r)]
    lat = [p.link.latency_s for p in pilots if p.link.latency_s is not None]
    one_way = max([r / 2.0 for r in rtts] + [float(x) for x in lat], default=0.0)
    loop = asyncio.get_running_loop()
    ages: list[float] = []
    acc = [math.nan] * len(pilots)
    end = loop.time() + duration_s
    while loop.time() < end:
        now = time.monotonic()
        ages.extend(p.sample_age_s(now) for p in pilots)
        for i, p in enumerate(pilots):
            a = p.position_accuracy_m()
            if math.isfinite(a):
                acc[i] = a  # the latest report (it only settles downwards after boot)
        await asyncio.sleep(period_s)  # the sampling period of the measurement
    a = np.asarray(ages, dtype=float)
    a = a[np.isfinite(a)]
    known = [x for x in acc if math.isfinite(x)]
    return LinkMeasurement(float(np.percentile(a, 95)) if a.size else 0.0, one_way,
                           max(known) if known else math.nan, tuple(acc))


#: Measurements :func:`measure_budget_links` takes before a measured L that is too large
#: refuses the mission.
MEASURE_TRIES = 3


async def measure_budget_links(
    pilots: Sequence[VehiclePilot], mission: Mission, duration_s: float = MEASURE_S, *,
    too_slow: Callable[[LinkMeasurement], str | None] | None = None,
    on_wait: Callable[[str], None] | None = None,
) -> tuple[LinkMeasurement, list[str]]:
    """:func:`measure_links` and :func:`~vtube_fleet.fleet.budget.budget_problems`; while the
    measured L is too large (above ``max_latency_s``, or ``too_slow(measured)`` returns the
    caller's reason: the MQTT agent's, that the run's δ does not cover it), measured again,
    up to :data:`MEASURE_TRIES` times. A fleet's processes all start their flight at once
    (planning, recordings, every agent at the same moment), and a second of that load is not
    the link's latency. The budget is built on the measurement returned (the last), and the
    in-flight watch (:class:`~vtube_fleet.fleet.budget.BudgetWatch`) judges L against it from
    then on. A refusal names every try's L. ``on_wait``: where the "measuring again" line goes
    (the supervisor's events; default: the log, as a warning)."""
    period_s = mission.config.period_s
    tries: list[LinkMeasurement] = []
    while True:
        measured = await measure_links(pilots, period_s, duration_s)
        tries.append(measured)
        over = latency_over(mission, measured)
        reason = None if too_slow is None else too_slow(measured)
        if not (over or reason) or len(tries) >= MEASURE_TRIES:
            break
        limit = (f"> max_latency_s = {1000 * mission.config.max_latency_s:.0f} ms" if over
                 else "too large for the run")
        (on_wait or log.warning)(
            f"link latency L = {1000 * budget_latency_s(mission, measured):.0f} ms {limit}: "
            f"measuring again ({len(tries) + 1} of {MEASURE_TRIES})")
    problems = budget_problems(mission, measured)
    if reason:
        problems.append(reason)
    if (over or reason) and len(tries) > 1:
        problems.append(
            f"the same in {len(tries)} measurements of {duration_s:g} s (L = "
            + ", ".join(f"{1000 * budget_latency_s(mission, m):.0f}" for m in tries) + " ms)")
    return measured, problems


#: Seconds :func:`wait_accuracy` waits for ESTIMATOR_STATUS before it accepts GNSS h_acc.
ESTIMATOR_WAIT_S = 5.0
#: The reported accuracy counts as settled when it changed by at most 10 % in this long.
SETTLE_S = 1.0


async def wait_accuracy(pilots: Sequence[VehiclePilot], max_m: float, timeout_s: float,
                        on_wait: Callable[[str], None] | None = None) -> None:
    """Wait until every vehicle reports a horizontal accuracy of at most ``max_m`` and it has
    settled (PX4's estimate settles for a few seconds after boot: 14 → 0.3 m);
    :class:`PilotError` naming the vehicles above ``max_m`` after ``timeout_s``."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    end = start + timeout_s
    said = False
    history: list[tuple[float, list[float]]] = []
    while True:
        # the estimator's own accuracy first; a vehicle that sends none for ESTIMATOR_WAIT_S
        # is judged by its GNSS receiver's (GPS_RAW_INT h_acc, larger)
        now = loop.time()
        gnss = now - start > ESTIMATOR_WAIT_S
        now_acc = [p.position_accuracy_m(allow_gnss=gnss) for p in pilots]
        bad = [(p, a) for p, a in zip(pilots, now_acc, strict=True)
               if not (math.isfinite(a) and a <= max_m)]
        # settled: within 10 % (or 2 cm) of what it was SETTLE_S ago (PX4 after boot:
        # 14 → 2.0 → 0.6 → 0.33 → 0.30 m over ~6 s)
        history.append((now, now_acc))
        while len(history) > 1 and history[1][0] <= now - SETTLE_S:
            history.pop(0)
        old_t, old_acc = history[0]
        settled = now - old_t >= SETTLE_S and all(
            abs(a - b) <= max(0.02, 0.1 * b) for a, b in zip(now_acc, old_acc, strict=True))
        if not bad and settled:
            return
        if loop.time() >= end and not bad:
            return  # within the bound, still settling: the budget takes the latest value
        if loop.time() >= end:
            raise PilotError(
                f"{len(bad)} vehicle(s) do not report a horizontal position accuracy of at most "
                f"max_position_accuracy_m = {max_m:g} m within {timeout_s:g} s: " + "; ".join(
                    f"{p.name} {'none reported' if not math.isfinite(a) else f'{a:.2f} m'}"
                    for p, a in bad))
        if not said and on_wait is not None and now - start > 0.5:
            said = True
            shown = bad or list(zip(pilots, now_acc, strict=True))
            on_wait("waiting for the reported position accuracy to settle: " + ", ".join(
                f"{p.name} {'none yet' if not math.isfinite(a) else f'{a:.2f} m'}"
                for p, a in shown[:4]) + (" …" if len(shown) > 4 else ""))
        await asyncio.sleep(0.2)


#: Gain (1/s) and limit (m/s) of the horizontal position hold during the climb (on top of the
#: estimate-disturbance compensation, which cancels most of the take-off drift).
TAKEOFF_XY_GAIN_1_S = 0.5
TAKEOFF_XY_MAX_M_S = 0.5

#: ``sink(text, vehicle_id, level)``: where a pilot reports events (phase changes, faults).
EventSink = Callable[[str, int | None, str], None]


class PilotError(UserError):
    """A vehicle could not complete a step of its procedure (names the vehicle and why)."""


def _clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


class VehiclePilot:
    """One vehicle's flight procedure (module docstring).

    ``vehicle_id`` is the agent's id (the 0-based slot). ``on_event`` receives events;
    ``spawn`` schedules background coroutines (mode changes triggered from a tick), defaulting
    to ``asyncio.create_task`` with the pilot keeping a reference.
    """

    def __init__(
        self,
        link: VehicleLink,
        agent: Agent,
        bus: NeighbourBus,
        mission: Mission,
        *,
        frame: TubeFrame | None = None,
        on_event: EventSink | None = None,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.link = link
        self.agent = agent
        self.bus = bus
        self.mission = mission
        self.cfg = mission.config
        self.frame = frame if frame is not None else mission.frame
        self.on_event = on_event
        self.wall_clock = wall_clock
        self.vehicle_id = agent.vehicle_id
        # the tick state (tube-frame telemetry, command, phase …) is row ``_r`` of a table
        # (fleet/table.py): its own one-row table until it joins a fleet's (join_fleet)
        self._t = PilotTable(1)
        self._r = 0
        self._t.phase[0] = PHASE_CODE[agent.phase]
        agent.on_phase = self._phase_changed  # the table's phase column follows the agent's
        # the frame's (linear) horizontal rotations as 2×2 matrices, evaluated once on the
        # basis vectors, so a tick costs float arithmetic instead of numpy calls per vehicle
        n, e = self.frame.tube_velocity_to_ned(np.array([1.0, 0.0]), np.array([0.0, 1.0]))
        self._to_ned = (float(n[0]), float(n[1]), float(e[0]), float(e[1]))
        x, y = self.frame.ned_velocity_to_tube(np.array([1.0, 0.0]), np.array([0.0, 1.0]))
        self._to_tube = (float(x[0]), float(x[1]), float(y[0]), float(y[1]))
        self._t.note_rotation(self._to_tube)
        self._seq = 0
        self.last_state: NeighbourState | None = None  # the last one published
        self.takeoff_xy: np.ndarray | None = None
        #: :meth:`fly` audits the PX4 parameters and uploads the tube fence first
        #: (fleet/onboard.py; the supervisor does it for all its pilots at once)
        self.fence = True
        self.at_altitude = asyncio.Event()
        self.landed = asyncio.Event()
        self.sent_setpoint = asyncio.Event()
        self.reason: str | None = None
        self.exit_time_s: float | None = None
        self._clock_start_s: float | None = None  # monotonic time of the first tick()
        self._still_xy = np.full(2, np.nan)  # the position when it was first measured slow
        self._last_tick_s: float | None = None
        self._listening_since: float | None = None
        self._phase_waiters: list[asyncio.Future[None]] = []
        self._transition: asyncio.Task[None] | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        # the estimate-disturbance compensation (fleet/compensation.py): what is sent is the
        # command plus d̂ while flying offboard
        self.compensator = EstimateCompensator() if self.cfg.compensate_estimate else None
        self._residuals = ResidualTracker(1, self.cfg.period_s,
                                          self.cfg.disturbance_residual_m_s)
        self._residual_row = 0

    # -- the tick state: this pilot's row of its table ----------------------------------------
    @property
    def xy(self) -> np.ndarray:
        """Tube-frame position of the sample in use (NaN before one; a copy)."""
        return self._t.xy[self._r].copy()

    @xy.setter
    def xy(self, value: np.ndarray) -> None:
        self._t.xy[self._r] = value

    @property
    def vel_xy(self) -> np.ndarray:
        """Tube-frame velocity of the sample in use (a copy)."""
        return self._t.vel[self._r].copy()

    @vel_xy.setter
    def vel_xy(self, value: np.ndarray) -> None:
        self._t.vel[self._r] = value

    @property
    def up_m(self) -> float:
        """Height of the sample in use (m above the tube frame's origin)."""
        return float(self._t.up[self._r])

    @property
    def sample_s(self) -> float | None:
        """Monotonic arrival time of the position sample in use; None before one."""
        t = float(self._t.sample_s[self._r])
        return None if math.isnan(t) else t

    @property
    def _has_pos(self) -> bool:
        return bool(self._t.has[self._r])

    @_has_pos.setter
    def _has_pos(self, value: bool) -> None:
        self._t.has[self._r] = value

    @property
    def cmd_xy(self) -> np.ndarray | None:
        """The last horizontal tube-frame command (m/s), None if none (a copy)."""
        return self._t.cmd[self._r].copy() if self._t.cmd_set[self._r] else None

    @cmd_xy.setter
    def cmd_xy(self, value: np.ndarray | None) -> None:
        t, r = self._t, self._r
        if value is None:
            t.cmd_set[r] = False
            t.cmd[r] = np.nan
        else:
            t.cmd_set[r] = True
            t.cmd[r] = value

    @property
    def cmd_in_tube(self) -> bool:
        """This tick's command is the controller's (IN_TUBE)."""
        return bool(self._t.cmd_in_tube[self._r])

    @cmd_in_tube.setter
    def cmd_in_tube(self, value: bool) -> None:
        self._t.cmd_in_tube[self._r] = value

    @property
    def lost_xy(self) -> np.ndarray | None:
        """The position frozen when the vehicle was declared LOST (a copy), else None."""
        return self._t.lost[self._r].copy() if self._t.lost_set[self._r] else None

    @property
    def _offboard_seen(self) -> bool:
        return bool(self._t.offboard_seen[self._r])

    @_offboard_seen.setter
    def _offboard_seen(self, value: bool) -> None:
        self._t.offboard_seen[self._r] = value

    @property
    def _still_since(self) -> float | None:
        t = float(self._t.still_since_s[self._r])
        return None if math.isnan(t) else t

    @_still_since.setter
    def _still_since(self, value: float | None) -> None:
        self._t.still_since_s[self._r] = math.nan if value is None else value

    @property
    def setpoints_sent(self) -> int:
        """Setpoints sent so far."""
        return int(self._t.setpoints_sent[self._r])

    # -- naming / events ---------------------------------------------------------------------
    @property
    def name(self) -> str:
        """``slot 3 (udpin://127.0.0.1:14543)``: the slot index (= agent id) and endpoint (the
        link's own messages name the MAVLink system id instead: ``vehicle 4 (…)``)."""
        return f"slot {self.vehicle_id} ({self.link.endpoint.url})"

    @property
    def phase(self) -> Phase:
        return self.agent.phase

    def event(self, text: str, level: str = "info") -> None:
        if self.on_event is not None:
            self.on_event(text, self.vehicle_id, level)
        else:
            getattr(log, "warning" if level in ("warning", "error") else "info")(
                "%s: %s", self.name, text)

    def set_phase(self, phase: Phase, why: str = "") -> bool:
        old = self.agent.phase
        if not self.agent.set_phase(phase):
            return False
        waiters, self._phase_waiters = self._phase_waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_result(None)
        self.event(f"{old.value} → {phase.value}" + (f" ({why})" if why else ""),
                   "warning" if phase in (Phase.LOST, Phase.FAILED) else "info")
        return True

    def _phase_changed(self, phase: Phase) -> None:
        self._t.phase[self._r] = PHASE_CODE[phase]

    def spawn(self, coro: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # -- sensing ---------------------------------------------------------------------------
    def has_position(self) -> bool:
        return self._has_pos

    def pending_sample(self) -> bool:
        """A local position newer than the one in use has arrived (and the origin is known)."""
        s = self.link.state
        return (s.last_position_s is not None and s.origin is not None
                and s.last_position_s != self.sample_s)

    def sense(self, xyz: tuple[float, float, float] | None = None) -> bool:
        """Take the link's latest local position into the tube frame; True if it was new.

        ``xyz`` is the already converted tube position (the supervisor converts all vehicles
        in one vectorized call, :func:`sense_all`).
        """
        if not self.pending_sample():
            return False
        s = self.link.state
        if xyz is None:
            o = s.origin
            assert o is not None
            x, y, up = self.frame.local_ned_to_tube(
                s.north_m, s.east_m, s.down_m, o.lat_deg, o.lon_deg, o.alt_m)
            xyz = (float(x), float(y), float(up))
        self._take(s, xyz[0], xyz[1], xyz[2])
        return True

    def _take(self, s: VehicleState, x: float, y: float, up: float,
              compensate: bool = True) -> None:
        """Use the sample of ``s`` (a pending one) at tube position (x, y, up); ``compensate``
        False: the caller gives it to the compensator (:func:`sense_all`, for all at once)."""
        a, b, c, d = self._to_tube
        vn, ve = s.vn_m_s, s.ve_m_s
        vx, vy = a * vn + b * ve, c * vn + d * ve
        t = s.last_position_s
        has = math.isfinite(x) and math.isfinite(y)
        self._use(t, np.array((x, y)), up, np.array((vx, vy)), has)
        if compensate and self.compensator is not None and has and t is not None:
            self.compensator.add(t, x, y, vx, vy)

    def _use(self, t: float | None, xy: np.ndarray, up: float, vel_xy: np.ndarray,
             has: bool) -> None:
        """Take a converted sample: arrived at ``t``, tube position ``xy`` (finite: ``has``)
        and height ``up``, tube-frame velocity ``vel_xy``."""
        tab, r = self._t, self._r
        tab.xy[r] = xy
        tab.up[r] = up
        tab.vel[r] = vel_xy
        tab.sample_s[r] = math.nan if t is None else t
        tab.has[r] = has
        if (self.agent.phase == Phase.TAKEOFF and not self.at_altitude.is_set()
                and abs(up - self.cfg.altitude_m) <= self.cfg.altitude_tolerance_m):
            self.at_altitude.set()

    def position_accuracy_m(self, allow_gnss: bool = True) -> float:
        """The vehicle's reported horizontal position accuracy (1 σ): the estimator's
        (ESTIMATOR_STATUS) or, if it sends none and ``allow_gnss``, the GNSS receiver's
        (GPS_RAW_INT h_acc); NaN if neither."""
        s = self.link.state
        a = s.pos_accuracy_m
        return a if math.isfinite(a) or not allow_gnss else s.gnss_h_acc_m

    def sample_age_s(self, now_mono: float) -> float:
        """Age of the position in use: since it arrived plus the one-way link latency."""
        if self.sample_s is None:
            return math.inf
        return (now_mono - self.sample_s) + (self.link.latency_s or 0.0)

    def position(self) -> np.ndarray:
        """The position others should see: the frozen last position once LOST."""
        return self.lost_xy if self.lost_xy is not None else self.xy

    def state(self, now_mono: float, now_wall: float) -> NeighbourState | None:
        if self.sample_s is None:
            return None
        p = self.position()
        v = (0.0, 0.0) if self.lost_xy is not None else (float(self.vel_xy[0]),
                                                          float(self.vel_xy[1]))
        self._seq += 1
        stamp = now_wall - self.sample_age_s(now_mono)
        return NeighbourState(self.vehicle_id, float(p[0]), float(p[1]), v[0], v[1],
                              self.phase, stamp, self._seq)

    def publish(self, now_mono: float, now_wall: float) -> None:
        """Publish this tick's :meth:`state` (kept as :attr:`last_state`)."""
        st = self.state(now_mono, now_wall)
        if st is not None:
            self.last_state = st
            self.bus.publish(st)

    # -- faults ---------------------------------------------------------------------------
    def check_faults(self, now_mono: float, listening_since: float | None = None
                     ) -> str | None:
        """Detect a lost vehicle; on a fault switch to LOST and return the reason.

        ``listening_since``: monotonic time our own loop resumed after a stall; silence is only
        counted from then (after a stall the socket backlog still holds the telemetry).
        """
        phase = self.phase
        s = self.link.state
        if phase in (Phase.LANDING,) and s.landed_state == "ON_GROUND" and s.armed is False:
            self.set_phase(Phase.LANDED, "on the ground, disarmed")
            self.landed.set()
            return None
        if phase == Phase.HOLDING and s.landed_state == "ON_GROUND" and s.armed is False:
            self.set_phase(Phase.LANDED, "on the ground, disarmed")
            self.landed.set()
            return None
        if phase not in AIRBORNE_PHASES and phase != Phase.ARMING:
            return None
        if phase in OFFBOARD_PHASES and s.flight_mode == "OFFBOARD":
            self._offboard_seen = True
        reason = None
        last = s.last_position_s
        heard = last if listening_since is None or last is None else max(last, listening_since)
        if last is None or now_mono - heard > self.cfg.lost_after_s:
            age = "never" if last is None else f"{now_mono - last:.2f} s ago"
            reason = (f"no telemetry for more than lost_after_s = {self.cfg.lost_after_s:g} s "
                      f"(last position {age})")
        elif (phase in OFFBOARD_PHASES and self._offboard_seen
              and self._transition is None and s.flight_mode != "OFFBOARD"):
            reason = f"left OFFBOARD unexpectedly (mode {s.flight_mode}, status "\
                     f"{s.system_status})"
            texts = [t.text for t in s.statustexts
                     if 0 <= t.severity <= 2 and now_mono - t.time_s <= 3.0]
            if texts:  # e.g. PX4's geofence or offboard-loss failsafe: "Failsafe activated"
                reason += f"; vehicle says \"{texts[-1]}\""
        elif phase in (Phase.IN_TUBE, Phase.EXITED) and s.armed is False:
            reason = "disarmed in the air"
        elif phase == Phase.IN_TUBE and (listening_since is None
                                         or now_mono - listening_since > self.unresponsive_s):
            reason = self._check_unresponsive(now_mono)
        if reason is None:
            return None
        if phase == Phase.ARMING:
            self.reason = reason
            self.set_phase(Phase.FAILED, reason)
            return reason
        self.declare_lost(reason)
        return reason

    #: The floor of :attr:`slow_m_s`: below this a vehicle is still whatever v_min is.
    STILL_M_S = 0.05

    @property
    def slow_m_s(self) -> float:
        """max(v_min / 2, :attr:`STILL_M_S`): a vehicle in the tube is always commanded at
        least v_min (> 0, paper note 9) and PX4's steady shortfall is 10–20 %, so one whose
        measured speed stays below half of v_min for :attr:`unresponsive_s` has slowed below
        v_min in the tube (issue 9): it is declared lost, an obstacle for everyone."""
        return max(0.5 * self.mission.scenario.robots.v_min, self.STILL_M_S)

    @property
    def unresponsive_s(self) -> float:
        """τ_d + 3 t63 + 1 s: longer than PX4 needs to follow any command change."""
        return self.cfg.tracking_dead_time_s + 3.0 * self.cfg.tracking_t63_s + 1.0

    def _check_unresponsive(self, now_mono: float) -> str | None:
        speed = math.hypot(float(self.vel_xy[0]), float(self.vel_xy[1]))
        cmd = self.cmd_xy
        commanded = cmd is not None and math.hypot(float(cmd[0]), float(cmd[1])) > 0.0
        slow = self.slow_m_s
        if not (commanded and speed < slow):
            self._still_since = None
            return None
        if self._still_since is None:
            self._still_since, self._still_xy = now_mono, self.xy.copy()
            return None
        still = now_mono - self._still_since
        if still < self.unresponsive_s:
            return None
        moved = math.hypot(float(self.xy[0] - self._still_xy[0]),
                           float(self.xy[1] - self._still_xy[1]))
        if moved >= slow * still:
            # the estimated position kept moving: the velocity estimate is off (with the
            # compensation PX4 flies v_c + d̂, not v_c), not the vehicle; count afresh
            self._still_since, self._still_xy = now_mono, self.xy.copy()
            return None
        why = "v_min / 2" if slow > self.STILL_M_S else "still"
        return (f"not following its setpoints: measured speed < {slow:g} m/s ({why}) for "
                f"{still:.1f} s, moved {moved:.2f} m, while commanded "
                f"{math.hypot(*cmd):.2f} m/s")  # type: ignore[misc]

    def declare_lost(self, reason: str) -> None:
        """Become a static obstacle at the last known position; stop commanding."""
        if self.phase == Phase.LOST:
            return
        self.reason = reason
        tab, r = self._t, self._r
        if self.has_position():
            tab.lost[r], tab.lost_set[r] = tab.xy[r], True
        self.cmd_xy = None
        self.cmd_in_tube = False
        where = ("" if self.lost_xy is None else
                 f"; static obstacle at ({self.lost_xy[0]:.2f}, {self.lost_xy[1]:.2f})")
        self.set_phase(Phase.LOST, reason + where)

    # -- actuation ---------------------------------------------------------------------------
    def vertical_down_m_s(self, climb: bool = False) -> float:
        """Altitude-hold term (NED down velocity)."""
        if not math.isfinite(self.up_m):
            return 0.0
        cfg = self.cfg
        up = cfg.altitude_gain_1_s * (cfg.altitude_m - self.up_m)
        hi = cfg.climb_speed_m_s if climb else cfg.max_vertical_speed_m_s
        return -_clamp(up, -cfg.max_vertical_speed_m_s, hi)

    def airborne(self) -> bool:
        """Off the ground: PX4 says IN_AIR, or more than 0.5 m up."""
        return (self.link.state.landed_state == "IN_AIR"
                or (math.isfinite(self.up_m) and self.up_m > 0.5))

    def join_fleet(self, row: int, compensators: CompensatorBank,
                   residuals: ResidualTracker, table: PilotTable) -> None:
        """Be row ``row`` of a fleet's tick-state table, compensator bank and residual
        tracker (the supervisor's, updated for all its vehicles at once) instead of ones of its
        own; the state so far comes along."""
        table.take_row(row, self._t, self._r)
        table.note_rotation(self._to_tube)
        self._t, self._r = table, row
        if self.compensator is not None:
            self.compensator = EstimateCompensator(bank=compensators, row=row)
        self._residuals, self._residual_row = residuals, row

    @property
    def disturbance_residual_m_s(self) -> np.ndarray:
        """|d̂(t) − d̂(t − Δ)| per tick in the tube so far (:class:`ResidualTracker`)."""
        return self._residuals.residuals(self._residual_row)

    def residual_lag_s(self) -> float:
        """The compensation's delay Δ = W/2 + T + L (what PX4 cannot have been told yet)."""
        comp = self.compensator
        window = comp.window_s if comp is not None else 0.0
        return 0.5 * window + self.cfg.period_s + (self.link.latency_s or 0.0)

    def _track_residual(self, now_mono: float) -> None:
        """This tick's compensation residual (:class:`ResidualTracker`), one value per tick in
        the tube; warns once if its mean stays above the budgeted D."""
        comp = self.compensator
        if comp is None:
            return
        row = np.array([self._residual_row])
        if self._residuals.track(row, now_mono, np.array([comp.correction], dtype=float),
                                 np.array([self.residual_lag_s()])).size:
            self.warn_residual()

    def warn_residual(self) -> None:
        """WARN: a limit crossed — the safety budget's D no longer covers the estimate."""
        mean = float(self._residuals.mean_m_s[self._residual_row])
        budget = self.cfg.disturbance_residual_m_s
        self.event(f"estimate compensation residual {mean:.2f} m/s "
                   f"(mean over {RESIDUAL_WINDOW_S:g} s) > the budgeted D = "
                   f"{budget:.2f} m/s: the flown radii may not cover the estimate error "
                   f"(mission key disturbance_residual_m_s)", "warning")

    def send_tube_velocity(self, vx: float, vy: float, down: float,
                           compensate: bool = False) -> None:
        """Send a tube-frame horizontal velocity (+ NED down) as a LOCAL_NED setpoint;
        ``compensate`` adds the estimate-disturbance correction d̂ (flying offboard)."""
        comp = self.compensator
        if compensate and comp is not None:
            dx, dy = comp.correction
            vx, vy = vx + dx, vy + dy
        a, b, c, d = self._to_ned
        self._send_ned(a * vx + b * vy, c * vx + d * vy, float(down))

    def _send_ned(self, north_m_s: float, east_m_s: float, down_m_s: float) -> None:
        """Send the setpoint (the vehicle's LOCAL_NED) and count it."""
        self.link.send_velocity_ned(north_m_s, east_m_s, down_m_s)
        tab, r = self._t, self._r
        tab.setpoints_sent[r] += 1
        if not tab.ever_sent[r]:
            tab.ever_sent[r] = True
            self.sent_setpoint.set()

    def actuate(
        self,
        now_mono: float,
        cmd_xy: np.ndarray | None = None,
        view: NeighbourView | None = None,
    ) -> None:
        """Send this tick's setpoint for the current phase.

        ``cmd_xy`` is the controller's command when IN_TUBE; ``view`` the neighbour view used by
        the exit behaviour when EXITED.
        """
        phase = self.phase
        self.cmd_in_tube = False
        if self.link.closed:
            return
        try:
            if self._transition is not None or phase == Phase.ARMING:
                # streaming before OFFBOARD / while a mode change is in flight: stay put
                self.cmd_xy = np.zeros(2)
                self.send_tube_velocity(0.0, 0.0, self.vertical_down_m_s()
                                        if phase != Phase.ARMING else 0.0)
            elif phase == Phase.TAKEOFF:
                vx = vy = 0.0
                if self.takeoff_xy is not None and self.has_position():
                    d = TAKEOFF_XY_GAIN_1_S * (self.takeoff_xy - self.xy)
                    n = float(np.hypot(*d))
                    if n > TAKEOFF_XY_MAX_M_S:
                        d *= TAKEOFF_XY_MAX_M_S / n
                    vx, vy = float(d[0]), float(d[1])
                self.cmd_xy = np.array([vx, vy])
                self.send_tube_velocity(vx, vy, self.vertical_down_m_s(climb=True),
                                        compensate=self.airborne())
            elif phase == Phase.IN_TUBE:
                cmd = np.zeros(2) if cmd_xy is None else np.asarray(cmd_xy, dtype=float)
                vx, vy = float(cmd[0]), float(cmd[1])
                if self.compensator is not None:
                    dx, dy = self.compensator.correction
                    vx, vy = vx + dx, vy + dy
                a, b, c, d = self._to_ned
                self.cmd_xy = cmd
                self.cmd_in_tube = True
                self._send_ned(a * vx + b * vy, c * vx + d * vy, self.vertical_down_m_s())
                self._track_residual(now_mono)
            elif phase == Phase.EXITED:
                self._actuate_exited(now_mono, view)
            else:
                self.cmd_xy = None
        except LinkError as exc:
            self.setpoint_failed(exc)

    def setpoint_failed(self, exc: LinkError) -> None:
        """A setpoint could not be sent (the link says why): a warning, the next tick tries
        again."""
        self.event(f"setpoint not sent: {exc}", "warning")

    def _actuate_exited(self, now_mono: float, view: NeighbourView | None) -> None:
        cfg = self.cfg
        plan = self.agent.plan
        past = float(plan.tube.xi(self.xy) - plan.tube.length) if self.has_position() else 0.0
        if cfg.after_exit in ("hold", "land") and past >= cfg.exit_clear_m:
            self.cmd_xy = np.zeros(2)
            self.send_tube_velocity(0.0, 0.0, self.vertical_down_m_s())
            if cfg.after_exit == "hold":
                self.begin_hold(f"{past:.1f} m past the finishing line")
            else:
                self.begin_land(f"{past:.1f} m past the finishing line")
            return
        v = None
        if view is not None and self.has_position():
            stop = 2.0 * plan.flown.r_s + plan.flown.v * (
                cfg.tracking_dead_time_s + cfg.tracking_t63_s + cfg.period_s)
            v = exit_velocity(plan, self.xy, view, stop_distance_m=stop)
            if v is None:
                self.cmd_xy = np.zeros(2)
                self.send_tube_velocity(0.0, 0.0, self.vertical_down_m_s())
                self.begin_hold("a stopped vehicle ahead past the finishing line")
                return
        if v is None:
            v = plan.flown.v * plan.tube.n_c
        self.cmd_xy = np.asarray(v, dtype=float)
        self.send_tube_velocity(float(v[0]), float(v[1]), self.vertical_down_m_s(),
                                compensate=True)

    # -- mode changes (background) -----------------------------------------------------------
    def _run_transition(self, coro: Awaitable[None], what: str) -> None:
        async def run() -> None:
            try:
                await coro
            except (LinkError, UserError) as exc:
                self.event(f"{what} failed: {exc}", "warning")
            finally:
                self._transition = None
                self._t.in_transition[self._r] = False

        self._transition = self.spawn(run())
        self._t.in_transition[self._r] = True

    def begin_hold(self, why: str) -> None:
        """Leave OFFBOARD into Hold (keeps streaming zero velocity until PX4 confirms)."""
        if self.phase in (Phase.HOLDING, Phase.LANDING, Phase.LANDED, Phase.LOST):
            return
        self.set_phase(Phase.HOLDING, why)
        self._offboard_seen = False
        self._run_transition(self.link.stop_offboard(), "hold")

    def begin_land(self, why: str) -> None:
        if self.phase in (Phase.LANDING, Phase.LANDED, Phase.LOST):
            return
        self.set_phase(Phase.LANDING, why)
        self._offboard_seen = False
        self._run_transition(self.link.land(), "land")

    # -- the procedure -------------------------------------------------------------------------
    async def wait_ready(self) -> None:
        """Heartbeat, positions, home, GPS origin and health (``ready_timeout_s``); phase
        CONNECTING → READY (no-op when already past CONNECTING)."""
        if self.phase != Phase.CONNECTING:
            return
        await self.link.wait_ready(self.cfg.ready_timeout_s)
        if not self.sense() and not self.has_position():
            await self.link.wait_until(lambda s: s.last_position_s is not None,
                                       self.cfg.ready_timeout_s, "a local position")
            self.sense()
        self.set_phase(Phase.READY, f"at ({self.xy[0]:.2f}, {self.xy[1]:.2f}) "
                                    f"up {self.up_m:.2f} m")

    async def prepare_onboard(self) -> None:
        """This vehicle alone (:meth:`fly`): the PX4 parameter audit (hard mismatches raise
        :class:`PilotError`, soft ones warn) and, unless ``fence`` is off, the tube as its
        geofence (GF_ACTION, upload, read back); backends without them warn and go on."""
        from vtube_fleet.fleet.onboard import (
            GF_ACTION_VALUES,
            NO_FENCE_WARNING,
            audit_fleet,
            fence_geometry,
            fence_items,
            install_fence,
        )
        from vtube_fleet.link.base import LinkUnsupported

        res = await audit_fleet([self.link], self.mission)
        for w in res.warnings:
            self.event(w, "warning")
        if res.problems:
            raise PilotError("nothing armed: PX4 parameters: " + "; ".join(res.problems))
        if not self.fence:
            self.event(NO_FENCE_WARNING, "warning")  # a safety layer turned off
            return
        geom = fence_geometry(self.mission)
        problems = geom.problems(self.xy.reshape(1, 2), [self.name])
        if problems:
            raise PilotError("nothing armed: the fence would be breached at once: "
                             + "; ".join(problems))
        try:
            await install_fence(self.link, fence_items(self.mission, geom),
                                GF_ACTION_VALUES[self.cfg.fence_action])
        except LinkUnsupported as exc:
            self.event(f"fence NOT uploaded: {exc}", "warning")
            return
        self.event(f"fence uploaded ({len(geom.polygon)} vertices, "
                   f"{geom.circle_radii.size} circle(s), GF_ACTION {self.cfg.fence_action})")

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

        Requires a control clock calling :meth:`actuate` (the supervisor's or :meth:`fly`'s).
        """
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
        self.takeoff_xy = self.xy.copy() if self.has_position() else None
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

    def enter_tube(self) -> None:
        if self.phase == Phase.TAKEOFF:
            self.set_phase(Phase.IN_TUBE)

    def mark_exit(self, t_s: float) -> None:
        self.exit_time_s = t_s
        self.set_phase(Phase.EXITED, f"crossed the finishing line at t = {t_s:.2f} s")

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
        """Land now; waits for the LAND command's acknowledgement (not for touch-down)."""
        if self.phase in AIRBORNE_PHASES and self.phase != Phase.LANDING:
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
            self.set_phase(Phase.LANDED, "never took off") if self.phase != Phase.CONNECTING \
                else None
            self.landed.set()

    def needs_landing(self) -> bool:
        """Airborne under our responsibility (:data:`~vtube_fleet.state.AIRBORNE_PHASES`)."""
        return self.phase in AIRBORNE_PHASES

    # -- standalone operation -------------------------------------------------------------
    def tick(self, now_mono: float, now_wall: float) -> None:
        """All per-tick steps for this vehicle alone (the MQTT agent's control clock)."""
        last = self._last_tick_s
        if self._clock_start_s is None:
            self._clock_start_s = now_mono  # this pilot's mission time counts from its 1st tick
        if last is not None and now_mono - last > 2.0 * self.cfg.period_s + 0.1:
            self._listening_since = now_mono  # our loop stalled: do not blame the vehicle
        self._last_tick_s = now_mono
        self.sense()
        self.check_faults(now_mono, self._listening_since)
        self.publish(now_mono, now_wall)
        agent = self.agent
        agent.observe(self.bus.latest())
        heard = (None if self._listening_since is None
                 else now_wall - (now_mono - self._listening_since))
        view = agent.view(now_wall, heard)
        if (agent.update_plan(view) and self.phase == Phase.IN_TUBE and self.has_position()
                and cannot_pass(agent.plan.partition, self.xy, agent.plan.zones)[0]):
            # inside the region the new partition takes around a lost vehicle: no safe
            # sub-tube for this one (core/loss.cannot_pass); the caller holds it
            raise PartitionError(None, f"vehicle {self.vehicle_id} at ({self.xy[0]:.2f}, "
                                 f"{self.xy[1]:.2f}) is inside the region the new partition "
                                 f"takes around it (no safe sub-tube for it)")
        cmd = None
        if self.phase == Phase.IN_TUBE and self.has_position():
            if agent.has_exited(self.xy):
                self.mark_exit(now_mono - self._clock_start_s)
            else:
                sp = agent.setpoint(self.xy, view)
                cmd = np.array([sp.vx_m_s, sp.vy_m_s])
        self.actuate(now_mono, cmd, view)

    async def run_clock(self, stop: asyncio.Event) -> None:
        """Call :meth:`tick` at ``rate_hz`` until ``stop`` is set."""
        loop = asyncio.get_running_loop()
        period = self.cfg.period_s
        next_t = loop.time()
        while not stop.is_set():
            self.tick(loop.time(), self.wall_clock())
            next_t += period
            now = loop.time()
            if next_t < now:
                next_t = now
            try:
                async with asyncio.timeout(next_t - now):
                    await stop.wait()
            except TimeoutError:
                pass

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
        """The whole procedure for this vehicle alone, with its own control clock.

        ``start`` is awaited at altitude before entering the tube (e.g. the fleet's "start"
        command), ``finish`` after this vehicle exited (e.g. "all vehicles exited") before
        ``on_complete`` (land or hold). Returns the final phase once landed / holding / lost.
        """
        stop = asyncio.Event()
        clock = asyncio.get_running_loop().create_task(self.run_clock(stop))
        cfg = self.cfg
        try:
            await self.wait_ready()
            await self.prepare_onboard()
            await self.arm_and_climb()
            if start is not None:
                await start()
            self.enter_tube()
            await self.wait_phase(lambda ph: ph != Phase.IN_TUBE, cfg.mission_timeout_s,
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
        finally:
            stop.set()
            await clock


def fleet_table(pilots: Sequence[VehiclePilot]) -> PilotTable:
    """The table whose rows ``pilots`` are, in order (a supervisor's fleet: ``join_fleet``);
    :class:`ValueError` otherwise (the fleet steps below read and write whole columns)."""
    if not pilots:
        return PilotTable(0)
    t = pilots[0]._t
    if t.n != len(pilots) or pilots[0]._r != 0 or pilots[-1]._t is not t or (
            pilots[-1]._r != t.n - 1):
        raise ValueError("the fleet steps need the pilots of one table, in its row order "
                         "(VehiclePilot.join_fleet)")
    return t


_TAKEOFF = PHASE_CODE[Phase.TAKEOFF]
_IN_TUBE = PHASE_CODE[Phase.IN_TUBE]
_OFFBOARD_MASK = phase_mask(OFFBOARD_PHASES)


@dataclass(frozen=True, slots=True)
class LinkColumns:
    """What a fleet's steps read from the links in a tick, gathered in ONE pass over them
    (:func:`link_columns`): each link's ``states`` (its :class:`VehicleState`), the arrival of
    its latest local position ``position_s`` (NaN: none), whether its GPS origin is known
    (``origin_known``), whether it reports OFFBOARD and armed (``offboard_armed``), its one-way
    latency ``latency_s`` (NaN: not measured yet) and whether it is ``closed``. The links only
    change between ticks (their telemetry arrives in the event loop), so one snapshot serves
    every step of a tick."""

    states: list[VehicleState]
    position_s: np.ndarray
    origin_known: np.ndarray
    offboard_armed: np.ndarray
    latency_s: np.ndarray
    closed: np.ndarray


def link_columns(pilots: Sequence[VehiclePilot]) -> LinkColumns:
    """The pilots' links as :class:`LinkColumns`, in the pilots' order."""
    n = len(pilots)
    links = [p.link for p in pilots]
    states = [lk.state for lk in links]
    nan = math.nan
    cols = np.array([(nan if (t := s.last_position_s) is None else t, s.origin is not None,
                      s.flight_mode == "OFFBOARD" and s.armed is True,
                      nan if (x := lk.latency_s) is None else x, lk.closed)
                     for lk, s in zip(links, states, strict=True)],
                    dtype=float).reshape(n, 5)
    return LinkColumns(states, cols[:, 0], cols[:, 1] == 1.0, cols[:, 2] == 1.0, cols[:, 3],
                       cols[:, 4] == 1.0)


def sense_all(pilots: Sequence[VehiclePilot], frame: TubeFrame,
              links: LinkColumns | None = None) -> int:
    """:meth:`VehiclePilot.sense` for a fleet (:func:`fleet_table`): the new samples found in
    one pass over the links, ONE vectorized frame conversion of the positions (pymap3d on
    arrays) and of the velocities, written into the table's columns, and, for the pilots of
    one compensator bank (a supervisor's fleet), one compensator update for all; the same
    arithmetic as one by one. Returns how many had a new sample. ``links``:
    :func:`link_columns` of this tick, if the caller has it."""
    if not pilots:
        return 0
    tab = fleet_table(pilots)
    if links is None:
        links = link_columns(pilots)
    states = links.states
    last = links.position_s
    rows = np.flatnonzero(np.isfinite(last) & links.origin_known
                          & (last != tab.sample_s))  # pending_sample
    if not rows.size:
        return 0
    todo_rows = rows.tolist()
    st = [states[i] for i in todo_rows]
    k = len(st)
    cols = np.array([(s.north_m, s.east_m, s.down_m, s.origin.lat_deg,  # type: ignore[union-attr]
                      s.origin.lon_deg, s.origin.alt_m,  # type: ignore[union-attr]
                      s.vn_m_s, s.ve_m_s) for s in st], dtype=float).reshape(k, 8).T
    x, y, up = (np.atleast_1d(v).astype(float) for v in frame.local_ned_to_tube(*cols[:6]))
    todo = [pilots[i] for i in todo_rows]
    rot = tab.to_tube
    if rot is None:  # not one frame: each pilot rotates its own
        for p, s, xi, yi, ui in zip(todo, st, x.tolist(), y.tolist(), up.tolist(),
                                    strict=True):
            p._take(s, xi, yi, ui)
        return k
    a, b, c, d = rot
    vn, ve, t = cols[6], cols[7], last[rows]
    vx, vy = a * vn + b * ve, c * vn + d * ve  # VehiclePilot._take's rotation
    has = np.isfinite(x) & np.isfinite(y)
    tab.xy[rows, 0], tab.xy[rows, 1] = x, y  # VehiclePilot._use, for all
    tab.vel[rows, 0], tab.vel[rows, 1] = vx, vy
    tab.up[rows] = up
    tab.sample_s[rows] = t
    tab.has[rows] = has
    cfg = todo[0].cfg
    climbing = (tab.phase[rows] == _TAKEOFF) & (
        np.abs(up - cfg.altitude_m) <= cfg.altitude_tolerance_m)
    for j in np.flatnonzero(climbing).tolist():
        if not todo[j].at_altitude.is_set():
            todo[j].at_altitude.set()
    comps = [p.compensator for p in todo]
    bank = comps[0].bank if comps[0] is not None else None
    if bank is not None and all(cp is not None and cp.bank is bank for cp in comps):
        bank.add(np.fromiter((cp.row for cp in comps), np.int64, k),  # type: ignore[union-attr]
                 t, x, y, vx, vy)
    else:
        for cp, ti, xi, yi, vxi, vyi, hi in zip(comps, t.tolist(), x.tolist(), y.tolist(),
                                                vx.tolist(), vy.tolist(), has.tolist(),
                                                strict=True):
            if cp is not None and hi:
                cp.add(ti, xi, yi, vxi, vyi)
    return k


@dataclass(frozen=True, slots=True)
class FleetStates:
    """:meth:`VehiclePilot.state` of many pilots at once, as arrays: the pilots that have a
    position sample, in their order (``ids`` (n,), ``pos``/``vel`` (n, 2) tube frame, ``phases``
    n, ``stamps_s`` wall clock, ``sample_s`` monotonic arrival, ``ages_s`` =
    :meth:`VehiclePilot.sample_age_s`)."""

    ids: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    phases: list[Phase]
    stamps_s: np.ndarray
    sample_s: np.ndarray
    ages_s: np.ndarray


def fleet_states(pilots: Sequence[VehiclePilot], now_mono: float, now_wall: float,
                 links: LinkColumns | None = None) -> FleetStates:
    """What each pilot's :meth:`VehiclePilot.state` would say now (the same arithmetic),
    from the fleet's table (:func:`fleet_table`): a LOST vehicle at its frozen position with
    zero velocity, the stamp the wall-clock time its position was measured. ``links``:
    :func:`link_columns` of this tick, if the caller has it."""
    tab = fleet_table(pilots)
    have = np.flatnonzero(np.isfinite(tab.sample_s))
    lost = tab.lost_set[have, None]
    pos = np.where(lost, tab.lost[have], tab.xy[have])
    vel = np.where(lost, 0.0, tab.vel[have])
    sample = tab.sample_s[have]
    latency = (link_columns(pilots) if links is None else links).latency_s
    ages = (now_mono - sample) + np.nan_to_num(latency[have], nan=0.0)  # sample_age_s
    return FleetStates(np.fromiter((pilots[i].vehicle_id for i in have.tolist()), np.int64,
                                   have.size),
                       pos, vel, [PHASES[c] for c in tab.phase[have].tolist()],
                       now_wall - ages, sample, ages)


def actuate_all(pilots: Sequence[VehiclePilot], now_mono: float, commanded: Sequence[VehiclePilot],
                cmds: np.ndarray, view: NeighbourView | None,
                links: LinkColumns | None = None) -> None:
    """:meth:`VehiclePilot.actuate` for a fleet (:func:`fleet_table`): ``commanded`` (IN_TUBE)
    get the rows of ``cmds`` (K, 2), the others no command. The in-tube pilots' arithmetic
    (command + d̂, the altitude hold, the rotation to NED) is done for all of them at once with
    the same operations as :meth:`VehiclePilot.actuate` (the same bits), their commands written
    into the table and their setpoints sent together
    (:func:`~vtube_fleet.link.base.send_velocities_ned`); the other pilots take
    :meth:`VehiclePilot.actuate` one by one, in order. The pilots share one mission and frame
    (the supervisor's). ``links``: :func:`link_columns` of this tick, if the caller has it."""
    if not pilots:
        return
    tab = fleet_table(pilots)
    if links is None:
        links = link_columns(pilots)
    crow = np.fromiter((p._r for p in commanded), np.int64, len(commanded))
    ok = (tab.phase[crow] == _IN_TUBE) & ~tab.in_transition[crow] & ~links.closed[crow]
    batch = np.flatnonzero(ok)
    brows = crow[batch]
    in_batch = np.zeros(len(pilots), bool)
    in_batch[brows] = True
    slow = {int(crow[k]): cmds[k] for k in np.flatnonzero(~ok).tolist()}
    for r in np.flatnonzero(~in_batch).tolist():
        pilots[r].actuate(now_mono, slow.get(r), view)
    if not batch.size:
        return
    bp = [pilots[r] for r in brows.tolist()]
    first = bp[0]
    cfg = first.cfg
    cmd = cmds[batch]
    v = cmd
    corr: np.ndarray | None = None
    bank: CompensatorBank | None = None  # the batch's one bank, if they share one
    if cfg.compensate_estimate:
        comps = [p.compensator for p in bp]
        bank = comps[0].bank  # type: ignore[union-attr]
        if all(c.bank is bank for c in comps):  # type: ignore[union-attr]
            at = np.fromiter((c.row for c in comps), np.int64, len(comps))  # type: ignore
            corr = np.stack((bank.dx_m_s[at], bank.dy_m_s[at]), axis=1)
        else:
            bank = None
            corr = np.array([c.correction for c in comps],  # type: ignore[union-attr]
                            dtype=float).reshape(-1, 2)
        v = cmd + corr
    vx, vy = v[:, 0], v[:, 1]
    a, b, c, d = first._to_ned
    up = tab.up[brows]
    u = cfg.altitude_gain_1_s * (cfg.altitude_m - up)  # vertical_down_m_s, vectorized
    lo = -cfg.max_vertical_speed_m_s
    hi = cfg.max_vertical_speed_m_s
    down = np.where(np.isfinite(up), -np.where(u < lo, lo, np.where(u > hi, hi, u)), 0.0)
    # the IN_TUBE branch of VehiclePilot.actuate: the command, then the send
    tab.cmd[brows] = cmd
    tab.cmd_set[brows] = True
    tab.cmd_in_tube[brows] = True
    failed = send_velocities_ned([p.link for p in bp], a * vx + b * vy, c * vx + d * vy, down)
    sent = np.fromiter((e is None for e in failed), bool, len(failed))
    tab.setpoints_sent[brows[sent]] += 1
    for j in np.flatnonzero(sent & ~tab.ever_sent[brows]).tolist():
        tab.ever_sent[brows[j]] = True
        bp[j].sent_setpoint.set()
    for j in np.flatnonzero(~sent).tolist():
        bp[j].setpoint_failed(failed[j])  # type: ignore[arg-type]
    if corr is None or not sent.any():
        return
    sent_at = np.flatnonzero(sent)
    tracked = [bp[j] for j in sent_at.tolist()]
    tracker = tracked[0]._residuals
    if bank is None or any(p._residuals is not tracker for p in tracked):
        for p in tracked:  # not one fleet's bank and tracker: each pilot on its own
            p._track_residual(now_mono)
        return
    ids = np.fromiter((p._residual_row for p in tracked), np.int64, len(tracked))
    # residual_lag_s, vectorized: (W/2 + T) + L, W the shared bank's
    lag = (0.5 * bank.window_s + cfg.period_s) + np.nan_to_num(links.latency_s[brows[sent_at]],
                                                               nan=0.0)
    crossed = tracker.track(ids, now_mono, corr[sent_at], lag)
    if crossed.size:
        by_row = {p._residual_row: p for p in tracked}
        for r in crossed.tolist():
            by_row[r].warn_residual()


def check_faults_all(pilots: Sequence[VehiclePilot], now_mono: float,
                     listening_since: float | None = None,
                     links: LinkColumns | None = None) -> None:
    """:meth:`VehiclePilot.check_faults` for a fleet (:func:`fleet_table`). One vectorized
    pass first finds the pilots for which it can neither find a fault nor change anything
    (flying offboard and confirmed so, armed, heard within ``lost_after_s``, and in the tube
    not slow, or not commanded, with no slow spell being timed); only the others are checked
    one by one. The pass is conservative: a speed within 1 ppm of the threshold is checked.
    The pilots share one mission (the supervisor's). ``links``: :func:`link_columns` of this
    tick, if the caller has it."""
    if not pilots:
        return
    tab = fleet_table(pilots)
    if links is None:
        links = link_columns(pilots)
    cfg = pilots[0].cfg
    last = links.position_s
    heard = last if listening_since is None else np.maximum(last, listening_since)
    quiet = _OFFBOARD_MASK[tab.phase] & tab.offboard_seen & links.offboard_armed
    quiet &= now_mono - heard <= cfg.lost_after_s  # NaN (never heard): not quiet
    first = pilots[0]
    if listening_since is None or now_mono - listening_since > first.unresponsive_s:
        tube = tab.phase == _IN_TUBE
        timing = np.isfinite(tab.still_since_s)
        vel = tab.vel
        cmd = np.where(tab.cmd_set[:, None], tab.cmd, 0.0)
        idle = (cmd[:, 0] == 0.0) & (cmd[:, 1] == 0.0)  # not commanded (NaN: maybe)
        fast = vel[:, 0] ** 2 + vel[:, 1] ** 2 >= (first.slow_m_s * (1.0 + 1e-6)) ** 2
        quiet &= ~tube | (~timing & (idle | fast))
    for i in np.flatnonzero(~quiet).tolist():
        pilots[i].check_faults(now_mono, listening_since)
