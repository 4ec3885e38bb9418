"""The offline simulator on reduced and full paper scenarios and on the Robotarium scenario."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from vtube_fleet.config.scenario import load_scenario, parse_scenario
from vtube_fleet.core.metrics import METRIC_KEYS
from vtube_fleet.core.validation import ScenarioError
from vtube_fleet.errors import ConfigError
from vtube_fleet.sim import ProgressBar, SimError, default_record_every, simulate

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "paper.toml"
ROBOTARIUM = ROOT / "configs" / "robotarium.toml"


@pytest.fixture(scope="module")
def paper():
    return load_scenario(PAPER)


@pytest.fixture(scope="module")
def reduced(paper):
    """The first 24 robots of the paper scenario at dt = 2 ms (safe per docs/paper.md)."""
    return simulate(paper, robots=24, dt=0.002, duration=30.0)


def test_reduced_paper_all_exit_safely(reduced, paper) -> None:
    s = reduced.summary
    assert s["robots"] == 24 and s["exited"] == 24 and s["all_exited"]
    assert s["violations"] == 0, s["violations_by_condition"]
    r = paper.robots
    assert s["min_pair_distance_m"] > 2 * r.r_s
    assert s["min_obstacle_center_distance_m"] > 0.9 + r.r_s
    assert s["min_left_leg_distance_m"] > r.r_s and s["min_right_leg_distance_m"] > r.r_s
    assert r.v_min - 1e-9 <= s["min_speed_m_s"] <= s["max_speed_m_s"] <= r.v_max + 1e-9
    assert s["sub_tubes"] == 15 and s["remark5"] == [1] and s["controller"] == "new"
    assert s["steps"] == len(reduced.metrics) == reduced.step_t.size
    assert s["t_end_s"] == pytest.approx(s["steps"] * 0.002)
    assert s["dt_s"] == 0.002 and s["last_exit_s"] <= s["t_end_s"]


def test_trajectory_layout(reduced, paper) -> None:
    res = reduced
    t, pos, vel = res.t, res.pos, res.vel
    m = 24
    assert pos.shape == (t.size, m, 2) and vel.shape == pos.shape
    np.testing.assert_array_equal(pos[0], paper.robots.positions[:m])  # config order
    assert t[0] == 0.0
    # every record_every-th step, and the final state (the last exit)
    np.testing.assert_allclose(np.diff(t)[:-1], res.record_every * res.dt)
    assert 0 < t[-1] - t[-2] <= res.record_every * res.dt + 1e-12
    t_end = res.summary["t_end_s"]
    assert t[-1] == pytest.approx(t_end) and res.summary["last_exit_s"] == t_end
    tube = paper.tube
    line = float(tube.n_c @ tube.p_r1) - paper.controller.eps_0
    final = np.arange(t.size) == t.size - 1
    for i in range(m):
        te = res.exit_time_s[i]
        assert math.isfinite(te)
        present = ~np.isnan(pos[:, i, 0])
        # present exactly until the exit time, NaN afterwards (and velocities too); the final
        # state also holds the robots that exit there
        np.testing.assert_array_equal(present, (t < te - 1e-12) | (final & (te == t_end)))
        np.testing.assert_array_equal(present, ~np.isnan(vel[:, i, 0]))
        before = present & ~final
        assert np.all(pos[before, i] @ tube.n_c < line)
        assert res.exit_pos[i] @ tube.n_c >= line
        if te == t_end:
            np.testing.assert_array_equal(pos[-1, i], res.exit_pos[i])
    speeds = np.linalg.norm(vel, axis=-1)
    ok = ~np.isnan(speeds)
    assert np.all(speeds[ok] >= 0.5 - 1e-9) and np.all(speeds[ok] <= 3.5 + 1e-9)
    arrays = res.trajectory_arrays()
    assert set(arrays) == {"t", "pos", "vel", "exit_time_s", "exit_pos"}


def test_metrics_series_match_recorded_frames(reduced, paper) -> None:
    """The per-step metrics at recorded steps equal a recomputation from the recorded frames."""
    from vtube_fleet.core.metrics import SafetyMonitor

    res = reduced
    mon = SafetyMonitor.from_params(paper.tube, paper.obstacles, paper.controller)
    t = res.t[:-1]  # (the final state, after the last step, is not a metrics step)
    assert res.t[-1] == pytest.approx(res.step_t[-1] + res.dt)
    idx = np.searchsorted(res.step_t, t)
    np.testing.assert_allclose(res.step_t[idx], t)  # every other frame is a step
    again = mon.evaluate(res.pos[:-1], res.vel[:-1])
    for key in METRIC_KEYS:
        a = getattr(res.metrics, key)[idx]
        b = getattr(again, key)
        if key == "min_pair_distance_m":  # the search sees pairs within r_s + r_a only
            a = np.where(a > 0.75, np.inf, a)
        np.testing.assert_allclose(a, b, rtol=1e-9, err_msg=key)


def test_full_paper_run_new_and_old(paper) -> None:
    """The issue's acceptance run: dt = 1 ms, 120 robots; and (Oldcontroller) for comparison."""
    new = simulate(paper).summary
    assert new["exited"] == 120 and new["violations"] == 0
    assert 0.5 - 1e-9 <= new["min_speed_m_s"] and new["max_speed_m_s"] <= 3.5 + 1e-9
    old = simulate(paper, controller="old").summary
    assert old["exited"] == 120
    assert old["min_speed_m_s"] < 0.5  # the paper's point: the old law breaks v_min
    assert old["violations_by_condition"]["speed"] > 0
    assert old["violations_by_condition"]["pair"] == 0
    assert old["violations_by_condition"]["obstacle"] == 0


