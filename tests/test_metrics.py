"""Safety metrics against brute force, violation thresholds, and the summary accumulator."""

from __future__ import annotations

import contextlib
import json
import math

import numpy as np
import pytest

from vtube_fleet.core.metrics import (
    CONDITIONS,
    METRIC_KEYS,
    SafetyMonitor,
    StepMetrics,
    SummaryAccumulator,
)
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.tube import Obstacle, Trapezoid

TUBE = Trapezoid([0.0, 9.0], [30.0, 4.5], [0.0, -9.0], [30.0, -4.5])
OBSTACLES = (Obstacle([12.0, 0.0], 0.9), Obstacle([20.0, 2.0], 0.5))
PARAMS = ControllerParams(r_s=0.25, r_a=0.5, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5)


@pytest.fixture
def monitor() -> SafetyMonitor:
    return SafetyMonitor.from_params(TUBE, OBSTACLES, PARAMS)


def _brute(pos: np.ndarray, vel: np.ndarray) -> dict[str, np.ndarray]:
    """Straightforward O(M²) reference, NaN rows = absent robots."""
    k, m = pos.shape[:2]
    i, j = np.triu_indices(m, 1)
    pair = np.linalg.norm(pos[:, i] - pos[:, j], axis=-1)
    centers = np.array([o.center for o in OBSTACLES])
    radii = np.array([o.radius for o in OBSTACLES])
    dob = np.linalg.norm(pos[:, :, None, :] - centers, axis=-1)
    speed = np.linalg.norm(vel, axis=-1)
    speed[np.isnan(pos[..., 0])] = np.nan
    return {
        "min_pair_distance_m": np.nanmin(pair, axis=1),
        "min_obstacle_center_distance_m": np.nanmin(dob, axis=(1, 2)),
        "min_obstacle_clearance_m": np.nanmin(dob - radii, axis=(1, 2)),
        "min_left_leg_distance_m": np.nanmin(TUBE.d_Th(pos), axis=1),
        "min_right_leg_distance_m": np.nanmin(TUBE.d_Tr(pos), axis=1),
        "min_speed_m_s": np.nanmin(speed, axis=1),
        "max_speed_m_s": np.nanmax(speed, axis=1),
    }


def _nothing() -> contextlib.AbstractContextManager:
    return contextlib.nullcontext()


def _cloud(rng: np.random.Generator, k: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    pos = rng.uniform([1.0, -4.0], [28.0, 4.0], size=(k, m, 2))
    vel = rng.normal(scale=1.5, size=(k, m, 2))
    return pos, vel


@pytest.mark.parametrize("m", [2, 30, 200])
def test_metrics_match_brute_force(monitor: SafetyMonitor, m: int) -> None:
    rng = np.random.default_rng(m)
    pos, vel = _cloud(rng, 6, m)
    pos[2, 0] = np.nan  # an exited robot
    # make sure some pair is closer than the search radius in every step
    pos[:, 1] = pos[:, m - 1] + [0.3, 0.1]
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning) if m == 2 else _nothing():
        ref = _brute(pos, vel)
    i, j = np.triu_indices(m, 1)
    for pairs in (None, (i, j)):
        got = monitor.evaluate(pos, vel, pairs=pairs)
        for key in METRIC_KEYS:
            want = ref[key]
            if key == "min_pair_distance_m":
                # no pair at all → inf; a search (pairs=None) sees only pairs within r_s + r_a
                far = np.isnan(want) | ((want > 0.75) if pairs is None else False)
                want = np.where(far, np.inf, want)
            np.testing.assert_allclose(getattr(got, key), want, rtol=1e-12, err_msg=key)
        np.testing.assert_array_equal(got.robots, [m, m, m - 1, m, m, m])


def test_single_step_and_non_contiguous_input(monitor: SafetyMonitor) -> None:
    rng = np.random.default_rng(1)
    buf_p = rng.uniform([1.0, -4.0], [28.0, 4.0], size=(5, 40, 2))
    buf_v = rng.normal(size=(5, 40, 2))
    # a slice of a bigger buffer, as the simulator passes it
    pos, vel = buf_p[:3, :25], buf_v[:3, :25]
    pos[:, 3] = pos[:, 4] + [0.2, 0.0]
    ref = _brute(pos, vel)
    got = monitor.evaluate(pos, vel)
    one = monitor.evaluate(pos[1], vel[1])
    for key in METRIC_KEYS:
        np.testing.assert_allclose(getattr(got, key), ref[key], rtol=1e-12)
        assert getattr(one, key).shape == (1,)
        assert getattr(one, key)[0] == pytest.approx(ref[key][1], rel=1e-12)


def test_pairs_beyond_search_radius_are_inf(monitor: SafetyMonitor) -> None:
    pos = np.array([[5.0, 0.0], [5.0, 2.0], [8.0, 0.0]])
    got = monitor.evaluate(pos, np.ones_like(pos))
    assert got.min_pair_distance_m[0] == math.inf  # nothing within r_s + r_a = 0.75 m
    assert not got.pair_violation[0]


