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
    binding_constraints,
    check_scenario,
    further_failures,
    nearest_fixes,
    validate_route,
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


# ----------------------------------------------------------------------------------------------
# Infeasible: what binds and the nearest fixes; `check` of scenario and mission files
# ----------------------------------------------------------------------------------------------

# Two obstacles too close along n_c for the default apex distance 1.3 h_min: the tube between
# obstacle #1's base and obstacle #2's apex is 0.7 m < 2 r_a = 1 m.
DENSE_TUBE = Trapezoid((0.0, 6.0), (22.0, 5.0), (0.0, -6.0), (22.0, -5.0))
DENSE = (Obstacle((8.0, 0.5), 0.9), Obstacle((12.0, -0.5), 0.9))
DENSE_ROBOTS = np.array([(1.0 + i, -3.0 + j) for i in range(3) for j in range(7)], float)

DENSE_TOML = """
[tube]
p_h0 = [0.0, 6.0]
p_h1 = [22.0, 5.0]
p_r0 = [0.0, -6.0]
p_r1 = [22.0, -5.0]
{partition}
[[obstacles]]
center = [8.0, 0.5]
radius = 0.9

[[obstacles]]
center = [12.0, -0.5]
radius = 0.9

[robots]
r_s = 0.25
r_a = 0.5
v_min = 0.5
v_max = 3.5
grid = {{ origin = [1.0, -3.0], rows = 3, cols = 7, spacing = 1.0 }}

[controller]
v = 2.0
v_max_prime = 1.5
"""

# The authors' published first simulation (issue 11): triangles about O in their code, about O'
# here, so obstacle #3's Remark-5 apex cannot be placed.
AUTHORS_TUBE = Trapezoid((-5.0, 10.0), (35.0, 4.0), (-5.0, -10.0), (35.0, -4.0))
AUTHORS = tuple(Obstacle(c, 0.9, f * 0.9) for c, f in
                zip([(6.0, -4.0), (13.5, 3.0), (20.0, -2.0), (27.0, 2.0), (33.0, 0.0)],
                    [3, 5, 4, 5, 3], strict=True))
AUTHORS_ROBOTS = grid_positions((-4.0, -7.0), 8, 15, 1.0)
AUTHORS_PARAMS = dataclasses.replace(PARAMS, k_t=2.5)


def test_binding_constraints_name_tube_condition_and_amount():
    lines = binding_constraints(DENSE_TUBE, DENSE, PARAMS, DENSE_ROBOTS)
    assert lines == ["the tube before obstacle #2: Assumption 3' length > 2 r_a, violated by "
                     "0.3 m"]
    lines = binding_constraints(AUTHORS_TUBE, AUTHORS, AUTHORS_PARAMS, AUTHORS_ROBOTS)
    assert len(lines) == 1 and lines[0].startswith("obstacle #3 at (20.0, -2.0)")
    assert "Assumption 3' fails: L ∩ R is not empty (area 0.012 m²" in lines[0]


def test_nearest_fixes_are_feasible_and_nearest():
    _, v = validate_scenario(DENSE_TUBE, DENSE, PARAMS, DENSE_ROBOTS)
    assert conditions(v) == ["Assumption3'"]
    fixes = {f.parameter: f for f in nearest_fixes(DENSE_TUBE, DENSE, PARAMS, DENSE_ROBOTS)}
    assert set(fixes) >= {"apex_distance", "r_a", "obstacle #2 along n_c"}
    # each fix alone makes it feasible ...
    r_a = fixes["r_a"].value
    assert fixes["r_a"].text == f"r_a ≤ {r_a:.2f} m (now 0.5 m)"
    assert not validate_scenario(DENSE_TUBE, DENSE, dataclasses.replace(PARAMS, r_a=r_a),
                                 DENSE_ROBOTS)[1]
    move = fixes["obstacle #2 along n_c"].value
    assert 0.3 <= move <= 0.32  # the 0.3 m missing, rounded up to centimetres
    assert "obstacles #1 and #2 need 0.31 m more between them" in fixes[
        "obstacle #2 along n_c"].text

    def moved(d: float) -> tuple[Obstacle, ...]:
        return (DENSE[0], Obstacle(DENSE[1].center + [d, 0.0], 0.9))

    assert not validate_scenario(DENSE_TUBE, moved(move), PARAMS, DENSE_ROBOTS)[1]
    # ... and a little less does not: they are the nearest
    assert validate_scenario(DENSE_TUBE, moved(move - 0.02), PARAMS, DENSE_ROBOTS)[1]
    assert validate_scenario(DENSE_TUBE, DENSE, dataclasses.replace(PARAMS, r_a=r_a + 0.02),
                             DENSE_ROBOTS)[1]
    # a feasible scenario needs no fix
    assert nearest_fixes(PAPER_TUBE, PAPER_OBSTACLES, PARAMS, PAPER_ROBOTS) == []


