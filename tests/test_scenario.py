"""Scenario TOML parsing: the shipped configs, grid order, defaults and every error path."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest

from vtube_fleet.config.scenario import grid_positions, load_scenario, parse_scenario
from vtube_fleet.errors import ConfigError, UserError

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "paper.toml"
ROBOTARIUM = ROOT / "configs" / "robotarium.toml"


@pytest.fixture
def paper_data() -> dict:
    with open(PAPER, "rb") as fh:
        return tomllib.load(fh)


def test_paper_config_matches_the_paper() -> None:
    sc = load_scenario(PAPER)
    r, c = sc.robots, sc.controller
    assert r.count == 120 and r.model == "single_integrator"
    assert (r.r_s, r.r_a, r.v_min, r.v_max) == (0.25, 0.5, 0.5, 3.5)
    assert (c.v, c.v_max_prime, c.k2, c.k3, c.k_t) == (2.0, 1.5, 1.0, 1.0, 1.5)
    assert (c.eps_m, c.eps_t, c.eps_s, c.eps_0) == (1e-6, 1e-6, 1e-6, 0.01)
    assert (c.r_s, c.r_a, c.v_min, c.v_max) == (0.25, 0.5, 0.5, 3.5)  # merged from [robots]
    assert len(sc.obstacles) == 5 and all(o.radius == 0.9 for o in sc.obstacles)
    assert sc.sim.dt == 0.001
    assert sc.source == str(PAPER)
    assert r.headings is None and r.nid_distance is None


def test_robotarium_config_matches_the_experiment() -> None:
    sc = load_scenario(ROBOTARIUM)
    r, c = sc.robots, sc.controller
    assert r.count == 7 and r.model == "unicycle"
    assert (r.r_s, r.r_a, r.v_min, r.v_max, r.nid_distance) == (0.075, 0.125, 0.01, 0.09, 0.02)
    assert (c.v, c.v_max_prime) == (0.06, 0.03)
    assert len(sc.obstacles) == 2 and all(o.radius == 0.07 for o in sc.obstacles)
    assert r.headings is not None and r.headings.shape == (7,)
    # everything inside the 3.2 m x 2 m arena
    pts = np.concatenate([sc.tube.polygon(), r.positions])
    assert np.all(np.abs(pts[:, 0]) <= 1.6) and np.all(np.abs(pts[:, 1]) <= 1.0)


def test_grid_order_is_row_major(paper_data: dict) -> None:
    paper_data["robots"]["grid"] = {"origin": [1.0, -2.0], "rows": 3, "cols": 4, "spacing": 0.5}
    pos = parse_scenario(paper_data, "x.toml").robots.positions
    assert pos.shape == (12, 2)
    for i in range(3):
        for j in range(4):
            np.testing.assert_allclose(pos[i * 4 + j], [1.0 + 0.5 * i, -2.0 + 0.5 * j])
    np.testing.assert_allclose(grid_positions((0.0, 0.0), 2, 2, 1.0),
                               [[0, 0], [0, 1], [1, 0], [1, 1]])


def test_explicit_positions_and_defaults(paper_data: dict) -> None:
    d = paper_data
    del d["robots"]["grid"]
    d["robots"]["positions"] = [[1.0, 0.0], [2.0, 1.0], [3, -1]]
    d["controller"] = {"v": 2.0, "v_max_prime": 1.5}
    del d["sim"]
    sc = parse_scenario(d, "x.toml")
    np.testing.assert_allclose(sc.robots.positions, [[1, 0], [2, 1], [3, -1]])
    c = sc.controller
    assert (c.k2, c.k3, c.k_t, c.eps_m, c.eps_t, c.eps_s, c.eps_0) == (
        1.0, 1.0, 1.5, 1e-6, 1e-6, 1e-6, 0.01)
    assert sc.sim.dt == 0.001 and sc.sim.duration == 60.0 and sc.sim.record_every is None
    assert not sc.robots.positions.flags.writeable


def test_unicycle_headings(paper_data: dict) -> None:
    d = paper_data
    d["robots"].update(model="unicycle", nid_distance=0.05)
    sc = parse_scenario(d, "x.toml")
    # default: facing n_c (+x here)
    np.testing.assert_allclose(sc.robots.headings, np.zeros(120), atol=1e-12)
    cp = sc.robots.control_points()
    np.testing.assert_allclose(cp - sc.robots.positions, np.tile([0.05, 0.0], (120, 1)),
                               atol=1e-12)
    d["robots"]["headings"] = 0.5
    np.testing.assert_allclose(parse_scenario(d, "x.toml").robots.headings, np.full(120, 0.5))
    d["robots"]["headings"] = [0.1 * i for i in range(120)]
    h = parse_scenario(d, "x.toml").robots.headings
    assert h[7] == pytest.approx(0.7)


def test_with_robots_keeps_the_first_n() -> None:
    sc = load_scenario(PAPER)
    sub = sc.with_robots(20)
    assert sub.robots.count == 20
    np.testing.assert_array_equal(sub.robots.positions, sc.robots.positions[:20])
    for bad in (0, 121, -1):
        with pytest.raises(ConfigError, match="--robots must be between 1 and 120"):
            sc.with_robots(bad)


def test_extra_sections(paper_data: dict) -> None:
    d = paper_data
    d["mission"] = {"altitude_m": 5.0}
    with pytest.raises(ConfigError, match=r"x.toml: \[mission\]: unknown key"):
        parse_scenario(d, "x.toml")
    sc = parse_scenario(d, "x.toml", extra_sections=("mission",))
    assert sc.extra == {"mission": {"altitude_m": 5.0}}
    assert parse_scenario(paper_data | {"mission": {}}, "x", ("mission",)).extra["mission"] == {}


def _set(d: dict, path: str, value: object) -> None:
    keys = path.split(".")
    for k in keys[:-1]:
        d = d[int(k)] if isinstance(d, list) else d[k]
    if value is _DELETE:
        del d[keys[-1]]
    else:
        d[keys[-1]] = value


_DELETE = object()

# (dotted path in the TOML document, new value, expected message fragment)
ERRORS = [
    ("foo", {"a": 1}, "paper.toml: [foo]: unknown key"),
    ("tube.p_x0", [0.0, 0.0], "paper.toml: [tube].p_x0: unknown key"),
    ("tube.p_h1", _DELETE, "paper.toml: [tube].p_h1: missing required key"),
    ("tube.p_h0", [0.0], "[tube].p_h0: expected a point [x, y] of two numbers, got [0.0]"),
    ("tube.p_h0", ["a", 1.0], "[tube].p_h0: expected a point [x, y]"),
    ("tube.p_h0", [float("nan"), 1.0], "[tube].p_h0: expected finite numbers"),
    ("tube.p_h1", [33.0, -9.0], "paper.toml: [tube]:"),  # legs cross: GeometryError text
    ("tube", [1, 2], "paper.toml: [tube]: expected a table"),
    ("robots", _DELETE, "paper.toml: [robots]: missing required table"),
    ("robots.r_s", "abc", 'paper.toml: [robots].r_s: expected a number, got "abc"'),
    ("robots.r_s", True, "[robots].r_s: expected a number, got true"),
    ("robots.r_s", -0.25, "[robots].r_s: must be > 0"),
    ("robots.r_a", 0.2, "[robots].r_a: r_a = 0.2 must be > r_s = 0.25"),
    ("robots.v_max", float("inf"), "[robots].v_max: expected a finite number, got inf"),
    ("robots.v_max", 0.4, "[robots].v_max: v_max = 0.4 must be > v_min = 0.5"),
    ("robots.v_min", _DELETE, "[robots].v_min: missing required key"),
    ("robots.model", "double_integrator", '[robots].model: expected one of "single_integrator"'),
    ("robots.speed", 2.0, "[robots].speed: unknown key"),
    ("robots.grid", _DELETE, "[robots].grid: missing required key (or positions)"),
    ("robots.positions", [[0.0, 0.0]], "[robots]: give either grid or positions, not both"),
    ("robots.grid.rows", 2.5, "[robots].grid.rows: expected an integer, got 2.5"),
    ("robots.grid.cols", 0, "[robots].grid.cols: must be >= 1, got 0"),
    ("robots.grid.spacing", "0.8", '[robots].grid.spacing: expected a number, got "0.8"'),
    ("robots.grid.origin", _DELETE, "[robots].grid.origin: missing required key"),
    ("robots.grid.step", 1.0, "[robots].grid.step: unknown key"),
    ("robots.grid", 5, "[robots].grid: expected a table, got 5"),
    ("robots.nid_distance", 0.1, '[robots].nid_distance: only allowed with model = "unicycle"'),
    ("robots.headings", 0.0, '[robots].headings: only allowed with model = "unicycle"'),
    ("obstacles.0.radius", _DELETE, "paper.toml: [[obstacles]][0].radius: missing required key"),
    ("obstacles.1.radius", 0.0, "[[obstacles]][1].radius: must be > 0"),
    ("obstacles.2.centre", [1.0, 2.0], "[[obstacles]][2].centre: unknown key"),
    ("obstacles.3.apex_distance", 0.5, "[[obstacles]][3].apex_distance: must exceed the radius"),
    ("obstacles", {"center": [1, 1]}, "[[obstacles]]: expected an array of tables"),
    ("controller.v", _DELETE, "paper.toml: [controller].v: missing required key"),
    ("controller.v", False, "[controller].v: expected a number, got false"),
    ("controller.k_t", "1.5", '[controller].k_t: expected a number, got "1.5"'),
    ("controller.eps_m", 2.0, "paper.toml: [controller]: eps_m = 2.0 must be in [1e-12, 1]"),
    ("controller.eps_0", -1.0, "[controller].eps_0: must be > 0"),
    ("controller.gain", 1.0, "[controller].gain: unknown key"),
    ("sim.dt", 0.0, "paper.toml: [sim].dt: must be >= 1e-06, got 0.0"),
    ("sim.duration", "long", '[sim].duration: expected a number, got "long"'),
    ("sim.record_every", 0, "[sim].record_every: must be >= 1, got 0"),
    ("sim.record_every", 2.0, "[sim].record_every: expected an integer"),
    ("sim.steps", 10, "[sim].steps: unknown key"),
]


@pytest.mark.parametrize(("path", "value", "message"), ERRORS, ids=[e[0] for e in ERRORS])
def test_each_error_names_file_and_key(paper_data: dict, path: str, value: object,
                                       message: str) -> None:
    d = copy.deepcopy(paper_data)
    _set(d, path, value)
    with pytest.raises(ConfigError) as info:
        parse_scenario(d, "paper.toml")
    assert message in str(info.value)
    assert "\n" not in str(info.value)
    assert isinstance(info.value, UserError)


def test_unicycle_errors(paper_data: dict) -> None:
    d = paper_data
    d["robots"]["model"] = "unicycle"
    with pytest.raises(ConfigError, match=r"\[robots\]\.nid_distance: missing required key"):
        parse_scenario(d, "paper.toml")
    d["robots"]["nid_distance"] = 0.02
    d["robots"]["headings"] = [0.0, 1.0]
    with pytest.raises(ConfigError, match=r"\[robots\]\.headings: expected a number or 120"):
        parse_scenario(d, "paper.toml")
    d["robots"]["headings"] = "north"
    with pytest.raises(ConfigError, match=r"\[robots\]\.headings: expected a number or an arr"):
        parse_scenario(d, "paper.toml")


def test_positions_errors(paper_data: dict) -> None:
    d = paper_data
    del d["robots"]["grid"]
    d["robots"]["positions"] = []
    with pytest.raises(ConfigError, match=r"\[robots\]\.positions: expected a non-empty array"):
        parse_scenario(d, "paper.toml")
    d["robots"]["positions"] = [[0.0, 0.0], [1.0]]
    with pytest.raises(ConfigError, match=r"\[robots\]\.positions\[1\]: expected a point"):
        parse_scenario(d, "paper.toml")


def test_file_errors(tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError, match="nope.toml: no such file"):
        load_scenario(missing)
    with pytest.raises(ConfigError, match="is a directory"):
        load_scenario(tmp_path)
    bad = tmp_path / "bad.toml"
    bad.write_text("[tube]\np_h0 = [0.0, 9.0]\np_h1 [1, 2]\n")
    with pytest.raises(ConfigError) as info:
        load_scenario(bad)
    msg = str(info.value)
    assert msg.startswith(f"{bad}: invalid TOML:") and "line" in msg and "\n" not in msg
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_scenario(binary)


def test_a_byte_order_mark_is_read_past(tmp_path: Path) -> None:
    """Found: a mission saved by a Windows editor (UTF-8 with a BOM) was refused 'invalid TOML:
    Invalid statement (at line 1, column 1)', naming nothing the user could see."""
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + (ROOT / "configs" / "paper.toml").read_bytes())
    assert load_scenario(path).robots.count == 120
