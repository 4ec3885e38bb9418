"""Mission files: a scenario (tube, obstacles, robots = the vehicles' start slots, controller)
plus a ``[mission]`` table that anchors the paper's 2-D tube frame on the Earth and says how the
fleet flies it.

The scenario part is parsed by :func:`vtube_fleet.config.scenario.load_scenario` (the same
parser the simulator uses, with ``extra_sections=("mission",)``); this module parses
``[mission]`` as strictly: an unknown key, a wrong type or an impossible value raises
:class:`~vtube_fleet.errors.ConfigError` naming the file and the key, e.g.
``mission.toml: [mission].rate_hz: must be > 0, got -5``.

Every ``[mission]`` key, with its type, unit, default, bounds and meaning, is declared once in
:data:`MISSION_KEYS` (:class:`~vtube_fleet.config.keys.Key`): the parser reads it, and the table
in ``docs/fleet.md`` is generated from it (:func:`mission_keys_table`; a test keeps them equal).
Bounds are physical: ``altitude_m`` within the documented ceiling :data:`MAX_ALTITUDE_M`,
``rate_hz`` within the position stream rate :data:`POSITION_STREAM_HZ`, vertical speeds within
PX4's defaults, timeouts finite and positive; relations between keys (a take-off timeout shorter
than the climb, a tolerance that completes the take-off on the ground, …) are refused too.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtube_fleet.config.keys import NON_NEGATIVE, POSITIVE, Bound, Key, markdown_table, show_value
from vtube_fleet.config.scenario import PX4_MAX_HORIZONTAL_M_S, Scenario, load_scenario
from vtube_fleet.core.fence import RouteFence, route_fence
from vtube_fleet.errors import ConfigError
from vtube_fleet.frames import TubeFrame

__all__ = [
    "AFTER_EXIT",
    "DEFAULT_BATTERY_DRAIN_PCT_PER_MIN",
    "DEFAULT_MAX_CLOCK_OFFSET_S",
    "MAX_CLOCK_OFFSET_S",
    "PX4_LAND_SPEED_M_S",
    "FENCE_ACTIONS",
    "MAX_ALTITUDE_M",
    "MISSION_KEYS",
    "ON_COMPLETE",
    "POSITION_STREAM_HZ",
    "SlotError",
    "Mission",
    "MissionConfig",
    "load_mission",
    "mission_keys_table",
    "parse_mission_config",
]

#: k: the estimate error budgeted is k × the reported 1-σ accuracy (real SITL: max 1.83 σ).
DEFAULT_ACCURACY_FACTOR = 2.0
#: … with ``tracking = "reference"`` (no lag term hides a larger error there): the mock's
#: px4-sih estimate reached 2.8 σ in flight and 3.6 σ in the first seconds after lift-off,
#: real PX4 SITL 2.4 σ (docs/fleet.md, reference tracking).
REFERENCE_ACCURACY_FACTOR = 3.0
#: D: the estimate disturbance left after compensation (m/s; docs/fleet.md).
DEFAULT_DISTURBANCE_M_S = 0.25

#: The charge a vehicle uses per minute in the air (%/min) unless the mission says: a
#: multicopter that flies 20 minutes on a full pack (docs/fleet.md, "Batteries").
DEFAULT_BATTERY_DRAIN_PCT_PER_MIN = 5.0
#: How far an MQTT agent's clock may be from the coordinator's (s) unless the mission says
#: (docs/mqtt.md, "Clocks"): two agents within it are within 50 ms (one control period at
#: 20 Hz) of each other.
DEFAULT_MAX_CLOCK_OFFSET_S = 0.025
#: The largest ``max_clock_offset_s``: half the bus's limit on stamps from the future
#: (``vtube_fleet.bus.validate.MAX_FUTURE_S`` = 0.25 s): two agents within it of the coordinator
#: are within 0.25 s of each other, so no honest state is refused as coming from the future.
MAX_CLOCK_OFFSET_S = 0.125
#: PX4's MPC_LAND_SPEED default (m/s): how fast a vehicle comes down in Land near the ground
#: (faster above MPC_LAND_ALT1), for the mission's expected airborne time.
PX4_LAND_SPEED_M_S = 0.7

#: What a vehicle does once it has crossed the finishing line (Assumption 2).
AFTER_EXIT: tuple[str, ...] = ("continue", "hold", "land")
#: What every vehicle does once all have exited.
ON_COMPLETE: tuple[str, ...] = ("land", "hold")
#: What a vehicle the partition around stopped vehicles traps does (docs/fleet.md).
ON_TRAPPED: tuple[str, ...] = ("wait", "land")
#: PX4's geofence breach actions the mission may choose (GF_ACTION 2, 5, 3).
FENCE_ACTIONS: tuple[str, ...] = ("hold", "land", "rtl")
#: ``tracking``: how the vehicles are held to the paper's single integrator (docs/fleet.md, the
#: safety budget): ``velocity`` sends the controller's command (its lag to PX4's response is
#: budgeted: τ_d + t63); ``reference`` integrates each command into a reference position the
#: controller works on and closes a position loop on it (its measured error is budgeted).
TRACKING_MODES: tuple[str, ...] = ("velocity", "reference")
#: ``tracking_error_m`` by default: the bound e of |p̂ − r| (docs/fleet.md, reference tracking).
DEFAULT_TRACKING_ERROR_M = 0.7


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
    on_abort: str = "land"
    on_trapped: str = "wait"
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
    tracking: str = "velocity"
    tracking_error_m: float = DEFAULT_TRACKING_ERROR_M
    tracking_gain_1_s: float = 2.0
    response_check: bool = True
    response_watch: bool = True
    latency_s: float | None = None
    latency_headroom_s: float = 0.05
    max_latency_s: float = 0.25
    position_accuracy_m: float | None = None
    accuracy_factor: float = DEFAULT_ACCURACY_FACTOR
    max_position_accuracy_m: float = 1.0
    disturbance_residual_m_s: float = DEFAULT_DISTURBANCE_M_S
    compensate_estimate: bool = True
    safety_margin_m: float | None = None
    fence_action: str = "hold"
    fence_margin_m: float = 1.0
    battery_reserve_pct: float = 20.0
    battery_drain_pct_per_min: float = DEFAULT_BATTERY_DRAIN_PCT_PER_MIN
    expected_airborne_s: float | None = None
    max_clock_offset_s: float = DEFAULT_MAX_CLOCK_OFFSET_S
    signing_key_file: str | None = None

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


#: LOCAL_POSITION_NED rate (Hz) both link backends ask every vehicle for on connect (mavlink:
#: ``DEFAULT_MESSAGE_RATES_HZ``, MAVSDK: ``set_rate_position_velocity_ned``); PX4 SITL delivers
#: 49-49.5 Hz of it (tests/data/px4_sitl). A control tick faster than this recomputes the
#: setpoint from positions it has already used: ``rate_hz`` is refused above it.
POSITION_STREAM_HZ = 50.0
#: The documented flight ceiling (m above the take-off ground): the 120 m of EASA's open
#: category and FAA Part 107 (400 ft). PX4 does not bound it by default (GF_MAX_VER_DIST
#: defaults to 0, i.e. disabled), so the mission does.
MAX_ALTITUDE_M = 120.0
#: PX4's default limits of the velocity setpoints it follows in offboard (MPC_Z_VEL_MAX_UP,
#: MPC_Z_VEL_MAX_DN); a larger setpoint is silently clipped, so the mission refuses it.
PX4_MAX_CLIMB_M_S = 3.0
PX4_MAX_DESCENT_M_S = 1.5
#: PX4's default limit of the horizontal velocity (MPC_XY_VEL_MAX) is
#: ``vtube_fleet.config.scenario.PX4_MAX_HORIZONTAL_M_S``: the scenario parser bounds every
#: speed (v_max, the fastest the controller ever commands, included) by it.

def _timeout(name: str, default: float, what: str) -> Key:
    return Key(name, "number", f"timeout: {what}", "s", default, bound=POSITIVE)


#: Every ``[mission]`` key: type, unit, default, bounds, meaning. The one source of
#: :func:`parse_mission_config` and of the table in docs/fleet.md (:func:`mission_keys_table`).
MISSION_KEYS: tuple[Key, ...] = (
    Key("origin_lat_deg", "number", "latitude of the tube frame's geodetic anchor (WGS84)",
        "deg", required=True, bound=Bound(-90.0, 90.0, high_inclusive=False, interval=True)),
    Key("origin_lon_deg", "number", "longitude of the tube frame's geodetic anchor (WGS84)",
        "deg", required=True, bound=Bound(-180.0, 180.0, low_inclusive=True, interval=True)),
    Key("origin_alt_m", "number", "AMSL altitude of the anchor (ground level)", "m",
        required=True, bound=Bound(-500.0, 9000.0, low_inclusive=True,
                                   why="the Earth's surface: Dead Sea to Everest")),
    Key("heading_deg", "number", "heading of the tube's x axis, clockwise from true north",
        "deg", required=True, bound=Bound(-360.0, 360.0, low_inclusive=True, interval=True)),
    Key("altitude_m", "number", "flight height above `origin_alt_m`", "m", required=True,
        bound=Bound(0.0, MAX_ALTITUDE_M, why="the documented ceiling: EASA open category / "
                    "FAA Part 107; PX4's GF_MAX_VER_DIST is off by default")),
    Key("rate_hz", "number", "control rate", "Hz", 20.0,
        bound=Bound(0.0, POSITION_STREAM_HZ, why="the position stream rate the vehicles send: "
                    "LOCAL_POSITION_NED at 50 Hz")),
    Key("after_exit", "choice", "past the finishing line: `continue` (fly on at v along n_c "
        "until everyone has exited, at most to a stopping distance before the fence's "
        "exit), `hold` or `land` once `exit_clear_m` past the line",
        default="continue", choices=AFTER_EXIT),
    Key("on_complete", "choice", "when every vehicle has exited: `land` or `hold`",
        default="land", choices=ON_COMPLETE),
    Key("on_abort", "choice", "after an abort in the air (budget exceeded, no partition, "
        "timeout, lost vehicles): `land` (every vehicle holds, then lands in place; the run "
        "waits for touch-down) or `hold` (left holding for an operator, said in red)",
        default="land", choices=ON_COMPLETE),
    Key("on_trapped", "choice", "a vehicle in the tube that a re-partition around stopped "
        "vehicles leaves inside a region (no safe sub-tube, none of its own): `wait` (it "
        "stops there, an obstacle for the others, until nobody else flies the tube, then "
        "steps aside into a sub-tube and flies on; when no partition around all the stopped "
        "vehicles exists, each vehicle flies one of its own or waits) or `land` (in place; "
        "a failed re-partition aborts the mission)",
        default="wait", choices=ON_TRAPPED),
    Key("exit_clear_m", "number", "distance flown past the finishing line before `hold` / "
        "`land`", "m", 3.0, bound=NON_NEGATIVE),
    Key("climb_speed_m_s", "number", "offboard climb rate", "m/s", 1.0,
        bound=Bound(0.0, PX4_MAX_CLIMB_M_S, why="PX4's MPC_Z_VEL_MAX_UP default")),
    Key("max_vertical_speed_m_s", "number", "clamp of the altitude-hold term: v_up = "
        "clamp(k (altitude − up), ±max)", "m/s", 1.0,
        bound=Bound(0.0, PX4_MAX_DESCENT_M_S, why="PX4's MPC_Z_VEL_MAX_DN default")),
    Key("altitude_gain_1_s", "number", "k of the altitude-hold term (at most `rate_hz`: one "
        "period must not overshoot)", "1/s", 1.0, bound=POSITIVE),
    Key("altitude_tolerance_m", "number", "take-off is complete within this of the mission "
        "altitude (less than `altitude_m`)", "m", 0.3, bound=POSITIVE),
    _timeout("connect_timeout_s", 15.0, "connect every endpoint"),
    _timeout("ready_timeout_s", 30.0, "every vehicle ready (position, home, accuracy)"),
    _timeout("arm_timeout_s", 20.0, "every vehicle armed in offboard"),
    _timeout("takeoff_timeout_s", 40.0, "every vehicle at the mission altitude (at least "
             "`altitude_m / climb_speed_m_s`)"),
    _timeout("mission_timeout_s", 600.0, "every vehicle out of the tube"),
    _timeout("land_timeout_s", 60.0, "every vehicle on the ground"),
    Key("lost_after_s", "number", "no telemetry for this long → the vehicle is LOST (at least "
        "one control period)", "s", 1.0, bound=POSITIVE),
    Key("neighbour_max_age_s", "number", "a neighbour state older than this is not used as a "
        "live position (at most `lost_after_s`)", "s", 0.5, bound=POSITIVE),
    Key("lost_obstacle_margin_m", "number", "a LOST vehicle becomes an obstacle of radius "
        "r_s + this", "m", 0.5, bound=NON_NEGATIVE),
    Key("tracking_dead_time_s", "number", "τ_d: PX4's velocity-tracking dead time, for the "
        "safety budget (captures: 0.27-0.35 s)", "s", 0.3, bound=NON_NEGATIVE),
    Key("tracking_t63_s", "number", "t63: PX4's horizontal velocity time constant, for the "
        "safety budget (captures: 0.8-1.2 s)", "s", 1.0, bound=NON_NEGATIVE),
    Key("tracking", "choice", "`velocity`: send the controller's command, PX4's response lag "
        "budgeted (τ_d + t63); `reference`: the controller flies reference positions (its "
        "commands integrated) and a position loop holds each vehicle to its own, the tracking "
        "error budgeted instead (docs/fleet.md, reference tracking)", default="velocity",
        choices=TRACKING_MODES),
    Key("tracking_error_m", "number", "e: with `tracking = \"reference\"`, the budgeted bound "
        "of a vehicle's estimated position from its reference; the tube holds when a vehicle "
        "is further", "m", DEFAULT_TRACKING_ERROR_M, bound=POSITIVE),
    Key("tracking_gain_1_s", "number", "K: with `tracking = \"reference\"`, the position "
        "loop's gain (setpoint v_c + K (r − p̂) + d̂)", "1/s", 2.0,
        bound=Bound(0.0, 3.0, low_inclusive=False,
                    why="above it the loop rings with PX4's ~0.5 s velocity response")),
    Key("response_check", "flag", "after the climb, every vehicle flies a step of the cruise "
        "speed v and back to zero; one that lags behind it more than the budget's τ_d, t63 "
        "model (plus σ / v) aborts the mission before the tube (docs/fleet.md, the response "
        "check)", default=True),
    Key("response_watch", "flag", "with `tracking = \"velocity\"`, in flight: a vehicle whose "
        "estimated path leaves the path the budget's τ_d, t63 model gives its commands by more "
        "than D W + k σ over the last W = 4 H holds the tube (docs/fleet.md, the response "
        "watch)",
        default=True),
    Key("latency_s", "number", "L of the safety budget: position age + setpoint delay",
        "s", None, bound=NON_NEGATIVE,
        default_text="measured (round trip + `latency_headroom_s`)"),
    Key("latency_headroom_s", "number", "added to the measured L (jitter in flight)", "s",
        0.05, bound=NON_NEGATIVE),
    Key("max_latency_s", "number", "above this L the mission is refused before arming", "s",
        0.25, bound=POSITIVE),
    Key("position_accuracy_m", "number", "σ of the safety budget", "m", None,
        bound=NON_NEGATIVE, default_text="measured (the worst settled accuracy the vehicles "
        "report: ESTIMATOR_STATUS `pos_horiz_accuracy`, else GPS_RAW_INT `h_acc`)"),
    Key("accuracy_factor", "number", "k: the estimate error budgeted is k σ (default "
        f"{REFERENCE_ACCURACY_FACTOR:g} with `tracking = \"reference\"`)", "",
        DEFAULT_ACCURACY_FACTOR, bound=NON_NEGATIVE),
    Key("max_position_accuracy_m", "number", "wait (up to `ready_timeout_s`) until every "
        "vehicle reports at most this σ", "m", 1.0, bound=POSITIVE),
    Key("disturbance_residual_m_s", "number", "D: the estimate disturbance left after "
        "compensation", "m/s", DEFAULT_DISTURBANCE_M_S, bound=NON_NEGATIVE),
    Key("compensate_estimate", "flag", "send v_c + d̂ instead of v_c (below)", default=True),
    Key("safety_margin_m", "number", "override the safety budget δ", "m", None,
        bound=NON_NEGATIVE, default_text="computed"),
    Key("fence_action", "choice", "PX4's GF_ACTION on a breach of the tube fence uploaded "
        "before arming: `hold`, `land` or `rtl` (docs/fleet.md, the fence on the vehicle)",
        default="hold", choices=FENCE_ACTIONS),
    Key("fence_margin_m", "number", "the fence polygon lies r_s + this outside the tube's "
        "legs and behind the start base", "m", 1.0, bound=NON_NEGATIVE),
    Key("battery_reserve_pct", "number", "the battery charge a vehicle keeps in reserve: "
        "before arming every vehicle must report this plus the mission's use "
        "(`battery_drain_pct_per_min` × `expected_airborne_s`); in the air a vehicle that "
        "reports less lands where it is (an obstacle for the others). 0 with a drain of 0: no "
        "battery check", "%", 20.0,
        bound=Bound(0.0, 100.0, low_inclusive=True, high_inclusive=False, interval=True)),
    Key("battery_drain_pct_per_min", "number", "the charge a vehicle uses per minute in the "
        "air (100 / its endurance in minutes on a full pack)", "%/min",
        DEFAULT_BATTERY_DRAIN_PCT_PER_MIN,
        bound=Bound(0.0, 100.0, low_inclusive=True,
                    why="more empties a full pack in under a minute")),
    Key("expected_airborne_s", "number", "how long each vehicle is in the air, for the "
        "battery check before arming", "s", None, bound=POSITIVE,
        default_text="derived: the climb (`altitude_m / climb_speed_m_s`) + the longest slot's "
        "path to the finishing line plus `exit_clear_m` at v_min (at most "
        "`mission_timeout_s`) + the descent at PX4's MPC_LAND_SPEED (0.7 m/s)"),
    Key("max_clock_offset_s", "number", "an MQTT agent refuses to fly when its clock may be "
        "further than this from the coordinator's (measured offset + half the round trip; "
        "docs/mqtt.md, clocks)", "s", DEFAULT_MAX_CLOCK_OFFSET_S,
        bound=Bound(0.0, MAX_CLOCK_OFFSET_S, why="half the bus's 0.25 s limit on stamps "
                    "from the future")),
    Key("signing_key_file", "text", "MAVLink 2 signing key file (32 bytes, mode 0600), "
        "relative to the mission file; `{slot}` in the name = one key per vehicle. Every "
        "MAVLink packet is then signed and only signed ones are accepted (mavlink backend "
        "only; docs/security.md)", default=None, default_text="none: no signing"),
)
_BY_NAME: dict[str, Key] = {k.name: k for k in MISSION_KEYS}


def mission_keys_table() -> str:
    """The ``[mission]`` table of docs/fleet.md, generated from :data:`MISSION_KEYS`."""
    return markdown_table(MISSION_KEYS)


def parse_mission_config(table: Mapping[str, Any], source: str = "<mission>") -> MissionConfig:
    """Parse a decoded ``[mission]`` table against :data:`MISSION_KEYS`, then the relations
    between keys; raise :class:`ConfigError` naming the key, the value and the bound."""

    def err(key: str | None, msg: str) -> ConfigError:
        where = f"[mission].{key}" if key else "[mission]"
        return ConfigError(f"{source}: {where}: {msg}")

    for key in table:
        if key not in _BY_NAME:
            raise err(key, f"unknown key (allowed: {', '.join(_BY_NAME)})")
    values: dict[str, Any] = {}
    for k in MISSION_KEYS:
        if k.name not in table:
            if k.required:
                raise err(k.name, "missing required key")
            values[k.name] = k.default
            continue
        try:
            values[k.name] = k.parse(table[k.name])
        except ValueError as exc:
            raise err(k.name, str(exc)) from None
    if values["tracking"] == "reference" and "accuracy_factor" not in table:
        values["accuracy_factor"] = REFERENCE_ACCURACY_FACTOR
    cfg = MissionConfig(**values)
    if cfg.lost_after_s < cfg.period_s:
        raise err("lost_after_s", f"must be at least one control period "
                                  f"({cfg.period_s:.3f} s at rate_hz = {cfg.rate_hz:g}), "
                                  f"got {cfg.lost_after_s:g}")
    if cfg.neighbour_max_age_s > cfg.lost_after_s:
        raise err("neighbour_max_age_s", f"must not exceed lost_after_s = {cfg.lost_after_s:g}, "
                                         f"got {cfg.neighbour_max_age_s:g}")
    if cfg.altitude_tolerance_m >= cfg.altitude_m:
        raise err("altitude_tolerance_m", f"must be less than altitude_m = {cfg.altitude_m:g} "
                                          f"(take-off would be complete on the ground), got "
                                          f"{cfg.altitude_tolerance_m:g}")
    climb_s = cfg.altitude_m / cfg.climb_speed_m_s
    if climb_s > cfg.takeoff_timeout_s:
        raise err("takeoff_timeout_s", f"must be at least altitude_m / climb_speed_m_s = "
                                       f"{cfg.altitude_m:g} / {cfg.climb_speed_m_s:g} = "
                                       f"{climb_s:.3g} s (the climb), got "
                                       f"{cfg.takeoff_timeout_s:g}")
    if cfg.altitude_gain_1_s > cfg.rate_hz:
        raise err("altitude_gain_1_s", f"must be at most rate_hz = {cfg.rate_hz:g} (k T <= 1: "
                                       f"one control period must not overshoot), got "
                                       f"{cfg.altitude_gain_1_s:g}")
    return cfg


class SlotError(ConfigError):
    """The mission's start slots overlap, touch an obstacle or leave the tube."""


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

    @property
    def expected_airborne_s(self) -> float:
        """How long each vehicle is in the air (s): ``expected_airborne_s`` when the mission
        says, else the climb (``altitude_m / climb_speed_m_s``) + the tube (the longest slot's
        path to the (last) finishing line along the route's segments, plus ``exit_clear_m``, at
        v_min: the controller never
        commands less, paper note 9; at most ``mission_timeout_s``, after which the run ends)
        + the descent (``altitude_m`` at :data:`PX4_LAND_SPEED_M_S`). The fleet climbs and
        enters the tube together and lands once the last vehicle is out, so every vehicle is
        in the air about as long as the slowest."""
        cfg = self.config
        if cfg.expected_airborne_s is not None:
            return float(cfg.expected_airborne_s)
        sc = self.scenario
        corridor = sc.corridor  # a route: to its last finishing line, segment after segment
        tubes = corridor.segments
        start = np.asarray(corridor.start_segment_of(self.slots), int).reshape(-1)
        path = max((tubes[s].length - float(tubes[s].xi(p))
                    + sum(t.length for t in tubes[s + 1:]))
                   for s, p in zip(start.tolist(), self.slots, strict=True))
        tube_s = min((max(path, 0.0) + cfg.exit_clear_m) / sc.robots.v_min,
                     cfg.mission_timeout_s)
        return (cfg.altitude_m / cfg.climb_speed_m_s + tube_s
                + cfg.altitude_m / PX4_LAND_SPEED_M_S)

    @property
    def battery_needed_pct(self) -> float:
        """The charge (%) every vehicle must report before arming: ``battery_reserve_pct`` +
        ``battery_drain_pct_per_min`` × :attr:`expected_airborne_s` (in minutes)."""
        cfg = self.config
        return (cfg.battery_reserve_pct
                + cfg.battery_drain_pct_per_min * self.expected_airborne_s / 60.0)

    def slot_geodetic(self) -> np.ndarray:
        """(M, 3) lat_deg, lon_deg, alt_m (AMSL, ground = ``origin_alt_m``) of the slots."""
        lat, lon, alt = self.frame.tube_to_geodetic(self.slots[:, 0], self.slots[:, 1], 0.0)
        return np.stack(np.broadcast_arrays(lat, lon, alt), axis=-1)

    def fence_geometry(self) -> RouteFence:
        """The mission's PX4 geofence in the tube frame: the route's outline, one inclusion
        polygon per segment, and the obstacles' exclusion circles
        (:func:`~vtube_fleet.core.fence.route_fence` with the physical r_s, every slot inside
        the first segment, ``fence_margin_m`` and ``exit_clear_m`` past the last): what the fleet
        uploads (``fleet/onboard.py``) and what the recording's map draws."""
        sc, cfg = self.scenario, self.config
        return route_fence(sc.corridor, sc.controller.r_s, slots=self.slots,
                           margin_m=cfg.fence_margin_m, exit_clear_m=cfg.exit_clear_m)

    def with_vehicles(self, n: int) -> Mission:
        """The same mission flying only the first ``n`` slots."""
        return Mission(self.scenario.with_robots(n), self.config)

    def require_slots(self, count: int | None = None) -> None:
        """Refuse slots 0..count-1 that overlap each other, an obstacle, or leave the tube
        (Assumption 1 with the scenario's own r_s; the run's preflight re-checks with the safety
        budget): raises :class:`SlotError` listing each offending slot with the numbers."""
        from vtube_fleet.core.validation import validate_route

        n = self.count if count is None else count
        sc = self.scenario
        violations = validate_route(sc.corridor, sc.controller, self.slots[:n]).violations
        bad = [v.message.removeprefix("Assumption1 violated: ") for v in violations
               if v.condition == "Assumption1"]
        if bad:
            text = "; ".join(bad).replace("robots ", "slots ").replace("robot ", "slot ")
            raise SlotError(f"{self.source}: [robots].positions: {len(bad)} problem(s) with the "
                            f"start slots (Assumption 1, r_s = {sc.robots.r_s:g} m): {text}")