def test_full_paper_run_sub_tubes_equal_locate_at_every_step(paper, monkeypatch) -> None:
    """The simulator's sub-tube indices come from a SubTubeTracker: at every step of the full
    paper run they equal Partition.locate of the same positions, while locating (all robots
    or the few whose rows failed) runs at a small fraction of the steps."""
    from vtube_fleet.core.partition import SubTubeTracker

    seen = {"steps": 0, "trackers": []}
    update = SubTubeTracker.update

    def checked(self, p, max_move=None):
        k = update(self, p, max_move)
        np.testing.assert_array_equal(k, self._loc(p))
        seen["steps"] += 1
        if self not in seen["trackers"]:
            seen["trackers"].append(self)
        return k

    monkeypatch.setattr(SubTubeTracker, "update", checked)
    s = simulate(paper).summary
    assert s["exited"] == 120 and seen["steps"] == s["steps"]
    (tr,) = seen["trackers"]
    assert tr.locates + tr.partial < 0.1 * s["steps"]


def test_robotarium_unicycles_all_exit() -> None:
    sc = load_scenario(ROBOTARIUM)
    res = simulate(sc)
    s = res.summary
    assert s["model"] == "unicycle" and s["exited"] == 7 and s["violations"] == 0
    r = sc.robots
    # robot centres are reported too (paper note 10)
    for key in ("min_pair_distance_m", "min_obstacle_center_distance_m",
                "min_left_leg_distance_m", "min_right_leg_distance_m"):
        assert s[f"{key}_center"] is not None
    assert s["min_pair_distance_m_center"] > 2 * r.r_s
    assert res.heading is not None and res.heading.shape == res.pos.shape[:2]
    # control point = centre + s [cos θ, sin θ]
    h = res.heading
    cp = res.pos + r.nid_distance * np.stack([np.cos(h), np.sin(h)], axis=-1)
    np.testing.assert_allclose(cp, res.control_pos, atol=1e-12, equal_nan=True)
    np.testing.assert_array_equal(res.pos[0], r.positions)
    assert res.metrics_center is not None and len(res.metrics_center) == s["steps"]


