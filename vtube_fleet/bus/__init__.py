"""Neighbour buses: in-process (supervisor) and MQTT (one agent process per vehicle)."""

from vtube_fleet.bus.base import InProcessBus, NeighbourBus

__all__ = ["InProcessBus", "NeighbourBus"]
