"""The recorder interface every run records through, the do-nothing recorder, and the error.

The simulator, the fleet, the MQTT coordinator and the agents all record through
:class:`Recorder`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from vtube_fleet.errors import UserError

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.config.mission import MissionConfig
    from vtube_fleet.config.scenario import Scenario
    from vtube_fleet.core.partition import Partition

__all__ = [
    "NullRecorder",
    "Recorder",
    "RecordingError",
]

class RecordingError(UserError):
    """A recording cannot be written or read (bad path, not an .rrd, not ours, ...)."""


# ----------------------------------------------------------------------------------------------
# the interface
# ----------------------------------------------------------------------------------------------
@runtime_checkable
class Recorder(Protocol):
    """What the simulator and the fleet call. See the module docstring for the layout.

    Implementations never raise from ``log_*`` or :meth:`close`: a recording problem is logged
    by the recorder and the run goes on, so callers do not guard their calls. Problems with the
    destination (a bad path, a bad viewer address) are found when the recorder is opened."""

    def log_scene(
        self, scenario: Scenario, partition: Partition | None = None, *,
        mission: MissionConfig | None = None, meta: Mapping[str, Any] | None = None,
    ) -> None:
        """Static scene + scenario metadata; ``mission``: the fleet's ``[mission]`` settings,
        stored too; ``meta`` adds JSON-able keys (``dt_s``, ``rate_hz`` ...)."""

    def log_partition(self, partition: Any, t_s: float) -> None:
        """The sub-tubes and triangles of a (re)partition, valid from ``t_s`` on."""

    def log_tick(
        self,
        *,
        t_s: float,
        tick: int,
        ids: np.ndarray,
        pos: np.ndarray,
        vel: np.ndarray,
        phases: Sequence[str] | None = None,
        cmd: np.ndarray | None = None,
        metrics: Mapping[str, float] | None = None,
        safety: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> None:
        """One control tick: ids (M,) int, pos/vel/cmd (M, 2) tube frame, NaN rows = absent.

        ``safety``: the (positions, velocities) (M, 2) each, rows as ``ids``, that the run fed
        to :class:`vtube_fleet.core.metrics.SafetyMonitor`, per summary stream suffix (``""``, and
        ``"_center"`` for unicycle centres), when they differ from (pos, vel) — e.g. the fleet
        counts only vehicles in the tube, with their commanded velocity. ``review`` recomputes
        the summary from exactly these."""

    def log_metrics(self, t_s: np.ndarray, ticks: np.ndarray,
                    metrics: Mapping[str, np.ndarray], *, every: int = 1) -> None:
        """Per-step metric series in bulk (K,) each — for a caller that evaluates metrics in
        chunks (the simulator); blocks of ``every`` ticks are reduced to their extrema."""

    def log_exits(self, t_s: float, tick: int, ids: Sequence[int] | np.ndarray) -> None:
        """Vehicles ``ids`` crossed the finishing line at ``t_s`` (TraCondition)."""

    def log_event(
        self, t_s: float, text: str, *, vehicle_id: int | None = None, level: str = "info"
    ) -> None:
        """A text event (``events`` or ``events/vehicle_<id>``)."""

    def log_summary(self, summary: Mapping[str, Any]) -> None:
        """The run's own summary (the ``summary.json`` dict), stored for ``review``."""

    def close(self) -> None:
        """Send what is buffered, flush, close the file. Idempotent."""

    def __enter__(self) -> Recorder: ...

    def __exit__(self, *exc: object) -> None: ...


class NullRecorder:
    """A :class:`Recorder` that records nothing (recording disabled)."""

    path: Path | None = None
    closed: bool = False

    def log_scene(
        self, scenario: Scenario, partition: Partition | None = None, *,
        mission: MissionConfig | None = None, meta: Mapping[str, Any] | None = None,
    ) -> None:
        pass

    def log_partition(self, partition: Any, t_s: float) -> None:
        pass

    def log_tick(self, **kwargs: Any) -> None:
        pass

    def log_metrics(self, t_s: np.ndarray, ticks: np.ndarray,
                    metrics: Mapping[str, np.ndarray], *, every: int = 1) -> None:
        pass

    def log_exits(self, t_s: float, tick: int, ids: Sequence[int] | np.ndarray) -> None:
        pass

    def log_event(
        self, t_s: float, text: str, *, vehicle_id: int | None = None, level: str = "info"
    ) -> None:
        pass

    def log_summary(self, summary: Mapping[str, Any]) -> None:
        pass

    def close(self) -> None:
        self.closed = True

    def __enter__(self) -> NullRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
