"""Neighbour bus: how an agent learns its neighbours' states (Assumption 4).

The paper's controller is distributed: robot i only needs the relative positions of the robots
in N_m,i. At runtime each vehicle's agent *publishes* its own :class:`NeighbourState` at the
control rate and reads the others' latest states from a :class:`NeighbourBus`. Two
implementations share this interface: :class:`InProcessBus` (the embedded supervisor) and the
MQTT bus (``vtube_fleet.bus.mqtt``, one agent process per vehicle).

Time stamps are wall-clock seconds (``time.time()``) so that states from other processes or
machines can be aged; an agent never uses a state older than its configured maximum age as if it
were fresh (see ``vtube_fleet.fleet.agent``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

__all__ = ["Phase", "NeighbourState", "NeighbourBus", "InProcessBus"]


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


class NeighbourBus(Protocol):
    """What an agent needs from the network: publish own state, read the others' latest."""

    def publish(self, state: NeighbourState) -> None:
        """Share this vehicle's latest state (non-blocking; may be dropped if the link is down)."""

    def latest(self) -> dict[int, NeighbourState]:
        """The latest known state of every other vehicle heard from (may include stale ones)."""


class InProcessBus:
    """A :class:`NeighbourBus` for agents living in one process (the supervisor)."""

    def __init__(self) -> None:
        self._states: dict[int, NeighbourState] = {}

    def publish(self, state: NeighbourState) -> None:
        prev = self._states.get(state.vehicle_id)
        if prev is None or state.seq >= prev.seq:
            self._states[state.vehicle_id] = state

    def latest(self) -> dict[int, NeighbourState]:
        return self._states
