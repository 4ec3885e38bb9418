"""Tests of the scenario checks run before anything moves (vtube_fleet.core.validation)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from vtube_fleet.config.scenario import grid_positions
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.partition import Partition
from vtube_fleet.core.tube import Obstacle, Trapezoid
from vtube_fleet.core.validation import (
    MAX_LISTED,
    ScenarioError,
    Violation,
    check_scenario,
    validate_scenario,
)
from vtube_fleet.errors import UserError

PARAMS = ControllerParams(r_s=0.25, r_a=0.5, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5)

# Recommended paper-like scenario: 120 robots in a 10 × 12 grid (0.8 m), five obstacles
# r_o = 0.9 at the default apex distance 1.3 h_min = 2.15 m.
PAPER_TUBE = Trapezoid((0.0, 9.0), (31.0, 4.5), (0.0, -9.0), (31.0, -4.5))
PAPER_OBSTACLES = [Obstacle(c, 0.9) for c in
                   [(10.5, 0.0), (15.0, 1.5), (19.5, -1.5), (24.0, 1.0), (28.5, -0.5)]]
PAPER_ROBOTS = grid_positions((0.5, -4.4), 10, 12, 0.8)

RECT = Trapezoid((0.0, 5.0), (20.0, 5.0), (0.0, -5.0), (20.0, -5.0))


def conditions(violations: list[Violation]) -> list[str]:
    return [v.condition for v in violations]


def messages(violations: list[Violation]) -> str:
    return "\n".join(v.message for v in violations)


def test_paper_scenario_is_feasible():
    assert PAPER_ROBOTS.shape == (120, 2)
    part, violations = validate_scenario(PAPER_TUBE, PAPER_OBSTACLES, PARAMS, PAPER_ROBOTS)
    assert violations == []
    part = check_scenario(PAPER_TUBE, PAPER_OBSTACLES, PARAMS, PAPER_ROBOTS)
    assert isinstance(part, Partition)
    assert part.K == 16 and all(t.remark5 is None for t in part.triangles)
    # every robot starts in the first sub-tube, upstream of the first apex
    assert np.all(part.locate(PAPER_ROBOTS) == 0)


def test_constraint1_both_inequalities():
    p = dataclasses.replace(PARAMS, v=2.5)
    _, v = validate_scenario(RECT, [], p)
    assert conditions(v) == ["Constraint1"]
    assert v[0].message.startswith("Constraint1 violated: v + v'_max = 4.0 > v_max = 3.5")
    p = dataclasses.replace(PARAMS, v=1.9)
    _, v = validate_scenario(RECT, [], p)
    assert conditions(v) == ["Constraint1"]
    assert v[0].message.startswith("Constraint1 violated: v - v'_max = 0.4 < v_min = 0.5")
    p = dataclasses.replace(PARAMS, v_max_prime=2.0, v_max=3.0)  # both at once
    _, v = validate_scenario(RECT, [], p)
    assert conditions(v)[:2] == ["Constraint1", "Constraint1"]


def test_constraint2_main_tube_leg_too_steep():
    # left leg converging at 50° > α_max = 44.05°
    tube = Trapezoid((0.0, 10.0), (5.0, 10.0 - 5.0 * np.tan(np.radians(50))), (0.0, -5.0),
                     (5.0, -5.0))
    _, v = validate_scenario(tube, [], PARAMS)
    assert conditions(v) == ["Constraint2"]
    assert "left leg" in v[0].message and "> v'_max = 1.5" in v[0].message
    assert "50.0°" in v[0].message


def test_assumption3_main_tube():
    short = Trapezoid((0.0, 5.0), (0.8, 5.0), (0.0, -5.0), (0.8, -5.0))
    _, v = validate_scenario(short, [], PARAMS)
    assert conditions(v) == ["Assumption3"]
    assert "length 0.8 m ≤ 2 r_a = 1.0 m" in v[0].message
    narrow = Trapezoid((0.0, 0.7), (10.0, 0.5), (0.0, -0.7), (10.0, -0.5))
    _, v = validate_scenario(narrow, [], PARAMS)
    assert "Assumption3" in conditions(v)
    assert "L ∩ R is not empty" in messages(v) and "M is empty" in messages(v)
    too_narrow = Trapezoid((0.0, 0.2), (10.0, 0.2), (0.0, -0.2), (10.0, -0.2))
    _, v = validate_scenario(too_narrow, [], PARAMS)
    assert "too narrow to contain one robot" in messages(v)


def test_pothk_for_a_configured_apex_distance():
    obs = [Obstacle((10.0, 0.0), 0.9, apex_distance=1.5)]
    part, v = validate_scenario(RECT, obs, PARAMS)
    assert part is not None
    assert conditions(v) == ["pothk", "Constraint3", "Constraint3"]
    assert ("pothk violated: obstacle #1 at (10.0, 0.0) r_o=0.9: apex_distance h = 1.5 m < "
            "h_min") in v[0].message and "1.654 m" in v[0].message
    # a configured distance above h_min is fine; the default is never reported
    _, v = validate_scenario(RECT, [Obstacle((10.0, 0.0), 0.9, apex_distance=1.7),
                                    Obstacle((15.0, 0.0), 0.5)], PARAMS)
    assert v == []


def test_partition_failure_is_reported():
    narrow = Trapezoid((0.0, 2.0), (20.0, 2.0), (0.0, -2.0), (20.0, -2.0))
    part, v = validate_scenario(narrow, [Obstacle((12.0, 0.0), 0.9)], PARAMS)
    assert part is None
    assert conditions(v) == ["Partition"]
    assert v[0].message.startswith(
        "Partition failed: obstacle #1 at (12.0, 0.0) r_o=0.9: the obstacle blocks the tube")


def test_assumption3_prime_per_sub_tube():
    part, v = validate_scenario(RECT, [Obstacle((18.5, 0.0), 0.9)], PARAMS)
    assert part is not None and part.K == 4
    assert conditions(v) == ["Assumption3'"]
    assert "T_o4 (the tube after obstacle #1): length 0.35 m ≤ 2 r_a = 1.0 m" in v[0].message


def test_assumption1_robot_not_inside_tube():
    pos = np.array([[5.0, 0.0], [5.0, 4.9], [-0.5, 0.0], [21.0, 0.0], [6.0, -4.8]])
    _, v = validate_scenario(RECT, [], PARAMS, pos)
    assert conditions(v) == ["Assumption1"] * 4
    m = messages(v)
    assert "robot 1 at (5.0, 4.9) is not inside T (S_i ⊄ T): distance to the left leg 0.1 m" \
        in m
    assert "robot 2 at (-0.5, 0.0)" in m and "before the start base" in m
    assert "robot 3 at (21.0, 0.0)" in m and "beyond the finishing line" in m
    assert "robot 4" in m and "right leg 0.2 m < r_s = 0.25 m" in m


def test_assumption1_overlapping_robots():
    pos = grid_positions((1.0, -4.0), 4, 5, 0.8)
    pos[17] = pos[3] + [0.29, 0.29]  # 0.41 m from robot 3, 0.59 m from its grid neighbours
    _, v = validate_scenario(RECT, [], PARAMS, pos)
    assert conditions(v) == ["Assumption1"]
    assert v[0].message == ("Assumption1 violated: robots 3 and 17 overlap: distance 0.41 m "
                            "≤ 2 r_s = 0.5 m")


def test_assumption1_overlaps_are_capped():
    pos = np.stack([np.linspace(1.0, 19.0, 60), np.zeros(60)], axis=1)  # 0.305 m apart
    _, v = validate_scenario(RECT, [], PARAMS, pos)
    assert len(v) == MAX_LISTED + 1
    assert v[-1].message == "Assumption1 violated: … and 49 more overlapping pairs"


def test_assumption1_many_robots_use_no_quadratic_memory():
    pos = grid_positions((0.5, -4.5), 24, 15, 0.6) * [0.8, 1.0]  # 360 robots, 0.48 m rows
    _, v = validate_scenario(RECT, [], PARAMS, pos)
    assert v[-1].message.endswith("more overlapping pairs")
    big = np.random.default_rng(0).uniform((0.5, -4.5), (19.5, 4.5), size=(20000, 2))
    _, v = validate_scenario(RECT, [], PARAMS, big)
    assert v and set(conditions(v)) == {"Assumption1"}


def test_assumption1_robot_overlaps_obstacle_and_triangle():
    obs = [Obstacle((5.0, 0.0), 0.5), Obstacle((12.0, 0.0), 0.9)]
    pos = np.array([[1.0, 0.0], [5.0, 0.7], [11.0, 0.6], [12.0, 3.0]])
    part, v = validate_scenario(RECT, obs, PARAMS, pos)
    assert part is not None
    assert conditions(v) == ["Assumption1", "Assumption1"]
    assert v[0].message == ("Assumption1 violated: robot 1 at (5.0, 0.7) overlaps obstacle #1 "
                            "at (5.0, 0.0) r_o=0.5: centre distance 0.7 m ≤ r_o + r_s = 0.75 m")
    assert v[1].message.startswith("Assumption1 violated: robot 2 at (11.0, 0.6) starts inside "
                                   "the circumscribed triangle of obstacle #2")


def test_parameter_sanity():
    bad = SimpleNamespace(**{**dataclasses.asdict(PARAMS), "r_a": 0.2, "k_t": 0.5,
                             "eps_m": 0.0, "v_min": -1.0})
    part, v = validate_scenario(RECT, [], bad)
    assert part is None
    assert set(conditions(v)) == {"Parameters"}
    m = messages(v)
    for text in ("r_a = 0.2 must be > r_s = 0.25", "k_t = 0.5 must be ≥ 1",
                 "eps_m = 0.0 must be in [1e-12, 1]", "v_min = -1.0 must be ≥ 0"):
        assert f"Parameters invalid: {text}" in m


def test_check_scenario_raises_a_readable_multi_violation_error():
    p = dataclasses.replace(PARAMS, v=2.5)
    pos = np.array([[5.0, 0.0], [5.2, 0.0], [5.0, 4.95]])
    with pytest.raises(ScenarioError) as ei:
        check_scenario(RECT, [Obstacle((10.0, 0.0), 0.9, apex_distance=1.5)], p, pos)
    e = ei.value
    assert isinstance(e, UserError)
    lines = str(e).splitlines()
    assert lines[0] == ("scenario rejected: 6 violations (Constraint1, pothk, Constraint3 ×2, "
                        "Assumption1 ×2)")
    assert len(lines) == 1 + len(e.violations) == 7
    assert lines[1] == "  Constraint1 violated: v + v'_max = 4.0 > v_max = 3.5 (v = 2.5, " \
        "v'_max = 1.5)"


def test_positions_shape_is_checked():
    with pytest.raises(ValueError, match=r"shape \(M, 2\)"):
        validate_scenario(RECT, [], PARAMS, np.zeros((3, 3)))


def test_assumption1_obstacle_overlaps_are_capped_and_nan_reported():
    ob = [Obstacle((10.0, 0.0), 0.9)]
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)  # 0.58 m apart: no robot pair overlaps
    ring = np.array([10.0, 0.0]) + 1.1 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    pos = np.vstack([ring, [[np.nan, 1.0]]])
    _, v = validate_scenario(RECT, ob, PARAMS, pos)
    m = [x.message for x in v if "obstacle #1" in x.message or "more" in x.message]
    assert m[-1] == "Assumption1 violated: … and 2 more robot–obstacle overlaps"
    assert len(m) == MAX_LISTED + 1
    assert "Assumption1 violated: robot 12 position (nan, 1.0) is not a finite point" in \
        messages(v)
