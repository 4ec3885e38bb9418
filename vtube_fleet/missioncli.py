"""``vtube-fleet mission start|abort|status``: the thin coordinator of distributed agents.

The coordinator computes nobody's setpoint. It only

* announces a **run** of the mission (retained ``vtube/<m>/config``: mission id, a new run id,
  the config hash of the mission file, the vehicle count), so an agent with a different mission
  file refuses to fly with a clear error, and a late agent sees that the run already started;
* waits until every agent (``vtube-fleet agent``, one per vehicle) has joined the run and its
  vehicle is READY, then publishes ``start`` (retained ``vtube/<m>/cmd``); ``abort`` likewise;
* reads the states the agents publish: ``status`` prints them; ``start --wait --out DIR`` follows
  the flight until every vehicle has exited and landed (or failed / was lost) and writes
  ``DIR/summary.json`` computed from those states with :mod:`vtube_fleet.core.metrics` (the same
  :class:`~vtube_fleet.core.metrics.SummaryAccumulator` the simulator and the supervisor use).

Exit codes: 0 done (``start --wait``: every vehicle exited and landed), 2 user error (bad
file, broker unreachable, an agent refused or did not join), 3 the run ended incomplete
(aborted, a vehicle lost or failed, timeout), 130 interrupted (``start --wait``: the coordinator
publishes ``abort`` first, so the agents hold and land).

See ``docs/mqtt.md``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import json
import logging
import math
import re
import signal
import sys
import time
import tomllib
import uuid
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vtube_fleet.bus.codec import Command, MissionConfigMsg, encode_command, encode_config
from vtube_fleet.bus.mqtt import MqttBus
from vtube_fleet.bus.topics import validate_mission_id
from vtube_fleet.core.metrics import verdict
from vtube_fleet.errors import ConfigError, UserError
from vtube_fleet.state import (
    COUNTED_AIRBORNE_PHASES,
    STOPPED_PHASES,
    NeighbourState,
    Phase,
)

__all__ = [
    "DEFAULT_BROKER",
    "Coordinator",
    "MissionRunError",
    "RunMonitor",
    "add_bus_args",
    "config_hash",
    "default_mission_id",
    "register",
    "write_summary",
]

log = logging.getLogger(__name__)

DEFAULT_BROKER = "mqtt://127.0.0.1:1883"
EXIT_OK = 0
EXIT_INCOMPLETE = 3
EXIT_INTERRUPTED = 130
EXIT_UNSAFE = 4

class MissionRunError(UserError):
    """The run could not start: broker unreachable, an agent refused or did not join."""


# ----------------------------------------------------------------------------------------------
# mission identity (shared with the agent)
# ----------------------------------------------------------------------------------------------
def config_hash(path: str | Path) -> str:
    """Hash of the mission file's *content* (parsed TOML, canonical JSON; comments and
    formatting do not count): 16 hex digits of SHA-256."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    canonical = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(canonical.encode()).hexdigest()[:16]


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


def bus_safety_budget(mission: Any, measured: Any, max_age_s: float) -> Any:
    """The MQTT agents' :class:`~vtube_fleet.fleet.budget.SafetyBudget`: the fleet's
    :func:`~vtube_fleet.fleet.budget.mission_budget` with ``max_age_s`` added to L (a
    neighbour's state is used up to that old). ``measured``: a
    :class:`~vtube_fleet.fleet.budget.LinkMeasurement` (an agent's own), or None for the
    coordinator's assumptions (:data:`ASSUMED_LINK_LATENCY_S`, :data:`ASSUMED_ACCURACY_M`)."""
    from vtube_fleet.fleet.budget import LinkMeasurement, mission_budget

    if measured is None:
        measured = LinkMeasurement(ASSUMED_LINK_LATENCY_S - mission.config.latency_headroom_s,
                                   0.0, ASSUMED_ACCURACY_M)
    return mission_budget(mission, measured, extra_latency_s=max_age_s)


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


