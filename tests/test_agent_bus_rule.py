"""The standalone agent's broker-loss rule (``BusNeighbours.problem``), without processes.

The rule: while the broker is away, and after it is back until every airborne neighbour is
fresh again, the vehicle stands still; a neighbour still silent after ``rejoin_grace_s`` is
left to the agent's lost rule. The grace must cover the other agents' reconnect back-off,
which ends at a different moment for each of them.
"""

from __future__ import annotations

import pytest

from vtube_fleet.fleet.distributed.vehicle_agent import (
    BACKOFF_JITTER,
    BusNeighbours,
    rejoin_grace_s,
)
from vtube_fleet.state import NeighbourState, Phase


class FakeMqtt:
    host, port = "127.0.0.1", 1883

    def __init__(self, backoff_max_s: float = 2.0) -> None:
        self.connected = True
        self.echo_silence_s = 0.0
        self.lost: set[int] = set()
        self.states: dict[int, NeighbourState] = {}
        self.backoff_max_s = backoff_max_s

    def latest(self) -> dict[int, NeighbourState]:
        return self.states


def pilot(mqtt: FakeMqtt, lost_after_s: float = 1.0) -> BusNeighbours:
    return BusNeighbours(mqtt, max_age_s=0.15, lost_after_s=lost_after_s, period_s=0.05)


def state(vid: int, stamp_s: float, phase: Phase = Phase.IN_TUBE) -> NeighbourState:
    return NeighbourState(vid, 1.0, 0.0, 1.0, 0.0, phase, stamp_s, 1)


def problem(p: BusNeighbours, now: float) -> str | None:
    return p.problem(now)


def test_grace_covers_one_back_off_of_the_slowest_agent() -> None:
    assert rejoin_grace_s(1.0, 2.0, 0.05) == pytest.approx(1.0 + BACKOFF_JITTER * 2.0 + 0.1)
    # longer than lost_after_s by at least the longest back-off with its jitter
    assert rejoin_grace_s(1.0, 2.0, 0.05) - 1.0 >= 2.0 * 1.2


def test_unreachable_broker_is_a_problem() -> None:
    mq = FakeMqtt()
    mq.connected = False
    p = pilot(mq)
    assert "unreachable" in (problem(p, 100.0) or "")
    assert p._healthy_since is None


def test_silent_broker_is_a_problem() -> None:
    mq = FakeMqtt()
    mq.echo_silence_s = 0.5  # > max age 0.15 + 2 periods
    assert "silent" in (problem(pilot(mq), 100.0) or "")


def test_after_the_outage_a_reconnecting_teammate_is_waited_for_then_given_up() -> None:
    """The case seen in a test run: the broker came back, one agent reconnected 2.1 s before
    two teammates did. It must still be standing still for them at 2.1 s (> lost_after_s)."""
    mq = FakeMqtt()
    p = pilot(mq)
    p.holding = "MQTT broker unreachable"  # standing still since the outage
    t_back = 100.0
    mq.states = {1: state(1, t_back - 3.0), 2: state(2, t_back + 0.0)}  # 1 is still away
    assert problem(p, t_back) is not None  # healthy since now
    assert p._healthy_since == t_back
    waiting = problem(p, t_back + 2.1)
    assert waiting is not None and "vehicle(s) 1" in waiting  # still waiting, not lost yet
    mq.states[1] = state(1, t_back + 2.1)  # it is back; 2 kept publishing
    mq.states[2] = state(2, t_back + 2.1)
    assert problem(p, t_back + 2.15) is None
    # a teammate that never comes back: after the grace the agent's lost rule takes over
    p.holding, p._healthy_since = "MQTT broker unreachable", None
    mq.states[1] = state(1, t_back - 3.0)
    assert problem(p, t_back) is not None
    grace = rejoin_grace_s(1.0, 2.0, 0.05)
    assert problem(p, t_back + grace - 0.01) is not None
    assert problem(p, t_back + grace + 0.01) is None


