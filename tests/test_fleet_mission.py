"""Mission files: the scenario parser plus a strict [mission] table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from missions import MISSION_TABLE, NARROWING

from vtube_fleet.config.mission import load_mission, parse_mission_config
from vtube_fleet.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ("mock_fleet.toml", "px4_sitl_3.toml", "mock_fleet_rtk.toml")

BASE = NARROWING
MISSION = MISSION_TABLE


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "m.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("name", CONFIGS)
def test_shipped_configs_load(name: str) -> None:
    m = load_mission(ROOT / "configs" / name)
    assert m.count == m.slots.shape[0] >= 3
    assert m.config.rate_hz > 0
    geo = m.slot_geodetic()
    assert geo.shape == (m.count, 3)
    # the geodetic slots come back to the tube frame
    x, y, up = m.frame.geodetic_to_tube(geo[:, 0], geo[:, 1], geo[:, 2])
    np.testing.assert_allclose(np.stack([x, y], axis=-1), m.slots, atol=1e-6)
    np.testing.assert_allclose(up, 0.0, atol=1e-6)


def test_mock_fleet_config_size() -> None:
    m = load_mission(ROOT / "configs" / "mock_fleet.toml")
    assert m.count >= 12 and len(m.scenario.obstacles) >= 1
    m3 = load_mission(ROOT / "configs" / "px4_sitl_3.toml")
    assert m3.count == 3 and len(m3.scenario.obstacles) == 1


def test_defaults_and_frame(tmp_path: Path) -> None:
    m = load_mission(write(tmp_path, BASE + MISSION))
    c = m.config
    assert (c.rate_hz, c.after_exit, c.on_complete) == (20.0, "continue", "land")
    assert c.period_s == pytest.approx(0.05)
    assert c.altitude_amsl_m == pytest.approx(491.0)
    assert m.frame.heading_deg == 30.0
    assert m.with_vehicles(1).count == 1


def test_missing_mission_table(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"\[mission\]: missing required table"):
        load_mission(write(tmp_path, BASE))


@pytest.mark.parametrize(
    ("line", "pattern"),
    [
        ("rate_hz = -5", r"\[mission\]\.rate_hz: must be > 0, got -5"),
        ("rate_hz = true", r"\[mission\]\.rate_hz: expected a number, got true"),
        ('after_exit = "vanish"', r"\[mission\]\.after_exit: expected one of .*\"vanish\""),
        ('on_complete = "continue"', r"\[mission\]\.on_complete: expected one of"),
        ("speed = 3", r"\[mission\]\.speed: unknown key"),
        ("lost_after_s = 0.01", r"\[mission\]\.lost_after_s: must be at least one control "
                                r"period"),
        ("neighbour_max_age_s = 5.0", r"neighbour_max_age_s: must not exceed lost_after_s"),
        ("latency_s = -0.1", r"\[mission\]\.latency_s: must be >= 0"),
    ],
)
def test_bad_values_name_the_key(tmp_path: Path, line: str, pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern) as info:
        load_mission(write(tmp_path, BASE + MISSION + line + "\n"))
    assert "m.toml" in str(info.value)


def test_missing_required_key(tmp_path: Path) -> None:
    text = BASE + MISSION.replace("altitude_m = 3.0\n", "")
    with pytest.raises(ConfigError, match=r"\[mission\]\.altitude_m: missing required key"):
        load_mission(write(tmp_path, text))


def test_latitude_range() -> None:
    table = {"origin_lat_deg": 95.0, "origin_lon_deg": 0.0, "origin_alt_m": 0.0,
             "heading_deg": 0.0, "altitude_m": 3.0}
    with pytest.raises(ConfigError, match=r"origin_lat_deg: must be within \(-90, 90\)"):
        parse_mission_config(table, "x.toml")


def test_unicycle_rejected(tmp_path: Path) -> None:
    text = (BASE + MISSION).replace(
        "r_s = 0.3", 'model = "unicycle"\nnid_distance = 0.1\nr_s = 0.3')
    with pytest.raises(ConfigError, match=r"\[robots\]\.model: the fleet flies multicopters"):
        load_mission(write(tmp_path, text))


def test_scenario_errors_pass_through(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"\[robots\]\.r_s"):
        load_mission(write(tmp_path, (BASE + MISSION).replace("r_s = 0.3", 'r_s = "x"')))


def test_a_mission_far_from_its_anchor_is_refused(tmp_path: Path) -> None:
    """A tube reaching 20 km from the anchor (a sign or a unit wrong) is one error naming how
    far; 10 km is the bound (config/mission.MAX_EXTENT_M), a shipped-size tube passes."""
    from missions import straight_mission

    far = tmp_path / "far.toml"
    far.write_text(straight_mission(20_000.0, [[2.0, 0.0]]))
    with pytest.raises(ConfigError, match=r"the tube reaches 20\.0 km from the mission's "
                                          r"anchor .* within 10 km"):
        load_mission(far)
    near = tmp_path / "near.toml"
    near.write_text(straight_mission(9_000.0, [[2.0, 0.0]]))
    assert load_mission(near).scenario.geometry.segments[0].length == pytest.approx(9_000.0)
