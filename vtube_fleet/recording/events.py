"""What the recorder derives from the calls it gets, pure (no rerun, no threads): the rule that
decimation keeps a metric's extreme, and the vehicles' phase changes and exits.

* :func:`merge_metric` — two values of one metric over consecutive ticks: the minimum of a
  ``min_*`` key, the maximum of a ``max_*`` key and of the tick duration and link latency, else
  the newer value.
* :class:`ChangeDetector` — at every call: the vehicles whose phase changed (one event per
  fact: a change the owner already told in a ``"old → new (why)"`` event is not told again),
  and the exits (Assumption 2, (TraCondition)): a phase that becomes ``exited``, or — without
  phases (the simulator) — a vehicle present at the previous call whose row is now NaN or gone.

The writer (:mod:`vtube_fleet.recording.writer`) sends what these return.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtube_fleet.recording.layout import PHASE_CLASSES

__all__ = [
    "ALARM_PHASES",
    "ChangeDetector",
    "Exits",
    "PhaseChanges",
    "announced_phase",
    "merge_metric",
    "phase_str",
]

#: Phases whose change is a warning (a vehicle lost or failed); every other change is INFO.
ALARM_PHASES = frozenset({"lost", "failed"})

_PHASE_NAMES = frozenset(p for _, p, _, _ in PHASE_CLASSES if p not in ("", "?"))


def phase_str(p: Any) -> str:
    """``Phase.IN_TUBE`` → ``"in_tube"``; plain strings unchanged."""
    return str(getattr(p, "value", p))


def merge_metric(key: str, old: float, new: float) -> float:
    """Combine two values of one metric over consecutive ticks (decimation keeps extremes)."""
    if math.isnan(old):
        return new
    if math.isnan(new):
        return old
    if key.startswith("min_"):
        return min(old, new)
    if key.startswith("max_") or key in ("tick_duration_s", "link_latency_s"):
        return max(old, new)
    return new


def announced_phase(text: str) -> str | None:
    """The new phase when ``text`` tells a phase change ("in_tube → exited (why)"), else
    None."""
    old, sep, rest = text.partition(" → ")
    if not sep:
        return None
    new = rest.split(" ", 1)[0]
    return new if new in _PHASE_NAMES and (old in _PHASE_NAMES or old == "-") else None


@dataclass(frozen=True)
class PhaseChanges:
    """Phase changes seen at one call: per vehicle id its event text and level."""

    ids: list[int]
    texts: list[str]
    levels: list[str]


@dataclass(frozen=True)
class Exits:
    """Vehicles that exited at one call; ``untold``: not every exit was told by an event."""

    ids: list[int]
    untold: bool


class ChangeDetector:
    """Phase changes and exits from consecutive calls (module docstring).

    ``detect_exits=False``: exits only from :meth:`explicit_exits` (an owner that decides
    exits itself, e.g. the MQTT monitor)."""

    def __init__(self, detect_exits: bool = True) -> None:
        self.detect_exits = bool(detect_exits)
        self.exited: set[int] = set()
        self._prev_ids: np.ndarray | None = None
        self._prev_present: np.ndarray | None = None
        self._prev_phases: tuple[Any, ...] | None = None
        self._announced: dict[int, str] = {}  # vehicle → phase its owner announced in a text
        self._told_exited: set[int] = set()  # vehicles whose exit a phase-change event told

    def announced(self, vehicle_id: int, text: str) -> None:
        """An owner's event text about one vehicle: a told phase change is not told again."""
        told = announced_phase(text)
        if told is not None:  # "old → new (why)": the change is told, once
            self._announced[vehicle_id] = told
            if told == "exited":
                self._told_exited.add(vehicle_id)

    def explicit_exits(self, ids: Sequence[int] | np.ndarray) -> Exits | None:
        """Exits the owner states (the simulator knows the exact step); vehicles already
        reported exited are ignored, and :meth:`update` will not report them again."""
        gone = [int(i) for i in np.asarray(ids).reshape(-1).tolist() if int(i) not in
                self.exited]
        return self._exits(gone) if gone else None

    def update(self, ids: np.ndarray, pos: np.ndarray, phases: Sequence[Any] | None
               ) -> tuple[PhaseChanges | None, Exits | None]:
        """One call's phase changes (None: none) and exits (None: none)."""
        gone: list[int] = []
        changes = None
        if phases is not None:
            ph = tuple(phases)
            if ph != self._prev_phases or not np.array_equal(ids, self._prev_ids):
                prev = {}
                if self._prev_phases is not None and self._prev_ids is not None:
                    prev = dict(zip(self._prev_ids.tolist(), self._prev_phases, strict=True))
                changed_ids, texts, levels = [], [], []
                for i, p in zip(ids.tolist(), ph, strict=True):
                    q = prev.get(i)
                    if q != p:
                        ps = phase_str(p)
                        if ps == "exited":
                            gone.append(i)
                        if self._announced.get(i) == ps:  # the owner told it already
                            del self._announced[i]
                            continue
                        if ps == "exited":
                            self._told_exited.add(i)
                        changed_ids.append(i)
                        texts.append(f"vehicle {i}: {phase_str(q)} → {ps}" if q is not None
                                     else f"vehicle {i}: {ps}")
                        levels.append("WARN" if ps in ALARM_PHASES else "INFO")
                if texts:
                    changes = PhaseChanges(changed_ids, texts, levels)
                self._prev_phases = ph
                self._prev_ids = ids.copy()
        else:
            present = ~np.isnan(pos[:, 0])
            pids, pprev = self._prev_ids, self._prev_present
            if pids is not None and pprev is not None:
                if np.array_equal(ids, pids):
                    left = pprev & ~present
                    if left.any():
                        gone = [int(i) for i in ids[left]]
                else:
                    now = set(ids[present].tolist())
                    gone = [int(i) for i in pids[pprev].tolist() if int(i) not in now]
            if pids is None or not np.array_equal(ids, pids):
                self._prev_ids = ids.copy()
            self._prev_present = present
        gone = [i for i in gone if i not in self.exited] if self.detect_exits else []
        return changes, (self._exits(gone) if gone else None)

    def _exits(self, gone: list[int]) -> Exits:
        self.exited.update(gone)
        return Exits(gone, not set(gone) <= self._told_exited)
