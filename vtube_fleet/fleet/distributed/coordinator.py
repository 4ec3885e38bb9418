"""The thin coordinator of the distributed agents.

It announces a run with the fleet's parameters (staleness limit, cells, safety budget δ), then
starts, aborts and follows it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import re
import time
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vtube_fleet.artifacts import write_interim_summary, write_summary
from vtube_fleet.bus.codec import Command, MissionConfigMsg, encode_command, encode_config
from vtube_fleet.bus.mqtt import MqttBus
from vtube_fleet.bus.topics import validate_mission_id
from vtube_fleet.bus.validate import mission_state_limits
from vtube_fleet.config.keys import POSITIVE
from vtube_fleet.core.metrics import verdict
from vtube_fleet.core.partition import PartitionError
from vtube_fleet.errors import UserError
from vtube_fleet.fleet.distributed import unsupported
from vtube_fleet.fleet.distributed.monitor import RunMonitor
from vtube_fleet.fleet.flight_plan import FlightPlan
from vtube_fleet.recording.api import NullRecorder, Recorder
from vtube_fleet.state import (
    Phase,
)

__all__ = [
    "ASSUMED_ACCURACY_M",
    "ASSUMED_LINK_LATENCY_S",
    "Coordinator",
    "DEFAULT_BROKER",
    "MissionRunError",
    "RunResult",
    "bus_safety_budget",
    "clock_latency_s",
    "default_max_age_s",
    "default_mission_id",
    "mission_bus_setup",
    "needed_cell_m",
    "run_cell_m",
]

log = logging.getLogger(__name__)


DEFAULT_BROKER = "mqtt://127.0.0.1:1883"


class MissionRunError(UserError):
    """The run could not start: broker unreachable, an agent refused or did not join."""


# ----------------------------------------------------------------------------------------------
# mission identity (shared with the agent)
# ----------------------------------------------------------------------------------------------
#: Link latency L (position age + setpoint delay) the coordinator assumes for every vehicle
#: when it fixes the run's safety budget and cells; an agent whose own link needs more refuses.
ASSUMED_LINK_LATENCY_S = 0.1


#: Position accuracy σ assumed when the mission does not say (``position_accuracy_m``): PX4
#: SITL reports 0.29-0.32 m; an agent whose vehicle reports more refuses.
ASSUMED_ACCURACY_M = 0.35


def default_max_age_s(mission: Any) -> float:
    """The run's staleness limit: 3 control periods, at most ``neighbour_max_age_s``."""
    cfg = mission.config
    return min(3.0 * cfg.period_s, cfg.neighbour_max_age_s)


def clock_latency_s(mission: Any, own_bound_s: float | None = None) -> float:
    """What clocks add to L (docs/mqtt.md, "Clocks"): a neighbour's state is stamped by its
    agent's clock and aged by ours, so its true age is off by the difference of the two
    clocks: at most this agent's measured bound (``own_bound_s``, |offset| + delay / 2 to the
    coordinator's) plus ``max_clock_offset_s`` (the bound every other agent kept, or it
    refused); 2 × ``max_clock_offset_s`` before anybody measured (the coordinator)."""
    bound = float(mission.config.max_clock_offset_s)
    return 2.0 * bound if own_bound_s is None else float(own_bound_s) + bound


def bus_safety_budget(mission: Any, measured: Any, max_age_s: float,
                      clock_bound_s: float | None = None) -> Any:
    """The MQTT agents' :class:`~vtube_fleet.fleet.budget.SafetyBudget`: the fleet's
    :func:`~vtube_fleet.fleet.budget.mission_budget` with ``max_age_s`` (a neighbour's state
    is used up to that old) and the clocks' share (:func:`clock_latency_s` of this agent's
    measured ``clock_bound_s``) added to L. ``measured``: a
    :class:`~vtube_fleet.fleet.budget.LinkMeasurement` (an agent's own), or None for the
    coordinator's assumptions (:data:`ASSUMED_LINK_LATENCY_S`, :data:`ASSUMED_ACCURACY_M`)."""
    from vtube_fleet.fleet.budget import LinkMeasurement, mission_budget

    if measured is None:
        measured = LinkMeasurement(ASSUMED_LINK_LATENCY_S - mission.config.latency_headroom_s,
                                   0.0, ASSUMED_ACCURACY_M)
    return mission_budget(mission, measured,
                          extra_latency_s=max_age_s + clock_latency_s(mission, clock_bound_s))