#: How far (m) a mission's tube or route may reach from its geodetic anchor: PX4's local frame
#: and the fence's WGS84 corners are flat-Earth projections about an origin, and a multicopter
#: fleet's flight is a few kilometres at most.
MAX_EXTENT_M = 10_000.0


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
                          f"{show_value(scenario.robots.model)}")
    if scenario.robots.v_max > PX4_MAX_HORIZONTAL_M_S:
        raise ConfigError(f"{source}: [robots].v_max: must be <= {PX4_MAX_HORIZONTAL_M_S:g} "
                          f"(PX4's MPC_XY_VEL_MAX default: faster setpoints are clipped), got "
                          f"{scenario.robots.v_max:g}")
    far = max(float(np.hypot(*np.asarray(t.polygon(), float).T).max())
              for t in scenario.geometry.segments)
    if not far <= MAX_EXTENT_M:
        raise ConfigError(f"{source}: the {'route' if scenario.is_route else 'tube'} reaches "
                          f"{far / 1000.0:.1f} km from the mission's anchor (the tube frame's "
                          f"origin); a mission must lie within {MAX_EXTENT_M / 1000.0:g} km of "
                          f"it (a sign or a unit wrong in a waypoint or a corner?)")
    mission = Mission(scenario, parse_mission_config(scenario.extra["mission"], source))
    cfg = mission.config
    if cfg.tracking == "reference" and scenario.is_route:
        raise ConfigError(f"{source}: [mission].tracking = \"reference\" is not flown on a "
                          f"[route] yet (its hand-overs and exits are judged on the estimate, "
                          f"the commands on the reference): use a [tube], or tracking = "
                          f"\"velocity\"")
    need = mission.battery_needed_pct
    if need > 100.0:
        raise ConfigError(f"{source}: [mission].battery_reserve_pct: the reserve "
                          f"{cfg.battery_reserve_pct:g} % + battery_drain_pct_per_min "
                          f"{cfg.battery_drain_pct_per_min:g} %/min × the expected "
                          f"{mission.expected_airborne_s:.0f} s in the air = {need:.0f} % of a "
                          f"full pack: no vehicle could fly it (lower the drain or the reserve, "
                          f"or set expected_airborne_s)")
    return mission
