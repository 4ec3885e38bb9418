"""The per-tick state of a fleet's pilots as arrays, one row per vehicle (issue 16).

A supervisor ticks a thousand :class:`~vtube_fleet.fleet.pilot.VehiclePilot` objects 20 times
a second. Gathering their positions, commands and phases from a thousand Python objects on
every step of every tick cost more than the steps themselves, so the state those steps read
lives here, in arrays: each pilot is a row, reads and writes its own row through properties
(:attr:`VehiclePilot.xy`, :attr:`~VehiclePilot.cmd_xy`, its phase …), and the supervisor's
fleet steps (:func:`~vtube_fleet.fleet.pilot.sense_all` and the others) read and write whole
columns. A pilot on its own (one agent process per vehicle) has a table of one row.

"Not set" is NaN for the float columns (``sample_s``, ``still_since_s``; ``cmd`` and ``lost``
have a mask of their own). Phases are stored as their index in :data:`PHASES`;
:func:`phase_mask` turns a set of phases into a lookup over those codes.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from vtube_fleet.state import Phase

__all__ = ["PHASES", "PHASE_CODE", "PilotTable", "phase_mask"]

#: every phase, in the order of their codes in :attr:`PilotTable.phase`
PHASES: tuple[Phase, ...] = tuple(Phase)
#: phase → its code
PHASE_CODE: dict[Phase, int] = {ph: k for k, ph in enumerate(PHASES)}


def phase_mask(phases: Iterable[Phase]) -> np.ndarray:
    """A boolean lookup by phase code: ``phase_mask(S)[table.phase]`` is "phase in S"."""
    mask = np.zeros(len(PHASES), bool)
    for ph in phases:
        mask[PHASE_CODE[ph]] = True
    return mask


class PilotTable:
    """``n`` pilots' tick state (module docstring). Columns: tube-frame position ``xy`` and
    velocity ``vel`` (n, 2), height ``up`` and ``sample_s`` (the monotonic arrival of the
    sample in use) (n,), ``has`` (a finite position), the controller's command ``cmd`` (n, 2)
    with ``cmd_set``, ``cmd_in_tube``, the frozen position of a LOST vehicle ``lost`` with
    ``lost_set``, ``phase`` codes, ``offboard_seen``, ``still_since_s`` (a slow spell being
    timed), ``in_transition`` (a mode change in flight), ``setpoints_sent`` and ``ever_sent``."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.xy = np.full((n, 2), np.nan)
        self.vel = np.full((n, 2), np.nan)
        self.up = np.full(n, np.nan)
        self.sample_s = np.full(n, np.nan)
        self.has = np.zeros(n, bool)
        self.cmd = np.full((n, 2), np.nan)
        self.cmd_set = np.zeros(n, bool)
        self.cmd_in_tube = np.zeros(n, bool)
        self.lost = np.full((n, 2), np.nan)
        self.lost_set = np.zeros(n, bool)
        self.phase = np.full(n, PHASE_CODE[Phase.CONNECTING], np.int8)
        self.offboard_seen = np.zeros(n, bool)
        self.still_since_s = np.full(n, np.nan)
        self.in_transition = np.zeros(n, bool)
        self.setpoints_sent = np.zeros(n, np.int64)
        self.ever_sent = np.zeros(n, bool)
        #: the pilots' NED → tube velocity rotation (2×2, row-major) while they all share one
        #: (one mission frame: a supervisor's fleet); None with none yet or several
        self.to_tube: tuple[float, float, float, float] | None = None
        self._rotations: set[tuple[float, float, float, float]] = set()

    def note_rotation(self, to_tube: tuple[float, float, float, float]) -> None:
        """A pilot with this NED → tube rotation takes a row (:attr:`to_tube`)."""
        self._rotations.add(to_tube)
        self.to_tube = to_tube if len(self._rotations) == 1 else None

    _COLUMNS = ("xy", "vel", "up", "sample_s", "has", "cmd", "cmd_set", "cmd_in_tube", "lost",
                "lost_set", "phase", "offboard_seen", "still_since_s", "in_transition",
                "setpoints_sent", "ever_sent")

    def take_row(self, row: int, other: PilotTable, other_row: int) -> None:
        """Row ``row`` becomes a copy of ``other``'s row ``other_row`` (a pilot joining a
        fleet brings its state along)."""
        for name in self._COLUMNS:
            getattr(self, name)[row] = getattr(other, name)[other_row]