def default_mission_id(path: str | Path) -> str:
    """The mission id used in the topics: the file name without extension, with characters
    that are not letters, digits, ``_.-`` replaced by ``-``."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "-", Path(path).stem)[:64] or "mission"
    return validate_mission_id(stem)


# ----------------------------------------------------------------------------------------------
# following a run: the summary from the agents' states
# ----------------------------------------------------------------------------------------------
def _pct(values: Iterable[float], q: float) -> float | None:
    a = np.asarray(list(values), dtype=float)
    a = a[np.isfinite(a)]
    return float(np.percentile(a, q)) if a.size else None


def _num(x: float | None) -> float | None:
    if x is None:
        return None
    return float(x) if math.isfinite(float(x)) else None


@dataclass
class RunMonitor:
    """Folds snapshots of the agents' states into the fleet summary (``summary.json``).

    Each :meth:`sample` (at the mission's control rate) takes the latest state of every vehicle:
    the ``""`` metric stream holds the vehicles IN_TUBE (and LOST ones inside the tube, at
    their frozen position), as the supervisor's does; the coordinator knows no commanded
    velocities, so the commanded speed keys are ``None`` and the measured speeds are
    ``min_measured_speed_m_s``/``max_measured_speed_m_s``. Exit times are the stamps of each
    vehicle's first state past the finishing line; times (``*_exit_s``, metric steps, the
    recording's mission time) count from ``t0_s``, the start command, as the supervisor's count
    from its own start; ``flight_time_s`` from the fleet's first IN_TUBE state.
    """

    mission: Any
    vehicles: int
    monitor: Any = None
    acc: Any = None
    tube_start_s: float | None = None
    exit_stamp: dict[int, float] = field(default_factory=dict)
    ages: list[float] = field(default_factory=list)
    min_pair_airborne: float = math.inf
    measured_speed: list[float] = field(default_factory=lambda: [math.inf, -math.inf])
    events: list[dict[str, Any]] = field(default_factory=list)
    phases: dict[int, Phase] = field(default_factory=dict)
    #: a :class:`vtube_fleet.recording.Recorder` (the fleet as its states reported it), or None
    recorder: Any = None
    t0_s: float = 0.0  # wall time the run started: the recording's mission time 0
    ticks: int = 0

    def __post_init__(self) -> None:
        from vtube_fleet.core.metrics import SafetyMonitor, SummaryAccumulator, ViolationLog

        sc = self.mission.scenario
        self.monitor = SafetyMonitor.from_params(sc.tube, sc.obstacles, sc.controller)
        self.acc = SummaryAccumulator(self.vehicles)
        self.violations = ViolationLog(self.monitor)

    def on_state(self, state: NeighbourState, received_s: float, *, count_age: bool = True
                 ) -> None:
        """Every live state heard (bus state listener): ages, phase changes, exits.
        ``count_age=False``: a state that did not travel through the broker (an agent's own)."""
        vid = state.vehicle_id
        if not 0 <= vid < self.vehicles:
            return
        if count_age:
            self.ages.append(received_s - state.stamp_s)
        prev = self.phases.get(vid)
        if prev != state.phase:
            self.phases[vid] = state.phase
            if self.recorder is not None:
                self._record(
                    "log_event",
                    state.stamp_s - self.t0_s,
                    f"{prev.value if prev else '-'} → {state.phase.value}",
                    vehicle_id=vid,
                )
            self.events.append(
                {
                    "t_wall": round(state.stamp_s, 3),
                    "vehicle": vid,
                    "text": f"{prev.value if prev else '-'} → {state.phase.value}",
                }
            )
        if state.phase == Phase.IN_TUBE and self.tube_start_s is None:
            self.tube_start_s = state.stamp_s
        if (
            state.phase in (Phase.EXITED, Phase.HOLDING, Phase.LANDING, Phase.LANDED)
            and prev in (Phase.IN_TUBE, Phase.EXITED)
            and vid not in self.exit_stamp
            and (state.phase == Phase.EXITED or self._past_finish(state))
        ):
            self.exit_stamp[vid] = state.stamp_s
            self.acc.add_exits(state.stamp_s - self.t0_s, [vid])
            if self.recorder is not None:  # the recording's exits are exactly these (its
                # own detection is off: it would see other moments, or a vehicle first heard
                # already exited, which is not an exit seen here)
                self._record("log_exits", state.stamp_s - self.t0_s, self.ticks, [vid])

    def _past_finish(self, st: NeighbourState) -> bool:
        tube = self.mission.scenario.tube
        p = np.array([st.x_m, st.y_m])
        eps0 = float(self.mission.scenario.controller.eps_0)
        return bool(-((p - tube.p_r1) @ tube.n_c) <= eps0)

    def _record(self, method: str, *args: Any, **kwargs: Any) -> None:
        try:
            getattr(self.recorder, method)(*args, **kwargs)
        except Exception as exc:  # the recording must never stop the coordinator
            log.warning("recorder: %s failed: %s", method, exc)

    def sample(self, states: dict[int, NeighbourState], now_s: float,
               cmd: dict[int, np.ndarray] | None = None) -> None:
        """One snapshot of the latest states (the coordinator's tick). ``cmd``: commanded
        tube-frame velocities known for some vehicles (an agent knows its own), recorded."""
        if self.tube_start_s is None:
            if self.recorder is not None:
                self._record_tick(states, now_s, cmd=cmd)
            return
        m = self.vehicles
        pos = np.full((m, 2), np.nan)
        air = np.full((m, 2), np.nan)
        tube = self.mission.scenario.tube
        for vid, st in states.items():
            if not 0 <= vid < m:
                continue
            p = (st.x_m, st.y_m)
            if st.phase in COUNTED_AIRBORNE_PHASES:
                air[vid] = p
            # judged in the tube: flying it, or stopped inside it (lost, holding, landing)
            if st.phase == Phase.IN_TUBE or (
                (st.phase == Phase.LOST or st.phase in STOPPED_PHASES)
                and bool(tube.contains(np.array(p)))
            ):
                pos[vid] = p
            if st.phase == Phase.IN_TUBE and now_s - st.stamp_s < 1.0:
                sp = math.hypot(st.vx_m_s, st.vy_m_s)
                self.measured_speed[0] = min(self.measured_speed[0], sp)
                self.measured_speed[1] = max(self.measured_speed[1], sp)
        sm = self.monitor.evaluate(pos, None)
        self.acc.add(now_s - self.t0_s, sm)
        e = self.violations.note(now_s - self.t0_s, "", sm, pos, None, range(m))
        if e is not None:
            self.events.append({"t_s": e["t_s"], "vehicle": None, "level": "error",
                                "text": f"LIMIT BROKEN ({e['source']}): {e['condition']} "
                                        f"{e['value']:.3f} m, limit {e['limit']:.3f} m: "
                                        f"vehicle(s) {e['vehicles']}"})
        if self.recorder is not None:
            self._record_tick(states, now_s, safety={"": (pos, np.full_like(pos, np.nan))},
                              cmd=cmd)
        q = air[np.isfinite(air[:, 0])]
        if q.shape[0] > 1:
            d = np.hypot(*(q[:, None, :] - q[None, :, :]).transpose(2, 0, 1))
            d[np.diag_indices_from(d)] = np.inf
            self.min_pair_airborne = min(self.min_pair_airborne, float(d.min()))

    def _record_tick(
        self, states: dict[int, NeighbourState], now_s: float, safety: Any = None,
        cmd: dict[int, np.ndarray] | None = None,
    ) -> None:
        m = self.vehicles
        pos = np.full((m, 2), np.nan)
        vel = np.full((m, 2), np.nan)
        phases = [""] * m
        for vid, st in states.items():
            if 0 <= vid < m:
                pos[vid] = (st.x_m, st.y_m)
                vel[vid] = (st.vx_m_s, st.vy_m_s)
                phases[vid] = st.phase.value
        cmd_arr = None
        if cmd:
            cmd_arr = np.full((m, 2), np.nan)
            for vid, c in cmd.items():
                if 0 <= vid < m:
                    cmd_arr[vid] = c
        self._record(
            "log_tick",
            t_s=now_s - self.t0_s,
            tick=self.ticks,
            ids=np.arange(m),
            pos=pos,
            vel=vel,
            phases=phases,
            cmd=cmd_arr,
            safety=safety,
        )
        self.ticks += 1

    def summary(self, **extra: Any) -> dict[str, Any]:
        sc = self.mission.scenario
        params = sc.controller
        last_exit = max(self.exit_stamp.values()) if self.exit_stamp else None
        out: dict[str, Any] = {
            "kind": "mqtt",
            "source": self.mission.source,
            "vehicles": self.vehicles,
            "r_s": params.r_s,
            "r_a": params.r_a,
            "pair_limit_m": self.monitor.limits.pair_m,
            "min_pair_distance_airborne_m": _num(self.min_pair_airborne),
            "min_commanded_speed_m_s": None,
            "max_commanded_speed_m_s": None,
            "min_measured_speed_m_s": _num(self.measured_speed[0]),
            "max_measured_speed_m_s": _num(self.measured_speed[1]),
            "rate_hz": self.mission.config.rate_hz,
            "state_age_p50_s": _num(_pct(self.ages, 50)),
            "state_age_p99_s": _num(_pct(self.ages, 99)),
            "states_received": len(self.ages),
            "flight_time_s": (
                _num(last_exit - self.tube_start_s)
                if last_exit is not None and self.tube_start_s is not None
                else None
            ),
            "events": self.events[-400:],
            "first_violation": self.violations.first,
        }
        out.update(extra)
        return self.acc.summary(**out)


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
    ) -> None:
        from vtube_fleet.config.mission import load_mission

        self.path = Path(mission_path)
        self.mission = load_mission(self.path)
        self.mission_id = mission_id or default_mission_id(self.path)
        validate_mission_id(self.mission_id)
        self.config_hash = config_hash(self.path)
        n = self.mission.count if vehicles is None else int(vehicles)
        if not 1 <= n <= self.mission.count:
            raise MissionRunError(
                f"--vehicles must be between 1 and {self.mission.count} (the slots of "
                f"{self.path.name}), got {n}"
            )
        self.vehicles = n
        self.max_age_s = default_max_age_s(self.mission) if max_age_s is None else max_age_s
        lost_after = self.mission.config.lost_after_s
        if not 0 < self.max_age_s <= lost_after:
            raise MissionRunError(
                f"--max-age {self.max_age_s:g} s must be > 0 and <= lost_after_s = "
                f"{lost_after:g} s of {self.path.name}"
            )
        self.cells = cells
        self.broker = broker
        self.broker_timeout_s = broker_timeout_s
        self.bus = MqttBus(broker, self.mission_id)
        self.run_id = ""
        self.announced: MissionConfigMsg | None = None
        self.t_start_wall: float | None = None

    async def __aenter__(self) -> Coordinator:
        self.bus.start()
        try:
            await self.bus.wait_connected(self.broker_timeout_s)
        except TimeoutError:
            await self.bus.close()
            raise MissionRunError(
                f"cannot reach the MQTT broker {self.broker} within {self.broker_timeout_s:g} s "
                f"(is it running? --broker mqtt://HOST:PORT)"
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
                print(
                    f"waiting for agents: {len(joined)}/{self.vehicles} joined, "
                    f"{len(ready)}/{self.vehicles} ready",
                    file=sys.stderr,
                    flush=True,
                )
            with contextlib.suppress(TimeoutError):
                await self.bus.wait_for(lambda: False, 0.2)

    def _phase(self, vid: int) -> str:
        s = self.bus.latest().get(vid)
        return "no state" if s is None else s.phase.value

    async def follow(self, timeout_s: float, mon: RunMonitor, progress: bool = True) -> str:
        """Feed ``mon`` (states as they arrive, snapshots at the control rate) until every
        vehicle is finished; the outcome: ``completed``, ``incomplete`` or ``timeout``."""
        self.bus.add_state_listener(mon.on_state)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        period = self.mission.config.period_s
        last_print = -math.inf
        next_t = loop.time()
        aborted_for: str | None = None
        while True:
            mon.sample(self.bus.latest(), time.time())
            if all(self.finished(v) for v in range(self.vehicles)):
                break
            refused = self.refusals()
            if refused and aborted_for is None:
                aborted_for = "; ".join(refused)
                print(f"aborting: agent refused after start: {aborted_for}", file=sys.stderr)
                self.command("abort")
            now = loop.time()
            if now > deadline:
                return "timeout"
            if progress and now - last_print >= 5.0:
                last_print = now
                counts: dict[str, int] = {}
                for v in range(self.vehicles):
                    ph = self._phase(v)
                    counts[ph] = counts.get(ph, 0) + 1
                print(
                    "fleet: "
                    + ", ".join(f"{k} {n}" for k, n in sorted(counts.items()))
                    + f"; exited {len(mon.exit_stamp)}/{self.vehicles}",
                    file=sys.stderr,
                    flush=True,
                )
            next_t += period
            await asyncio.sleep(max(0.0, next_t - loop.time()))  # the coordinator's clock
        done = len(mon.exit_stamp) == self.vehicles and all(
            (s := self.bus.latest().get(v)) is not None and s.phase == Phase.LANDED
            for v in range(self.vehicles)
        )
        return "completed" if done and aborted_for is None else "incomplete"

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
                }
            )
        return rows