def test_authors_geometry_fix_is_computed():
    fixes = nearest_fixes(AUTHORS_TUBE, AUTHORS, AUTHORS_PARAMS, AUTHORS_ROBOTS)
    by = {f.parameter: f for f in fixes}
    assert "r_a" in by and "apex_distance" not in by  # no joint h helps (issue 11)
    assert not validate_scenario(AUTHORS_TUBE, AUTHORS,
                                 dataclasses.replace(AUTHORS_PARAMS, r_a=by["r_a"].value),
                                 AUTHORS_ROBOTS)[1]


def test_nothing_to_fix_outside_the_partition():
    """Constraint1 is not fixed by moving obstacles: no fixes are proposed."""
    bad = dataclasses.replace(PARAMS, v=2.5)
    assert nearest_fixes(DENSE_TUBE, DENSE, bad, DENSE_ROBOTS) == []


def test_check_scenario_file_prints_binding_and_fixes(tmp_path, capsys):
    from vtube_fleet.cli import main

    cfg = tmp_path / "dense.toml"
    cfg.write_text(DENSE_TOML.format(partition=""))
    assert main(["check", str(cfg)]) == 2
    out = capsys.readouterr().out
    assert "INVALID: 1 violation:" in out
    assert "binding:\n  the tube before obstacle #2: Assumption 3' length > 2 r_a, violated " \
           "by 0.3 m" in out
    assert "nearest fixes (each alone, the rest unchanged):" in out
    assert 'apex_distance = "auto"' in out and "m downstream" in out

    cfg.write_text(DENSE_TOML.format(partition='[partition]\napex_distance = "auto"\n'))
    assert main(["check", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert "h = 1.6" in out and "(auto)" in out
    assert "apex distances chosen (auto): #1 h = " in out
    assert out.rstrip().endswith("valid")


# Two obstacles that each block a 4 m wide tube (issue 11 / audit 11-12 gap 6): the
# construction stops at #1; strict `check` also names #2.
TWO_BLOCKING_TOML = """
[tube]
p_h0 = [0.0, 2.0]
p_h1 = [24.0, 2.0]
p_r0 = [0.0, -2.0]
p_r1 = [24.0, -2.0]

[[obstacles]]
center = [8.0, 0.0]
radius = 0.9

[[obstacles]]
center = [16.0, 0.0]
radius = 0.9

[robots]
r_s = 0.25
r_a = 0.5
v_min = 0.5
v_max = 3.5
grid = { origin = [1.0, -1.0], rows = 2, cols = 3, spacing = 1.0 }

[controller]
v = 2.0
v_max_prime = 1.5
"""


def test_check_names_every_failing_obstacle_not_only_the_first(tmp_path, capsys):
    from vtube_fleet.cli import main

    cfg = tmp_path / "two.toml"
    cfg.write_text(TWO_BLOCKING_TOML)
    assert main(["check", str(cfg)]) == 2
    out = capsys.readouterr().out
    blocks = ("the obstacle blocks the tube: neither side passage is valid (left: inverted: "
              "the triangle crosses the parent's left leg by 0.089 m; right: inverted: the "
              "triangle crosses the parent's right leg by 0.089 m)")
    verdict = out[out.index("INVALID"):].splitlines()
    assert verdict[:4] == [
        "INVALID: 1 violation:",  # the first line and the first failure stay as they were
        f"  [Partition] Partition failed: obstacle #1 at (8.0, 0.0) r_o=0.9: {blocks}",
        "further obstacles that fail (the construction continued without the failing ones "
        "above):",
        f"  obstacle #2 at (16.0, 0.0) r_o=0.9: {blocks}",
    ]
    assert verdict[4] == "nearest fixes (each alone, the rest unchanged):"
    assert 'apex_distance = "auto"' in verdict[5]


def test_further_failures_continue_the_construction_without_the_failing_ones():
    """The authors' geometry: #3 fails first (reported by validate_scenario); without it the
    construction reaches #5, which blocks the tube; #1, #2 and #4 split. A feasible scenario
    and one failing for no single obstacle give nothing."""
    got = further_failures(AUTHORS_TUBE, AUTHORS, AUTHORS_PARAMS, AUTHORS_ROBOTS)
    assert len(got) == 1
    assert got[0].startswith("obstacle #5 at (33.0, 0.0) r_o=0.9: the obstacle blocks the tube")
    assert further_failures(PAPER_TUBE, PAPER_OBSTACLES, PARAMS, PAPER_ROBOTS) == []
    narrow = Trapezoid((0.0, 2.0), (20.0, 2.0), (0.0, -2.0), (20.0, -2.0))
    assert further_failures(narrow, [Obstacle((12.0, 0.0), 0.9)], PARAMS) == []


def test_scenario_apex_distance_keys(tmp_path):
    from vtube_fleet.config.scenario import load_scenario
    from vtube_fleet.errors import ConfigError

    cfg = tmp_path / "s.toml"
    cfg.write_text(DENSE_TOML.format(partition='[partition]\napex_distance = "auto"\n'))
    assert [o.apex_distance for o in load_scenario(cfg).obstacles] == ["auto", "auto"]
    text = DENSE_TOML.format(partition="").replace(
        "center = [12.0, -0.5]\n", 'center = [12.0, -0.5]\napex_distance = "auto"\n')
    cfg.write_text(text)
    assert [o.apex_distance for o in load_scenario(cfg).obstacles] == [None, "auto"]
    cfg.write_text(DENSE_TOML.format(partition='[partition]\napex_distance = "best"\n'))
    with pytest.raises(ConfigError, match=r'\[partition\].apex_distance: expected one of '
                                          r'"auto", "default", got "best"'):
        load_scenario(cfg)


def test_check_mission_uses_the_flown_radii(tmp_path, capsys):
    """`check MISSION` (issue 11 item 3): the budget's r_s', r_a', the fleet's partition."""
    from missions import MOCK_FLEET

    from vtube_fleet.check import check_file
    from vtube_fleet.cli import main
    from vtube_fleet.config.mission import load_mission
    from vtube_fleet.fleet.budget import LinkMeasurement, mission_budget
    from vtube_fleet.fleet.flight_plan import FlightPlan

    rep = check_file(MOCK_FLEET, latency_s=0.03, accuracy_m=0.1)
    mission = load_mission(MOCK_FLEET)
    budget = mission_budget(mission, LinkMeasurement(0.03, 0.0, 0.1))
    assert rep.kind == "mission" and rep.ok
    assert rep.budget.delta_m == budget.delta_m > 0
    assert rep.params.r_s == mission.scenario.controller.r_s + budget.delta_m
    assert rep.params.r_a == mission.scenario.controller.r_a + budget.delta_m
    fleet = FlightPlan.for_mission(mission, budget.inflate(mission.scenario.controller))
    assert [t.polygon().tolist() for t in rep.partition.sub_tubes] == \
        [t.polygon().tolist() for t in fleet.route.sub_tubes]

    assert main(["check", str(MOCK_FLEET)]) == 0
    out = capsys.readouterr().out
    assert "mission: 12 vehicles at 20 Hz; safety budget δ = " in out
    assert "flown: r_s' = " in out and "\nvalid\nmargin: valid up to L ≤ " in out
    # by default L and σ are what real PX4 SITL measured, so check predicts run
    assert "σ = 0.3 m (default: what PX4 SITL reports" in out
    assert "measured latency 0.124 s (default: what PX4 SITL measures" in out
    # a link the budget refuses (L > max_latency_s)
    assert main(["check", str(MOCK_FLEET), "--latency-s", "0.5"]) == 2
    cap = capsys.readouterr()
    assert "[Budget] Budget refused: link latency L = 550 ms" in cap.out
    assert cap.err.startswith(f"error: {MOCK_FLEET}: invalid mission: [Budget] Budget refused: "
                              "link latency L = 550 ms") and cap.err.count("\n") == 1
    # the options are for missions only
    assert main(["check", str(MOCK_FLEET.parent / "paper.toml"), "--latency-s", "0.1"]) == 2
    assert "apply to mission files" in capsys.readouterr().err


def test_check_mission_with_auto_apex_flies_the_fleet_partition(tmp_path):
    """A mission with "auto" apex distances: check prints the partition the fleet builds
    (the same planner input in every process: the start slots)."""
    from missions import MISSION_TABLE, NARROWING, write_mission

    from vtube_fleet.check import check_file
    from vtube_fleet.fleet.budget import LinkMeasurement, mission_budget
    from vtube_fleet.fleet.flight_plan import FlightPlan

    text = NARROWING.replace("[robots]", "[partition]\napex_distance = \"auto\"\n\n"
                             "[[obstacles]]\ncenter = [13.0, 0.5]\nradius = 0.3\n\n[robots]")
    text = text.replace("positions = [[2.0, 0.0], [2.0, 2.5]]",
                        "positions = [[2.0, -2.5], [2.0, 2.5]]")
    mission = write_mission(tmp_path, text + MISSION_TABLE)
    rep = check_file(tmp_path / "mission.toml", latency_s=0.0, accuracy_m=0.0)  # (RTK-like)
    assert rep.partition is not None and rep.partition.apex is not None, rep.violations
    flown = mission_budget(mission, LinkMeasurement(0.0, 0.0, 0.0)).inflate(
        mission.scenario.controller)
    fleet = FlightPlan.for_mission(mission, flown)
    assert rep.partition.apex.h == fleet.route.segments[0].partition.apex.h
    assert any("(auto)" in line for line in rep.lines)


def test_k_t_and_lateral_fixes():
    """An obstacle blocking a narrowing tube (neither side passage valid at k_t = 2.5): the
    largest k_t that works, and the lateral moves either way."""
    tube = Trapezoid((0.0, 5.0), (22.0, 3.0), (0.0, -5.0), (22.0, -3.0))
    params = dataclasses.replace(PARAMS, k_t=2.5)
    obs = (Obstacle((12.0, 0.5), 0.9),)
    _, v = validate_scenario(tube, obs, params, DENSE_ROBOTS)
    assert conditions(v) == ["Partition"] and "blocks the tube" in v[0].message
    by = {f.parameter: f for f in nearest_fixes(tube, obs, params, DENSE_ROBOTS)}
    k = by["k_t"].value
    assert by["k_t"].text == f"k_t ≤ {k:.2f} (now 2.5)" and 1.0 < k < 2.5
    assert not validate_scenario(tube, obs, dataclasses.replace(params, k_t=k),
                                 DENSE_ROBOTS)[1]
    assert validate_scenario(tube, obs, dataclasses.replace(params, k_t=k + 0.02),
                             DENSE_ROBOTS)[1]
    lateral = [f for f in nearest_fixes(tube, obs, params, DENSE_ROBOTS)
               if f.parameter == "obstacle #1 lateral"]
    assert {f.text.split(" m ")[1] for f in lateral} == {"towards the left leg",
                                                          "towards the right leg"}
    for f in lateral:  # value: the signed move along m (+: towards the right leg)
        moved = (Obstacle(obs[0].center + tube.m * f.value, 0.9),)
        assert not validate_scenario(tube, moved, params, DENSE_ROBOTS)[1]


TAPERED_TWO_OBSTACLES = """
[tube]
p_h0 = [0.0, 18.0]
p_h1 = [50.0, 13.0]
p_r0 = [0.0, -18.0]
p_r1 = [50.0, -13.0]

[partition]
apex_distance = "auto"

[[obstacles]]
center = [20.0, 0.5]
radius = 0.6

[[obstacles]]
center = [36.0, -2.0]
radius = 0.5

[robots]
r_s = 0.3
r_a = 1.0
v_min = 0.3
v_max = 1.8
positions = [[3.0, -9.0], [3.0, -4.5], [3.0, 0.0], [3.0, 4.5], [3.0, 9.0]]

[controller]
v = 1.2
v_max_prime = 0.5
"""


def test_auto_apex_keeps_start_slots_out_of_the_apex_look_ahead(tmp_path):
    """The planner scores the apex look-ahead too (Assumption 1): with PX4 SITL's budget
    (r_s' ≈ 2 m) the longest triangle for obstacle #1 (h ≈ 12.7 m, what the planner chose
    before) puts the middle slot 1.4 m from the side tube it would fly, and the mission was
    refused; the plan must keep every slot flyable."""
    from missions import MISSION_TABLE, write_mission

    from vtube_fleet.check import check_file
    from vtube_fleet.fleet.budget import LinkMeasurement, mission_budget
    from vtube_fleet.fleet.flight_plan import FlightPlan
    from vtube_fleet.fleet.margin import lookahead_violations

    mission = write_mission(tmp_path, TAPERED_TWO_OBSTACLES + MISSION_TABLE)
    rep = check_file(tmp_path / "mission.toml", latency_s=0.1, accuracy_m=0.31)
    assert rep.ok, messages(rep.violations)
    flown = mission_budget(mission, LinkMeasurement(0.1, 0.0, 0.31)).inflate(
        mission.scenario.controller)
    assert flown.r_s > 2.0
    plan = FlightPlan.for_mission(mission, flown)
    assert lookahead_violations(plan.route, mission.slots) == []
    assert [t.h for t in plan.route.triangles] == [t.h for t in rep.partition.triangles]


def test_an_obstacle_outside_the_tube_is_refused_not_ignored() -> None:
    """Found: check refused (exit 2) an obstacle whose O' misses the tube with the lenient
    partition's own words, "…; ignored". Refused, it says what to do; a route's segments too."""
    from vtube_fleet.core.route import Corridor, RouteGeometry, Waypoint

    far = Obstacle((10.0, 30.0), 0.5)
    _, v = validate_scenario(RECT, [far], PARAMS)
    corridor = Corridor(RouteGeometry.from_waypoints(
        [Waypoint(np.array(p, float), 5.0) for p in [(0, 0), (20, 0), (40, 10)]]), (far,))
    for msgs in ([x.message for x in v],
                 [x.message for x in validate_route(corridor, PARAMS).violations]):
        (msg,) = [m for m in msgs if "lies outside the tube" in m]
        assert "ignored" not in msg
        assert msg.endswith("m away from T: move it into the tube or leave it out"), msg