def test_apf_uses_the_main_tube_only(paper) -> None:
    res = simulate(paper, controller="apf", robots=12, dt=0.002, duration=2.0)
    s = res.summary
    assert s["controller"] == "apf" and s["sub_tubes"] == 1 and s["steps"] == 1000


def test_overrides_and_errors(paper) -> None:
    res = simulate(paper, robots=3, dt=0.004, duration=0.4, record_every=5)
    # steps 0, 5, ..., 95 and the final state, after step 99
    assert res.summary["steps"] == 100 and res.pos.shape == (21, 3, 2)
    np.testing.assert_allclose(res.t[-2:], [0.38, 0.4])
    assert res.summary["exited"] == 0 and not res.summary["all_exited"]
    with pytest.raises(SimError, match="unknown controller"):
        simulate(paper, controller="fast")
    with pytest.raises(SimError, match="dt must be > 0"):
        simulate(paper, dt=0.0)
    with pytest.raises(SimError, match="duration must be > 0"):
        simulate(paper, duration=-1.0)
    with pytest.raises(ConfigError, match="--robots must be between 1 and 120"):
        simulate(paper, robots=500)
    import dataclasses

    with pytest.raises(SimError, match="controller 'apf' needs obstacles"):
        simulate(dataclasses.replace(paper, obstacles=()), controller="apf")


def test_invalid_scenario_is_rejected_before_running(paper) -> None:
    import tomllib

    with open(PAPER, "rb") as fh:
        data = tomllib.load(fh)
    data["robots"]["grid"]["origin"] = [9.0, -4.4]  # the block overlaps obstacle #1
    sc = parse_scenario(data, "bad.toml")
    with pytest.raises(ScenarioError) as info:
        simulate(sc, duration=0.1)
    assert any(v.condition == "Assumption1" for v in info.value.violations)


def test_ctrl_c_keeps_the_partial_run(paper) -> None:
    calls = []

    def progress(t: float, total: float, in_tube: int, exited: int) -> None:
        calls.append((t, total, in_tube, exited))
        if t >= 0.3 and len(calls) < 1000:
            calls.extend([None] * 1000)  # Ctrl-C once
            raise KeyboardInterrupt

    res = simulate(paper, robots=10, dt=0.002, duration=5.0, progress=progress)
    assert res.interrupted and res.summary["interrupted"]
    assert 0.3 <= res.summary["t_end_s"] < 0.5
    assert res.summary["steps"] == len(res.metrics)
    assert calls and calls[0][1] == pytest.approx(5.0)


def test_default_record_every_bounds_the_file() -> None:
    assert default_record_every(0.001, 40_000, 120) == 10  # 10 ms frames
    k = default_record_every(0.001, 1_000_000, 10_000)
    frames = 1_000_000 // k + 1
    assert frames * 10_000 * 4 * 8 <= 40_000_000 * 1.01


def test_progress_bar_output() -> None:
    import io

    buf = io.StringIO()
    bar = ProgressBar(buf)
    bar.close("nothing")  # never updated: prints nothing
    assert buf.getvalue() == ""
    bar(1.0, 4.0, 3, 1)
    bar(2.0, 4.0, 2, 2)
    assert buf.getvalue() == ""  # not a terminal: silent until close
    bar.close("done")
    out = buf.getvalue()
    assert out.count("\n") == 1 and "t =   2.00/4.00 s" in out and "exited 2/4" in out
    assert out.rstrip().endswith("done")


