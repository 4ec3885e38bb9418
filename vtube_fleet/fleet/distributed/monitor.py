"""The fleet as its states reported it.

:class:`RunMonitor` folds the vehicles' published states into the run summary (and the
recording), for the coordinator and for each agent.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vtube_fleet.core.metrics import finite_or_none, percentile_or_none
from vtube_fleet.state import (
    COUNTED_AIRBORNE_PHASES,
    STOPPED_PHASES,
    NeighbourState,
    Phase,
)

__all__ = [
    "RunMonitor",
]

log = logging.getLogger(__name__)

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

    ``flown``: the radii the fleet flies (r_s', r_a' of its safety budget). The ``""`` stream
    then searches pairs as the supervisor's does (:meth:`SafetyMonitor.for_run`: within
    r_s' + r_a' + 1 m), so ``min_pair_distance_m`` is reported although a fleet flying r_s'
    keeps its vehicles farther apart than the physical r_s + r_a (without ``flown`` only pairs
    within r_s + r_a are searched: none, ``null``). The limits stay the physical ones.

    ``route``: the route the fleet flies (a :class:`~vtube_fleet.core.route.Route` planned with
    the flown radii, as every agent plans it). On a route of several segments each vehicle's
    leg distances are judged against the segment it flies, which the monitor derives from the
    states themselves: the hand-overs replayed on the judged positions of every snapshot
    (:meth:`Route.advance <vtube_fleet.core.route.Route.advance>`, what ``review`` replays on
    the recording), not a segment the vehicles publish — the bus's state message stays as it
    is, and the judge does not take a vehicle's word for the segment it is judged against.
    Without ``route``: each position's start segment (no hand-overs).
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
    #: a :class:`vtube_fleet.recording.api.Recorder` (the fleet as its states reported it), or None
    recorder: Any = None
    t0_s: float = 0.0  # wall time the run started: the recording's mission time 0
    ticks: int = 0
    flown: Any = None  # r_s', r_a' flown (a ControllerParams), or None: see the docstring
    route: Any = None  # the Route flown (its hand-overs replayed), or None: see the docstring

    def __post_init__(self) -> None:
        from vtube_fleet.core.metrics import SafetyMonitor, SummaryAccumulator, ViolationLog

        sc = self.mission.scenario
        self.monitor = SafetyMonitor.for_corridor(sc.corridor, sc.controller, self.flown)
        self.acc = SummaryAccumulator(self.vehicles)
        self.violations = ViolationLog(self.monitor)
        #: each vehicle's segment as replayed from its judged positions (−1: not judged yet)
        self.segment = np.full(self.vehicles, -1, np.intp)

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
                self.recorder.log_event(state.stamp_s - self.t0_s,
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
                self.recorder.log_exits(state.stamp_s - self.t0_s, self.ticks, [vid])

    def _past_finish(self, st: NeighbourState) -> bool:
        """Past the route's last finishing line, by its position (:meth:`Corridor.past_finish
        <vtube_fleet.core.route.Corridor.past_finish>`)."""
        sc = self.mission.scenario
        return bool(sc.corridor.past_finish(np.array([st.x_m, st.y_m]),
                                            sc.controller.eps_0)[0])

    def _segments(self, pos: np.ndarray) -> np.ndarray:
        """(M,) the segment each vehicle is judged against at this snapshot (its judged
        position ``pos``, NaN: not judged): the route's hand-overs replayed (class
        docstring)."""
        corridor = self.mission.scenario.corridor
        if corridor.is_single:
            return np.zeros(self.vehicles, np.intp)
        if self.route is not None:
            self.segment = self.route.advance(pos, self.segment)
        else:
            here = np.isfinite(pos).all(axis=1) & (self.segment < 0)
            if here.any():
                self.segment[here] = corridor.start_segment_of(pos[here])
        return np.maximum(self.segment, 0)

    def sample(self, states: dict[int, NeighbourState], now_s: float,
               cmd: dict[int, np.ndarray] | None = None) -> None:
        """One snapshot of the latest states (the coordinator's tick). ``cmd``: commanded
        tube-frame velocities known for some vehicles (an agent knows its own), recorded."""
        m = self.vehicles
        air = np.full((m, 2), np.nan)  # every airborne pair from the take-off on
        for vid, st in states.items():
            if 0 <= vid < m and st.phase in COUNTED_AIRBORNE_PHASES:
                air[vid] = (st.x_m, st.y_m)
        q = air[np.isfinite(air[:, 0])]
        if q.shape[0] > 1:
            d = np.hypot(*(q[:, None, :] - q[None, :, :]).transpose(2, 0, 1))
            d[np.diag_indices_from(d)] = np.inf
            self.min_pair_airborne = min(self.min_pair_airborne, float(d.min()))
        if self.tube_start_s is None:
            if self.recorder is not None:
                self._record_tick(states, now_s, cmd=cmd)
            return
        pos = np.full((m, 2), np.nan)
        corridor = self.mission.scenario.corridor
        for vid, st in states.items():
            if not 0 <= vid < m:
                continue
            p = (st.x_m, st.y_m)
            # judged in the tube: flying it, or stopped (lost, holding, landing, waiting) or
            # stepping aside inside it
            if st.phase == Phase.IN_TUBE or (
                (st.phase in (Phase.LOST, Phase.STEPPING) or st.phase in STOPPED_PHASES)
                and bool(corridor.inside(np.array(p))[0])
            ):
                pos[vid] = p
            if st.phase == Phase.IN_TUBE and now_s - st.stamp_s < 1.0:
                sp = math.hypot(st.vx_m_s, st.vy_m_s)
                self.measured_speed[0] = min(self.measured_speed[0], sp)
                self.measured_speed[1] = max(self.measured_speed[1], sp)
        seg = self._segments(pos)
        sm = self.monitor.evaluate(pos, None, segment=seg)
        self.acc.add(now_s - self.t0_s, sm)
        e = self.violations.note(now_s - self.t0_s, "", sm, pos, None, range(m), seg)
        if e is not None:
            self.events.append({"t_s": e["t_s"], "vehicle": None, "level": "error",
                                "text": f"LIMIT BROKEN ({e['source']}): {e['condition']} "
                                        f"{e['value']:.3f} m, limit {e['limit']:.3f} m: "
                                        f"vehicle(s) {e['vehicles']}"})
        if self.recorder is not None:
            self._record_tick(states, now_s, safety={"": (pos, np.full_like(pos, np.nan))},
                              cmd=cmd)

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
        self.recorder.log_tick(t_s=now_s - self.t0_s,
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
            "segments": sc.corridor.S,  # of the route flown (1: a [tube])
            **({"r_s_flown": self.flown.r_s, "r_a_flown": self.flown.r_a}
               if self.flown is not None else {}),
            "min_pair_distance_airborne_m": finite_or_none(self.min_pair_airborne),
            "min_commanded_speed_m_s": None,
            "max_commanded_speed_m_s": None,
            "min_measured_speed_m_s": finite_or_none(self.measured_speed[0]),
            "max_measured_speed_m_s": finite_or_none(self.measured_speed[1]),
            "rate_hz": self.mission.config.rate_hz,
            "state_age_p50_s": finite_or_none(percentile_or_none(self.ages, 50)),
            "state_age_p99_s": finite_or_none(percentile_or_none(self.ages, 99)),
            "states_received": len(self.ages),
            "flight_time_s": (
                finite_or_none(last_exit - self.tube_start_s)
                if last_exit is not None and self.tube_start_s is not None
                else None
            ),
            "events": self.events[-400:],
            "first_violation": self.violations.first,
        }
        out.update(extra)
        return self.acc.summary(**out)
