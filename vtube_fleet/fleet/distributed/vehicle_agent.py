"""One vehicle flown by its own process (``vtube-fleet agent``).

Its control loop (:class:`AgentControl`: the fleet's control tick over a table of one row) reads
the neighbours' states from an MQTT broker (:class:`BusNeighbours`), stands still when that
information cannot be trusted, and records its own view of the flight (:class:`AgentRecording`);
:class:`AgentProcess` joins a run, measures, checks and flies it.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from vtube_fleet.bus.codec import MissionConfigMsg
from vtube_fleet.bus.mqtt import MqttBus
from vtube_fleet.bus.validate import mission_state_limits
from vtube_fleet.config.keys import POSITIVE
from vtube_fleet.core.metrics import finite_or_none, percentile_or_none, verdict
from vtube_fleet.core.partition import PartitionError
from vtube_fleet.errors import UserError, bug_text
from vtube_fleet.fleet.budget import (
    BudgetWatch,
    LinkMeasurement,
    ResponseModel,
    SafetyBudget,
    mission_budget,
)
from vtube_fleet.fleet.distributed import unsupported
from vtube_fleet.fleet.distributed.coordinator import (
    ASSUMED_ACCURACY_M,
    ASSUMED_LINK_LATENCY_S,
    DEFAULT_BROKER,
    bus_safety_budget,
    clock_latency_s,
    default_max_age_s,
    default_mission_id,
    needed_cell_m,
)
from vtube_fleet.fleet.flight_plan import FlightPlan
from vtube_fleet.fleet.neighbour_view import States, states_of
from vtube_fleet.fleet.onboard import NO_FENCE_WARNING
from vtube_fleet.fleet.pilot import VehiclePilot
from vtube_fleet.fleet.preflight import (
    Preflight,
    PreflightError,
    measure_budget_links,
    preflight_report,
    wait_accuracy,
)
from vtube_fleet.fleet.response_check import ResponseProbe, ResponseReport, run_response_check
from vtube_fleet.fleet.table import FleetTable
from vtube_fleet.fleet.tick import ControlClock, Tick, watch_budget
from vtube_fleet.outcome import EXIT_INCOMPLETE, EXIT_OK, EXIT_UNSAFE
from vtube_fleet.recording.api import NullRecorder, Recorder
from vtube_fleet.state import AIRBORNE_PHASES, TUBE_PHASES, NeighbourState, Phase

__all__ = [
    "AgentAborted",
    "AgentProcess",
    "AgentRecording",
    "AgentRefused",
    "BACKOFF_JITTER",
    "CLOCK_SAMPLES",
    "CLOCK_TIMEOUT_S",
    "AgentControl",
    "BusNeighbours",
    "rejoin_grace_s",
]

log = logging.getLogger(__name__)










#: Clock round trips an agent makes to the coordinator before it joins a run, and how long it
#: waits for each (docs/mqtt.md, "Clocks"): the one of least delay is kept.
CLOCK_SAMPLES = 8
CLOCK_TIMEOUT_S = 1.0

#: Teammate stages that count as "at altitude or further" for the response check …
_UP_STAGES = ("at_altitude", "checked", "in_tube", "exited", "done")
#: … and as "checked or further" for the tube-entry barrier.
_CHECKED_STAGES = _UP_STAGES[1:]
#: A teammate refused at the tube-entry barrier: how long to wait for the coordinator's abort
#: (one coordinator period and two broker hops, normally) before landing without it.
REFUSAL_ABORT_WAIT_S = 5.0


#: The status stages of an agent whose vehicle waits in the tube, by how many times it was
#: released and found no path (docs/fleet.md, "Waiting for a way").
WAITING_STAGES = ("waiting", "waiting again")
#: Teammate stages that count as "past the finishing line" for the exit barrier.
_OUT_STAGES = ("exited", "done")


class AgentRefused(UserError):
    """This agent will not fly the announced run (config hash, slot, late, preflight)."""


class AgentAborted(UserError):
    """The run was aborted (by the coordinator) or could not be completed after arming."""

    exit_code = EXIT_INCOMPLETE


class AgentInterrupted(Exception):
    """SIGINT / SIGTERM arrived; the message says what became of the vehicle (held and landed
    after the start; nothing armed before it; never reached during the join)."""


# ----------------------------------------------------------------------------------------------
# the neighbours over the bus, and the vehicle's control loop
# ----------------------------------------------------------------------------------------------
#: The reconnect back-off's jitter (:class:`~vtube_fleet.bus.mqtt.MqttBus`: ±20 %).
BACKOFF_JITTER = 1.2


def rejoin_grace_s(lost_after_s: float, backoff_max_s: float, period_s: float) -> float:
    """How long after the broker is back an agent waits, standing still, for a silent airborne
    neighbour before it counts as lost: the neighbour's agent may still be in one reconnect
    back-off (≤ ``BACKOFF_JITTER`` × ``backoff_max_s``; a broker outage ends for every agent
    at a different moment), then needs two control periods to publish, then the usual
    ``lost_after_s``. Shorter, a fleet that lost its broker would count its slowest
    reconnecting members as lost obstacles (measured: agents reconnected up to 2.1 s apart
    after a 3 s outage with ``backoff_max_s`` = 2 s, ``lost_after_s`` = 1 s)."""
    return lost_after_s + BACKOFF_JITTER * backoff_max_s + 2.0 * period_s


class BusNeighbours:
    """The other vehicles as an agent hears them on the bus
    (:class:`~vtube_fleet.fleet.tick.NeighbourSource`), and when not to trust them ("Broker
    loss"): disconnected, silent (our own state does not come back), or healthy again for less
    than :func:`rejoin_grace_s` with an airborne neighbour whose state is older than
    ``max_age_s``. While :meth:`problem` says why, the tick stands the vehicle still in the
    tube (zero horizontal velocity of the estimated position, altitude hold) and leaves the
    plan alone."""

    def __init__(self, mqtt: Any, *, max_age_s: float, lost_after_s: float,
                 period_s: float, teammates: Callable[[], Iterable[int]] | None = None,
                 gone: Callable[[int], bool] | None = None) -> None:
        self.mqtt = mqtt
        self.teammates = teammates
        self.gone = gone
        self.max_age_s = float(max_age_s)
        self.lost_after_s = float(lost_after_s)
        self.period_s = float(period_s)
        self.holding: str | None = None  # why the vehicle stands still now (None: it flies)
        self._healthy_since: float | None = None  # wall time the bus became healthy again

    def states(self, now_wall: float) -> States:
        return states_of(self.mqtt.latest().values())

    def tube_stages(self, now_wall: float) -> tuple[bool, dict[int, int]]:
        """The fleet-wide part of releasing a waiting vehicle (Tick._waiting; states reach
        only nearby cells, statuses every agent): whether a teammate that is not gone may fly
        among the others (its status stage neither waiting nor past the tube: ``exited`` or
        ``done``), and the teammates waiting with how many times each was released without
        a path (stage ``waiting``: 0, ``waiting again``: 1). Without teammates (no run):
        (False, {})."""
        if self.teammates is None:
            return False, {}
        own = getattr(self.mqtt, "vehicle_id", None)
        busy, waiting = False, {}
        for v in self.teammates():
            if v == own or (self.gone is not None and self.gone(v)):
                continue
            st = self.mqtt.statuses.get(v)
            stage = st.stage if st is not None and st.run_id == self.mqtt.run_id else ""
            if stage in WAITING_STAGES:
                waiting[v] = WAITING_STAGES.index(stage)
            elif stage not in _OUT_STAGES:
                busy = True
        return busy, waiting

    def problem(self, now_wall: float) -> str | None:
        """Why neighbour information cannot be trusted now (None: it can)."""
        why = self._problem(now_wall)
        self.holding = why
        return why

    def _problem(self, now_wall: float) -> str | None:
        mqtt = self.mqtt
        if not mqtt.connected:
            self._healthy_since = None
            return f"MQTT broker {mqtt.host}:{mqtt.port} unreachable"
        silence = mqtt.echo_silence_s
        if silence > self.max_age_s + 2.0 * self.period_s:
            self._healthy_since = None
            return (f"MQTT broker {mqtt.host}:{mqtt.port} silent (our own state has not "
                    f"come back for {silence:.2f} s)")
        if self._healthy_since is None:
            self._healthy_since = now_wall
        if self.holding is None:
            return None
        grace = rejoin_grace_s(self.lost_after_s, mqtt.backoff_max_s, self.period_s)
        if now_wall - self._healthy_since > grace:
            return None  # the still silent ones are lost now (the tick's classification)
        lost = mqtt.lost
        stale = sorted(vid for vid, st in mqtt.latest().items()
                       if st.phase in AIRBORNE_PHASES and vid not in lost
                       and now_wall - st.stamp_s > self.max_age_s)
        if stale:
            return f"waiting for fresh states of vehicle(s) {', '.join(map(str, stale))}"
        return None


class AgentControl:
    """One vehicle's control loop in its agent process: the control tick
    (:class:`~vtube_fleet.fleet.tick.Tick`) over a one-row table, with the neighbours from the
    bus (:class:`BusNeighbours`), run by a :class:`~vtube_fleet.fleet.tick.ControlClock` from
    connect to the end; after each tick the agent's own rules: standing still for the bus (told
    once, and landing after ``broker_hold_limit_s`` without a broker), the budget watch
    (``watch``, set once the budget is measured), and the recording (``recording``, from the
    start command on). A failed re-partition makes the vehicle hold, as the supervisor does."""

    def __init__(self, pilot: VehiclePilot, mqtt: MqttBus, mission: Any, plan: FlightPlan, *,
                 max_age_s: float, broker_hold_limit_s: float = 30.0,
                 wall_clock: Callable[[], float] = time.time,
                 teammates: Callable[[], Iterable[int]] | None = None,
                 gone: Callable[[int], bool] | None = None) -> None:
        cfg = mission.config
        self.pilot = pilot
        self.mqtt = mqtt
        self.cfg = cfg
        self.broker_hold_limit_s = broker_hold_limit_s
        self.neighbours = BusNeighbours(mqtt, max_age_s=max_age_s,
                                        lost_after_s=cfg.lost_after_s, period_s=cfg.period_s,
                                        teammates=teammates, gone=gone)
        self._told_waiting: str | None = None  # the waiting stage told (None: none)
        self._replan_worker = ThreadPoolExecutor(1, thread_name_prefix="replan")
        self.tick = Tick(pilot.table, [pilot], mission, plan, frame=pilot.frame,
                         neighbours=self.neighbours, publish=mqtt.publish,
                         on_exit=self._exited, on_replan_failed=self._replan_failed,
                         replan_worker=self._replan_worker)
        self.clock = ControlClock(cfg.period_s, self.step, guard=self._tick_failed,
                                  wall_clock=wall_clock)
        self.bus_hold: str | None = None  # why the vehicle stands still for the bus
        self.bus_hold_since: float | None = None  # monotonic
        self.bus_holds = 0  # how many times it stood still for the bus
        self.recording: AgentRecording | None = None  # fed after every tick once flying
        self.watch: BudgetWatch | None = None  # the in-flight budget check (set when measured)
        self.probe: ResponseProbe | None = None  # the response check's, while it flies
        self.response: ResponseReport | None = None  # the response check, once flown
        self._forgotten: set[int] = set()
        self._aborted = False  # abort_for has run
        self._clock_task: asyncio.Task[None] | None = None
        self._stop = asyncio.Event()

    # -- what the recording and the summary read ------------------------------------------------
    @property
    def phase(self) -> Phase:
        return self.pilot.phase

    @property
    def reason(self) -> str | None:
        return self.pilot.reason

    @property
    def last_state(self) -> NeighbourState | None:
        return self.tick.last_states.get(self.pilot.vehicle_id)

    @property
    def cmd_xy(self) -> np.ndarray | None:
        return self.pilot.cmd_xy

    @property
    def cmd_in_tube(self) -> bool:
        return self.pilot.cmd_in_tube

    @property
    def battery_pct(self) -> float | None:
        """The vehicle's last reported charge (%; None: none reported)."""
        return finite_or_none(round(100.0 * self.pilot.link.state.battery_remaining, 1))

    @property
    def tick_gaps_s(self) -> list[float]:
        """Every gap between two control ticks (s)."""
        return self.clock.gaps_s

    # -- the clock -------------------------------------------------------------------------------
    def start(self) -> None:
        """Run the control clock (until :meth:`stop`)."""
        if self._clock_task is None:
            self._clock_task = asyncio.get_running_loop().create_task(
                self.clock.run(self._stop))

    async def stop(self) -> None:
        self._stop.set()
        if self._clock_task is not None:
            await self._clock_task
            self._clock_task = None
        self._replan_worker.shutdown(wait=False, cancel_futures=True)

    def set_plan(self, plan: FlightPlan) -> None:
        self.tick.set_plan(plan)

    # -- one tick and the agent's rules after it --------------------------------------------------
    def step(self, now_mono: float, now_wall: float, listening_since: float | None) -> None:
        try:
            result = self.tick(now_mono, now_wall, listening_since)
            if self.probe is not None:
                self.probe.on_tick(now_mono)
            self._bus_rule(now_mono, result.untrusted)
            self._tell_waiting()
            if result.untrusted is None and self.watch is not None:
                warning, hold = watch_budget(
                    self.watch, self.pilot.table, result, self.clock.take_recent_gap(),
                    lambda rows: [self.pilot.position_accuracy_m() for _ in rows.tolist()],
                    forgotten=self._forgotten)
                if warning:
                    self.pilot.event(warning, "warning")
                if hold:  # holding, this vehicle becomes an obstacle for every other agent
                    self.stop_for(hold)
                    self.pilot.begin_hold(hold)
        finally:
            rec = self.recording
            if rec is not None:
                try:
                    rec.sample(self, now_wall)
                except Exception:  # noqa: BLE001 - the safety evaluation failed (noted there)
                    self.abort_for(rec.failure or "safety monitor failed")
                rec.after_tick(self, now_mono, now_wall)  # the interim summary, when due

    def _bus_rule(self, now_mono: float, problem: str | None) -> None:
        """Standing still while the neighbours cannot be trusted: told once; landing after
        ``broker_hold_limit_s`` without a broker; told again when it resumes."""
        pilot = self.pilot
        if problem is None:
            if self.bus_hold is not None:
                held = now_mono - (self.bus_hold_since or now_mono)
                pilot.event(f"resuming after {held:.1f} s: broker back, neighbour states fresh")
                self.bus_hold = self.bus_hold_since = None
            return
        if self.bus_hold is None:
            self.bus_hold_since = now_mono
            self.bus_holds += 1
            pilot.event(f"{problem}: standing still in the tube (zero horizontal velocity of "
                        f"the estimated position, altitude hold) until the broker is back and "
                        f"neighbour states are fresh", "warning")
        self.bus_hold = problem
        held = now_mono - (self.bus_hold_since or now_mono)
        if held > self.broker_hold_limit_s and not self.mqtt.connected:
            why = (f"no MQTT broker for {held:.0f} s > --broker-hold-limit "
                   f"{self.broker_hold_limit_s:g} s")
            self.stop_for(why)
            pilot.begin_land(why)

    def _tell_waiting(self) -> None:
        """Every teammate hears (the status stage) when this vehicle starts and stops waiting
        in the tube: the release of a waiting vehicle is fleet-wide (Tick._waiting)."""
        pilot = self.pilot
        stage = (WAITING_STAGES[min(int(pilot.table.step_tries[pilot.row]), 1)]
                 if pilot.phase == Phase.WAITING else None)
        if stage != self._told_waiting:
            if stage is not None or self._told_waiting is not None:
                self.mqtt.announce("online", stage=stage or "in_tube")
            self._told_waiting = stage

    def _exited(self, rows: np.ndarray, t_s: float) -> None:
        self.mqtt.announce("online", stage="exited")  # every teammate hears it

    def _replan_failed(self, exc: Exception, view: Any) -> None:
        why = f"cannot re-partition the tube around the lost or stopped vehicles: {exc}"
        self.stop_for(why)
        self.pilot.begin_hold(why)

    def _tick_failed(self, exc: Exception) -> None:
        log.exception("agent %d: control tick failed", self.pilot.vehicle_id, exc_info=exc)
        self.abort_for(f"control tick failed: {type(exc).__name__}: {exc}")

    def stop_for(self, why: str) -> None:
        """Keep the first reason this vehicle stopped flying the tube (its summary's and its
        state's ``reason``): a hold or landing is never left unexplained."""
        if not self.pilot.reason:
            self.pilot.reason = why

    def abort_for(self, why: str) -> None:
        """What the supervisor's ``request_abort`` does for one vehicle: keep the reason, hold
        while in the tube (every tick: a vehicle still taking off holds once it is in)."""
        if not self._aborted:
            self._aborted = True
            self.pilot.event(f"ABORT: {why}", "error")
        self.stop_for(why)
        if self.pilot.phase in TUBE_PHASES | {Phase.EXITED}:
            self.pilot.begin_hold("mission aborted")