# ----------------------------------------------------------------------------------------------
# the final step of a decimated trajectory (issue 11, item 6)
# ----------------------------------------------------------------------------------------------
def test_decimated_trajectory_ends_with_the_final_state(paper) -> None:
    """A decimated trajectory's last frame is the run's final state (after its last step),
    bitwise the same as the last frame of the undecimated run."""
    kw = dict(robots=24, dt=0.002, duration=1.0)
    coarse = simulate(paper, record_every=7, **kw)
    fine = simulate(paper, record_every=1, **kw)
    assert coarse.summary["steps"] == fine.summary["steps"] == 500
    assert coarse.t[-1] == fine.t[-1] == pytest.approx(500 * 0.002)
    assert coarse.t[-2] == pytest.approx(497 * 0.002)  # 500 is no multiple of 7
    np.testing.assert_array_equal(coarse.pos[-1], fine.pos[-1])
    np.testing.assert_array_equal(coarse.vel[-1], fine.vel[-1])
    assert not np.isnan(coarse.pos[-1]).any()
    # the final state's velocity is the last step's command: it moved the robots there
    np.testing.assert_allclose(fine.pos[-1], fine.pos[-2] + 0.002 * fine.vel[-2], atol=1e-12)
    np.testing.assert_array_equal(fine.vel[-1], fine.vel[-2])
    assert fine.t.size == 501 and coarse.summary["frames"] == coarse.t.size == 73


def test_last_frame_holds_the_last_exit(reduced, paper) -> None:
    """The run ends when the last robot exits: the last frame is that final state, with that
    robot at its exit point, past the line, reached within one step (issue 11: it was missing
    when decimated; issue 31: the frame stopped one step before it)."""
    res = reduced
    assert res.record_every > 1
    t_end = res.summary["t_end_s"]
    last = int(np.nanargmax(res.exit_time_s))
    assert res.exit_time_s[last] == t_end and res.t[-1] == pytest.approx(t_end)
    line = paper.tube.finish_threshold(paper.controller.eps_0)
    past = res.pos[-1, last] @ paper.tube.n_c - line
    assert 0 <= past <= np.linalg.norm(res.vel[-1, last]) * res.dt + 1e-12
    np.testing.assert_array_equal(res.pos[-1, last], res.exit_pos[last])


def test_unicycle_final_frame() -> None:
    sc = load_scenario(ROBOTARIUM)
    res = simulate(sc, duration=0.55, record_every=7)  # 55 steps of 10 ms
    assert res.t[-1] == pytest.approx(0.55) and res.t[-2] == pytest.approx(0.49)
    for arr in (res.pos, res.vel, res.control_pos, res.control_vel):
        assert not np.isnan(arr[-1]).any()
    assert not np.isnan(res.heading[-1]).any()
    np.testing.assert_allclose(
        res.control_pos[-1],
        res.pos[-1] + sc.robots.nid_distance * np.stack(
            [np.cos(res.heading[-1]), np.sin(res.heading[-1])], axis=-1))


# ----------------------------------------------------------------------------------------------
# integrators (issue 11, item 5)
# ----------------------------------------------------------------------------------------------
#: A certified perturbation of configs/paper.toml (obstacle centres moved at random, seed 3,
#: trial 25 of bench-like search; docs/config.md "Integrators") where forward Euler at the paper's
#: dt = 1 ms brings a pair to 0.491 m < 2 r_s = 0.5.
EULER_BREAKS = [[10.551, -0.028], [17.228, 4.628], [21.574, -0.888], [26.062, 0.176],
                [30.677, -0.585]]


def _paper_with_obstacles(centers: list[list[float]]):
    import tomllib

    data = tomllib.loads(PAPER.read_text())
    for ob, c in zip(data["obstacles"], centers, strict=True):
        ob["center"] = c
    return parse_scenario(data, "perturbed_paper")


