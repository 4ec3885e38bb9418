"""The layout of a recording, shared by writer and reader.

Entity paths, timelines, component names, the metadata format, colours and metric names.
"""

from __future__ import annotations

from collections.abc import Iterator

__all__ = [
    "COMMAND_COLOR",
    "DEFAULT_COLOR",
    "DEFAULT_CONNECT_URL",
    "DEFAULT_RECORDING_NAME",
    "EVENT_ARCHETYPE",
    "EXIT_ARCHETYPE",
    "E_COMMANDS",
    "E_EVENTS",
    "E_AXES",
    "E_EXITS",
    "E_LEGEND",
    "E_MAP",
    "E_MAP_FENCE",
    "E_MAP_OBSTACLES",
    "E_MAP_OUTLINE",
    "E_MAP_SLOTS",
    "E_META",
    "E_OBSTACLES",
    "E_OBSTACLES_EXT",
    "E_STATUS",
    "E_SUB_TUBES",
    "E_SUMMARY",
    "E_JUNCTIONS",
    "E_TRIANGLES",
    "E_TUBE",
    "E_VEHICLES",
    "E_VEHICLE_EVENTS",
    "E_VELOCITY",
    "E_WORLD",
    "LABELS_MAX_VEHICLES",
    "LIMITS_PREFIX",
    "LIMIT_COLOR",
    "LOG_LEVELS",
    "MAP_FENCE_COLOR",
    "MAP_OBSTACLE_COLOR",
    "MAP_OUTLINE_COLOR",
    "MAP_POINT_RADIUS_PT",
    "MAP_SLOT_COLOR",
    "LIMIT_PERIOD_S",
    "META_FORMAT",
    "META_VERSION",
    "METRICS_PREFIX",
    "METRIC_COLORS",
    "METRIC_NAMES",
    "METRIC_VARIANTS",
    "METRIC_VIEWS",
    "OBSTACLE_COLOR",
    "OTHER_COLOR",
    "PHASE_CLASSES",
    "PHASE_COLORS",
    "SAFETY_ARCHETYPE",
    "SAFETY_PREFIX",
    "SIM_MIN_PERIOD_S",
    "STATE_ARCHETYPE",
    "SUB_TUBE_COLOR",
    "TIMELINE_TICK",
    "TIMELINE_TIME",
    "PATH_COLOR",
    "PATH_STEP_S",
    "TRAIL_S",
    "TRAIL_STEP_S",
    "TRIANGLE_COLOR",
    "TUBE_COLOR",
    "VELOCITY_COLOR",
    "class_color",
    "class_of",
    "metric_name",
    "metric_variants",
    "stream_entity",
    "vehicle_entity",
    "vehicle_path_entity",
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


#: The tube frame (x along the tube, y to the left of the heading). No transform: the 2-D view
#: shows these coordinates as they are, y drawn downwards (rerun's 2-D convention); the axis key
#: ``world/axes`` says so in the view, and hover / selection read the true (x, y).
E_WORLD = "world"


E_AXES = "world/axes"


#: The phase colour key: one labelled point per annotation class, under the framed region.
E_LEGEND = "world/legend"


#: The corridor: one outline per segment of the route (one ``tube T`` for a single tube).
E_TUBE = "world/tube"


#: A route's junctions: each bend's mitre line (the corridor's inner to outer corner) and its
#: waypoint, labelled with the bend angle.
E_JUNCTIONS = "world/junctions"


E_OBSTACLES = "world/obstacles"


E_OBSTACLES_EXT = "world/obstacles/extended"


E_SUB_TUBES = "world/sub_tubes"


E_TRIANGLES = "world/triangles"


#: The map (WGS84): static outlines as ``GeoLineStrings``, converted from the tube frame with the
#: mission's geodetic anchor (:class:`vtube_fleet.frames.TubeFrame`, the fence's geodesy). The
#: vehicles are drawn on the map from their own entities (``world/vehicles/<id>`` carry
#: ``GeoPoints`` and a ``GeoLineStrings`` trail beside the 2-D point), so one selection
#: highlights a drone in both views.
E_MAP = "map"


#: The tube outline (one polyline per tube; a route of several segments adds one per segment).
E_MAP_OUTLINE = "map/tube"


E_MAP_OBSTACLES = "map/obstacles"


#: The PX4 geofence the fleet uploads: its inclusion polygon and exclusion circles.
E_MAP_FENCE = "map/fence"


#: The start slots: a circle of radius r_s around each.
E_MAP_SLOTS = "map/slots"


#: The exact float64 state of every vehicle per tick (``vtube_fleet.VehicleState:*``, one row per
#: tick for the whole fleet: ``review`` reads it); the display is per vehicle, see
#: :func:`vehicle_entity`.
E_VEHICLES = "world/vehicles"


#: Not written any more (the velocity arrow is on each vehicle's entity); kept for old readers.
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


#: Metric keys shown in the default blueprint, by view: (view name, metric keys).
METRIC_VIEWS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("min pair distance [m]", ("min_pair_distance_m",)),
    ("min obstacle-centre distance [m]", ("min_obstacle_center_distance_m",)),
    ("min obstacle clearance [m]", ("min_obstacle_clearance_m",)),
    ("min leg distances [m]", ("min_left_leg_distance_m", "min_right_leg_distance_m")),
    ("speed min / max [m/s]", ("min_speed_m_s", "max_speed_m_s")),
    ("tick duration [s]", ("tick_duration_s",)),
    ("link latency [s]", ("link_latency_s",)),
)


