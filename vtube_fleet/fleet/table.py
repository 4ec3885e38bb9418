"""The tick state of the vehicles one process flies, as a table: one row per vehicle.

A supervisor flies a thousand vehicles 20 times a second, an MQTT agent one. Both keep the state
the control tick reads and writes here, in numpy columns, and the tick's steps
(:mod:`vtube_fleet.fleet.tick`) work on whole columns: one implementation for one vehicle and for
a thousand (a one-row table is still a table). A :class:`~vtube_fleet.fleet.pilot.VehiclePilot`
(the flight procedure: arm, climb, hold, land) reads and writes its own row.

"Not set" is NaN for the float columns (``sample_s``, ``still_since_s``, ``exit_s``; ``cmd``
and ``lost`` have a mask of their own). Phases are stored as their index in :data:`PHASES`;
:func:`phase_mask` turns a set of phases into a lookup over those codes.

The table also owns what the tick keeps per vehicle beyond one row of numbers: the estimate
compensation's history (:class:`~vtube_fleet.fleet.compensation.CompensatorBank`, ``None`` when
the mission does not compensate) and the compensation residuals
(:class:`~vtube_fleet.fleet.compensation.ResidualTracker`), and the mission frame's horizontal
rotations between a vehicle's local NED and the tube frame (the same for every vehicle).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Sequence

import numpy as np

from vtube_fleet.config.mission import Mission
from vtube_fleet.fleet.compensation import CompensatorBank, ResidualTracker
from vtube_fleet.frames import TubeFrame
from vtube_fleet.state import Phase

__all__ = ["PHASES", "PHASE_CODE", "FleetTable", "phase_mask"]

#: every phase, in the order of their codes in :attr:`FleetTable.phase`
PHASES: tuple[Phase, ...] = tuple(Phase)
#: phase → its code
PHASE_CODE: dict[Phase, int] = {ph: k for k, ph in enumerate(PHASES)}
#: phase code → the phase's value (an Enum's ``.value`` is a slow descriptor)
PHASE_VALUES: tuple[str, ...] = tuple(ph.value for ph in PHASES)


def phase_mask(phases: Iterable[Phase]) -> np.ndarray:
    """A boolean lookup by phase code: ``phase_mask(S)[table.phase]`` is "phase in S"."""
    mask = np.zeros(len(PHASES), bool)
    for ph in phases:
        mask[PHASE_CODE[ph]] = True
    return mask


def _rotations(frame: TubeFrame) -> tuple[tuple[float, float, float, float],
                                          tuple[float, float, float, float]]:
    """The frame's (linear) horizontal rotations as 2×2 matrices (row-major): tube → NED
    velocity and NED → tube velocity, evaluated once on the basis vectors."""
    n, e = frame.tube_velocity_to_ned(np.array([1.0, 0.0]), np.array([0.0, 1.0]))
    x, y = frame.ned_velocity_to_tube(np.array([1.0, 0.0]), np.array([0.0, 1.0]))
    return ((float(n[0]), float(n[1]), float(e[0]), float(e[1])),
            (float(x[0]), float(x[1]), float(y[0]), float(y[1])))


#: Reference tracking: the ticks of references kept (0.5 s at 20 Hz: longer than a sample's
#: age, so that p̂ is compared with r at the sample's time).
REF_HISTORY = 10


class FleetTable:
    """The tick state of ``len(ids)`` vehicles of one mission (module docstring).

    Columns: the vehicle ``ids`` (the mission slot each row flies), tube-frame position ``xy``
    and velocity ``vel`` (n, 2), height ``up`` and ``sample_s`` (the monotonic arrival of the
    sample in use) (n,), ``has`` (a finite position), the controller's command ``cmd`` (n, 2)
    with ``cmd_set`` and ``cmd_in_tube`` (this tick's command is the tube controller's), the
    frozen position of a LOST vehicle ``lost`` with ``lost_set``, ``phase`` codes,
    ``offboard_seen`` (OFFBOARD confirmed once), ``still_since_s`` / ``still_xy`` (a slow spell
    being timed, and where it began), ``stop_xy`` / ``stop_set`` (where a stopped vehicle tells
    the others it is: :func:`~vtube_fleet.fleet.tick.own_states`), ``step_xy`` / ``step_set``
    (where a vehicle released from waiting steps aside to, once the plan without it is known;
    ``step_via``: the point back along the tube it goes to first, NaN once passed;
    ``step_tries``: how many times it was released and found no path:
    :meth:`~vtube_fleet.fleet.tick.Tick.step_aside`), ``in_transition`` (a mode
    change in flight), ``standstill`` (stand still in the tube: zero velocity, no controller;
    the MQTT agent's broker rule), ``takeoff_xy`` (the spot held during the climb, NaN: none),
    ``probe_vel`` (n, 2) the velocity a hovering vehicle flies instead of holding that spot
    during the response check (NaN: none; :mod:`~vtube_fleet.fleet.response_check`),
    ``exit_s`` (mission time of the exit), ``setpoints_sent``, ``ever_sent``, the published
    state's ``seq`` and ``segment``: the route segment each vehicle flies (the hand-over state
    the tick passes back to the plan every tick; −1 until its first position, then the segment
    that position starts in; 0 for a one-segment route). With reference tracking
    (:func:`~vtube_fleet.fleet.tick.track_references`): ``ref_xy`` (n, 2) each in-tube vehicle's
    reference position r (its commands integrated; NaN: none), ``ref_vel`` (n, 2) the velocity
    it flies along r until the next tick, ``ref_since_s`` (n,) the monotonic time r (re)started
    from the estimate, ``track_off`` (n, 2) r − p̂ at
    the last sample's time and ``track_err_m`` (n,) its norm (NaN: none), ``ref_s`` the
    monotonic time r was last advanced to, ``ref_hist`` the last :data:`REF_HISTORY` ticks
    (time, ``ref_xy``), to judge a sample against r at its own time."""

    def __init__(self, ids: Sequence[int], mission: Mission, frame: TubeFrame | None = None
                 ) -> None:
        n = len(ids)
        self.n = n
        self.ids = np.asarray(ids, dtype=np.int64).reshape(n)
        if len(set(self.ids.tolist())) != n:
            raise ValueError(f"a fleet table needs distinct vehicle ids, got {self.ids.tolist()}")
        cfg = mission.config
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
        self.still_xy = np.full((n, 2), np.nan)
        self.stop_xy = np.full((n, 2), np.nan)
        self.stop_set = np.zeros(n, bool)
        self.step_xy = np.full((n, 2), np.nan)
        self.step_via = np.full((n, 2), np.nan)
        self.step_set = np.zeros(n, bool)
        self.step_tries = np.zeros(n, np.int64)
        self.in_transition = np.zeros(n, bool)
        self.standstill = np.zeros(n, bool)
        self.takeoff_xy = np.full((n, 2), np.nan)
        self.probe_vel = np.full((n, 2), np.nan)
        self.exit_s = np.full(n, np.nan)
        self.setpoints_sent = np.zeros(n, np.int64)
        self.ever_sent = np.zeros(n, bool)
        self.seq = np.zeros(n, np.int64)
        self.segment = np.full(n, -1, np.intp)
        self.ref_xy = np.full((n, 2), np.nan)
        self.ref_vel = np.full((n, 2), np.nan)
        self.ref_since_s = np.full(n, np.nan)
        self.track_off = np.full((n, 2), np.nan)
        self.track_err_m = np.full(n, np.nan)
        self.ref_s = math.nan
        self.ref_hist: deque[tuple[float, np.ndarray]] = deque(maxlen=REF_HISTORY)
        self.to_ned, self.to_tube = _rotations(mission.frame if frame is None else frame)
        #: the estimate compensation (fleet/compensation.py); None: not compensated
        self.compensator = CompensatorBank(n) if cfg.compensate_estimate else None
        self.residuals = ResidualTracker(n, cfg.period_s, cfg.disturbance_residual_m_s)

    def positions(self) -> np.ndarray:
        """(n, 2): where the others must see each vehicle: the frozen last position once LOST,
        else the position in use (NaN: none yet)."""
        return np.where(self.lost_set[:, None], self.lost, self.xy)
