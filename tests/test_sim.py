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
    np.testing.assert_allclose(np.diff(t), res.record_every * res.dt)
    tube = paper.tube
    line = float(tube.n_c @ tube.p_r1) - paper.controller.eps_0
    for i in range(m):
        te = res.exit_time_s[i]
        assert math.isfinite(te)
        present = ~np.isnan(pos[:, i, 0])
        # present exactly until the exit time, NaN afterwards (and velocities too)
        np.testing.assert_array_equal(present, t < te - 1e-12)
        np.testing.assert_array_equal(present, ~np.isnan(vel[:, i, 0]))
        assert np.all(pos[present, i] @ tube.n_c < line)
    speeds = np.linalg.norm(vel, axis=-1)
    ok = ~np.isnan(speeds)
    assert np.all(speeds[ok] >= 0.5 - 1e-9) and np.all(speeds[ok] <= 3.5 + 1e-9)
    arrays = res.trajectory_arrays()
    assert set(arrays) == {"t", "pos", "vel", "exit_time_s"}


def test_metrics_series_match_recorded_frames(reduced, paper) -> None:
    """The per-step metrics at recorded steps equal a recomputation from the recorded frames."""
    from vtube_fleet.core.metrics import SafetyMonitor

    res = reduced
    mon = SafetyMonitor.from_params(paper.tube, paper.obstacles, paper.controller)
    idx = np.searchsorted(res.step_t, res.t)
    again = mon.evaluate(res.pos, res.vel)
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
    assert res.summary["steps"] == 100 and res.pos.shape == (20, 3, 2)  # steps 0, 5, ..., 95
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
