"""Mission files for the tests, in one place (tests and benchmarks import them from here).

* :data:`COMPACT_12` — 12 vehicles in a 10 m wide tube, slots 2.5 m apart: sized for the
  *lag-only* budget δ ≈ 0.7 m that the agent and preflight unit tests compute themselves (it is
  refused by the full budget of a real run, which needs ≈ 1.6 m on PX4 SITL-like estimates);
* :data:`STRAIGHT` — a template (``length``, ``positions``, ``on_complete``): a 20 m wide tube
  without obstacles, sized for the full budget;
* :func:`write_mission` writes a text to ``tmp_path`` and loads it.

The shipped missions (``configs/mock_fleet.toml``, ``configs/px4_sitl_3.toml``) are read from
``configs/`` by the tests that are about them.
"""

from __future__ import annotations

from pathlib import Path

from vtube_fleet.fleet.mission import Mission, load_mission

ROOT = Path(__file__).resolve().parents[1]
MOCK_FLEET = ROOT / "configs" / "mock_fleet.toml"
PX4_SITL_3 = ROOT / "configs" / "px4_sitl_3.toml"

COMPACT_12 = """# 12 vehicles, one obstacle, sized for the lag-only budget (tests/missions.py)
[tube]
p_h0 = [0.0, 5.0]      # left leg (y > 0 is left of the direction of flight)
p_h1 = [19.0, 5.5]
p_r0 = [0.0, -5.0]     # right leg
p_r1 = [19.0, -5.5]

[[obstacles]]
center = [12.0, 0.0]
radius = 0.5           # a pole

[robots]
model = "single_integrator"
r_s = 0.3              # quadrotor body radius incl. propellers
r_a = 1.0              # avoidance radius (the pair barrier acts from r_s + r_a down to 2 r_s)
v_min = 0.3
v_max = 1.6
grid = { origin = [1.5, -3.75], rows = 3, cols = 4, spacing = 2.5 }

[controller]
v = 1.0                # cruise speed along the tube
v_max_prime = 0.5      # authority of the avoidance terms; Constraint1: v ± v'_max in [v_min, v_max]

[mission]
origin_lat_deg = 47.397742   # PX4 SIH default location
origin_lon_deg = 8.545594
origin_alt_m = 488.0         # ground level AMSL at the anchor
heading_deg = 0.0            # tube x axis points north
altitude_m = 3.0             # flight height above origin_alt_m
rate_hz = 20.0
after_exit = "continue"
on_complete = "land"
climb_speed_m_s = 1.5
connect_timeout_s = 15.0
ready_timeout_s = 30.0
arm_timeout_s = 20.0
takeoff_timeout_s = 40.0
mission_timeout_s = 180.0
land_timeout_s = 60.0
lost_after_s = 1.0
"""

STRAIGHT = """
[tube]
p_h0 = [0.0, 10.0]
p_h1 = [{length}, 10.0]
p_r0 = [0.0, -10.0]
p_r1 = [{length}, -10.0]

[robots]
r_s = 0.3
r_a = 1.0
v_min = 0.3
v_max = 1.6
positions = {positions}

[controller]
v = 1.0
v_max_prime = 0.5

[mission]
origin_lat_deg = 47.397742
origin_lon_deg = 8.545594
origin_alt_m = 488.0
heading_deg = 20.0
altitude_m = 3.0
climb_speed_m_s = 1.5
on_complete = "{on_complete}"
mission_timeout_s = 120.0
"""


def write_mission(tmp_path: Path, text: str, name: str = "mission.toml") -> Mission:
    """Write ``text`` as ``tmp_path/name`` and load it as a mission."""
    p = tmp_path / name
    p.write_text(text)
    return load_mission(p)


def compact_12() -> Mission:
    """:data:`COMPACT_12` as a Mission (no file needed: written to a temporary name)."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        return write_mission(Path(d), COMPACT_12, "compact_12.toml")
