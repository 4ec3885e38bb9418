"""What a vehicle knows of the others: their states as a table, sorted into a neighbour view.

:class:`States` is a table of vehicle states (ids, tube-frame positions and velocities, phase
codes, wall-clock stamps): the vehicles a process flies (:func:`vtube_fleet.fleet.tick.own_states`)
and, for an MQTT agent, the other vehicles' states heard on the bus (:func:`states_of`).

:func:`classify` sorts such a table at a given time into a :class:`NeighbourView`:

* *live*: airborne and younger than ``max_age_s``: neighbours at their reported positions;
* *static*: a flying vehicle heard from between ``max_age_s`` and ``lost_after_s`` ago is never
  used as a live position: it is kept as a static point at its last position (so the pair
  barrier still keeps clear of where it was);
* *lost*: silent for longer than ``lost_after_s``, or says it is ``LOST``, or is airborne but
  stopped flying the controller (holding, landing: :data:`~vtube_fleet.state.STOPPED_PHASES`):
  a static obstacle at its last position, inside the tube for everyone, at once, by the same
  rule in every process (:func:`~vtube_fleet.fleet.flight_plan.lost_obstacles`).

Vehicles on the ground (connecting, ready, arming, landed, failed) are ignored.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from vtube_fleet.fleet.table import PHASE_CODE, PHASES
from vtube_fleet.state import AIRBORNE_PHASES, STOPPED_PHASES, NeighbourState, Phase

__all__ = ["NeighbourView", "States", "classify", "states_of"]

_EMPTY_POS = np.zeros((0, 2))
_EMPTY_IDS = np.zeros(0, dtype=np.int64)


@dataclass(frozen=True, slots=True)
class States:
    """A table of vehicle states: ``ids`` (n,), ``pos``/``vel`` (n, 2) tube frame, ``phase``
    codes (n,) (:data:`~vtube_fleet.fleet.table.PHASES`), ``stamps_s`` (n,) wall clock (when
    the position was measured)."""

    ids: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    phase: np.ndarray
    stamps_s: np.ndarray

    @classmethod
    def empty(cls) -> States:
        return cls(_EMPTY_IDS, _EMPTY_POS, _EMPTY_POS, np.zeros(0, np.int8), np.zeros(0))

    def __len__(self) -> int:
        return int(self.ids.size)

    def concat(self, other: States) -> States:
        """These states, then ``other``'s."""
        if not len(other):
            return self
        return States(np.concatenate([self.ids, other.ids]),
                      np.concatenate([self.pos, other.pos]),
                      np.concatenate([self.vel, other.vel]),
                      np.concatenate([self.phase, other.phase]),
                      np.concatenate([self.stamps_s, other.stamps_s]))

    def messages(self, seqs: np.ndarray) -> list[NeighbourState]:
        """The states as :class:`~vtube_fleet.state.NeighbourState` messages (with ``seqs``)."""
        return [NeighbourState(i, x, y, vx, vy, PHASES[c], t, q) for i, (x, y), (vx, vy), c, t, q
                in zip(self.ids.tolist(), self.pos.tolist(), self.vel.tolist(),
                       self.phase.tolist(), self.stamps_s.tolist(), seqs.tolist(), strict=True)]


def states_of(messages: Iterable[NeighbourState], exclude: Iterable[int] = ()) -> States:
    """The :class:`States` table of ``messages`` (e.g. the bus's latest state of every other
    vehicle), leaving out the vehicles ``exclude``."""
    skip = set(exclude)
    st = [s for s in messages if s.vehicle_id not in skip]
    n = len(st)
    if not n:
        return States.empty()
    return States(
        np.fromiter((s.vehicle_id for s in st), np.int64, n),
        np.array([(s.x_m, s.y_m) for s in st], dtype=float).reshape(n, 2),
        np.array([(s.vx_m_s, s.vy_m_s) for s in st], dtype=float).reshape(n, 2),
        np.fromiter((PHASE_CODE[s.phase] for s in st), np.int8, n),
        np.fromiter((s.stamp_s for s in st), float, n))


@dataclass(frozen=True, eq=False)
class NeighbourView:
    """The neighbour table sorted at one time (all positions tube frame, (n, 2); each group
    sorted by vehicle id).

    ``live``: airborne and fresh (``live_vel`` their measured velocities); ``static``:
    airborne, stale but not yet lost (kept at the last position); ``lost``: said LOST, silent
    for longer than ``lost_after_s``, or stopped (:data:`STOPPED_PHASES`: holding or landing):
    inside the tube these become obstacles.
    """

    live_ids: np.ndarray = field(default_factory=lambda: _EMPTY_IDS)
    live_pos: np.ndarray = field(default_factory=lambda: _EMPTY_POS)
    live_vel: np.ndarray = field(default_factory=lambda: _EMPTY_POS)
    static_ids: np.ndarray = field(default_factory=lambda: _EMPTY_IDS)
    static_pos: np.ndarray = field(default_factory=lambda: _EMPTY_POS)
    lost_ids: np.ndarray = field(default_factory=lambda: _EMPTY_IDS)
    lost_pos: np.ndarray = field(default_factory=lambda: _EMPTY_POS)

    def points(self) -> np.ndarray:
        """Every position the pair barrier must respect: live, static and lost (n, 2)."""
        return np.concatenate([self.live_pos, self.static_pos, self.lost_pos])

    def ids(self) -> np.ndarray:
        """The vehicle of each of :meth:`points`."""
        return np.concatenate([self.live_ids, self.static_ids, self.lost_ids])


#: :func:`classify`'s sorting of a phase code: 0 lost (said LOST, or stopped), 1 airborne
#: (live, static or lost by age), 2 on the ground (ignored).
_PHASE_CLASS = np.array([0 if ph == Phase.LOST or ph in STOPPED_PHASES
                         else 1 if ph in AIRBORNE_PHASES else 2 for ph in PHASES], np.int8)


def classify(
    states: States,
    now_s: float,
    *,
    max_age_s: float,
    lost_after_s: float | np.ndarray,
    heard_since_s: float | None = None,
) -> NeighbourView:
    """Sort ``states`` (vehicle ids unique) at wall-clock time ``now_s`` (module docstring).

    ``lost_after_s``: one value, or one per state (a process's own vehicles are lost when its
    fault rules say so, ``inf``; the others' by silence). ``heard_since_s`` (wall clock): when
    our own loop resumed after a stall; a state cannot be *lost* by silence before
    ``lost_after_s`` has passed since then (the backlog of a stalled process is not the
    neighbours' silence); it is still not used as a live position."""
    ids, pos = states.ids, states.pos
    ok = np.isfinite(pos).all(axis=1)
    kind = _PHASE_CLASS[states.phase]
    age = now_s - states.stamps_s
    silence = age if heard_since_s is None else np.minimum(age, now_s - heard_since_s)
    flying = ok & (kind == 1)
    lost = (ok & (kind == 0)) | (flying & (silence > lost_after_s))
    static = flying & ~lost & (age > max_age_s)
    live = flying & ~lost & ~static

    def arr(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rows = np.flatnonzero(mask)
        if not rows.size:
            return _EMPTY_IDS, _EMPTY_POS, rows
        rows = rows[np.argsort(ids[rows], kind="stable")]
        return ids[rows].astype(np.int64, copy=False), pos[rows], rows

    li, lp, lr = arr(live)
    lv = np.nan_to_num(states.vel[lr]) if lr.size else _EMPTY_POS
    si, sp, _ = arr(static)
    oi, op, _ = arr(lost)
    return NeighbourView(li, lp, lv, si, sp, oi, op)
