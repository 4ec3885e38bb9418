"""The layout of a recording, shared by writer and reader.

Entity paths, timelines, component names, the metadata format, colours and metric names.
"""

from __future__ import annotations

__all__ = [
    "DEFAULT_COLOR",
    "DEFAULT_CONNECT_URL",
    "DEFAULT_RECORDING_NAME",
    "EVENT_ARCHETYPE",
    "EXIT_ARCHETYPE",
    "E_COMMANDS",
    "E_EVENTS",
    "E_EXITS",
    "E_META",
    "E_OBSTACLES",
    "E_OBSTACLES_EXT",
    "E_STATUS",
    "E_SUB_TUBES",
    "E_SUMMARY",
    "E_TRIANGLES",
    "E_TUBE",
    "E_VEHICLES",
    "E_VEHICLE_EVENTS",
    "E_VELOCITY",
    "LIMITS_PREFIX",
    "LOG_LEVELS",
    "LIMIT_PERIOD_S",
    "META_FORMAT",
    "META_VERSION",
    "METRICS_PREFIX",
    "METRIC_NAMES",
    "METRIC_VIEWS",
    "OTHER_COLOR",
    "PHASE_COLORS",
    "SAFETY_ARCHETYPE",
    "SAFETY_PREFIX",
    "SIM_MIN_PERIOD_S",
    "STATE_ARCHETYPE",
    "TIMELINE_TICK",
    "TIMELINE_TIME",
    "stream_entity",
]

#: ``--rerun-connect`` without an address: the viewer's default gRPC proxy.
DEFAULT_CONNECT_URL = "rerun+http://127.0.0.1:9876/proxy"


#: File name of the recording inside a run's output folder.
DEFAULT_RECORDING_NAME = "recording.rrd"


#: ``vtube-fleet sim`` records a frame at most this often (simulated seconds) by default.
SIM_MIN_PERIOD_S = 0.04


#: ``format`` tag of the ``meta/scenario`` JSON document.
META_FORMAT = "vtube_fleet.recording"


META_VERSION = 1


TIMELINE_TIME = "mission_time"


TIMELINE_TICK = "tick"


E_META = "meta/scenario"


E_SUMMARY = "meta/summary"


E_TUBE = "world/tube"


E_OBSTACLES = "world/obstacles"


E_OBSTACLES_EXT = "world/obstacles/extended"


E_SUB_TUBES = "world/sub_tubes"


E_TRIANGLES = "world/triangles"


E_VEHICLES = "world/vehicles"


E_VELOCITY = "world/velocity"


E_COMMANDS = "world/commands"


E_STATUS = "status"


E_EVENTS = "events"


E_EXITS = "events/exits"


E_VEHICLE_EVENTS = "events/vehicles"


METRICS_PREFIX = "metrics/"


SAFETY_PREFIX = "safety/"


#: The limit lines (``limits/*``) get a point every this many seconds of mission time.
LIMIT_PERIOD_S = 5.0


LIMITS_PREFIX = "limits/"


#: Archetype name of the exact float64 vehicle state components.
STATE_ARCHETYPE = "vtube_fleet.VehicleState"


#: Archetype name of the exit event components.
EXIT_ARCHETYPE = "vtube_fleet.Exit"


#: Archetype name of the per-vehicle event components.
EVENT_ARCHETYPE = "vtube_fleet.Event"


#: Archetype name of the exact safety-metric inputs.
SAFETY_ARCHETYPE = "vtube_fleet.SafetyInput"


#: Metric keys shown in the default blueprint, by view: (view name, metric keys, unit label).
METRIC_VIEWS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("min pair distance [m]", ("min_pair_distance_m",)),
    ("min obstacle-centre distance [m]", ("min_obstacle_center_distance_m",)),
    ("min leg distances [m]", ("min_left_leg_distance_m", "min_right_leg_distance_m")),
    ("speed min / max [m/s]", ("min_speed_m_s", "max_speed_m_s")),
    ("tick duration [s]", ("tick_duration_s",)),
    ("link latency [s]", ("link_latency_s",)),
)


#: Legend names of the known metric series.
METRIC_NAMES: dict[str, str] = {
    "min_pair_distance_m": "min pair distance",
    "min_obstacle_center_distance_m": "min robot–obstacle centre distance",
    "min_left_leg_distance_m": "min left leg distance",
    "min_right_leg_distance_m": "min right leg distance",
    "min_speed_m_s": "min speed",
    "max_speed_m_s": "max speed",
    "tick_duration_s": "tick duration",
    "link_latency_s": "link latency",
}


#: Colour (RGBA) of a vehicle point by phase (``bus.base.Phase`` values); others grey.
PHASE_COLORS: dict[str, int] = {
    "connecting": 0x9E9E9EFF,
    "ready": 0x78909CFF,
    "arming": 0xFFB300FF,
    "takeoff": 0xFFB300FF,
    "in_tube": 0x1E88E5FF,
    "exited": 0x43A047FF,
    "holding": 0xFB8C00FF,
    "landing": 0x8E24AAFF,
    "landed": 0x6D4C41FF,
    "lost": 0xE53935FF,
    "failed": 0xB71C1CFF,
}


#: Colour of a vehicle without a phase (the simulator).
DEFAULT_COLOR = 0x1E88E5FF


#: Colour of a phase not in :data:`PHASE_COLORS`.
OTHER_COLOR = 0x9E9E9EFF


#: Event level → rerun TextLog level.
LOG_LEVELS = {
    "trace": "TRACE",
    "debug": "DEBUG",
    "info": "INFO",
    "warn": "WARN",
    "warning": "WARN",
    "error": "ERROR",
    "critical": "CRITICAL",
}


def stream_entity(suffix: str) -> str:
    """Summary stream suffix → entity path: ``""`` → ``safety/main``, ``"_center"`` →
    ``safety/center``."""
    return SAFETY_PREFIX + (suffix.lstrip("_") or "main")