#: Variants of a metric key drawn in the same view as the key (same limit): (key → variant key,
#: legend suffix). The unicycle's robot centres (simulator) and the ground truth (``run
#: --truth``).
METRIC_VARIANTS: tuple[tuple[str, str], ...] = (
    ("{}_center", " (robot centre)"),
    ("truth_{}", " (truth)"),
)


#: Legend names of the known metric series.
METRIC_NAMES: dict[str, str] = {
    "min_pair_distance_m": "min pair distance",
    "min_obstacle_center_distance_m": "min robot–obstacle centre distance",
    "min_obstacle_clearance_m": "min robot–obstacle clearance (to the disc)",
    "min_left_leg_distance_m": "min left leg distance",
    "min_right_leg_distance_m": "min right leg distance",
    "min_speed_m_s": "min speed",
    "max_speed_m_s": "max speed",
    "tick_duration_s": "tick duration",
    "link_latency_s": "link latency",
}


#: Curve colour (RGBA) of the known metric series: the two curves of one view differ clearly
#: (blue / amber), none is red (the limits are red), variants are drawn lighter.
METRIC_COLORS: dict[str, int] = {
    "min_pair_distance_m": 0x1E88E5FF,
    "min_obstacle_center_distance_m": 0x1E88E5FF,
    "min_obstacle_clearance_m": 0x1E88E5FF,
    "min_left_leg_distance_m": 0x1E88E5FF,
    "min_right_leg_distance_m": 0xFFA000FF,
    "min_speed_m_s": 0x1E88E5FF,
    "max_speed_m_s": 0xFFA000FF,
    "tick_duration_s": 0x26A69AFF,
    "link_latency_s": 0x8D6E63FF,
}


def metric_variants(key: str) -> Iterator[tuple[str, str]]:
    """(base key, legend suffix) of every :data:`METRIC_VARIANTS` pattern ``key`` fits."""
    for pattern, suffix in METRIC_VARIANTS:
        head, _, tail = pattern.partition("{}")
        if key.startswith(head) and key.endswith(tail):
            yield (key[len(head):len(key) - len(tail)] if tail else key[len(head):]), suffix


def metric_name(key: str) -> str:
    """Legend name of a metric key (variants named after their base key; unknown keys as is)."""
    if key in METRIC_NAMES:
        return METRIC_NAMES[key]
    for base, suffix in metric_variants(key):
        if base in METRIC_NAMES:
            return METRIC_NAMES[base] + suffix
    return key


#: Colour of the safety-limit lines in the plots.
LIMIT_COLOR = 0xE53935FF


#: Colours of the scene. Every phase colour below differs clearly from these and from each other
#: (``tests/test_recording.py`` checks the distances).
TUBE_COLOR = 0xE0E0E0FF
SUB_TUBE_COLOR = 0x7986CB80
TRIANGLE_COLOR = 0xFB8C00FF
OBSTACLE_COLOR = 0x616161FF
VELOCITY_COLOR = 0x66BB6AFF
COMMAND_COLOR = 0xBDBDBD90


