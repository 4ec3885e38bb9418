"""Reference tracking (``tracking = "reference"``, docs/fleet.md), pure: its budget, the
references the tick integrates and tells the others, the start ramp, the position loop, the
in-flight watch of |p̂ − r|, and the loop against the mock's own dynamics (no sockets)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from missions import COMPACT_12, write_mission

from sim_stub.dynamics import QuadState
from vtube_fleet.errors import ConfigError
from vtube_fleet.fleet.budget import (
    TRACKING_PERSIST_TICKS,
    BudgetWatch,
    LinkMeasurement,
    SafetyBudget,
    mission_budget,
)
from vtube_fleet.fleet.table import PHASE_CODE, FleetTable
from vtube_fleet.fleet.tick import (
    TRACKING_CORRECTION_MAX_M_S,
    TRACKING_RAMP_S,
    LinkColumns,
    own_states,
    reference_velocities,
    track_references,
    tracking_corrections,
)
from vtube_fleet.state import Phase

REFERENCE = '\ntracking = "reference"\ntracking_error_m = 0.4\ntracking_gain_1_s = 2.0\n'


@pytest.fixture()
def mission(tmp_path):
    return write_mission(tmp_path, COMPACT_12 + REFERENCE)


def links(n: int, latency_s: float = 0.0) -> LinkColumns:
    no = np.zeros(n, bool)
    return LinkColumns([], np.zeros(n), ~no, ~no, ~no, no, no, ~no, np.full(n, latency_s), no,
                       np.full(n, 100.0))


def in_tube(mission, xy: list[list[float]]) -> FleetTable:
    tab = FleetTable(list(range(len(xy))), mission)
    tab.xy[:] = xy
    tab.vel[:] = 0.0
    tab.has[:] = True
    tab.sample_s[:] = 0.0
    tab.phase[:] = PHASE_CODE[Phase.IN_TUBE]
    return tab


def test_the_budget_of_reference_tracking_counts_e_instead_of_pxs_response(mission) -> None:
    m = LinkMeasurement(position_age_s=0.04, setpoint_delay_s=0.02, accuracy_m=0.29)
    b = mission_budget(mission, m)
    cfg = mission.config
    T, L = cfg.period_s, 0.04 + 0.02 + cfg.latency_headroom_s
    assert b.reference and b.tracking_error_m == 0.4
    assert b.accuracy_factor == 3.0  # its default: no lag term hides a larger estimate error
    assert b.delta_m == pytest.approx(0.5 * (T + L) + 0.4 + 3 * 0.29)
    assert b.dead_time_s == b.t63_s == b.disturbance_m_s == 0.0  # inside the measured e
    assert "v'_max·(T + L) + e + k σ" in b.describe() and "reference tracking" in b.describe()
    assert b.as_dict()["tracking"] == "reference" and b.as_dict()["tracking_error_m"] == 0.4
    # the same mission with velocity tracking budgets PX4's assumed response and D: larger
    v = SafetyBudget.compute(mission.scenario.controller, period_s=T, latency_s=L,
                             dead_time_s=0.3, t63_s=1.0, accuracy_m=0.29,
                             disturbance_m_s=0.25)
    assert not v.reference and v.delta_m == pytest.approx(0.75 * (T + L + 1.3) + 0.58)
    assert v.delta_m > b.delta_m + 0.3


@pytest.mark.parametrize("line, text", [
    ('tracking = "position"', "tracking"),
    ("tracking_error_m = 0", "tracking_error_m"),
    ("tracking_gain_1_s = 5", "tracking_gain_1_s"),
])
def test_reference_tracking_keys_are_checked(tmp_path, line: str, text: str) -> None:
    with pytest.raises(ConfigError, match=text):
        write_mission(tmp_path, COMPACT_12 + "\n" + line + "\n")


def test_a_mission_may_set_its_own_k_with_reference_tracking(tmp_path) -> None:
    m = write_mission(tmp_path, COMPACT_12 + REFERENCE + "accuracy_factor = 2.5\n")
    assert m.config.accuracy_factor == 2.5
    assert write_mission(tmp_path, COMPACT_12).config.accuracy_factor == 2.0


def test_a_reference_integrates_what_was_flown_and_restarts_from_the_estimate(mission) -> None:
    tab = in_tube(mission, [[0.0, 0.0], [5.0, 1.0]])
    lk = links(2)
    track_references(tab, lk, 10.0)  # entering the tube: r = p̂, nothing flown yet
    assert np.array_equal(tab.ref_xy, tab.xy) and np.all(tab.ref_since_s == 10.0)
    assert np.isnan(tab.track_err_m).all()
    tab.cmd_in_tube[:] = True
    tab.ref_vel[:] = [[1.0, 0.0], [0.0, -0.5]]
    tab.sample_s[:] = 10.2  # fresh samples: the vehicles did not move
    track_references(tab, lk, 10.2)
    assert tab.ref_xy == pytest.approx(np.array([[0.2, 0.0], [5.0, 0.9]]))
    assert tab.track_err_m == pytest.approx([0.2, 0.1])
    assert tab.track_off[0] == pytest.approx([0.2, 0.0])
    # a sample 0.1 s old is judged against r 0.1 s ago
    tab.sample_s[:] = 10.1
    track_references(tab, lk, 10.2)  # (dt = 0: r unchanged)
    assert tab.track_err_m == pytest.approx([0.1, 0.05])
    # standing still (no controller command): r is dropped, and restarts from p̂ after
    tab.cmd_in_tube[1] = False
    tab.xy[1] = [5.3, 0.6]
    track_references(tab, lk, 10.25)
    assert tab.ref_xy[1] == pytest.approx([5.3, 0.6]) and tab.ref_since_s[1] == 10.25
    assert math.isnan(tab.track_err_m[1])
    # out of the tube: none
    tab.phase[0] = PHASE_CODE[Phase.EXITED]
    track_references(tab, lk, 10.3)
    assert np.isnan(tab.ref_xy[0]).all() and math.isnan(tab.track_err_m[0])


def test_the_others_are_told_the_reference_and_its_velocity(mission) -> None:
    tab = in_tube(mission, [[0.0, 0.0], [5.0, 1.0]])
    tab.ref_xy[0] = [0.3, 0.1]
    tab.ref_vel[0] = [0.8, 0.0]
    tab.vel[:] = [[0.5, 0.5], [0.2, 0.0]]
    states, rows, _ = own_states(tab, links(2), 1.0, 100.0)
    assert states.pos[0] == pytest.approx([0.3, 0.1]) and states.vel[0] == pytest.approx([0.8, 0])
    assert states.pos[1] == pytest.approx([5.0, 1.0]) and states.vel[1] == pytest.approx([0.2, 0])


def test_the_start_ramp_is_a_common_time_scale(mission) -> None:
    tab = in_tube(mission, [[0.0, 0.0], [5.0, 1.0], [9.0, 2.0]])
    tab.ref_since_s[:] = [0.0, 0.0, np.nan]
    cmds = np.array([[1.0, 0.0], [0.6, 0.3], [1.0, 0.0]])
    half = reference_velocities(tab, np.arange(3), cmds, 0.5 * TRACKING_RAMP_S)
    assert half[:2] == pytest.approx(0.5 * cmds[:2])  # both scaled alike: the same paths
    assert half[2] == pytest.approx([0.0, 0.0])  # no reference: nothing
    assert tab.ref_vel[:2] == pytest.approx(half[:2])
    full = reference_velocities(tab, np.arange(2), cmds[:2], 2 * TRACKING_RAMP_S)
    assert full == pytest.approx(cmds[:2])


def test_the_position_loop_pulls_towards_the_reference_within_its_cap(mission) -> None:
    tab = in_tube(mission, [[0.0, 0.0], [5.0, 1.0], [9.0, 2.0]])
    tab.track_off[:] = [[0.1, -0.05], [3.0, 4.0], [np.nan, np.nan]]
    fix = tracking_corrections(tab, np.arange(3), 2.0)
    assert fix[0] == pytest.approx([0.2, -0.1])
    assert np.hypot(*fix[1]) == pytest.approx(TRACKING_CORRECTION_MAX_M_S)
    assert fix[1] == pytest.approx([0.6, 0.8])
    assert fix[2] == pytest.approx([0.0, 0.0])


def test_the_watch_holds_when_a_vehicle_stays_beyond_e(mission) -> None:
    b = mission_budget(mission, LinkMeasurement(0.04, 0.02, 0.29))
    w = BudgetWatch(mission, b)
    ids = np.array([3, 7])
    assert w.check_tracking(np.array([0.1, 0.39]), ids) is None
    assert w.check_tracking(np.array([0.1, 0.45]), ids) is None  # one tick over: a sample
    assert w.check_tracking(np.array([0.1, 0.2]), ids) is None  # … and back
    hold = None
    for _ in range(TRACKING_PERSIST_TICKS):
        hold = w.check_tracking(np.array([0.1, 0.52]), ids)
    assert hold is not None
    assert "vehicle 7 is 0.52 m from its reference > the budgeted tracking error e = 0.40 m" \
        in hold
    assert w.tracking_max_m == pytest.approx(0.52)
    assert w.tracking_percentile_m(50) == pytest.approx(0.11)  # half of 8 errors were 0.1
    assert w.check_tracking(np.array([np.nan, np.nan]), ids) is None  # none in the tube
    # a velocity-tracking budget has no e: nothing to judge
    plain = BudgetWatch(mission, SafetyBudget.compute(
        mission.scenario.controller, period_s=0.05, latency_s=0.1, dead_time_s=0.3,
        t63_s=1.0))
    assert plain.check_tracking(np.array([5.0]), np.array([1])) is None


@pytest.mark.parametrize("ramp_s, bound_m", [(0.0, 0.75), (TRACKING_RAMP_S, 0.4)])
def test_the_loop_holds_the_mock_dynamics_near_a_reference(ramp_s: float, bound_m: float
                                                           ) -> None:
    """The loop as the tick flies it (K = 2, a 50 ms period, positions 80 ms old, setpoints
    50 ms late) against the mock's velocity response (fitted to PX4 SITL): 1 m/s along the
    tube from the hover, then a 0.5 m/s step across. With the start ramp the estimate stays
    within 0.4 m of the reference (without it the start alone leaves it ~0.65 m behind)."""
    dt, T, K = 0.01, 0.05, 2.0
    q = QuadState(1)
    q.p[0, 2] = -5.0  # at altitude
    q.contact[:] = False
    old_p = [np.zeros(2)] * 9  # 80 ms of position age
    old_r = [np.zeros(2)] * 9
    late = [np.zeros(2)] * 6  # 50 ms uplink
    r, sp, worst = np.zeros(2), np.zeros(2), 0.0
    for k in range(2500):
        t = k * dt
        old_p = old_p[1:] + [q.p[0, :2].copy()]
        s = 1.0 if ramp_s == 0 else min(1.0, t / ramp_s)
        cmd = s * np.array([1.0, 0.5 if t > 12 else 0.0])
        if k % round(T / dt) == 0:
            sp = cmd + K * (old_r[0] - old_p[0])
        late = late[1:] + [sp.copy()]
        u = np.zeros((1, 3))
        u[0, :2] = late[0]
        q.step(dt, u, np.array([True]), np.array([False]), np.array([np.nan]), np.zeros(1))
        r = r + cmd * dt
        old_r = old_r[1:] + [r.copy()]
        worst = max(worst, float(np.hypot(*(r - q.p[0, :2]))))
    assert worst < bound_m
    if ramp_s:
        assert worst > 0.2  # (the bound is not loose: PX4's response is what e measures)


def test_mqtt_agents_refuse_reference_tracking_for_now(tmp_path) -> None:
    """The supervisor flies it; an agent and the coordinator say so, naming the key."""
    from vtube_fleet.fleet.distributed.coordinator import Coordinator, MissionRunError
    from vtube_fleet.fleet.distributed.vehicle_agent import AgentProcess, AgentRefused

    path = tmp_path / "reference.toml"
    path.write_text(COMPACT_12 + REFERENCE)
    with pytest.raises(AgentRefused, match=r'tracking = "reference" is flown by `vtube-fleet '
                                           r'run` only'):
        AgentProcess(path, 0, broker="mqtt://127.0.0.1:1")
    with pytest.raises(MissionRunError, match=r'tracking = "reference"'):
        Coordinator(path, "mqtt://127.0.0.1:1")


def test_the_rtk_mission_is_accepted_with_rtk_estimates_only(tmp_path) -> None:
    """configs/mock_fleet_rtk.toml: 12 vehicles in a 12 m tube, slots 2.5 m apart. With RTK
    (σ = 0.02 m) reference tracking's δ is under 0.85 m and the slots validate; with PX4 SITL's
    σ = 0.29 m they are refused before arming, as they are with velocity tracking at RTK."""
    from missions import ROOT

    from vtube_fleet.config.mission import load_mission
    from vtube_fleet.fleet.margin import slot_violations

    m = load_mission(ROOT / "configs" / "mock_fleet_rtk.toml")
    assert m.count == 12 and m.config.tracking == "reference"
    rtk = LinkMeasurement(0.1, 0.0, 0.02)
    budget, _, _, problems = slot_violations(m, rtk)
    assert budget.delta_m < 0.85 and not problems
    budget, _, _, problems = slot_violations(m, LinkMeasurement(0.1, 0.0, 0.29))
    assert budget.delta_m > 1.4 and problems
    text = (ROOT / "configs" / "mock_fleet_rtk.toml").read_text()
    velocity = write_mission(tmp_path, text.replace('tracking = "reference"',
                                                    'tracking = "velocity"'))
    assert slot_violations(velocity, rtk)[3]  # velocity tracking: refused even with RTK


def test_a_route_with_reference_tracking_is_refused_for_now(tmp_path) -> None:
    from missions import ROOT

    text = (ROOT / "configs" / "route_mock.toml").read_text()
    with pytest.raises(ConfigError, match=r'tracking = "reference" is not flown on a \[route\]'):
        write_mission(tmp_path, text.replace("[mission]\n", '[mission]\ntracking = "reference"\n',
                                             1))


def test_a_sample_older_than_a_restart_is_judged_against_the_restart(mission) -> None:
    tab = in_tube(mission, [[0.0, 0.0]])
    lk = links(1)
    track_references(tab, lk, 1.0)
    tab.cmd_in_tube[:] = True
    tab.ref_vel[:] = [[1.0, 0.0]]
    tab.sample_s[:] = 2.0
    tab.xy[:] = [[1.0, 0.0]]
    track_references(tab, lk, 2.0)  # r = (1, 0), on p̂
    assert tab.track_err_m[0] == pytest.approx(0.0)
    tab.cmd_in_tube[:] = False  # a tick without the controller: r restarts from p̂
    tab.xy[:] = [[5.0, 0.0]]
    track_references(tab, lk, 2.5)
    assert tab.ref_xy[0] == pytest.approx([5.0, 0.0])
    tab.cmd_in_tube[:] = True
    tab.ref_vel[:] = [[0.0, 0.0]]
    tab.sample_s[:] = 2.25  # measured before the restart: not against the old r of 2.25 s
    track_references(tab, lk, 2.6)
    assert tab.track_err_m[0] == pytest.approx(0.0)