# ----------------------------------------------------------------------------------------------
# the agent's recording
# ----------------------------------------------------------------------------------------------
class AgentRecording:
    """What ``vtube-fleet agent`` records from the start command on: ``OUT/recording.rrd``
    and ``OUT/summary.json``.

    The fleet *as this agent heard it*, folded by the coordinator's
    :class:`~vtube_fleet.fleet.distributed.monitor.RunMonitor` (same layout, same summary keys, so
    ``vtube-fleet review`` recomputes the summary the agent wrote): the neighbours' states as
    they arrived through the broker (their ages are the summary's ``state_age_*``), and this
    vehicle's own state and velocity command at every control tick, also while the broker is
    away. Vehicles outside the agent's spatial cells are not heard, so fleet-wide counts
    (``exited``) cover only the vehicles it heard; the agent's own figures are
    ``exit_time_s`` (seconds since the start command, like every time in the summary),
    ``min/max_commanded_speed_m_s`` (its tube controller's commands),
    ``bus_holds``, ``tick_gap_p99_s`` / ``tick_gap_max_s`` (the time between two of its control
    ticks; ``tick_gap_max_in_tube_s`` over the ticks in the tube, where the budget watch holds
    the vehicle after 2 s in a row of gaps above T + L), ``response_check`` (its vehicle's, as
    ``run``'s summary gives it), ``response_watch`` (velocity tracking, once in the tube) and
    ``phase``.

    While flying, ``OUT/summary.json`` is rewritten atomically every
    :data:`~vtube_fleet.artifacts.SUMMARY_EVERY_S` with ``complete: false``
    (:meth:`after_tick`); the one :meth:`finish` writes says ``complete: true``.
    """

    def __init__(self, mission: Any, vehicles: int, vehicle: int, recorder: Any,
                 t0_s: float, out: Path | None = None,
                 meta: dict[str, Any] | None = None, flown: Any = None,
                 wall_clock: Callable[[], float] = time.time, route: Any = None,
                 work_clock: Callable[[], float] = time.perf_counter) -> None:
        """``out``: where the interim summaries go (:meth:`after_tick`; None: none);
        ``meta``: keys every summary carries (mission and run id, config hash, broker, the
        clock); ``flown``: the radii the run flies (r_s', r_a'), where the monitor looks for
        pairs; ``wall_clock``: the agent's; ``route``: the route it flies (the monitor replays
        its hand-overs); ``work_clock``: times the writing of an interim summary (the pacer
        stretches the period when writing is slow)."""
        from vtube_fleet.artifacts import SummaryPacer
        from vtube_fleet.fleet.distributed.monitor import RunMonitor

        self.vehicle = vehicle
        self.recorder = recorder
        self.wall_clock = wall_clock
        self.work_clock = work_clock
        self.monitor = RunMonitor(mission, vehicles, recorder=recorder, t0_s=t0_s, flown=flown,
                                  route=route)
        self.out = out
        self.meta = dict(meta or {})
        self.pacer = SummaryPacer(-math.inf)  # the first interim summary at the first tick
        self.cmd_speed = [math.inf, -math.inf]
        self.unsafe = False
        self._own_seq: int | None = None
        #: the safety evaluation's first failure: the summary's outcome is "aborted" with this
        #: reason, as the supervisor's for a failed control tick
        self.failure: str | None = None

    def on_neighbour(self, state: NeighbourState, received_s: float) -> None:
        """The bus's state listener: every live state of another vehicle."""
        if state.vehicle_id != self.vehicle:
            self.monitor.on_state(state, received_s)

    def sample(self, pilot: AgentControl, now_wall: float) -> None:
        """After each control tick: this vehicle's state and command, the latest neighbours.

        The recorder never raises (:class:`~vtube_fleet.recording.api.Recorder`: it logs its own
        problems), so an error here is the safety evaluation's: it is noted in
        :attr:`failure` (logged once) and raised again; the pilot aborts its tube run on it
        (:meth:`AgentControl.step`), as the supervisor does for a failed control tick."""
        try:
            own = pilot.last_state
            states = dict(pilot.mqtt.latest())
            if own is not None:
                states[self.vehicle] = own
                if own.seq != self._own_seq:
                    self._own_seq = own.seq
                    self.monitor.on_state(own, now_wall, count_age=False)
            cmd = None
            if pilot.cmd_xy is not None:
                cmd = {self.vehicle: pilot.cmd_xy}
                if pilot.cmd_in_tube:
                    sp = float(np.hypot(*pilot.cmd_xy))
                    self.cmd_speed = [min(self.cmd_speed[0], sp), max(self.cmd_speed[1], sp)]
            self.monitor.sample(states, now_wall, cmd)
        except Exception as exc:
            if self.failure is None:
                self.failure = f"safety monitor failed: {type(exc).__name__}: {exc}"
                log.exception("agent %d: %s", self.vehicle, self.failure)
            raise

    def summary(self, pilot: AgentControl | None, now_wall: float | None = None,
                **extra: Any) -> dict[str, Any]:
        """The summary so far: the monitor's keys, this vehicle's own, :attr:`meta`, ``wall_s``
        (seconds since the start command) and ``extra``; THE verdict applied (``unsafe``), or
        ``aborted`` after a failed safety evaluation. Sets :attr:`unsafe`."""
        mon = self.monitor
        now = self.wall_clock() if now_wall is None else now_wall
        stamp = mon.exit_stamp.get(self.vehicle)
        own: dict[str, Any] = {
            "kind": "agent",
            "vehicle": self.vehicle,
            # the summary's time base (the start command), as the recording's exit event
            "exit_time_s": None if stamp is None else stamp - mon.t0_s,
        }
        if pilot is not None:
            own.update(phase=pilot.phase.value, reason=pilot.reason, bus_holds=pilot.bus_holds,
                       battery_pct=getattr(pilot, "battery_pct", None),
                       # its own control loop's health: a stall beyond T + L makes it hold
                       tick_gap_p99_s=finite_or_none(percentile_or_none(pilot.tick_gaps_s, 99)),
                       tick_gap_max_s=finite_or_none(max(pilot.tick_gaps_s, default=math.nan)),
                       tick_gap_max_in_tube_s=None if pilot.watch is None else finite_or_none(
                           pilot.watch.longest_tick_gap_s),
                       # PX4's answer against the budget's model in the tube (velocity tracking)
                       response_watch=None if pilot.watch is None or pilot.watch.response
                       is None else pilot.watch.response.as_dict(),
                       response_check=None if pilot.response is None
                       else pilot.response.as_dict())
        own.update(
            min_commanded_speed_m_s=finite_or_none(self.cmd_speed[0]),
            max_commanded_speed_m_s=finite_or_none(self.cmd_speed[1]),
            **self.meta,
            wall_s=round(now - mon.t0_s, 3),
        )
        own.update(extra)
        summary = mon.summary(**own)
        v = verdict(summary)
        if not v.safe:  # THE verdict, over what this agent heard
            summary["outcome"] = "unsafe"
            summary["reason"] = v.summary_line
        self.unsafe = not v.safe
        if self.failure is not None and v.safe:  # its safety data stops at the failure
            summary["outcome"] = "aborted"
            summary["reason"] = self.failure
        return summary

    def after_tick(self, pilot: AgentControl, now_mono: float, now_wall: float) -> None:
        """After each control tick (its setpoint sent): when due (at the first tick, then every
        :data:`~vtube_fleet.artifacts.SUMMARY_EVERY_S`, :class:`~vtube_fleet.artifacts.
        SummaryPacer`, as ``run`` and the coordinator do), rewrite ``OUT/summary.json``
        atomically with ``complete: false``: an agent killed without a chance to clean up
        (SIGKILL, a power cut) still leaves its last summary. Never raises."""
        if self.out is None or not self.pacer.due(now_mono):
            return
        t_c = self.work_clock()
        self.write_interim(pilot, now_wall)
        self.pacer.written(now_mono, now_mono + self.work_clock() - t_c)

    def write_interim(self, pilot: AgentControl | None, now_wall: float | None = None) -> None:
        """The interim summary (``complete: false``, ``outcome: running``) to :attr:`out`."""
        from vtube_fleet.artifacts import write_interim_summary

        if self.out is None:
            return
        try:
            summary = self.summary(pilot, now_wall)
        except Exception as exc:  # noqa: BLE001 - a checkpoint never stops the flight
            log.warning("agent %d: cannot build the interim summary: %s", self.vehicle, exc)
            return
        write_interim_summary(self.out, summary, f"the agent was still flying (phase "
                                                 f"{summary.get('phase', '?')}, "
                                                 f"{summary.get('wall_s', 0.0):.1f} s after start)")

    def finish(self, out: Path, pilot: AgentControl | None, **extra: Any) -> Path:
        """Write ``OUT/summary.json`` (``complete: true``), store it in the recording and close
        it (every exit path); returns the summary's path."""
        from vtube_fleet.artifacts import write_summary

        summary = self.summary(pilot, **extra)
        summary["complete"] = True
        try:
            return write_summary(out, summary)
        finally:
            self.monitor.recorder.log_summary(summary)
            self.monitor.recorder.close()


