"""Neighbour bus: how an agent learns its neighbours' states (Assumption 4).

The paper's controller is distributed: robot i only needs the relative positions of the robots
in N_m,i. At runtime each vehicle's agent *publishes* its own :class:`NeighbourState` at the
control rate and reads the others' latest states from a :class:`NeighbourBus`. Two
implementations share this interface: :class:`InProcessBus` (the embedded supervisor) and the
MQTT bus (``vtube_fleet.bus.mqtt``, one agent process per vehicle).

Time stamps are wall-clock seconds (``time.time()``) so that states from other processes or
machines can be aged; an agent never uses a state older than its configured maximum age as if it
were fresh (see ``vtube_fleet.fleet.neighbours``).
"""

from __future__ import annotations

from typing import Protocol

from vtube_fleet.state import NeighbourState

__all__ = ["NeighbourBus", "InProcessBus"]


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