def _ids(ids: Iterable[int]) -> str:
    return ", ".join(str(i) for i in ids)


# ----------------------------------------------------------------------------------------------
# the commands
# ----------------------------------------------------------------------------------------------
def write_summary(out: Path, summary: dict[str, Any]) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / "summary.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(summary, indent=2) + "\n")
    tmp.replace(path)
    return path


async def _start(args: argparse.Namespace) -> int:
    loop = asyncio.get_running_loop()
    interrupted = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, interrupted.set)
    async with Coordinator(
        args.mission,
        args.broker,
        mission_id=args.mission_id,
        vehicles=args.vehicles,
        broker_timeout_s=args.broker_timeout,
        max_age_s=args.max_age,
        cells=not args.no_cells,
    ) as co:
        cfg = co.mission.config
        run = co.announce()
        print(
            f"mission {co.mission_id} run {run}: config {co.config_hash} announced on "
            f"{args.broker} (neighbour max age {1000 * co.max_age_s:.0f} ms, cells "
            f"{co.announced.cell_m:g} m); waiting for {co.vehicles} agents",
            file=sys.stderr,
            flush=True,
        )
        ready_timeout = (
            args.ready_timeout
            if args.ready_timeout is not None
            else cfg.connect_timeout_s + cfg.ready_timeout_s
        )
        waiting = asyncio.ensure_future(co.wait_ready(ready_timeout))
        if not await _race(waiting, interrupted):
            await _cancel(waiting)
            co.command("abort")
            await co.bus.sync()
            print("interrupted before start: abort published", file=sys.stderr)
            return EXIT_INTERRUPTED
        co.command("start")
        co.t_start_wall = time.time()
        await co.bus.sync()
        print(f"run {run}: start published ({co.vehicles} vehicles ready)", file=sys.stderr)
        if not args.wait:
            return EXIT_OK
        timeout = (
            args.timeout
            if args.timeout is not None
            else cfg.arm_timeout_s
            + cfg.takeoff_timeout_s
            + cfg.mission_timeout_s
            + cfg.land_timeout_s
        )
        out = args.out if args.out is not None else Path("runs") / co.mission_id
        recorder = _recorder(args, out)
        mon = RunMonitor(
            co.mission, co.vehicles, recorder=recorder, t0_s=co.t_start_wall or time.time()
        )
        if recorder is not None:
            mon._record(
                "log_scene",
                co.mission.with_vehicles(co.vehicles),
                None,
                meta={
                    "kind": "mqtt",
                    "rate_hz": cfg.rate_hz,
                    "run_id": run,
                    "broker": args.broker,
                    "vehicles": co.vehicles,
                },
            )
        outcome = "failed"
        try:
            follow = asyncio.ensure_future(co.follow(timeout, mon))
            if await _race(follow, interrupted):
                outcome = follow.result()
            else:
                await _cancel(follow)
                co.command("abort")
                await co.bus.sync()
                print("interrupted: abort published; the agents hold, then land", file=sys.stderr)
                outcome = "interrupted"
        finally:  # the summary (and the recording) on every exit path
            summary = mon.summary(
                mission_id=co.mission_id,
                run_id=run,
                config_hash=co.config_hash,
                broker=args.broker,
                outcome=outcome,
                lost=co.lost_vehicles(),
                vehicle_states=co.vehicle_table(),
                wall_s=round(time.time() - (co.t_start_wall or time.time()), 3),
            )
            v = verdict(summary)
            if not v.safe:  # THE verdict: a broken limit makes the run unsafe, whatever else
                summary["outcome"] = outcome = "unsafe"
                summary["reason"] = v.summary_line
            path = write_summary(out, summary)
            if recorder is not None:
                mon._record("log_summary", summary)
                mon._record("close")
        print(
            f"{outcome}: {summary.get('exited')}/{co.vehicles} exited; min pair distance "
            f"{_fmt(summary.get('min_pair_distance_m'))} (2 r_s = {summary['pair_limit_m']:.2f} m),"
            f" obstacle centre {_fmt(summary.get('min_obstacle_center_distance_m'))}, "
            f"violations {summary.get('violations')}; state age p50/p99 "
            f"{_fmt(summary.get('state_age_p50_s'), 'ms', 1000)}/"
            f"{_fmt(summary.get('state_age_p99_s'), 'ms', 1000)}; summary {path}",
            file=sys.stderr,
        )
        if outcome == "unsafe":
            print(f"error: mission unsafe: {summary['reason']}", file=sys.stderr)
            return EXIT_UNSAFE
        if outcome == "interrupted":
            return EXIT_INTERRUPTED
        return EXIT_OK if outcome == "completed" else EXIT_INCOMPLETE


