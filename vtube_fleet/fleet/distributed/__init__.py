"""The distributed fleet: one agent process per vehicle, neighbours over MQTT.

:mod:`.vehicle_agent` flies one vehicle, :mod:`.coordinator` announces, starts, aborts and follows a
run, and :mod:`.monitor` folds the published states into a summary for both.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.config.mission import Mission


def unsupported(mission: Mission) -> str | None:
    """Why the distributed fleet cannot fly ``mission`` (None: it can). Reference tracking
    is the supervisor's only for now: an agent tells its neighbours its reference, and the
    coordinator would judge the fleet by the references, not by the estimates."""
    if mission.config.tracking == "reference":
        return ('[mission].tracking = "reference" is flown by `vtube-fleet run` only, not by '
                'MQTT agents yet (docs/fleet.md, reference tracking): use tracking = "velocity"')
    return None