def test_default_integrator_keeps_pair_safety_where_euler_breaks_it() -> None:
    from vtube_fleet.core.validation import validate_scenario

    sc = _paper_with_obstacles(EULER_BREAKS)
    _, violations = validate_scenario(sc.tube, sc.obstacles, sc.controller,
                                      sc.robots.control_points())
    assert violations == []  # certified: every condition of the paper holds
    euler = simulate(sc, integrator="euler", record_every=100_000).summary
    assert euler["integrator"] == "euler" and euler["min_pair_distance_m"] < 0.5
    assert euler["violations_by_condition"]["pair"] > 0
    res = simulate(sc, record_every=100_000)  # the default
    s = res.summary
    assert s["integrator"] == "adaptive" and s["exited"] == 120
    assert s["violations"] == 0 and s["min_pair_distance_m"] > 0.5
    st = s["integrator_stats"]
    assert st["split_steps"] > 0 and st["substeps"] > st["split_steps"]
    assert st["floor_steps"] == 0 and st["min_substep_s"] < 0.001
    assert s["steps"] == len(res.metrics)  # metrics stay per (full) step


def test_adaptive_keeps_the_guarantee_at_a_coarse_dt(paper) -> None:
    """At dt = 50 ms Euler breaks pairs (and a leg); the default, at the same dt, does not."""
    euler = simulate(paper, dt=0.05, integrator="euler", record_every=100_000).summary
    assert euler["violations_by_condition"]["pair"] > 0
    s = simulate(paper, dt=0.05, record_every=100_000).summary
    assert s["exited"] == 120 and s["violations"] == 0 and s["min_pair_distance_m"] > 0.5
    assert s["dt_s"] == 0.05 and s["integrator_stats"]["split_steps"] > 0


def test_adaptive_is_euler_far_from_the_margins(paper) -> None:
    """Where no margin is near, the adaptive integrator takes exactly the Euler steps."""
    kw = dict(robots=24, dt=0.002, duration=0.6, record_every=1)
    a = simulate(paper, integrator="adaptive", **kw)
    e = simulate(paper, integrator="euler", **kw)
    assert a.summary["integrator_stats"]["guarded_steps"] == 0
    np.testing.assert_array_equal(a.pos, e.pos)


def test_rk4_and_integrator_choice(paper) -> None:
    kw = dict(dt=0.05, duration=3.0, record_every=1)
    r = simulate(paper, integrator="rk4", **kw)
    e = simulate(paper, integrator="euler", **kw)
    assert r.summary["integrator"] == "rk4" and r.summary["steps"] == 60
    np.testing.assert_array_equal(r.pos[0], e.pos[0])
    # the same start; once robots interact the commands vary within a step and RK4 differs
    assert np.abs(r.pos[-1] - e.pos[-1]).max() > 1e-3
    with pytest.raises(SimError, match="unknown integrator"):
        simulate(paper, integrator="leapfrog")
    with pytest.raises(SimError, match="single integrator only"):
        simulate(load_scenario(ROBOTARIUM), integrator="rk4", duration=0.1)


def test_integrator_scenario_key() -> None:
    import tomllib

    data = tomllib.loads(PAPER.read_text())
    assert parse_scenario(data).sim.integrator == "adaptive"
    data["sim"]["integrator"] = "euler"
    sc = parse_scenario(data)
    assert sc.sim.integrator == "euler"
    assert simulate(sc, robots=3, duration=0.01).summary["integrator"] == "euler"
    data["sim"]["integrator"] = "ode45"
    with pytest.raises(ConfigError, match=r"\[sim\].integrator: expected one of"):
        parse_scenario(data, "x.toml")


def test_rk4_step_is_fourth_order() -> None:
    from vtube_fleet.core.integrate import rk4_step

    z = np.array([1.0 + 0.5j, -2.0 + 0j])
    for h in (0.1, 0.05):
        z1 = rk4_step(z, -z, h, lambda y, move: -y)
        err = np.abs(z1 - z * math.exp(-h)).max()
        assert err < 0.01 * h**4 and err > 1e-4 * h**5


