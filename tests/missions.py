"""Mission files for the tests, in one place (tests and benchmarks import them from here).

* :data:`COMPACT_12` (``data/missions/compact_12.toml``) — 12 vehicles in a 10 m wide tube,
  slots 2.5 m apart: sized for the *lag-only* budget δ ≈ 0.7 m that the agent and preflight
  unit tests compute themselves (it is refused by the full budget of a real run, which needs
  ≈ 1.6 m on PX4 SITL-like estimates);
* :data:`STRAIGHT` — a template (``length``, ``positions``, ``on_complete``): a 20 m wide tube
  without obstacles, sized for the full budget;
* :func:`straight_mission` fills it in (with a heading and extra ``[mission]`` lines);
* :data:`NARROWING` + :data:`MISSION_TABLE` — a small narrowing tube and a minimal
  ``[mission]`` table, for the mission-file parser tests;
* :func:`grid_mission` — ``count`` vehicles on a grid, one obstacle, sized for ``seconds`` of
  tube flight (the fleet benchmark);
* :func:`write_mission` writes a text to ``tmp_path`` and loads it.

The shipped missions (``configs/mock_fleet.toml``, ``configs/px4_sitl_3.toml``) are read from
``configs/`` by the tests that are about them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from vtube_fleet.config.mission import Mission, load_mission

ROOT = Path(__file__).resolve().parents[1]
MOCK_FLEET = ROOT / "configs" / "mock_fleet.toml"
PX4_SITL_3 = ROOT / "configs" / "px4_sitl_3.toml"

#: path and text of the 12-vehicle fixture (``tests/data/missions/compact_12.toml``)
COMPACT_12_PATH = Path(__file__).parent / "data" / "missions" / "compact_12.toml"
COMPACT_12 = COMPACT_12_PATH.read_text()

#: The vehicles, controller and origin the generated missions share (:data:`STRAIGHT`,
#: :func:`grid_mission`); ``{positions}`` to fill in, then the rest of ``[mission]``.
FLEET_BLOCK = """[robots]
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
"""

STRAIGHT = """
[tube]
p_h0 = [0.0, 10.0]
p_h1 = [{length}, 10.0]
p_r0 = [0.0, -10.0]
p_r1 = [{length}, -10.0]

""" + FLEET_BLOCK + """heading_deg = {heading_deg}
altitude_m = 3.0
climb_speed_m_s = 1.5
on_complete = "{on_complete}"
mission_timeout_s = 120.0
{extra}"""

NARROWING = """
[tube]
p_h0 = [0.0, 5.0]
p_h1 = [19.0, 5.5]
p_r0 = [0.0, -5.0]
p_r1 = [19.0, -5.5]

[robots]
r_s = 0.3
r_a = 1.0
v_min = 0.3
v_max = 1.6
positions = [[2.0, 0.0], [2.0, 2.5]]

[controller]
v = 1.0
v_max_prime = 0.5
"""

MISSION_TABLE = """
[mission]
origin_lat_deg = 47.397742
origin_lon_deg = 8.545594
origin_alt_m = 488.0
heading_deg = 30.0
altitude_m = 3.0
"""


#: A route of two segments: ``{first}`` m along x, a bend of ``{bend_deg}``° to the left, then
#: ``{second}`` m, 20 m wide (half_width 10; the mitre at the bend); the vehicles of
#: :data:`FLEET_BLOCK` in ``{positions}``; ``{extra}``: more ``[mission]`` lines.
ROUTE_2 = """
[route]
[[route.waypoints]]
position = [0.0, 0.0]
half_width = 10.0

[[route.waypoints]]
position = [{first}, 0.0]
half_width = 10.0

[[route.waypoints]]
position = [{end_x}, {end_y}]
half_width = 10.0

""" + FLEET_BLOCK + """heading_deg = {heading_deg}
altitude_m = 3.0
climb_speed_m_s = 1.5
on_complete = "land"
mission_timeout_s = 150.0
{extra}"""


def route_mission(first: float, bend_deg: float, second: float,
                  positions: list[list[float]], *, heading_deg: float = 20.0,
                  extra: str = "") -> str:
    """:data:`ROUTE_2` filled in."""
    a = math.radians(bend_deg)
    return ROUTE_2.format(first=first, end_x=first + second * math.cos(a),
                          end_y=second * math.sin(a), positions=positions,
                          heading_deg=heading_deg, extra=extra)


def straight_mission(length: float, positions: list[list[float]], *,
                     heading_deg: float = 20.0, on_complete: str = "land",
                     extra: str = "") -> str:
    """:data:`STRAIGHT` filled in; ``extra``: more ``[mission]`` lines."""
    return STRAIGHT.format(length=length, positions=positions, heading_deg=heading_deg,
                           on_complete=on_complete, extra=extra)


def grid_mission(count: int, rate_hz: float, seconds: float, spacing: float = 2.5) -> str:
    """``count`` vehicles on a grid (10 columns from 20 on) ``spacing`` m apart, a 0.5 m
    obstacle on the axis, a tube long enough for ``seconds`` of flight at ~1.2 m/s."""
    cols = 10 if count >= 20 else max(1, min(count, 4))
    rows = math.ceil(count / cols)
    width = (cols - 1) * spacing + 2 * 2.5
    length = rows * spacing + 2.0 + 15.0 + seconds * 1.2
    positions = []
    for k in range(count):
        i, j = divmod(k, cols)
        positions.append([1.5 + i * spacing, -width / 2 + 2.5 + j * spacing])
    half = width / 2
    ob_x = rows * spacing + 12.0
    return f"""
[tube]
p_h0 = [0.0, {half}]
p_h1 = [{length}, {half + 0.5}]
p_r0 = [0.0, {-half}]
p_r1 = [{length}, {-half - 0.5}]

[[obstacles]]
center = [{ob_x}, 0.0]
radius = 0.5

{FLEET_BLOCK.format(positions=json.dumps(positions))}heading_deg = 0.0
altitude_m = 3.0
rate_hz = {rate_hz}
climb_speed_m_s = 1.5
connect_timeout_s = 60.0
ready_timeout_s = 90.0
arm_timeout_s = 60.0
takeoff_timeout_s = 90.0
mission_timeout_s = {seconds + 60.0}
"""


def write_mission(tmp_path: Path, text: str, name: str = "mission.toml") -> Mission:
    """Write ``text`` as ``tmp_path/name`` and load it as a mission."""
    p = tmp_path / name
    p.write_text(text)
    return load_mission(p)


def compact_12() -> Mission:
    """:data:`COMPACT_12` as a Mission."""
    return load_mission(COMPACT_12_PATH)