def _recorder(args: argparse.Namespace, out: Path) -> Any:
    """The fleet recording of ``start --wait`` (``--rerun-save``, default OUT/recording.rrd)."""
    from vtube_fleet.recording import recorder_from_args

    # exits only as RunMonitor decides them (from every state heard, also between two ticks)
    return recorder_from_args(args, out, kind="fleet", app_id="vtube_fleet",
                              detect_exits=False)


def add_bus_args(parser: argparse.ArgumentParser) -> None:
    """``--broker`` and ``--mission-id``, the same for ``vtube-fleet agent`` and ``mission``."""
    parser.add_argument(
        "--broker", default=DEFAULT_BROKER, help=f"MQTT broker URL (default {DEFAULT_BROKER})"
    )
    parser.add_argument(
        "--mission-id", default=None, help="topic name of the mission (default: the file name)"
    )


def _fmt(v: float | None, unit: str = "m", scale: float = 1.0) -> str:
    return "—" if v is None else f"{v * scale:.2f} {unit}"


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


async def _abort(args: argparse.Namespace) -> int:
    async with Coordinator(
        args.mission, args.broker, mission_id=args.mission_id, broker_timeout_s=args.broker_timeout
    ) as co:
        await co.bus.sync()
        cfg = co.bus.config
        if cfg is None:
            raise MissionRunError(
                f"no run of mission {co.mission_id} announced on {args.broker} (nothing to abort)"
            )
        co.run_id = cfg.run_id
        co.command("abort")
        await co.bus.sync()
        print(f"mission {co.mission_id} run {cfg.run_id}: abort published", file=sys.stderr)
    return EXIT_OK