def test_margin_guard_sees_crossings_between_end_points() -> None:
    from vtube_fleet.core.integrate import MarginGuard
    from vtube_fleet.core.metrics import SafetyLimits
    from vtube_fleet.core.tube import Obstacle, Trapezoid

    tube = Trapezoid([0, 5], [20, 5], [0, -5], [20, -5])
    guard = MarginGuard(tube, (Obstacle(center=np.array([10.0, 0.0]), radius=0.5),),
                        SafetyLimits(0.25, 1.0, 2.0))
    pairs = (np.array([0]), np.array([1]))
    # two robots 1 m apart swap places: both end points are safe, the segment is not
    z0 = np.array([2.0 + 0j, 3.0 + 0j])
    assert not guard.accepts(z0, z0[::-1].copy(), pairs)
    assert guard.accepts(z0, z0 + 0.1j, pairs)  # a parallel move
    # pair margin 0.5 → 0.3 loses 40 % (accepted), → 0.2 loses 60 % (refused)
    assert guard.accepts(z0, np.array([2.1 + 0j, 2.9 + 0j]), pairs)
    assert not guard.accepts(z0, np.array([2.15 + 0j, 2.85 + 0j]), pairs)
    none = (np.zeros(0, np.intp), np.zeros(0, np.intp))
    # a robot passing through the obstacle, end points 2 m from its centre
    assert not guard.accepts(np.array([8.0 + 0j]), np.array([12.0 + 0j]), none)
    # towards the left leg (y = 5): margin 4.75 - 2 = 2.75 → 0.75 loses 73 %
    assert not guard.accepts(np.array([2.0 + 2j]), np.array([2.0 + 4j]), none)
    assert guard.accepts(np.array([2.0 + 2j]), np.array([2.0 + 3j]), none)
    # a margin already violated does not constrain the step
    assert guard.accepts(np.array([2.0 + 4.9j]), np.array([2.0 + 4.95j]), none)
    assert guard.single_margin(np.array([2.0 + 2j])) == pytest.approx(2.75)


def test_adaptive_unicycles_guard_their_control_points() -> None:
    """Robotarium at dt = 0.5 s: Euler breaks the control points' pair and leg limits; the
    adaptive step (sub-stepping the unicycles, margins of the (NID) control points) does not."""
    sc = load_scenario(ROBOTARIUM)
    euler = simulate(sc, dt=0.5, integrator="euler").summary
    assert euler["violations_by_condition"]["pair"] > 0
    s = simulate(sc, dt=0.5).summary
    assert s["exited"] == 7 and s["violations"] == 0
    assert s["integrator_stats"]["split_steps"] > 0


# ------------------------------------------------------------------------------ pinned bits
#: The trajectories of three short runs as the simulator computed them before the speed-up of
#: issue 16 (numpy 2.4.6, x86_64): sha256 (first 16 hex digits) of the float64 bytes of
#: ``pos``, ``vel`` and the per-step minimum pair distance, with a few plain values. A change
#: that reassociates a sum (or reorders any float operation) changes the bytes. ``pos`` and
#: ``vel`` are the frames before the final state (issue 31 made the last frame the state after
#: the last step instead of the last step, an off-grid frame for the perturbed run, whose pins
#: were taken from the code before that change without its last frame; robot7 is frame −2).
PINNED_NUMPY = "2.4.6"
PINNED = {
    "paper_adaptive_2s": {
        "pos": "e6bff1a20cd1447c", "vel": "1c43aba880a9d2f7", "min_pair": "2c58a52cce8ee26b",
        "split_steps": 0, "min_pair_m": 0.6744157726189018,
        "robot7": (4.489359294748476, 1.1999999953965035, 8.659683082347771e-07)},
    "perturbed_adaptive_6s": {
        "pos": "b2c929b92c9e321e", "vel": "c469a75249e30d5d", "min_pair": "ea8dc06404538c4c",
        "split_steps": 142, "min_pair_m": 0.500163355074004,
        "robot7": (11.363581494044585, 2.4243595080128673, 0.9719371516902385)},
    "paper_rk4_0.5s": {
        "pos": "e9b3917dd497bcf0", "vel": "0bd322944cd0a128", "min_pair": "aa6fd8f94d7b0742",
        "split_steps": 0, "min_pair_m": 0.692188284056291,
        "robot7": (1.4980000000000009, 1.2000000000000002, 0.0)},
}
#: obstacle centres of a certified perturbation of configs/paper.toml (bench_sim --search,
#: seed 3, draw 25) where the adaptive integrator splits steps between t = 4 and 6 s
PERTURBED_CENTRES = [[10.551, -0.028], [17.228, 4.628], [21.574, -0.888], [26.062, 0.176],
                     [30.677, -0.585]]