def test_ground_and_lost_neighbours_are_not_waited_for() -> None:
    mq = FakeMqtt()
    p = pilot(mq)
    p.holding = "MQTT broker unreachable"
    mq.states = {1: state(1, 0.0, Phase.LANDED), 2: state(2, 0.0)}
    mq.lost = {2}  # its last will arrived
    assert problem(p, 100.0) is None


def test_healthy_bus_without_a_hold_is_no_problem() -> None:
    mq = FakeMqtt()
    mq.states = {1: state(1, 0.0)}  # stale, but we are not holding: the lost rule decides
    assert problem(pilot(mq), 100.0) is None


# ----------------------------------------------------------------------------------------------
# the fleet-wide part of releasing a waiting vehicle (statuses reach every agent)
# ----------------------------------------------------------------------------------------------
def test_tube_stages_reads_every_teammates_status() -> None:
    """A teammate not gone whose status stage is neither waiting nor past the tube counts
    as flying among the others; waiting ones are listed with how many times they were
    released without a path (``waiting`` 0, ``waiting again`` 1); our own status, gone
    teammates and statuses of another run do not count; without teammates (no run) nothing
    does."""
    from vtube_fleet.bus.codec import Status

    mq = FakeMqtt()
    mq.vehicle_id, mq.run_id = 0, "run-1"
    mq.statuses = {0: Status(0, "online", run_id="run-1", stage="waiting"),
                   1: Status(1, "online", run_id="run-1", stage="waiting"),
                   5: Status(5, "online", run_id="run-1", stage="waiting again"),
                   2: Status(2, "online", run_id="run-1", stage="exited"),
                   3: Status(3, "online", run_id="run-1", stage="done"),
                   4: Status(4, "online", run_id="run-1", stage="in_tube")}
    gone = {4}
    p = BusNeighbours(mq, max_age_s=0.15, lost_after_s=1.0, period_s=0.05,
                      teammates=lambda: range(6), gone=lambda v: v in gone)
    assert p.tube_stages(100.0) == (False, {1: 0, 5: 1})
    gone.clear()  # vehicle 4 flies the tube
    assert p.tube_stages(100.0) == (True, {1: 0, 5: 1})
    mq.statuses[4] = Status(4, "online", run_id="run-0", stage="exited")  # an older run
    assert p.tube_stages(100.0) == (True, {1: 0, 5: 1})
    p = BusNeighbours(mq, max_age_s=0.15, lost_after_s=1.0, period_s=0.05)
    assert p.tube_stages(100.0) == (False, {})


def test_an_agent_tells_everyone_when_its_vehicle_starts_and_stops_waiting() -> None:
    """The status stage follows the vehicle's waiting: ``waiting`` once when it starts
    (``waiting again`` after a release without a path), ``in_tube`` once when it stops
    (released to step aside, or anything else); nothing in between or otherwise."""
    from types import SimpleNamespace

    import numpy as np

    from vtube_fleet.fleet.distributed.vehicle_agent import AgentControl

    told: list[str] = []
    ctl = SimpleNamespace(
        pilot=SimpleNamespace(phase=Phase.IN_TUBE, row=0,
                              table=SimpleNamespace(step_tries=np.zeros(1, np.int64))),
        _told_waiting=None,
        mqtt=SimpleNamespace(announce=lambda status, stage: told.append(stage)))
    for phase, tries in ((Phase.IN_TUBE, 0), (Phase.WAITING, 0), (Phase.WAITING, 0),
                         (Phase.STEPPING, 0), (Phase.WAITING, 1), (Phase.STEPPING, 1),
                         (Phase.IN_TUBE, 1), (Phase.LANDING, 1), (Phase.LANDED, 1)):
        ctl.pilot.phase = phase
        ctl.pilot.table.step_tries[0] = tries
        AgentControl._tell_waiting(ctl)
    assert told == ["waiting", "in_tube", "waiting again", "in_tube"]