#: Annotation classes of the vehicle points and trails (``AnnotationContext`` at ``world``):
#: (class id, phase value or ``""`` for a robot without phases (the simulator), legend label,
#: RGBA colour). Class ids are stable (recordings keep their meaning); "other" comes last.
PHASE_CLASSES: tuple[tuple[int, str, str, int], ...] = (
    (0, "", "robot", 0x1E88E5FF),
    (1, "connecting", "connecting", 0xBDBDBDFF),
    (2, "ready", "ready", 0x80DEEAFF),
    (3, "arming", "arming", 0xF48FB1FF),
    (4, "takeoff", "take-off", 0xFFEE58FF),
    (5, "in_tube", "in tube", 0x1E88E5FF),
    (6, "exited", "exited", 0x00E676FF),
    (7, "holding", "holding", 0xD500F9FF),
    (8, "landing", "landing", 0x7C4DFFFF),
    (9, "landed", "landed", 0xA1887FFF),
    (10, "lost", "LOST", 0xFF1744FF),
    (11, "failed", "FAILED", 0x880E4FFF),
    (13, "waiting", "waiting", 0xC6FF00FF),
    (14, "stepping", "stepping aside", 0x006064FF),
    (12, "?", "other", 0xFF6E40FF),  # (last: the colour of anything else)
)


_CLASS_OF = {phase: cid for cid, phase, _, _ in PHASE_CLASSES}
_CLASS_COLOR = {cid: color for cid, _, _, color in PHASE_CLASSES}


def class_of(phase: str | None) -> int:
    """Annotation class id of a phase value (``None``: a robot without phases)."""
    if phase is None:
        return 0
    return _CLASS_OF.get(phase, _CLASS_OF["?"])


def class_color(cid: int) -> int:
    """RGBA colour of an annotation class id (a phase's colour; unknown ids: "other")."""
    return _CLASS_COLOR.get(int(cid), PHASE_CLASSES[-1][3])


#: Colours of the map's outlines: they must read on the light map tiles and on the viewer's dark
#: background when no tile can be fetched (offline), and differ from the phase colours.
MAP_OUTLINE_COLOR = 0x3949ABFF
MAP_FENCE_COLOR = 0xE53935FF
MAP_OBSTACLE_COLOR = 0x757575FF
MAP_SLOT_COLOR = 0x9E9D24FF


#: Radius (UI points) of a vehicle's point on the map: r_s is a pixel or two at street zoom.
MAP_POINT_RADIUS_PT = 5.0


#: Colour (RGBA) of a vehicle by phase (``state.Phase`` values), from :data:`PHASE_CLASSES`.
PHASE_COLORS: dict[str, int] = {phase: color for _, phase, _, color in PHASE_CLASSES
                                if phase not in ("", "?")}


#: Colour of a vehicle without a phase (the simulator).
DEFAULT_COLOR = PHASE_CLASSES[0][3]


#: Colour of a phase not in :data:`PHASE_COLORS`.
OTHER_COLOR = PHASE_CLASSES[-1][3]


#: Trails: each vehicle's recent path, the last TRAIL_S seconds sampled every TRAIL_STEP_S.
TRAIL_S = 3.0
TRAIL_STEP_S = 0.2


#: Whole-flight paths: at close, each vehicle's path (a point every PATH_STEP_S), drawn thin
#: and faint under the trails, so the whole flight shows at any time cursor.
PATH_STEP_S = 0.5
PATH_COLOR = (120, 120, 120, 140)


#: Vehicle labels (ids) are shown in the view up to this many vehicles (beyond: hover / click).
LABELS_MAX_VEHICLES = 30


def vehicle_entity(vehicle_id: int) -> str:
    """Display entity of one vehicle: its point (radius r_s, phase class), velocity arrow and
    trail — a click selects one drone."""
    return f"{E_VEHICLES}/{int(vehicle_id)}"


def vehicle_path_entity(vehicle_id: int) -> str:
    """The whole-flight path of one vehicle (static, written at close), under its entity."""
    return f"{vehicle_entity(vehicle_id)}/path"


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