def _pinned_run(name: str, paper):
    if name == "paper_adaptive_2s":
        return simulate(paper, duration=2.0, record_every=1)
    if name == "paper_rk4_0.5s":
        return simulate(paper, duration=0.5, record_every=1, integrator="rk4")
    import tomllib

    data = tomllib.loads(PAPER.read_text())
    for ob, c in zip(data["obstacles"], PERTURBED_CENTRES, strict=True):
        ob["center"] = c
    return simulate(parse_scenario(data, "perturbed"), duration=6.0, record_every=10)


def _sha(a: np.ndarray) -> str:
    import hashlib

    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


@pytest.mark.parametrize("name", sorted(PINNED))
def test_trajectory_is_pinned_bit_for_bit(name, paper) -> None:
    """The optimised step computes exactly what the straightforward order of operations did
    (values to 1e-9 everywhere; the bytes themselves with the numpy the pins were made with:
    another numpy may round a library function differently, see PINNED)."""
    res = _pinned_run(name, paper)
    pin = PINNED[name]
    assert res.summary["integrator_stats"]["split_steps"] == pin["split_steps"]
    last = (res.pos[-2, 7, 0], res.pos[-2, 7, 1], res.vel[-2, 7, 1])
    np.testing.assert_allclose(last, pin["robot7"], rtol=0, atol=1e-9)
    assert res.summary["min_pair_distance_m"] == pytest.approx(pin["min_pair_m"], abs=1e-9)
    if np.__version__ != PINNED_NUMPY:
        pytest.skip(f"bytes pinned with numpy {PINNED_NUMPY}, this is {np.__version__}")
    got = {"pos": _sha(res.pos[:-1]), "vel": _sha(res.vel[:-1]),
           "min_pair": _sha(res.metrics.min_pair_distance_m)}
    assert got == {k: pin[k] for k in got}
    assert last == pin["robot7"]


def test_element_subset_changes_no_bit(paper, monkeypatch) -> None:
    """The simulator's controller calls skip the elements that are exactly 0
    (CommandEvaluator.step(move=...)); without that (every element evaluated) the run is the
    same to the last bit: trajectory, per-step metrics, summary."""
    from vtube_fleet.core import controller as ctl

    calls = {"subset": 0}
    core = ctl._Active.core

    def counted(self, z, *args):
        calls["subset"] += 1
        return core(self, z, *args)

    monkeypatch.setattr(ctl._Active, "core", counted)
    fast = _pinned_run("perturbed_adaptive_6s", paper)
    assert calls["subset"] > 5000
    step = ctl.CommandEvaluator.step
    monkeypatch.setattr(ctl.CommandEvaluator, "step",
                        lambda self, z, k, pairs, out=None, move=None: step(self, z, k, pairs,
                                                                            out))
    calls["subset"] = 0
    full = _pinned_run("perturbed_adaptive_6s", paper)
    assert calls["subset"] == 0
    for key, arr in fast.trajectory_arrays().items():
        assert arr.tobytes() == full.trajectory_arrays()[key].tobytes(), key
    for key in METRIC_KEYS:
        assert getattr(fast.metrics, key).tobytes() == getattr(full.metrics, key).tobytes(), key
    drop = ("wall_s", "us_per_step")
    assert ({k: v for k, v in fast.summary.items() if k not in drop}
            == {k: v for k, v in full.summary.items() if k not in drop})


