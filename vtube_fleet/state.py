"""The vocabulary every layer shares: a vehicle's mission :class:`Phase`, the sets of phases
the rules are written in, and the :class:`NeighbourState` vehicles share (links, buses, agents,
supervisor, recordings and tests all use these, one definition each)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from enum import Enum

__all__ = [
    "AIRBORNE_PHASES",
    "COUNTED_AIRBORNE_PHASES",
    "NeighbourState",
    "OFFBOARD_PHASES",
    "Phase",
    "STOPPED_PHASES",
    "TUBE_DONE_PHASES",
    "TUBE_PHASES",
]


class Phase(str, Enum):  # noqa: UP042 (str() and format() kept as in 3.10 semantics callers use)
    """Mission phase of one vehicle, as its agent sees it."""

    CONNECTING = "connecting"
    READY = "ready"  # connected, healthy, position known
    ARMING = "arming"
    TAKEOFF = "takeoff"
    IN_TUBE = "in_tube"  # flying the tube in offboard under the controller
    EXITED = "exited"  # crossed the finishing line (Assumption 2)
    HOLDING = "holding"
    LANDING = "landing"
    LANDED = "landed"
    LOST = "lost"  # stopped answering / left offboard: a static obstacle for the others
    FAILED = "failed"
    # (appended: a phase's code is its index, kept on the bus and in recordings)
    WAITING = "waiting"  # in the tube, stopped: no way past stopped vehicles yet (an obstacle)
    STEPPING = "stepping"  # released from waiting: moving aside, out of the region ahead


#: "Airborne": in the air (or may be) under our responsibility, so it matters to the others.
AIRBORNE_PHASES: frozenset[Phase] = frozenset(
    {Phase.TAKEOFF, Phase.IN_TUBE, Phase.EXITED, Phase.HOLDING, Phase.LANDING, Phase.WAITING,
     Phase.STEPPING}
)
#: What the summaries count as flying when they measure pair distances: airborne, or lost
#: (nobody knows where a lost vehicle is; it is kept at its last position).
COUNTED_AIRBORNE_PHASES: frozenset[Phase] = AIRBORNE_PHASES | {Phase.LOST}
#: Airborne but no longer flying the tube's controller: it stops (PX4 Hold, or waiting in
#: OFFBOARD) or comes down. The others cannot rely on the pair barrier alone to pass such a
#: vehicle (their speed never drops below v_min, paper note 9): inside the tube it is an
#: obstacle like a LOST one.
STOPPED_PHASES: frozenset[Phase] = frozenset({Phase.HOLDING, Phase.LANDING, Phase.WAITING})
#: Phases in which we stream setpoints and expect PX4 to be in OFFBOARD.
OFFBOARD_PHASES: frozenset[Phase] = frozenset(
    {Phase.ARMING, Phase.TAKEOFF, Phase.IN_TUBE, Phase.EXITED, Phase.WAITING, Phase.STEPPING}
)
#: "In the tube": flying its controller, waiting there for a way past stopped vehicles, or
#: stepping aside into one (docs/fleet.md, "Waiting for a way"). The tube stage lasts while a
#: vehicle is in one of these.
TUBE_PHASES: frozenset[Phase] = frozenset({Phase.IN_TUBE, Phase.WAITING, Phase.STEPPING})
#: Phases after which a vehicle is done with the tube (for the end of a run).
TUBE_DONE_PHASES: frozenset[Phase] = frozenset(
    {Phase.EXITED, Phase.HOLDING, Phase.LANDING, Phase.LANDED, Phase.LOST, Phase.FAILED}
)


@dataclass(frozen=True, slots=True)
class NeighbourState:
    """One vehicle's state as shared with the others, in the tube frame.

    ``x_m``/``y_m`` are tube-frame coordinates (x along the tube heading, y to its left),
    ``vx_m_s``/``vy_m_s`` the measured horizontal velocity in that frame, ``stamp_s`` the
    wall-clock time the position was measured, ``seq`` a per-vehicle counter.
    """

    vehicle_id: int
    x_m: float
    y_m: float
    vx_m_s: float
    vy_m_s: float
    phase: Phase
    stamp_s: float
    seq: int

    def age_s(self, now_s: float | None = None) -> float:
        return (time.time() if now_s is None else now_s) - self.stamp_s