def test_violation_thresholds(monitor: SafetyMonitor) -> None:
    r_s = 0.25
    base = np.array([[5.0, 0.0], [5.0, 1.0]])
    v_ok = np.array([[2.0, 0.0], [2.0, 0.0]])

    def flags(pos: np.ndarray, vel: np.ndarray = v_ok) -> dict[str, bool]:
        got = monitor.evaluate(pos, vel)
        return {c: bool(got.flags(c)[0]) for c in CONDITIONS} | {"any": bool(got.violation[0])}

    assert not flags(base)["any"]
    # pair: violation iff distance <= 2 r_s
    assert flags(np.array([[5.0, 0.0], [5.0, 2 * r_s]]))["pair"]
    assert not flags(np.array([[5.0, 0.0], [5.0, 2 * r_s + 1e-6]]))["pair"]
    # obstacle centre: violation iff distance <= r_o + r_s
    c = OBSTACLES[0].center
    assert flags(np.array([c + [0.0, 0.9 + r_s], [5.0, 0.0]]))["obstacle"]
    assert not flags(np.array([c + [0.0, 0.9 + r_s + 1e-6], [5.0, 0.0]]))["obstacle"]
    c2 = OBSTACLES[1].center  # smaller obstacle: its own radius counts
    assert not flags(np.array([c2 + [0.0, 0.5 + r_s + 1e-6], [5.0, 0.0]]))["obstacle"]
    # legs: violation iff signed distance <= r_s
    x = 10.0
    on_left = TUBE.lh(TUBE.xi(np.array([x, 0.0]))) + r_s * TUBE.n_h
    assert flags(np.array([on_left, [5.0, 0.0]]))["left_leg"]
    assert not flags(np.array([on_left + 1e-6 * TUBE.n_h, [5.0, 0.0]]))["left_leg"]
    on_right = TUBE.lr(TUBE.xi(np.array([x, 0.0]))) + (r_s + 1e-6) * TUBE.n_r
    f = flags(np.array([on_right, [5.0, 0.0]]))
    assert not f["right_leg"] and not f["any"]
    assert flags(np.array([on_right - 2e-6 * TUBE.n_r, [5.0, 0.0]]))["right_leg"]
    # speeds: [v_min, v_max] with a 1e-9 tolerance
    assert not flags(base, np.array([[0.5 - 5e-10, 0.0], [3.5 + 5e-10, 0.0]]))["speed"]
    assert flags(base, np.array([[0.5 - 1e-8, 0.0], [2.0, 0.0]]))["speed"]
    assert flags(base, np.array([[2.0, 0.0], [0.0, 3.5 + 1e-8]]))["speed"]


def test_no_robots_and_no_obstacles() -> None:
    mon = SafetyMonitor.from_params(TUBE, (), PARAMS)
    pos = np.full((2, 3, 2), np.nan)
    got = mon.evaluate(pos, np.zeros_like(pos))
    assert np.all(got.min_pair_distance_m == math.inf)
    assert np.all(got.min_obstacle_center_distance_m == math.inf)
    assert np.all(got.min_left_leg_distance_m == math.inf)
    assert np.all(np.isnan(got.min_speed_m_s)) and not got.violation.any()
    assert np.all(got.robots == 0)
    nov = mon.evaluate(np.array([[5.0, 0.0]]))
    assert np.isnan(nov.min_speed_m_s[0]) and not nov.speed_violation[0]


def test_concatenate_and_as_dict(monitor: SafetyMonitor) -> None:
    rng = np.random.default_rng(3)
    a = monitor.evaluate(*_cloud(rng, 2, 10))
    b = monitor.evaluate(*_cloud(rng, 3, 10))
    ab = StepMetrics.concatenate([a, b])
    assert len(ab) == 5
    np.testing.assert_array_equal(ab.min_speed_m_s[2:], b.min_speed_m_s)
    assert len(StepMetrics.concatenate([])) == 0
    d = ab.as_dict()
    assert set(METRIC_KEYS) <= set(d) and d["violation"].dtype == bool