def test_sub_tube_changes_update_the_element_subset_bitwise(paper, monkeypatch) -> None:
    """When a few robots change sub-tube, the controller's element subset is patched in place
    (their leg/σ elements only, _Active._legs_update) instead of chosen anew; the paper run
    is then the same to the last bit as with every element evaluated at every step."""
    from vtube_fleet.core import controller as ctl

    calls = {"patched": 0}
    update = ctl._Active._legs_update

    def counted(self, g, z, ch):
        ok = update(self, g, z, ch)
        calls["patched"] += ok
        return ok

    monkeypatch.setattr(ctl._Active, "_legs_update", counted)
    fast = simulate(paper, duration=4.0, record_every=1)
    assert calls["patched"] > 50
    step = ctl.CommandEvaluator.step
    monkeypatch.setattr(ctl.CommandEvaluator, "step",
                        lambda self, z, k, pairs, out=None, move=None: step(self, z, k, pairs,
                                                                            out))
    full = simulate(paper, duration=4.0, record_every=1)
    for key, arr in fast.trajectory_arrays().items():
        assert arr.tobytes() == full.trajectory_arrays()[key].tobytes(), key
    for key in METRIC_KEYS:
        assert getattr(fast.metrics, key).tobytes() == getattr(full.metrics, key).tobytes(), key


def test_tracker_locates_one_point_in_python_as_numpy(paper) -> None:
    """SubTubeTracker re-locates one or a few points with Python floats (_locate_one): the
    same sub-tube and rows as its numpy computation at random points around the paper tube
    (on and off the partition's boundaries), and update() equals locate() when points cross
    sub-tubes one at a time."""
    from vtube_fleet.core.validation import validate_scenario

    part, _ = validate_scenario(paper.tube, paper.obstacles, paper.controller,
                                paper.robots.control_points())
    tr = part.tracker()
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-3.0, 36.0, 4000), rng.uniform(-11.0, 11.0, 4000)])
    k, C, _ = tr._locate_rows(pts, (np.arange(len(pts)) * part.K)[:, None])
    Ctab = tr._tables[0]
    for i, (x, y) in enumerate(pts.tolist()):
        kk, code = tr._locate_one(x, y)
        assert kk == k[i] and np.array_equal(Ctab[:, code], C[:, i]), i
    assert tr._locate_one(math.nan, 0.0) is None
    # a swarm on a line across the tube moving downstream: robots change sub-tube singly
    p = np.column_stack([np.linspace(0.5, 12.0, 40), np.linspace(-4.0, 4.0, 40)])
    for _ in range(600):
        p = p + [0.004, 0.0]
        np.testing.assert_array_equal(tr.update(p, 0.0041), part.locate(p))
    assert tr.partial > 10


def test_pairs_within_sorted_as_lexsort() -> None:
    """pairs_within sorts the KD-tree's pairs by one integer key: the same (I, J) as a
    lexicographic sort of the brute-force pairs, NaN rows skipped, read-only int64."""
    from vtube_fleet.core.neighbours import pairs_within

    rng = np.random.default_rng(9)
    for m in (48, 120, 700):
        p = rng.uniform(0.0, 2.0 * math.sqrt(m), (m, 2))
        p[rng.random(m) < 0.05] = np.nan
        I, J = pairs_within(p, 1.1)
        ok = np.flatnonzero(np.isfinite(p).all(axis=1))
        d = np.hypot(*(p[ok, None, :] - p[None, ok, :]).transpose(2, 0, 1))
        ii, jj = np.nonzero(np.triu(d <= 1.1, 1))
        assert I.dtype == J.dtype == np.int64 and not I.flags.writeable
        assert np.array_equal(I, ok[ii]) and np.array_equal(J, ok[jj])