def needed_cell_m(mission: Any, max_age_s: float, delta_m: float) -> float:
    """Smallest cell size with which an agent hears every vehicle that matters to it: the
    flown neighbour radius r_s' + r_a' (= r_s + r_a + 2δ) plus what a neighbour covers at
    v_max in one control period and ``max_age_s`` (see ``docs/mqtt.md``)."""
    p = mission.scenario.controller
    return float(p.r_s + p.r_a + 2.0 * delta_m + p.v_max * (mission.config.period_s + max_age_s))


def run_cell_m(mission: Any, max_age_s: float) -> float:
    """The cell size a coordinator announces: :func:`needed_cell_m` with the run's δ
    (:func:`bus_safety_budget` under the coordinator's assumptions), rounded up to 0.5 m."""
    delta = bus_safety_budget(mission, None, max_age_s).delta_m
    return math.ceil(2.0 * needed_cell_m(mission, max_age_s, delta)) / 2.0


def mission_bus_setup(mission_path: str | Path, out: str | Path, *,
                      mission_id: str | None = None, vehicles: int | None = None,
                      **options: Any) -> Any:
    """``vtube-fleet bus-setup``: :func:`vtube_fleet.bus.security.bus_setup` for a mission
    file (its mission id and slots unless given); ``options`` go to ``bus_setup``."""
    from vtube_fleet.bus.security import SetupError, bus_setup
    from vtube_fleet.config.mission import load_mission

    path = Path(mission_path)
    mission = load_mission(path)
    n = mission.count if vehicles is None else int(vehicles)
    if not 1 <= n <= mission.count:
        raise SetupError(f"--vehicles must be between 1 and {mission.count} (the slots of "
                         f"{path.name}), got {n}")
    return bus_setup(out, mission_id or default_mission_id(path), n, **options)