async def _status(args: argparse.Namespace) -> int:
    async with Coordinator(
        args.mission, args.broker, mission_id=args.mission_id, broker_timeout_s=args.broker_timeout
    ) as co:
        await co.bus.sync()
        cfg = co.bus.config
        if cfg is not None:
            co.run_id = cfg.run_id
            co.vehicles = max(co.vehicles, cfg.vehicles) if cfg.vehicles else co.vehicles
        with contextlib.suppress(TimeoutError):  # listen a moment for live states
            await co.bus.wait_for(lambda: False, args.listen)
        rows = co.vehicle_table()
        cmd = co.bus.command
        info = {
            "mission_id": co.mission_id,
            "broker": args.broker,
            "config_hash": co.config_hash,
            "run": None
            if cfg is None
            else {
                "run_id": cfg.run_id,
                "config_hash": cfg.config_hash,
                "hash_matches": cfg.config_hash == co.config_hash,
                "vehicles": cfg.vehicles,
                "announced_s_ago": round(time.time() - cfg.stamp_s, 1),
                "source": cfg.source,
            },
            "command": None
            if cmd is None
            else {
                "command": cmd.command,
                "run_id": cmd.run_id,
                "s_ago": round(time.time() - cmd.stamp_s, 1),
            },
            "vehicles": rows,
        }
    if args.json:
        print(json.dumps(info, indent=2))
        return EXIT_OK
    print(f"mission {co.mission_id} on {args.broker} (this file's config hash {co.config_hash})")
    if cfg is None:
        print("  no run announced")
    else:
        r = info["run"]
        print(
            f"  run {cfg.run_id}: {cfg.vehicles} vehicles, hash {cfg.config_hash}"
            f"{'' if r['hash_matches'] else ' (DIFFERS from this file)'}, announced "
            f"{r['announced_s_ago']} s ago from {cfg.source}"
        )
    if cmd is not None:
        print(f"  last command: {cmd.command} (run {cmd.run_id}, {info['command']['s_ago']} s ago)")
    print(
        f"  {'id':>3} {'status':<8} {'stage':<12} {'phase':<11} {'x_m':>8} {'y_m':>8} {'age_s':>7}"
    )
    for r in rows:

        def f(v: Any, fmt: str) -> str:
            return "-" if v is None else format(v, fmt)

        print(
            f"  {r['id']:>3} {f(r['status'], '<8')} {f(r['stage'] or '', '<12')} "
            f"{f(r['phase'], '<11')} {f(r['x_m'], '8.2f')} {f(r['y_m'], '8.2f')} "
            f"{f(r['age_s'], '7.1f')}"
        )
    return EXIT_OK


