"""Mission files: a scenario (tube, obstacles, robots = the vehicles' start slots, controller)
plus a ``[mission]`` table that anchors the paper's 2-D tube frame on the Earth and says how the
fleet flies it.

The scenario part is parsed by :func:`vtube_fleet.config.scenario.load_scenario` (the same
parser the simulator uses, with ``extra_sections=("mission",)``); this module parses
``[mission]`` as strictly: an unknown key, a wrong type or an impossible value raises
:class:`~vtube_fleet.errors.ConfigError` naming the file and the key, e.g.
``mission.toml: [mission].rate_hz: must be > 0, got -5``.

``[mission]`` keys (see ``docs/fleet.md``)::

    origin_lat_deg, origin_lon_deg   geodetic anchor of the tube frame (WGS84), required
    origin_alt_m                      AMSL altitude of the anchor (ground level), required
    heading_deg                       heading of the tube's x axis, clockwise from north, required
    altitude_m                        flight height above origin_alt_m, required
    rate_hz = 20                      control rate
    after_exit = "continue"           what a vehicle does past the finishing line:
                                      "continue" | "hold" | "land"
    on_complete = "land"              when every vehicle has exited: "land" | "hold"
    exit_clear_m = 3.0                distance flown past the finishing line before "hold"/"land"
    climb_speed_m_s = 1.0             offboard climb rate during take-off
    max_vertical_speed_m_s = 1.0      clamp of the altitude-hold term
    altitude_gain_1_s = 1.0           P gain of the altitude-hold term
    altitude_tolerance_m = 0.3        take-off is complete within this of the mission altitude
    connect_timeout_s = 15, ready_timeout_s = 30, arm_timeout_s = 20, takeoff_timeout_s = 40,
    mission_timeout_s = 600, land_timeout_s = 60          timeouts
    lost_after_s = 1.0                no telemetry for this long → the vehicle is LOST
    neighbour_max_age_s = 0.5         older neighbour states are not used as live positions
    lost_obstacle_margin_m = 0.5      a LOST vehicle becomes an obstacle of radius r_s + this
    tracking_dead_time_s = 0.3        PX4 velocity-tracking dead time (captures: 0.27-0.35 s)
    tracking_t63_s = 1.0              PX4 horizontal velocity time constant (captures: 0.8-1.2 s)
    latency_s                         L of the safety budget: position age + setpoint delay
                                      (default: measured round trip + latency_headroom_s)
    latency_headroom_s = 0.05         added to the measured L (in-flight jitter)
    max_latency_s = 0.25              refuse to fly above this L
    position_accuracy_m               σ of the safety budget (default: the worst accuracy the
                                      vehicles report before arming, ESTIMATOR_STATUS)
    accuracy_factor = 2.0             k: the estimate error budgeted is k σ
    max_position_accuracy_m = 1.0     wait (ready_timeout_s) until every vehicle reports at
                                      most this σ
    disturbance_residual_m_s = 0.25   D: estimate disturbance left after compensation
    compensate_estimate = true        send v_c + d̂ (fleet/compensation.py) instead of v_c
    safety_margin_m                   override the safety budget δ (default: computed)
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtube_fleet.config.scenario import Scenario, load_scenario
from vtube_fleet.errors import ConfigError
from vtube_fleet.frames import TubeFrame

__all__ = [
    "AFTER_EXIT",
    "ON_COMPLETE",
    "Mission",
    "MissionConfig",
    "load_mission",
    "parse_mission_config",
]

#: k: the estimate error budgeted is k × the reported 1-σ accuracy (real SITL: max 1.83 σ).
DEFAULT_ACCURACY_FACTOR = 2.0
#: D: the estimate disturbance left after compensation (m/s; docs/fleet.md).
DEFAULT_DISTURBANCE_M_S = 0.25

#: What a vehicle does once it has crossed the finishing line (Assumption 2).
AFTER_EXIT: tuple[str, ...] = ("continue", "hold", "land")
#: What every vehicle does once all have exited.
ON_COMPLETE: tuple[str, ...] = ("land", "hold")


@dataclass(frozen=True)
class MissionConfig:
    """The ``[mission]`` table (units in the names; see the module docstring)."""

    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float
    heading_deg: float
    altitude_m: float
    rate_hz: float = 20.0
    after_exit: str = "continue"
    on_complete: str = "land"
    exit_clear_m: float = 3.0
    climb_speed_m_s: float = 1.0
    max_vertical_speed_m_s: float = 1.0
    altitude_gain_1_s: float = 1.0
    altitude_tolerance_m: float = 0.3
    connect_timeout_s: float = 15.0
    ready_timeout_s: float = 30.0
    arm_timeout_s: float = 20.0
    takeoff_timeout_s: float = 40.0
    mission_timeout_s: float = 600.0
    land_timeout_s: float = 60.0
    lost_after_s: float = 1.0
    neighbour_max_age_s: float = 0.5
    lost_obstacle_margin_m: float = 0.5
    tracking_dead_time_s: float = 0.3
    tracking_t63_s: float = 1.0
    latency_s: float | None = None
    latency_headroom_s: float = 0.05
    max_latency_s: float = 0.25
    position_accuracy_m: float | None = None
    accuracy_factor: float = DEFAULT_ACCURACY_FACTOR
    max_position_accuracy_m: float = 1.0
    disturbance_residual_m_s: float = DEFAULT_DISTURBANCE_M_S
    compensate_estimate: bool = True
    safety_margin_m: float | None = None

    @property
    def period_s(self) -> float:
        """Control period T = 1 / rate_hz."""
        return 1.0 / self.rate_hz

    @property
    def frame(self) -> TubeFrame:
        """The geodetic tube frame (x along ``heading_deg``, y to the left, z up)."""
        return TubeFrame(
            self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m, self.heading_deg
        )

    @property
    def altitude_amsl_m(self) -> float:
        """Flight altitude above mean sea level: ``origin_alt_m + altitude_m``."""
        return self.origin_alt_m + self.altitude_m


# (key, required, lower bound kind) — kinds: "pos" > 0, "nonneg" >= 0, None any finite number
_NUMBERS: tuple[tuple[str, bool, str | None], ...] = (
    ("origin_lat_deg", True, None),
    ("origin_lon_deg", True, None),
    ("origin_alt_m", True, None),
    ("heading_deg", True, None),
    ("altitude_m", True, "pos"),
    ("rate_hz", False, "pos"),
    ("exit_clear_m", False, "nonneg"),
    ("climb_speed_m_s", False, "pos"),
    ("max_vertical_speed_m_s", False, "pos"),
    ("altitude_gain_1_s", False, "pos"),
    ("altitude_tolerance_m", False, "pos"),
    ("connect_timeout_s", False, "pos"),
    ("ready_timeout_s", False, "pos"),
    ("arm_timeout_s", False, "pos"),
    ("takeoff_timeout_s", False, "pos"),
    ("mission_timeout_s", False, "pos"),
    ("land_timeout_s", False, "pos"),
    ("lost_after_s", False, "pos"),
    ("neighbour_max_age_s", False, "pos"),
    ("lost_obstacle_margin_m", False, "nonneg"),
    ("tracking_dead_time_s", False, "nonneg"),
    ("tracking_t63_s", False, "nonneg"),
    ("latency_s", False, "nonneg"),
    ("latency_headroom_s", False, "nonneg"),
    ("max_latency_s", False, "pos"),
    ("position_accuracy_m", False, "nonneg"),
    ("accuracy_factor", False, "nonneg"),
    ("max_position_accuracy_m", False, "pos"),
    ("disturbance_residual_m_s", False, "nonneg"),
    ("safety_margin_m", False, "nonneg"),
)
_CHOICES: dict[str, tuple[str, ...]] = {"after_exit": AFTER_EXIT, "on_complete": ON_COMPLETE}
_FLAGS: tuple[str, ...] = ("compensate_estimate",)


def _show(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a table"
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return repr(value)


def parse_mission_config(table: Mapping[str, Any], source: str = "<mission>") -> MissionConfig:
    """Parse a decoded ``[mission]`` table; raise :class:`ConfigError` naming the key."""

    def err(key: str | None, msg: str) -> ConfigError:
        where = f"[mission].{key}" if key else "[mission]"
        return ConfigError(f"{source}: {where}: {msg}")

    allowed = [k for k, _, _ in _NUMBERS] + list(_CHOICES) + list(_FLAGS)
    for key in table:
        if key not in allowed:
            raise err(key, f"unknown key (allowed: {', '.join(allowed)})")
    values: dict[str, Any] = {}
    for key, required, kind in _NUMBERS:
        if key not in table:
            if required:
                raise err(key, "missing required key")
            continue
        v = table[key]
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise err(key, f"expected a number, got {_show(v)}")
        x = float(v)
        if not math.isfinite(x):
            raise err(key, f"expected a finite number, got {_show(v)}")
        if kind == "pos" and not x > 0:
            raise err(key, f"must be > 0, got {_show(v)}")
        if kind == "nonneg" and not x >= 0:
            raise err(key, f"must be >= 0, got {_show(v)}")
        values[key] = x
    for key, choices in _CHOICES.items():
        if key in table:
            v = table[key]
            if not isinstance(v, str) or v not in choices:
                raise err(key, f"expected one of {', '.join(map(json.dumps, choices))}, "
                               f"got {_show(v)}")
            values[key] = v
    for key in _FLAGS:
        if key in table:
            v = table[key]
            if not isinstance(v, bool):
                raise err(key, f"expected true or false, got {_show(v)}")
            values[key] = v
    if not -90.0 < values["origin_lat_deg"] < 90.0:
        raise err("origin_lat_deg", f"must be within (-90, 90), got {values['origin_lat_deg']:g}")
    if not -180.0 <= values["origin_lon_deg"] <= 180.0:
        raise err("origin_lon_deg", f"must be within [-180, 180], got "
                                    f"{values['origin_lon_deg']:g}")
    cfg = MissionConfig(**values)
    if cfg.lost_after_s < cfg.period_s:
        raise err("lost_after_s", f"must be at least one control period "
                                  f"({cfg.period_s:.3f} s at rate_hz = {cfg.rate_hz:g}), "
                                  f"got {cfg.lost_after_s:g}")
    if cfg.neighbour_max_age_s > cfg.lost_after_s:
        raise err("neighbour_max_age_s", f"must not exceed lost_after_s = {cfg.lost_after_s:g}, "
                                         f"got {cfg.neighbour_max_age_s:g}")
    return cfg


@dataclass(frozen=True, eq=False)
class Mission:
    """A mission: the :class:`~vtube_fleet.config.scenario.Scenario` (whose robots are the vehicles'
    start slots, in endpoint order) and its :class:`MissionConfig`."""

    scenario: Scenario
    config: MissionConfig

    @property
    def source(self) -> str:
        return self.scenario.source

    @property
    def config_hash(self) -> str:
        """The mission file's content hash (:func:`~vtube_fleet.config.scenario.content_hash`):
        the coordinator and every agent must fly the same one."""
        return self.scenario.content_hash

    @property
    def slots(self) -> np.ndarray:
        """(M, 2) start slots in the tube frame; vehicle/endpoint ``i`` flies slot ``i``."""
        return self.scenario.robots.positions

    @property
    def count(self) -> int:
        return self.scenario.robots.count

    @property
    def frame(self) -> TubeFrame:
        return self.config.frame

    def slot_geodetic(self) -> np.ndarray:
        """(M, 3) lat_deg, lon_deg, alt_m (AMSL, ground = ``origin_alt_m``) of the slots."""
        lat, lon, alt = self.frame.tube_to_geodetic(self.slots[:, 0], self.slots[:, 1], 0.0)
        return np.stack(np.broadcast_arrays(lat, lon, alt), axis=-1)

    def with_vehicles(self, n: int) -> Mission:
        """The same mission flying only the first ``n`` slots."""
        return Mission(self.scenario.with_robots(n), self.config)


def load_mission(path: str | os.PathLike[str]) -> Mission:
    """Read a mission file: a scenario plus ``[mission]``. Raises :class:`ConfigError`."""
    scenario = load_scenario(path, extra_sections=("mission",))
    source = scenario.source
    if "mission" not in scenario.extra:
        raise ConfigError(f"{source}: [mission]: missing required table (a mission file is a "
                          f"scenario plus a [mission] table; see docs/fleet.md)")
    if scenario.robots.model != "single_integrator":
        raise ConfigError(f"{source}: [robots].model: the fleet flies multicopters, which take "
                          f"velocity setpoints (single_integrator); got "
                          f"{_show(scenario.robots.model)}")
    return Mission(scenario, parse_mission_config(scenario.extra["mission"], source))
