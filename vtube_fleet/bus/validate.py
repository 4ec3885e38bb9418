"""What an agent accepts from the bus: plausibility limits of the states it reads.

The codec (``vtube_fleet.bus.codec``) refuses what is not a message (wrong size, version, type,
non-finite numbers). This module refuses well-formed messages that cannot be true for this
mission, so that nobody on the bus can make a vehicle fly around a phantom:

* a vehicle id that is not a slot of the mission (or of the run, once joined);
* a position outside the mission's region (the tube and the start slots, plus the larger of
  :data:`REGION_MARGIN_M` and what a vehicle can fly in the mission's time, v_max ×
  ``mission_timeout_s``: past the line the first vehicles fly on until the last one exits) or
  a speed above ``max_speed_m_s``;
* a stamp from the future: more than ``max_future_s`` ahead of our clock (clocks must agree to
  better than the neighbour max age anyway, or the staleness rule means nothing);
* a sequence number that jumps ahead by more than a vehicle can count in the time between the
  two stamps (``max_seq_rate_hz`` × (Δstamp + :data:`SEQ_SLACK_S`)); a seq of 2³²−1 after 17.

What the limits cannot stop: a plausible lie (a valid id, a position in the region, a current
stamp). That is the broker's job: per-vehicle credentials and ACLs (``docs/security.md``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from vtube_fleet.state import NeighbourState

__all__ = [
    "MAX_FUTURE_S",
    "MAX_SEQ_RATE_HZ",
    "MAX_SPEED_M_S",
    "REGION_MARGIN_M",
    "SEQ_SLACK_S",
    "StateLimits",
    "mission_state_limits",
]

#: How far a state's stamp may be ahead of the receiver's clock (s).
MAX_FUTURE_S = 0.25
#: Fastest plausible horizontal speed of a vehicle of the fleet (m/s; PX4's MPC_XY_VEL_MAX is
#: at most 20 m/s).
MAX_SPEED_M_S = 30.0
#: Highest plausible rate of a vehicle's state counter (Hz; the control rate is at most 50 Hz).
MAX_SEQ_RATE_HZ = 100.0
#: Extra seconds of counting allowed for a seq jump (timer jitter, a restarted clock).
SEQ_SLACK_S = 10.0
#: Smallest margin around the mission's tube and start slots within which states are plausible
#: (m): vehicles fly past the finishing line and land there, and wait at their slots.
REGION_MARGIN_M = 100.0


@dataclass(frozen=True)
class StateLimits:
    """Plausibility limits of the states a bus accepts (module docstring).

    ``vehicle_ids``: the ids that exist (None: any); ``region``: ``(x_min, x_max, y_min,
    y_max)`` in the tube frame (None: anywhere).
    """

    vehicle_ids: frozenset[int] | None = None
    region: tuple[float, float, float, float] | None = None
    max_speed_m_s: float = MAX_SPEED_M_S
    max_future_s: float = MAX_FUTURE_S
    max_seq_rate_hz: float = MAX_SEQ_RATE_HZ

    def with_vehicles(self, count: int) -> StateLimits:
        """The same limits for the vehicle ids 0..count-1."""
        return dataclasses.replace(self, vehicle_ids=frozenset(range(int(count))))

    def id_problem(self, vehicle_id: int) -> str | None:
        """Why a message about ``vehicle_id`` is refused (None: it may exist)."""
        ids = self.vehicle_ids
        if ids is not None and vehicle_id not in ids:
            top = f"0..{max(ids)}" if ids else "none"
            return f"vehicle {vehicle_id} is not in the mission (vehicles {top})"
        return None

    def future_problem(self, stamp_s: float, now_s: float) -> str | None:
        """Why a stamp is refused as coming from the future (None: it is not)."""
        ahead = stamp_s - now_s
        if ahead > self.max_future_s:
            return (f"stamp {ahead:.3g} s in the future (at most {self.max_future_s:g} s: "
                    "clocks out of sync, or forged)")
        return None

    def problem(self, state: NeighbourState, prev: NeighbourState | None,
                now_s: float) -> tuple[str, str] | None:
        """``(kind, reason)`` if ``state`` is refused, else None. ``prev``: the state held for
        this vehicle (for the seq rule); ``now_s``: the receiver's wall clock."""
        # (the cheap comparisons inline: this runs for every state an agent receives)
        ids = self.vehicle_ids
        if ids is not None and state.vehicle_id not in ids:
            return "not_in_mission", str(self.id_problem(state.vehicle_id))
        if state.stamp_s - now_s > self.max_future_s:
            return "future", str(self.future_problem(state.stamp_s, now_s))
        r = self.region
        if r is not None and not (r[0] <= state.x_m <= r[1] and r[2] <= state.y_m <= r[3]):
            return "region", (f"position ({state.x_m:.6g}, {state.y_m:.6g}) m outside the "
                              f"mission's region x {r[0]:.0f}..{r[1]:.0f}, y {r[2]:.0f}.."
                              f"{r[3]:.0f} m")
        vx, vy, vmax = state.vx_m_s, state.vy_m_s, self.max_speed_m_s
        if abs(vx) + abs(vy) > vmax:  # (|vx| + |vy| >= the speed: most states stop here)
            speed = math.hypot(vx, vy)
            if speed > vmax:
                return "speed", f"speed {speed:.3g} m/s above {vmax:g} m/s"
        if prev is not None and state.seq > prev.seq:
            dt = max(0.0, state.stamp_s - prev.stamp_s)
            allowed = self.max_seq_rate_hz * (dt + SEQ_SLACK_S)
            if state.seq - prev.seq > allowed:
                return "seq_jump", (f"seq jumps from {prev.seq} to {state.seq} in {dt:.3g} s "
                                    f"(at most {allowed:.0f})")
        return None


def _bounds(points: Iterable[Any], margin_m: float) -> tuple[float, float, float, float]:
    xs, ys = [], []
    for p in points:
        xs.append(float(p[0]))
        ys.append(float(p[1]))
    return (min(xs) - margin_m, max(xs) + margin_m, min(ys) - margin_m, max(ys) + margin_m)


def mission_state_limits(mission: Any, vehicles: int | None = None, *,
                         margin_m: float = REGION_MARGIN_M) -> StateLimits:
    """The limits of a mission (a ``vtube_fleet.config.mission.Mission``): its slots
    0..vehicles-1 (default all); as the region its route (every segment's corners) and slots ±
    the larger of ``margin_m`` and v_max × ``mission_timeout_s``."""
    points = [q for t in mission.scenario.corridor.segments for q in t.polygon()]
    points += list(mission.slots)
    n = mission.count if vehicles is None else int(vehicles)
    reach = float(mission.scenario.controller.v_max) * float(mission.config.mission_timeout_s)
    return StateLimits(vehicle_ids=frozenset(range(n)),
                       region=_bounds(points, max(margin_m, reach)))