def default_mission_id(path: str | Path) -> str:
    """The mission id used in the topics: the file name without extension, with characters
    that are not letters, digits, ``_.-`` replaced by ``-``."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "-", Path(path).stem)[:64] or "mission"
    return validate_mission_id(stem)


# ----------------------------------------------------------------------------------------------
# the coordinator
# ----------------------------------------------------------------------------------------------
class Coordinator:
    """Announce a run, start / abort it and follow it (module docstring)."""

    def __init__(
        self,
        mission_path: str | Path,
        broker: str,
        *,
        mission_id: str | None = None,
        vehicles: int | None = None,
        broker_timeout_s: float = 10.0,
        max_age_s: float | None = None,
        cells: bool = True,
        say: Callable[[str], None] | None = None,
        credentials: str | Path | None = None,
        insecure: bool = False,
    ) -> None:
        """``say``: where progress lines go (the command prints them; default: the log);
        ``credentials``: the coordinator's broker credentials file (``vtube-fleet
        bus-setup``); ``insecure``: allow a plain-MQTT broker that is not on loopback."""
        from vtube_fleet.config.mission import load_mission

        self.path = Path(mission_path)
        self.mission = load_mission(self.path)
        why = unsupported(self.mission)
        if why is not None:
            raise MissionRunError(f"{self.path.name}: {why}")
        self.mission_id = mission_id or default_mission_id(self.path)
        validate_mission_id(self.mission_id)
        self.config_hash = self.mission.config_hash
        n = self.mission.count if vehicles is None else int(vehicles)
        if not 1 <= n <= self.mission.count:
            raise MissionRunError(
                f"--vehicles must be between 1 and {self.mission.count} (the slots of "
                f"{self.path.name}), got {n}"
            )
        self.vehicles = n
        self.end_reason = ""  # why the followed run ended (:meth:`follow`), if not completed
        self.max_age_s = default_max_age_s(self.mission) if max_age_s is None else max_age_s
        lost_after = self.mission.config.lost_after_s
        if not 0 < self.max_age_s <= lost_after:
            raise MissionRunError(
                f"--max-age {self.max_age_s:g} s must be > 0 and <= lost_after_s = "
                f"{lost_after:g} s of {self.path.name}"
            )
        self.cells = cells
        self.say: Callable[[str], None] = say if say is not None else log.info
        self.broker = broker
        why = POSITIVE.problem(float(broker_timeout_s))
        if why is not None:
            raise MissionRunError(f"--broker-timeout: {why}, got {broker_timeout_s:g}")
        self.broker_timeout_s = broker_timeout_s
        self.bus = MqttBus(broker, self.mission_id, credentials=credentials, insecure=insecure,
                           limits=mission_state_limits(self.mission), serve_clock=True)
        self.run_id = ""
        self.announced: MissionConfigMsg | None = None
        self.t_start_wall: float | None = None

    async def __aenter__(self) -> Coordinator:
        self.bus.start()
        try:
            await self.bus.wait_connected(self.broker_timeout_s)
        except TimeoutError:
            await self.bus.close()
            why = self.bus.last_error or "is it running? --broker mqtts://HOST:PORT"
            raise MissionRunError(
                f"cannot reach the MQTT broker {self.broker} within {self.broker_timeout_s:g} s "
                f"({why})"
            ) from None
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.bus.close()

    # -- publishing --------------------------------------------------------------------------
    def announce(self) -> str:
        """Publish a new run of this mission (retained config); returns the run id."""
        self.run_id = uuid.uuid4().hex[:12]
        cfg = MissionConfigMsg(
            self.mission_id,
            self.run_id,
            self.config_hash,
            self.vehicles,
            time.time(),
            self.path.name,
            max_age_s=self.max_age_s,
            cell_m=run_cell_m(self.mission, self.max_age_s) if self.cells else 0.0,
            delta_m=bus_safety_budget(self.mission, None, self.max_age_s).delta_m,
        )
        self.bus.set_retained(self.bus.topics.config, encode_config(cfg))
        self.announced = cfg
        return self.run_id

    def command(self, name: str) -> Command:
        cmd = Command(
            name,
            self.mission_id,
            self.run_id,
            self.config_hash,
            time.time_ns() // 1_000_000,
            time.time(),
        )
        self.bus.set_retained(self.bus.topics.cmd, encode_command(cmd))
        return cmd

    # -- reading -----------------------------------------------------------------------------
    def joined(self, vid: int) -> bool:
        st = self.bus.statuses.get(vid)
        return (
            st is not None
            and st.status == "online"
            and st.run_id == self.run_id
            and st.config_hash == self.config_hash
        )

    def ready(self, vid: int) -> bool:
        s = self.bus.latest().get(vid)
        return self.joined(vid) and s is not None and s.phase == Phase.READY and s.age_s() < 2.0

    def refusals(self) -> list[str]:
        out = []
        for vid in range(self.vehicles):
            st = self.bus.statuses.get(vid)
            if st is not None and st.status == "refused" and st.run_id in (self.run_id, ""):
                out.append(f"vehicle {vid}: {st.detail}")
        return out

    def finished(self, vid: int) -> bool:
        """The vehicle is done: landed / failed, or its agent left or was lost."""
        st = self.bus.statuses.get(vid)
        s = self.bus.latest().get(vid)
        if s is not None and s.phase in (Phase.LANDED, Phase.FAILED):
            return True
        # (a last will carries the run id the agent had when it connected: often none yet)
        return (
            st is not None
            and st.run_id in (self.run_id, "")
            and st.status in ("offline", "lost", "refused")
        )

    async def wait_ready(self, timeout_s: float, progress: bool = True) -> None:
        """Until every vehicle's agent joined this run and its vehicle is READY."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        last_print = -math.inf
        while True:
            refused = self.refusals()
            if refused:
                raise MissionRunError(
                    f"{len(refused)} agent(s) refused run {self.run_id} of "
                    f"{self.mission_id}: " + "; ".join(refused)
                )
            joined = [v for v in range(self.vehicles) if self.joined(v)]
            ready = [v for v in range(self.vehicles) if self.ready(v)]
            if len(ready) == self.vehicles:
                self.say(f"clocks: {self.clock_line()}")
                return
            now = loop.time()
            if now > deadline:
                missing = [v for v in range(self.vehicles) if v not in joined]
                unready = [v for v in joined if v not in ready]
                parts = []
                if missing:
                    parts.append(
                        f"no agent joined for vehicle(s) {_ids(missing)} (is `vtube-fleet "
                        f"agent {self.path.name} --vehicle I --broker {self.broker}` running "
                        f"for each?)"
                    )
                if unready:
                    phases = ", ".join(f"{v}: {self._phase(v)}" for v in unready)
                    parts.append(f"vehicle(s) not READY ({phases})")
                raise MissionRunError(
                    f"run {self.run_id}: after {timeout_s:g} s " + "; ".join(parts)
                )
            if progress and now - last_print >= 2.0:
                last_print = now
                self.say(f"waiting for agents: {len(joined)}/{self.vehicles} joined, "
                         f"{len(ready)}/{self.vehicles} ready")
            with contextlib.suppress(TimeoutError):
                await self.bus.wait_for(lambda: False, 0.2)

    def clocks(self) -> list[dict[str, Any] | None]:
        """Every vehicle's clock offset to ours, as its agent measured and reported it
        (docs/mqtt.md, "Clocks"; None: not reported)."""
        out: list[dict[str, Any] | None] = []
        for vid in range(self.vehicles):
            st = self.bus.statuses.get(vid)
            c = st.clock if st is not None else None
            out.append(None if c is None else {
                "vehicle": vid, "offset_s": round(c.offset_s, 6), "delay_s": round(c.delay_s, 6),
                "within_s": round(c.bound_s, 6), "samples": c.samples})
        return out

    def clock_line(self) -> str:
        """``vehicle 0 +0.4 ms (within 0.9 ms), …`` of :meth:`clocks`."""
        return ", ".join(f"vehicle {v} " + ("not reported" if c is None else
                                            f"{round(1000 * c['offset_s'], 1) + 0.0:+.1f}"
                                            f" ms (within "
                                            f"{1000 * c['within_s']:.1f} ms)")
                         for v, c in enumerate(self.clocks()))

    def _phase(self, vid: int) -> str:
        s = self.bus.latest().get(vid)
        return "no state" if s is None else s.phase.value

    async def follow(self, timeout_s: float, mon: RunMonitor, progress: bool = True,
                     checkpoint: Callable[[], None] | None = None) -> str:
        """Feed ``mon`` (states as they arrive, snapshots at the control rate) until every
        vehicle is finished; the outcome: ``completed``, ``incomplete`` or ``timeout``.
        ``checkpoint`` (the interim summary) is called at once, then every
        ``artifacts.SUMMARY_EVERY_S`` (:class:`~vtube_fleet.artifacts.SummaryPacer`), as ``run``
        does."""
        from vtube_fleet.artifacts import SummaryPacer

        self.bus.add_state_listener(mon.on_state)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        period = self.mission.config.period_s
        last_print = -math.inf
        next_t = loop.time()
        pacer = SummaryPacer(next_t)
        aborted_for: str | None = None
        self.end_reason = ""
        while True:
            mon.sample(self.bus.latest(), time.time())
            if all(self.finished(v) for v in range(self.vehicles)):
                break
            refused = self.refusals()
            if refused and aborted_for is None:
                aborted_for = "; ".join(refused)
                self.say(f"aborting: agent refused after start: {aborted_for}")
                self.command("abort")
            now = loop.time()
            if now > deadline:
                self.end_reason = (f"timeout: still following after {timeout_s:g} s: "
                                   + self._unfinished(mon, finished_only=True))
                return "timeout"
            if progress and now - last_print >= 5.0:
                last_print = now
                counts: dict[str, int] = {}
                for v in range(self.vehicles):
                    ph = self._phase(v)
                    counts[ph] = counts.get(ph, 0) + 1
                self.say("fleet: " + ", ".join(f"{k} {n}" for k, n in sorted(counts.items()))
                         + f"; exited {len(mon.exit_stamp)}/{self.vehicles}")
            if checkpoint is not None and pacer.due(now):
                t_c = loop.time()
                checkpoint()
                pacer.written(t_c, loop.time())
            next_t += period
            await asyncio.sleep(max(0.0, next_t - loop.time()))  # the coordinator's clock
        done = len(mon.exit_stamp) == self.vehicles and all(
            (s := self.bus.latest().get(v)) is not None and s.phase == Phase.LANDED
            for v in range(self.vehicles)
        )
        if done and aborted_for is None:
            return "completed"
        self.end_reason = (f"aborted: agent refused after start: {aborted_for}; "
                           if aborted_for is not None else "") + self._unfinished(mon)
        return "incomplete"

    def _unfinished(self, mon: RunMonitor, finished_only: bool = False) -> str:
        """``N of M vehicles …: vehicle 3 lost (its reason), …``: the vehicles that did not
        exit and land (``finished_only``: that are not finished yet)."""
        rows = []
        for row in self.vehicle_table():
            vid = int(row["id"])
            if vid >= self.vehicles:
                continue
            exited = vid in mon.exit_stamp
            if finished_only:
                if self.finished(vid):
                    continue
            elif exited and row["phase"] == Phase.LANDED.value:
                continue
            what = row["phase"] or (f"agent {row['status']}" if row["status"] else "no state")
            detail = row["detail"] or ""
            rows.append(f"vehicle {vid} {what}" + ("" if exited else ", not exited")
                        + (f" ({detail})" if detail else ""))
        verb = "not finished" if finished_only else "did not exit and land"
        return (f"{len(rows)} of {self.vehicles} vehicles {verb}: " + "; ".join(rows)
                if rows else "every vehicle finished")

    # -- a whole run -------------------------------------------------------------------------
    async def start_run(self, stop: asyncio.Event, ready_timeout_s: float | None = None) -> bool:
        """Announce a run, wait until every agent is READY, publish start; True once started.

        ``stop`` set before the start (a signal): abort is published and False returned.
        ``ready_timeout_s`` defaults to the mission's connect + ready timeouts."""
        cfg = self.mission.config
        run = self.announce()
        self.say(f"mission {self.mission_id} run {run}: config {self.config_hash} announced on "
                 f"{self.broker} (neighbour max age {1000 * self.max_age_s:.0f} ms, cells "
                 f"{self.announced.cell_m:g} m); waiting for {self.vehicles} agents")
        timeout = (cfg.connect_timeout_s + cfg.ready_timeout_s if ready_timeout_s is None
                   else ready_timeout_s)
        waiting = asyncio.ensure_future(self.wait_ready(timeout))
        if not await _race(waiting, stop):
            await _cancel(waiting)
            self.command("abort")
            await self.bus.sync()
            self.say("interrupted before start: abort published")
            return False
        self.command("start")
        self.t_start_wall = time.time()
        await self.bus.sync()
        self.say(f"run {run}: start published ({self.vehicles} vehicles ready)")
        return True

    async def follow_run(self, stop: asyncio.Event, out: Path, recorder: Recorder | None = None,
                         timeout_s: float | None = None) -> RunResult:
        """Follow the started run until every vehicle is finished, ``timeout_s`` passed
        (default: arm + take-off + mission + land timeouts) or ``stop`` is set (abort
        published). Writes ``out/summary.json`` and the recording on every exit path, and the
        interim summary (``complete: false``, atomically) every few seconds while following,
        so a SIGKILLed coordinator still leaves its last one; the final one says ``complete:
        true``. The verdict (:func:`~vtube_fleet.core.metrics.verdict`) makes a run that broke
        a limit ``unsafe``, whatever else happened."""
        cfg = self.mission.config
        timeout = (cfg.arm_timeout_s + cfg.takeoff_timeout_s + cfg.mission_timeout_s
                   + cfg.land_timeout_s) if timeout_s is None else timeout_s
        recorder = recorder if recorder is not None else NullRecorder()
        # the radii the agents fly (the run's δ, announced): pairs are searched as `run`
        # searches them, and review of the recording searches the same (r_s_flown, r_a_flown)
        radii = bus_safety_budget(self.mission, None, self.max_age_s).inflate(
            self.mission.scenario.controller)
        # the route the agents fly (each plans it so): the monitor replays its hand-overs to
        # judge each vehicle against its segment; the recording keeps its apex distances
        route = None
        if self.mission.scenario.is_route:
            try:  # (a few hundred ms with "auto" apex distances: not on the event loop)
                route = (await asyncio.to_thread(FlightPlan.for_mission, self.mission,
                                                 radii)).route
            except PartitionError:  # the agents refuse this run too: judged without hand-overs
                route = None
        mon = RunMonitor(self.mission, self.vehicles, recorder=recorder,
                         t0_s=self.t_start_wall or time.time(), flown=radii, route=route)
        fleet = self.mission.with_vehicles(self.vehicles)
        recorder.log_scene(fleet.scenario, route, mission=fleet.config, meta={
            "kind": "mqtt", "rate_hz": cfg.rate_hz, "run_id": self.run_id,
            "broker": self.broker, "vehicles": self.vehicles, "r_s_flown": radii.r_s,
            "r_a_flown": radii.r_a})
        outcome, reason = "failed", ""

        def summary(**extra: Any) -> dict[str, Any]:
            return mon.summary(
                mission_id=self.mission_id, run_id=self.run_id, config_hash=self.config_hash,
                broker=self.broker, lost=self.lost_vehicles(),
                vehicle_states=self.vehicle_table(), clocks=self.clocks(),
                max_clock_offset_s=cfg.max_clock_offset_s,
                wall_s=round(time.time() - (self.t_start_wall or time.time()), 3), **extra)

        def checkpoint() -> None:
            """The summary so far (``complete: false``): a coordinator killed without a
            chance to clean up (SIGKILL) still leaves its last summary."""
            t = time.time() - (self.t_start_wall or time.time())
            try:
                s = summary(outcome="running")
            except Exception as exc:  # noqa: BLE001 - a checkpoint never stops the run
                log.warning("cannot build the interim summary: %s", exc)
                return
            write_interim_summary(out, s, f"the coordinator was still following the run "
                                          f"({t:.1f} s after start)")

        try:
            follow = asyncio.ensure_future(self.follow(timeout, mon, checkpoint=checkpoint))
            if await _race(follow, stop):
                outcome = follow.result()
                reason = self.end_reason
            else:
                await _cancel(follow)
                self.command("abort")
                await self.bus.sync()
                self.say("interrupted: abort published; the agents hold, then land")
                outcome = "interrupted"
                reason = "interrupted: abort published; the agents hold, then land"
        finally:  # the summary (and the recording) on every exit path
            final = summary(outcome=outcome, reason=reason, complete=True)
            v = verdict(final)
            if not v.safe:  # THE verdict: a broken limit makes the run unsafe, whatever else
                before = outcome + (f": {reason}" if reason else "")
                final["outcome"] = outcome = "unsafe"
                final["reason"] = reason = f"{v.summary_line} (the run itself ended {before})"
            path = write_summary(out, final)
            recorder.log_summary(final)
            recorder.close()
        return RunResult(outcome, reason, final, path)

    async def abort_announced(self) -> str:
        """Publish abort for the run announced on the broker; returns its run id."""
        await self.bus.sync()
        cfg = self.bus.config
        if cfg is None:
            raise MissionRunError(
                f"no run of mission {self.mission_id} announced on {self.broker} "
                f"(nothing to abort)")
        self.run_id = cfg.run_id
        self.command("abort")
        await self.bus.sync()
        return cfg.run_id

    async def status(self, listen_s: float) -> dict[str, Any]:
        """The announced run, the last command and every vehicle's state (listening
        ``listen_s`` for live states), as a JSON-able dict."""
        await self.bus.sync()
        cfg = self.bus.config
        if cfg is not None:
            self.run_id = cfg.run_id
            self.vehicles = max(self.vehicles, cfg.vehicles) if cfg.vehicles else self.vehicles
        with contextlib.suppress(TimeoutError):  # listen a moment for live states
            await self.bus.wait_for(lambda: False, listen_s)
        cmd = self.bus.command
        now = time.time()
        return {
            "mission_id": self.mission_id,
            "broker": self.broker,
            "config_hash": self.config_hash,
            "run": None if cfg is None else {
                "run_id": cfg.run_id, "config_hash": cfg.config_hash,
                "hash_matches": cfg.config_hash == self.config_hash,
                "vehicles": cfg.vehicles, "announced_s_ago": round(now - cfg.stamp_s, 1),
                "source": cfg.source,
            },
            "command": None if cmd is None else {
                "command": cmd.command, "run_id": cmd.run_id,
                "s_ago": round(now - cmd.stamp_s, 1),
            },
            "vehicles": self.vehicle_table(),
        }

    def lost_vehicles(self) -> list[int]:
        """Vehicles whose agent was lost (last will) or that reported LOST."""
        out = []
        for v in range(self.vehicles):
            st = self.bus.statuses.get(v)
            s = self.bus.latest().get(v)
            if (st is not None and st.status == "lost") or (
                s is not None and s.phase == Phase.LOST
            ):
                out.append(v)
        return out

    def vehicle_table(self) -> list[dict[str, Any]]:
        rows = []
        now = time.time()
        for vid in sorted(set(range(self.vehicles)) | set(self.bus.latest())):
            s = self.bus.latest().get(vid)
            st = self.bus.statuses.get(vid)
            rows.append(
                {
                    "id": vid,
                    "status": st.status if st else None,
                    "stage": st.stage if st else None,
                    "run": st.run_id if st else None,
                    "hash_ok": (st.config_hash == self.config_hash) if st else None,
                    "detail": st.detail if st else None,
                    "phase": s.phase.value if s else None,
                    "x_m": round(s.x_m, 3) if s else None,
                    "y_m": round(s.y_m, 3) if s else None,
                    "age_s": round(now - s.stamp_s, 3) if s else None,
                    "clock_offset_s": (round(st.clock.offset_s, 6)
                                       if st is not None and st.clock is not None else None),
                }
            )
        return rows


@dataclass
class RunResult:
    """How a followed run ended: its outcome (:mod:`vtube_fleet.outcome`), the reason when it
    is unsafe, the summary and where it was written."""

    outcome: str
    reason: str
    summary: dict[str, Any]
    summary_path: Path


async def _race(task: asyncio.Future[Any], event: asyncio.Event) -> bool:
    """Wait for ``task`` or ``event``, whichever comes first; True if ``task`` finished
    (its exception, if any, is raised). The task is left running otherwise."""
    waiter = asyncio.ensure_future(event.wait())
    try:
        done, _ = await asyncio.wait({task, waiter}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        waiter.cancel()
    if task in done:
        task.result()
        return True
    return False


async def _cancel(task: asyncio.Future[Any]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


def _ids(ids: Iterable[int]) -> str:
    return ", ".join(str(i) for i in ids)