# ----------------------------------------------------------------------------------------------
# the agent process
# ----------------------------------------------------------------------------------------------
class AgentProcess:
    """Everything ``vtube-fleet agent`` does (module docstring); :meth:`run` returns the exit
    code."""

    def __init__(
        self,
        mission_path: str | Path,
        vehicle: int,
        *,
        broker: str = DEFAULT_BROKER,
        endpoint: str | None = None,
        backend: str = "mavlink",
        mission_id: str | None = None,
        join_timeout_s: float = 600.0,
        broker_hold_limit_s: float = 30.0,
        out: str | Path | None = None,
        recorder: Recorder | None = None,
        say: Callable[[str], None] | None = None,
        credentials: str | Path | None = None,
        insecure: bool = False,
        fence: bool = True,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        """``wall_clock``: this agent's wall clock (state stamps, ages, the clock round trips;
        a test skews it);
        ``credentials``: the agent's broker credentials file (``vtube-fleet bus-setup``);
        ``insecure``: allow a plain-MQTT broker that is not on loopback;
        ``fence``: upload the tube as the vehicle's PX4 geofence before arming (``--no-fence``
        turns it off, with :data:`~vtube_fleet.fleet.onboard.NO_FENCE_WARNING`);
        ``out``: folder for this agent's ``summary.json`` (None: nothing written);
        ``recorder``: records this agent's view (:class:`AgentRecording`; default: nothing);
        ``say``: where progress lines go (the command prints them; default: the log)."""
        from vtube_fleet.config.mission import load_mission
        from vtube_fleet.link.endpoints import parse_endpoint, px4_sitl_endpoints

        self.path = Path(mission_path)
        self.mission = load_mission(self.path)
        why = unsupported(self.mission)
        if why is not None:
            raise AgentRefused(f"{self.path.name}: {why}")
        if not 0 <= vehicle < self.mission.count:
            raise AgentRefused(
                f"--vehicle {vehicle}: {self.path.name} has slots 0..{self.mission.count - 1}"
            )
        self.vehicle = vehicle
        self.cfg = self.mission.config
        self.hash = self.mission.config_hash
        self.mission_id = mission_id or default_mission_id(self.path)
        self.endpoint = endpoint or px4_sitl_endpoints(vehicle + 1)[vehicle]
        parse_endpoint(self.endpoint)
        self.backend = backend
        self.max_age_s = default_max_age_s(self.mission)  # the run's value once joined
        for flag, value in (("--join-timeout", join_timeout_s),
                            ("--broker-hold-limit", broker_hold_limit_s)):
            why = POSITIVE.problem(float(value))  # NaN would wait forever
            if why is not None:
                raise AgentRefused(f"{flag}: {why}, got {value:g}")
        self.join_timeout_s = join_timeout_s
        self.broker_hold_limit_s = broker_hold_limit_s
        self.out = None if out is None else Path(out)
        self.recorder: Recorder = recorder if recorder is not None else NullRecorder()
        self._say: Callable[[str], None] = say if say is not None else log.info
        self.recording: AgentRecording | None = None
        self.summary_path: Path | None = None
        self.wall_clock = wall_clock
        self.bus = MqttBus(broker, self.mission_id, vehicle, config_hash=self.hash,
                           credentials=credentials, insecure=insecure,
                           limits=mission_state_limits(self.mission), wall_clock=wall_clock)
        self.run_cfg: MissionConfigMsg | None = None
        self.pilot: VehiclePilot | None = None
        self.control: AgentControl | None = None
        self.link_budget: SafetyBudget | None = None  # its own link's budget (no neighbours)
        self.budget: SafetyBudget | None = None
        self.fence = fence
        self._interrupt = asyncio.Event()
        self._abort = asyncio.Event()

    # -- helpers ----------------------------------------------------------------------------
    def say(self, text: str) -> None:
        """A progress line of this agent (``agent I: text``)."""
        self._say(f"agent {self.vehicle}: {text}")

    def interrupt(self, reason: str = "interrupted") -> None:
        """Stop as on a signal: hold, then land; :meth:`run` raises :class:`AgentInterrupted`."""
        log.warning("agent %d: %s", self.vehicle, reason)
        self._interrupt.set()

    def refuse(self, reason: str) -> AgentRefused:
        self.bus.announce("refused", reason)
        return AgentRefused(f"vehicle {self.vehicle} refuses to fly: {reason}")

    def _on_command(self, cmd: Any) -> None:
        if self.run_cfg is not None and cmd.run_id == self.run_cfg.run_id:
            if cmd.command == "abort":
                self._abort.set()

    def _teammates(self) -> range:
        n = self.run_cfg.vehicles if self.run_cfg is not None else self.mission.count
        return range(n)

    def _gone(self, vid: int) -> bool:
        """A teammate that will not fly (on): its agent left, refused or was lost, or its
        vehicle is lost / failed / landed."""
        st = self.bus.statuses.get(vid)
        s = self.bus.latest().get(vid)
        run = self.run_cfg.run_id if self.run_cfg is not None else ""
        # (a last will carries the run id its agent had when it connected: often none yet)
        if (
            st is not None
            and st.run_id in (run, "")
            and st.status in ("offline", "refused", "lost")
        ):
            return True
        return s is not None and s.phase in (Phase.LOST, Phase.FAILED, Phase.LANDED)

    async def _unless_interrupted(self, aw: Any, doing: str) -> Any:
        """Await ``aw`` (before the start: nothing armed) unless a signal comes first: then
        cancel it and raise :class:`AgentInterrupted` saying so."""
        task = asyncio.ensure_future(aw)
        stop = asyncio.ensure_future(self._interrupt.wait())
        try:
            await asyncio.wait({task, stop}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            stop.cancel()
        if task.done():
            return task.result()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, UserError):
            await task
        raise AgentInterrupted(f"interrupted while {doing} (nothing armed)")

    async def _wait(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Wait for ``predicate`` (False on timeout); an abort or a signal raises."""

        def check() -> bool:
            return predicate() or self._abort.is_set() or self._interrupt.is_set()

        with contextlib.suppress(TimeoutError):
            await self.bus.wait_for(check, timeout_s)
        if self._interrupt.is_set():  # only waits before the start: nothing is armed
            raise AgentInterrupted(
                "interrupted before reaching the vehicle (nothing armed)" if self.pilot is None
                else "interrupted before the start (vehicle connected, nothing armed)")
        if self._abort.is_set():
            raise AgentAborted(f"vehicle {self.vehicle}: run aborted by the coordinator")
        return predicate()

    # -- 1. join -----------------------------------------------------------------------------
    def check_run(self, cfg: MissionConfigMsg) -> None:
        """Refuse a run we must not fly (raises :class:`AgentRefused`)."""
        if cfg.config_hash != self.hash:
            raise self.refuse(
                f"the announced run {cfg.run_id} of mission {cfg.mission_id} has config hash "
                f"{cfg.config_hash} (from {cfg.source or '?'}), this agent's {self.path.name} "
                f"has {self.hash}: the mission files differ"
            )
        if not self.vehicle < cfg.vehicles:
            raise self.refuse(
                f"run {cfg.run_id} flies vehicles 0..{cfg.vehicles - 1}, not {self.vehicle}"
            )
        cmd = self.bus.command
        if cmd is not None and cmd.run_id == cfg.run_id and cmd.command == "start":
            raise self.refuse(
                f"run {cfg.run_id} already started {self.wall_clock() - cmd.stamp_s:.0f} s ago; a "
                f"late agent does not join a fleet in flight"
            )

    async def join(self) -> None:
        try:
            await self.bus.wait_connected(30.0)
        except TimeoutError:
            why = f" ({self.bus.last_error})" if self.bus.last_error else ""
            raise AgentRefused(
                f"cannot reach the MQTT broker {self.bus.url} within 30 s{why}") from None
        await self.bus.sync()
        if self.bus.config is None:
            self.say(
                f"waiting for `vtube-fleet mission start {self.path.name}` on {self.bus.url} "
                f"(mission id {self.mission_id})"
            )
        def future() -> bool:  # a run announced "from the future": our clock runs behind
            return self.bus.refusal_counts().get(("config", "future"), 0) > 0

        if not await self._wait(lambda: self.bus.config is not None or future(),
                                self.join_timeout_s):
            raise AgentRefused(
                f"no run of mission {self.mission_id} announced on {self.bus.url} within "
                f"{self.join_timeout_s:g} s"
            )
        await self.bus.sync()  # a retained command comes with it: see check_run
        cfg = self.bus.config
        if cfg is None:  # refused as stamped in the future: the clock says by how much
            await self.check_clock()
            raise self.refuse("the run's announcement is stamped in the future of this "
                              "agent's clock")
        self.check_run(cfg)
        await self.check_clock()
        self.run_cfg = cfg
        self.bus.set_limits(self.bus.limits.with_vehicles(cfg.vehicles))
        if cfg.max_age_s > 0:
            self.max_age_s = cfg.max_age_s
        if cfg.cell_m > 0:
            self.bus.set_cell_size(cfg.cell_m)
        self.bus.run_id = cfg.run_id
        self.bus.announce("online", stage="joined")
        self.say(f"joined run {cfg.run_id} ({cfg.vehicles} vehicles); vehicle {self.endpoint}")

    async def check_clock(self) -> None:
        """Measure this agent's clock against the coordinator's (:data:`CLOCK_SAMPLES` round
        trips, the one of least delay: :meth:`~vtube_fleet.bus.mqtt.MqttBus.measure_clock`;
        docs/mqtt.md, "Clocks"); refuse when it may be further than ``max_clock_offset_s``,
        or when the coordinator does not answer. The offset goes into this agent's status (the
        coordinator's summary) and summary, and what is left of it into its safety budget."""
        bound = self.cfg.max_clock_offset_s
        try:
            clock = await self.bus.measure_clock(CLOCK_SAMPLES, CLOCK_TIMEOUT_S)
        except TimeoutError:
            raise self.refuse(
                f"the coordinator answered none of {CLOCK_SAMPLES} clock round trips within "
                f"{CLOCK_TIMEOUT_S:g} s each (is `vtube-fleet mission start` of this version "
                f"running?)") from None
        if clock.bound_s > bound:
            raise self.refuse(
                f"{clock.describe()} > max_clock_offset_s = {1000 * bound:g} ms: synchronise "
                f"this machine's clock with the coordinator's (NTP: chrony, "
                f"systemd-timesyncd) or raise max_clock_offset_s (at most 125 ms)")
        self.say(f"{clock.describe()} ≤ max_clock_offset_s = {1000 * bound:g} ms")

    @property
    def clock_summary(self) -> dict[str, Any] | None:
        """The measured clock for the summary (None: not measured)."""
        c = self.bus.clock
        if c is None:
            return None
        return {"offset_s": round(c.offset_s, 6), "delay_s": round(c.delay_s, 6),
                "within_s": round(c.bound_s, 6), "samples": c.samples,
                "max_clock_offset_s": self.cfg.max_clock_offset_s,
                "budgeted_s": round(clock_latency_s(self.mission, c.bound_s), 6)}

    # -- 2. vehicle ready, budget, preflight -----------------------------------------------
    def _plan(self, budget: SafetyBudget) -> FlightPlan:
        sc = self.mission.scenario
        try:
            return FlightPlan.for_mission(self.mission, budget.inflate(sc.controller))
        except PartitionError as exc:
            raise self.refuse(
                f"with the safety budget {budget.describe(sc.controller)} the "
                f"{'route' if sc.is_route else 'tube'} cannot be partitioned: {exc}"
            ) from None

    async def measure_budget(self, control: AgentControl) -> None:
        """Measure this vehicle's link and estimate, compute what it needs; fly the run's
        announced δ (every agent the same partition) and refuse if it needs more."""
        cfg = self.cfg
        pilot = control.pilot
        if cfg.position_accuracy_m is None:
            try:
                await wait_accuracy([pilot], cfg.max_position_accuracy_m, cfg.ready_timeout_s)
            except PreflightError as exc:
                raise self.refuse(str(exc)) from None
        run_delta = self.run_cfg.delta_m if self.run_cfg is not None else 0.0
        params = self.mission.scenario.controller
        clock_bound = None if self.bus.clock is None else self.bus.clock.bound_s

        def too_slow(measured: LinkMeasurement) -> str | None:
            """The run's δ does not cover what this vehicle was measured to need."""
            own = bus_safety_budget(self.mission, measured, self.max_age_s, clock_bound)
            if run_delta <= 0 or own.overridden or own.delta_m <= run_delta + 1e-9:
                return None
            return (f"this vehicle needs the safety budget {own.describe(params)}, more than "
                    f"the run's δ = {run_delta:.3f} m (the coordinator assumed L = "
                    f"{1000 * ASSUMED_LINK_LATENCY_S:.0f} ms and σ = "
                    f"{cfg.position_accuracy_m or ASSUMED_ACCURACY_M:.2f} m; measured here: "
                    f"L = {1000 * measured.latency_s:.0f} ms, σ = {measured.accuracy_m:.2f} m)")

        measured, problems = await measure_budget_links([pilot], self.mission,
                                                        too_slow=too_slow)
        if problems:
            raise self.refuse("; ".join(problems))
        own = bus_safety_budget(self.mission, measured, self.max_age_s, clock_bound)
        if run_delta > 0 and not own.overridden:
            # its own measured terms, the run's δ (what SafetyBudget.compute's override does)
            self.budget = dataclasses.replace(own, delta_m=float(run_delta), overridden=True,
                                              override_source="the run's announced δ")
        else:
            self.budget = own
        control.set_plan(self._plan(self.budget))
        # PX4's answer to its own setpoints: its link's L (no neighbour age in it)
        self.link_budget = mission_budget(self.mission, measured)
        control.watch = BudgetWatch(self.mission, own,  # what THIS vehicle was measured to need
                                    response_budget=self.link_budget)
        self.say(
            f"safety budget: needs {own.describe(params)} (L = link {measured.latency_s * 1000:.1f}"
            f" ms + headroom + neighbour max age {self.max_age_s * 1000:.0f} ms + clocks "
            f"{1000 * clock_latency_s(self.mission, clock_bound):.0f} ms; σ "
            f"{measured.accuracy_m:.2f} m); flies the run's δ = {self.budget.delta_m:.3f} m"
        )
        cell = self.run_cfg.cell_m if self.run_cfg is not None else 0.0
        need = needed_cell_m(self.mission, self.max_age_s, self.budget.delta_m)
        if cell > 0 and need > cell:
            raise self.refuse(
                f"the run's cells of {cell:g} m are smaller than this agent needs, {need:.2f} m "
                f"(r_s + r_a + 2δ + v_max·(T + max age)); start the run with --no-cells"
            )

    async def check_battery(self, pilot: VehiclePilot) -> None:
        """The battery check before arming (:meth:`~vtube_fleet.fleet.preflight.Preflight.
        check_batteries`), before the vehicle is READY: a refusal, so the coordinator (which
        starts the run once every vehicle is READY) stops the run before anybody arms; the
        pilot checks again just before it arms."""

        def event(text: str, vehicle_id: int | None = None, level: str = "info",
                  echo: bool = True) -> None:
            pilot.event(text, level)

        try:
            await Preflight([pilot], self.mission, event=event).check_batteries()
        except PreflightError as exc:
            raise self.refuse(str(exc)) from None

    def preflight(self, pilot: VehiclePilot) -> None:
        """The paper's conditions with the READY positions of every vehicle of the run."""
        assert self.budget is not None and self.run_cfg is not None
        n = self.run_cfg.vehicles
        mission = self.mission.with_vehicles(n)
        pos = np.array(mission.slots, dtype=float)
        latest = self.bus.latest()
        for v in range(n):
            s = latest.get(v)
            if v == self.vehicle:
                pos[v] = pilot.xy
            elif s is not None:
                pos[v] = (s.x_m, s.y_m)
        flown = self.budget.inflate(mission.scenario.controller)
        names = [f"vehicle {v}" for v in range(n)]
        route, problems = preflight_report(mission, flown, pos, names)
        mine = [p for p in problems if f"vehicle {self.vehicle}" in p or "vehicle" not in p]
        altitude = pilot.check_altitude_margin(1.0)
        if altitude:
            mine.append(altitude)
        if mine or route is None:
            raise self.refuse("preflight failed, nothing armed: " + "; ".join(mine or problems))

    # -- 3. fly ------------------------------------------------------------------------------
    async def _wait_teammates(self, stages: Any, timeout_s: float) -> list[int]:
        """Wait (up to ``timeout_s``) until every teammate's status in this run is at one of
        ``stages`` or it is gone; returns the teammates still missing (empty: all there)."""
        mates = [v for v in self._teammates() if v != self.vehicle]

        def there(v: int) -> bool:
            st = self.bus.statuses.get(v)
            return ((st is not None and st.run_id == self.bus.run_id and st.stage in stages)
                    or self._gone(v))

        with contextlib.suppress(TimeoutError):
            await self.bus.wait_for(lambda: all(there(v) for v in mates), timeout_s)
        return [v for v in mates if not there(v)]

    async def _altitude_barrier(self) -> None:
        """At altitude: wait for the teammates, fly the response check with them, wait until
        they have flown it too, then enter the tube (announced at each stage)."""
        assert self.pilot is not None
        self.bus.announce("online", stage="at_altitude")
        late = await self._wait_teammates(_UP_STAGES, self.cfg.takeoff_timeout_s)
        if late:
            self.pilot.event(
                f"teammates not at altitude after {self.cfg.takeoff_timeout_s:g} s "
                f"({', '.join(map(str, late))}); flying on anyway",
                "warning",
            )
        await self._check_response()
        self.bus.announce("online", stage="checked")
        late = await self._wait_teammates(_CHECKED_STAGES, self.cfg.takeoff_timeout_s)
        if late:
            self.pilot.event(
                f"teammates not through the response check after "
                f"{self.cfg.takeoff_timeout_s:g} s ({', '.join(map(str, late))}); entering the "
                f"tube anyway", "warning")
        refused = self._refused_teammates()
        if refused and not self._abort.is_set():
            # a teammate refused (its response check): the coordinator aborts the run; wait
            # for that instead of entering the tube before it arrives
            with contextlib.suppress(TimeoutError):
                await self.bus.wait_for(self._abort.is_set, REFUSAL_ABORT_WAIT_S)
        if self._abort.is_set() or refused:  # never into the tube after an abort: it lands
            raise UserError("run aborted by the coordinator" if self._abort.is_set() else
                            f"teammate(s) {', '.join(map(str, refused))} refused after the "
                            f"start and no abort came within {REFUSAL_ABORT_WAIT_S:g} s")
        self.bus.announce("online", stage="in_tube")

    def _refused_teammates(self) -> list[int]:
        """The teammates whose agents refused this run (their status says so)."""
        out = []
        for v in self._teammates():
            st = self.bus.statuses.get(v)
            if (v != self.vehicle and st is not None and st.run_id == self.bus.run_id
                    and st.status == "refused"):
                out.append(v)
        return out

    async def _check_response(self) -> None:
        """The response check (:mod:`~vtube_fleet.fleet.response_check`) of this agent's own
        vehicle, as ``run`` flies it for its fleet: every agent starts it once its teammates
        are at altitude, so the steps are flown together, the same command along the first
        segment's n_c. Refused: the agent refuses (the coordinator aborts the run and every
        vehicle lands). Skipped, and said, with ``response_check = false`` or when this
        vehicle moved the step's reach ahead breaks the partition (an obstacle or a leg just
        ahead; the pairs keep their spacing)."""
        pilot, control = self.pilot, self.control
        assert pilot is not None and control is not None and self.budget is not None
        step = float(self.mission.scenario.controller.v)
        model = ResponseModel.of(self.link_budget or self.budget, self.cfg)
        report = ResponseReport(step, model, [self.vehicle])
        control.response = report
        u = np.asarray(control.tick.root.route.segments[0].tube.n_c, float)
        if not self.cfg.response_check:
            report.skipped = "response_check = false in the mission"
        elif pilot.phase != Phase.TAKEOFF:
            report.skipped = f"the vehicle is {pilot.phase.value}, not hovering"
        else:
            # this vehicle alone moved ahead (pairs keep their spacing: every vehicle flies
            # the same steps; the tube's own entry judges the pairs where they are)
            reach = model.reach_m(step)
            flown = self.budget.inflate(self.mission.scenario.controller)
            _, problems = await asyncio.to_thread(
                preflight_report, self.mission, flown, (pilot.xy + reach * u)[None, :],
                [f"vehicle {self.vehicle}"], where=f"{reach:.1f} m ahead",
                route=control.tick.root.route)
            if problems:
                report.skipped = (f"this vehicle moved {reach:.1f} m ahead (the step's reach) "
                                  f"breaks the partition: " + "; ".join(problems))
        if report.skipped is not None:
            pilot.event(report.describe(), "warning")
            return

        def attach(probe: ResponseProbe | None) -> None:
            control.probe = probe

        await run_response_check(ResponseProbe(pilot.table, np.array([0]), u), report, attach,
                                 self._abort.is_set)
        pilot.event(report.describe(), "info" if report.skipped is None else "warning")
        if report.skipped is None and report.refused():
            raise self.refuse(report.refusal([f"vehicle {v}" for v in range(self.vehicle + 1)]))

    async def _exit_barrier(self) -> None:
        """Past the finishing line: wait until every teammate is too (its status stage says
        so: statuses reach everyone, states only the vehicles in our cells) or gone."""
        await self._wait_teammates(_OUT_STAGES, self.cfg.mission_timeout_s)

    async def _land_now(self, control: AgentControl, why: str) -> None:
        """Hold, then land (the control clock keeps running); until touch-down (or timeout)."""
        pilot = control.pilot
        if pilot.exit_time_s is None:
            control.stop_for(why)
        pilot.event(f"{why}: hold, then land", "warning")
        with contextlib.suppress(UserError):
            await pilot.hold()
        with contextlib.suppress(UserError):
            await pilot.land()
        with contextlib.suppress(UserError):
            await pilot.wait_phase(
                lambda ph: ph in (Phase.LANDED, Phase.LOST, Phase.FAILED, Phase.READY,
                                  Phase.CONNECTING),
                self.cfg.land_timeout_s, "touch-down")

    async def fly(self, link: Any) -> int:
        from vtube_fleet.link.base import VehicleLink

        assert isinstance(link, VehicleLink)
        cfg = self.cfg
        budget = bus_safety_budget(self.mission, None, self.max_age_s)  # until measured
        table = FleetTable([self.vehicle], self.mission)
        pilot = VehiclePilot(link, table, 0, self.mission)
        pilot.fence = self.fence
        control = AgentControl(pilot, self.bus, self.mission, self._plan(budget),
                               teammates=self._teammates, gone=self._gone,
                               max_age_s=self.max_age_s,
                               broker_hold_limit_s=self.broker_hold_limit_s,
                               wall_clock=self.wall_clock)
        if not self.fence:
            self.say(NO_FENCE_WARNING)
        self.pilot = pilot
        self.control = control
        await self._unless_interrupted(link.connect(cfg.connect_timeout_s),
                                       "connecting to the vehicle")
        control.start()  # the control tick runs from here to the end (sensing at first)
        try:
            # before READY: a refusal reaches the coordinator before it can start the run
            await self._unless_interrupted(self.check_battery(pilot), "checking the battery")
            await self._unless_interrupted(pilot.wait_ready(), "waiting for the vehicle")
            self.bus.announce("online", stage="ready")
            await self._unless_interrupted(self.measure_budget(control), "measuring the link")
            self.say("vehicle READY; waiting for the start command")

            def started() -> bool:
                c = self.bus.command
                return c is not None and c.run_id == self.bus.run_id and c.command == "start"

            await self._wait(started, math.inf)
            self.preflight(pilot)
            self.say("start: arming")
            self._open_recording(control)
            outcome = "failed"
            rec = self.recording
            try:
                code = await self._fly_started(control)
                outcome = "completed" if code == EXIT_OK else "incomplete"
            except AgentInterrupted:
                outcome = "interrupted"
                raise
            except AgentAborted:
                outcome = "aborted"
                raise
            finally:  # the summary and the recording on every exit path
                self._close_recording(control, outcome)
        finally:
            await control.stop()
        if rec is not None and rec.unsafe:
            self.say("UNSAFE: a limit was broken in what this agent heard (summary.json)")
            return EXIT_UNSAFE
        return code

    def _open_recording(self, control: AgentControl) -> None:
        """Start :class:`AgentRecording` (at the start command; nothing before it is written)."""
        if self.out is None or self.run_cfg is None:
            return
        cfg = self.run_cfg
        cmd = self.bus.command
        # the coordinator's time base, on this agent's clock
        offset = self.bus.clock.offset_s if self.bus.clock is not None else 0.0
        t0 = cmd.stamp_s + offset if cmd is not None else self.wall_clock()
        mission = self.mission.with_vehicles(cfg.vehicles)
        flown = (None if self.budget is None
                 else self.budget.inflate(mission.scenario.controller))
        # the route this agent flies (its apex distances to the recording; a route's
        # hand-overs replayed by the monitor)
        route = control.tick.root.route if mission.scenario.is_route else None
        rec = AgentRecording(mission, cfg.vehicles, self.vehicle, self.recorder, t0,
                             out=self.out, meta={
                                 "mission_id": self.mission_id, "run_id": cfg.run_id,
                                 "config_hash": self.hash, "broker": self.bus.url,
                                 "clock": self.clock_summary},
                             flown=flown, wall_clock=self.wall_clock, route=route)
        radii = ({} if flown is None else {"r_s_flown": flown.r_s, "r_a_flown": flown.r_a})
        self.recorder.log_scene(mission.scenario, route, mission=mission.config,
            meta={"kind": "agent", "vehicle": self.vehicle, "rate_hz": self.cfg.rate_hz,
                  "run_id": cfg.run_id, "broker": self.bus.url, "vehicles": cfg.vehicles,
                  "fence": self.fence, **radii},  # review: pairs within the flown radii
        )
        self.bus.add_state_listener(rec.on_neighbour)
        self.recording = rec
        control.recording = rec

    def _close_recording(self, control: AgentControl, outcome: str) -> None:
        rec, self.recording = self.recording, None
        if rec is None or self.out is None:
            return
        control.recording = None
        try:
            self.summary_path = rec.finish(self.out, control, outcome=outcome)
            self.say(f"summary {self.summary_path}")
        except OSError as exc:
            log.error("agent %d: cannot write the summary to %s: %s", self.vehicle, self.out,
                      exc.strerror or exc)

    async def _fly_started(self, control: AgentControl) -> int:
        """From the start command to the end: fly, or hold and land on abort / a signal."""
        pilot = control.pilot
        fly_task = asyncio.ensure_future(
            pilot.fly(start=self._altitude_barrier, finish=self._exit_barrier)
        )
        stop_wait = asyncio.ensure_future(_first(self._abort.wait(), self._interrupt.wait()))
        try:
            await asyncio.wait({fly_task, stop_wait}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            stop_wait.cancel()
        if fly_task.done():
            try:
                phase = fly_task.result()
            except Exception as exc:  # UserError: take-off failed, timeouts ...; else a bug
                why = str(exc)
                if not isinstance(exc, UserError):  # a bug of ours: the vehicle comes down
                    log.error("agent %d: internal error, its vehicle is brought down",
                              self.vehicle, exc_info=exc)
                    why = f"internal error: {bug_text(exc)}"
                await self._land_now(control, why)
                raise AgentAborted(f"vehicle {self.vehicle}: {why}") from None
            ok = phase in (Phase.LANDED, Phase.HOLDING) and pilot.exit_time_s is not None
            why = "" if ok else (pilot.reason or f"did not exit (final phase {phase.value})")
            if why:
                control.stop_for(why)
            self.bus.announce("online", why, stage="done")  # the coordinator's reason hears it
            self.say(f"finished: {phase.value}" + ("" if ok else f" ({why})"))
            return EXIT_OK if ok else EXIT_INCOMPLETE
        fly_task.cancel()
        with contextlib.suppress(asyncio.CancelledError, UserError):
            await fly_task
        why = "interrupted" if self._interrupt.is_set() else "run aborted by the coordinator"
        await self._land_now(control, why)
        self.bus.announce("online", pilot.reason or why, stage="done")
        if self._interrupt.is_set():
            raise AgentInterrupted(f"interrupted: vehicle held, then landed (final phase "
                                   f"{pilot.phase.value})")
        raise AgentAborted(f"vehicle {self.vehicle}: {why}; final phase {pilot.phase.value}")

    async def run(self) -> int:
        from vtube_fleet.link import TelemetryBounds, backend_named, endpoint_sysid, open_links
        from vtube_fleet.link.signing import slot_signing

        self.bus.add_command_listener(self._on_command)
        # both backends fly one id: ?sysid=, PX4 SITL's 14540+i, else the slot's (issue 33)
        sysid = endpoint_sysid(self.endpoint, self.vehicle)
        signing = slot_signing(self.mission, self.vehicle)  # its key file, checked before joining
        if signing is not None:  # before joining: the refusal opening the link would give
            backend_named(self.backend).require_signing(self.endpoint)
        async with self.bus:
            await self.join()
            try:
                async with open_links([self.endpoint], self.backend, sysids=[sysid],
                                      signing=[signing],
                                      telemetry=TelemetryBounds.for_mission(self.mission)
                                      ) as links:
                    return await self.fly(links[0])
            except (AgentRefused, AgentAborted):
                raise
            except UserError as exc:  # vehicle not reachable / not ready: nothing armed
                self.bus.announce("refused", str(exc))
                raise


async def _first(*aws: Any) -> None:
    tasks = [asyncio.ensure_future(a) for a in aws]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