def test_summary_accumulator(monitor: SafetyMonitor) -> None:
    acc = SummaryAccumulator(robots=4)
    pos = np.array([[[5.0, 0.0], [5.0, 1.0], [6.0, 0.0], [7.0, 0.0]]] * 3)
    vel = np.full((3, 4, 2), 1.0)
    vel[1, 2] = [0.1, 0.0]  # a slow robot at step 1
    pos[2, 1] = [5.0, 0.3]  # too close at step 2
    met = monitor.evaluate(pos, vel)
    acc.add([0.0, 0.1, 0.2], met)
    acc.add([0.3], monitor.evaluate(pos[0], vel[0]))
    acc.add_exits(0.25, [0, 3])
    acc.add_exits(0.3, np.array([1]))
    s = acc.summary(dt_s=0.1, wall_s=0.01)
    json.dumps(s, allow_nan=False)  # strict JSON
    assert s["robots"] == 4 and s["exited"] == 3 and s["steps"] == 4
    assert s["last_exit_s"] == 0.3 and s["median_exit_s"] == 0.25
    assert s["violations"] == 2
    assert s["violations_by_condition"] == {"pair": 1, "obstacle": 0, "left_leg": 0,
                                            "right_leg": 0, "speed": 1}
    assert s["first_violation_s"] == pytest.approx(0.1)
    assert s["min_pair_distance_m"] == pytest.approx(0.3)
    assert s["min_speed_m_s"] == pytest.approx(0.1)
    assert s["max_speed_m_s"] == pytest.approx(math.sqrt(2))
    assert s["dt_s"] == 0.1
    np.testing.assert_array_equal(np.isnan(acc.exit_time_s), [False, False, True, False])


def test_summary_streams_and_empty_values() -> None:
    acc = SummaryAccumulator(robots=2)
    s = acc.summary()
    assert s["exited"] == 0 and s["last_exit_s"] is None and s["median_exit_s"] is None
    assert s["min_pair_distance_m"] is None and s["violations"] == 0 and s["steps"] == 0
    mon = SafetyMonitor.from_params(TUBE, OBSTACLES, PARAMS)
    pos = np.array([[5.0, 0.0], [9.0, 0.0]])
    acc.add(0.0, mon.evaluate(pos, np.ones_like(pos)))
    acc.add(0.0, mon.evaluate(pos + [0.0, 0.1], np.zeros_like(pos)), suffix="_center")
    s = acc.summary()
    json.dumps(s, allow_nan=False)
    assert s["min_pair_distance_m"] is None  # no pair within r_s + r_a: inf → null
    assert s["violations"] == 0 and s["violations_center"] == 1
    assert s["min_speed_m_s_center"] == 0.0 and s["steps"] == 1
    assert s["min_left_leg_distance_m_center"] < s["min_left_leg_distance_m"]


@pytest.mark.parametrize("k", [1, 2, 40])
def test_pruned_chunk_evaluation_is_exact(monitor: SafetyMonitor, k: int) -> None:
    """all_present=True (the simulator's chunks) gives the same minima as the full path."""
    rng = np.random.default_rng(k)
    m = 150
    start = rng.uniform([1.0, -4.0], [28.0, 4.0], size=(m, 2))
    steps = rng.normal(scale=0.05, size=(k, m, 2))
    steps[0] = 0.0
    pos = start + np.cumsum(steps, axis=0)  # a random walk, as robots move between steps
    vel = rng.normal(scale=1.5, size=(k, m, 2))
    i, j = np.triu_indices(m, 1)
    near = np.linalg.norm(start[i] - start[j], axis=-1) < 2.0
    pairs = (i[near], j[near])
    full = monitor.evaluate(pos, vel, pairs=pairs)
    fast = monitor.evaluate(pos, vel, pairs=pairs, all_present=True)
    ref = _brute(pos, vel)
    for key in METRIC_KEYS:
        np.testing.assert_allclose(getattr(fast, key), getattr(full, key), rtol=1e-12,
                                   err_msg=key)
        if key != "min_pair_distance_m":
            np.testing.assert_allclose(getattr(fast, key), ref[key], rtol=1e-12, err_msg=key)
    for c in CONDITIONS:
        np.testing.assert_array_equal(fast.flags(c), full.flags(c))
    np.testing.assert_array_equal(fast.robots, full.robots)


@pytest.mark.parametrize("all_present", [False, True])
def test_given_min_pair_is_used_as_is_and_copied(monitor: SafetyMonitor,
                                                 all_present: bool) -> None:
    """min_pair= (the simulator passes its controller's per-step minimum over the same
    list) replaces the pair computation; the other metrics are unchanged; the array is
    copied (the simulator reuses its buffer)."""
    rng = np.random.default_rng(9)
    pos, vel = _cloud(rng, 12, 40)
    i, j = np.triu_indices(40, 1)
    pairs = (i, j)
    ref = monitor.evaluate(pos, vel, pairs=pairs, all_present=all_present)
    given = ref.min_pair_distance_m.copy()
    buf = given.copy()
    got = monitor.evaluate(pos, vel, pairs=pairs, all_present=all_present, min_pair=buf)
    buf[:] = -1.0
    for key in METRIC_KEYS:
        np.testing.assert_array_equal(getattr(got, key), getattr(ref, key), err_msg=key)
    np.testing.assert_array_equal(got.pair_violation, ref.pair_violation)
    with pytest.raises(ValueError):
        monitor.evaluate(pos, vel, pairs=pairs, min_pair=given[:3])