def _cmd(args: argparse.Namespace) -> int:
    fn = {"start": _start, "abort": _abort, "status": _status}[args.mission_command]
    return asyncio.run(fn(args))


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "mission",
        help="coordinate distributed agents over MQTT: start | abort | status",
        description="The thin coordinator of `vtube-fleet agent` processes: announces a run "
        "(retained config with the mission file's hash), publishes start/abort and reads the "
        "agents' states. It computes nobody's setpoint. See docs/mqtt.md.",
    )
    sub = p.add_subparsers(dest="mission_command", metavar="ACTION")
    sub.required = True

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("mission", type=Path, help="mission file (scenario + [mission])")
        add_bus_args(sp)
        sp.add_argument(
            "--broker-timeout",
            type=float,
            default=10.0,
            metavar="S",
            help="seconds to wait for the broker connection (default 10)",
        )
        sp.set_defaults(func=_cmd)

    s = sub.add_parser("start", help="announce a run, wait for every agent, publish start")
    common(s)
    s.add_argument(
        "--vehicles",
        type=int,
        default=None,
        help="fly slots 0..N-1 only (default: every slot of the mission)",
    )
    s.add_argument(
        "--max-age",
        type=float,
        default=None,
        metavar="S",
        help="oldest neighbour state an agent uses as a live position, budgeted in the "
        "safety margin (default: 3 control periods, at most neighbour_max_age_s)",
    )
    s.add_argument(
        "--no-cells",
        action="store_true",
        help="every agent hears every other (default: spatial cells sized from the mission)",
    )
    s.add_argument(
        "--ready-timeout",
        type=float,
        default=None,
        metavar="S",
        help="seconds to wait for every agent to join with a READY vehicle "
        "(default: connect_timeout_s + ready_timeout_s)",
    )
    s.add_argument(
        "--wait",
        action="store_true",
        help="follow the flight until every vehicle has landed (or failed) and "
        "write OUT/summary.json",
    )
    from vtube_fleet.recording import add_recording_args

    add_recording_args(s)
    s.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder of --wait (default: runs/<mission id>)",
    )
    s.add_argument(
        "--timeout",
        type=float,
        default=None,
        metavar="S",
        help="give up following after S seconds (default: arm + take-off + "
        "mission + land timeouts of the mission)",
    )
    a = sub.add_parser("abort", help="publish abort: every agent holds, then lands")
    common(a)
    st = sub.add_parser("status", help="print the announced run and every vehicle's state")
    common(st)
    st.add_argument(
        "--listen",
        type=float,
        default=1.0,
        metavar="S",
        help="seconds to listen for live states (default 1)",
    )
    st.add_argument("--json", action="store_true", help="print JSON")
