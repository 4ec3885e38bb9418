"""Scenario configuration: a TOML file → a frozen :class:`Scenario`.

A scenario is everything the paper's simulation needs (Section V-A): the corridor — one
trapezoid virtual tube T(p_h0, p_h1, p_r0, p_r1) (``[tube]``) or a route of chained trapezoids
given by waypoints (``[[route.waypoints]]``, docs/route.md) — the circular obstacles O_k
(obstacle), the robots (model, initial positions, r_s, r_a, v_min, v_max), the controller
parameters of (ModifiedVectorField) and (TraCondition), and the simulation settings. The format
is documented in ``docs/config.md``. Waypoints may be given in latitude/longitude in a mission
file (its ``[mission]`` anchor places them in the tube frame, :mod:`vtube_fleet.frames`).

Parsing is strict: an unknown key, a wrong type (``true`` is not a number), a missing required
key or a non-finite number raises :class:`~vtube_fleet.errors.ConfigError` whose message names
the file and the key, e.g. ``paper.toml: [robots].r_s: expected a number, got "abc"``.

Every key, with its type, unit, default, bounds and meaning, is declared once in
:data:`SCENARIO_KEYS` (:class:`~vtube_fleet.config.keys.Key`, one tuple per section): the parser
reads it, and the table in ``docs/config.md`` is generated from it (:func:`scenario_keys_table`;
a test keeps them equal). Bounds are physical where they exist: radii and spacings > 0, speeds
within PX4's horizontal limit :data:`PX4_MAX_HORIZONTAL_M_S`, ``dt`` within [1 µs, 1 s] and at most
:data:`MAX_SIM_STEPS` steps, durations finite, at most :data:`MAX_ROBOTS` robots. The
controller's parameters come from :mod:`vtube_fleet.core.params` (their names, defaults and the
one domain check, :func:`~vtube_fleet.core.params.parameter_problems`).

Other programs reuse the parser for files that carry extra top-level tables (the fleet's mission
files add ``[mission]``): pass ``extra_sections=("mission",)`` and read the raw table from
:attr:`Scenario.extra`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from vtube_fleet.config.keys import (
    NON_NEGATIVE,
    POSITIVE,
    Bound,
    Key,
    markdown_table,
    show_value,
)
from vtube_fleet.core.integrate import DEFAULT_INTEGRATOR, INTEGRATORS
from vtube_fleet.core.params import (
    CONTROLLER_DEFAULTS,
    CONTROLLER_REQUIRED,
    ControllerParams,
    parameter_problems,
)
from vtube_fleet.core.route import Corridor, RouteGeometry, Waypoint
from vtube_fleet.core.tube import APEX_AUTO, Obstacle, Trapezoid
from vtube_fleet.errors import ConfigError, UserError

__all__ = [
    "MAX_ROBOTS",
    "MAX_SIM_STEPS",
    "MIN_DT_S",
    "MODELS",
    "PX4_MAX_HORIZONTAL_M_S",
    "SCENARIO_KEYS",
    "RobotsConfig",
    "Scenario",
    "SimConfig",
    "content_hash",
    "grid_positions",
    "load_scenario",
    "parse_scenario",
    "scenario_key",
    "scenario_keys_table",
]

#: Robot models understood by the simulator: (Single) and the unicycle driven through (NID).
MODELS: tuple[str, ...] = ("single_integrator", "unicycle")

#: Defaults of the optional [sim] table.
DEFAULT_DT_S = 0.001
DEFAULT_DURATION_S = 60.0

#: PX4's default limit of the horizontal velocity (MPC_XY_VEL_MAX, m/s): a faster setpoint is
#: silently clipped, so no speed of a scenario (v_min, v_max, v, v'_max) may exceed it.
PX4_MAX_HORIZONTAL_M_S = 12.0
#: The documented ceiling of the swarm's size: the controller's pair terms grow as M² per step
#: (the paper flies 120; MAVLink's system ids cap a real fleet at 255).
MAX_ROBOTS = 10_000
#: At most this many simulation steps (``[sim].duration / [sim].dt``): 10^8 steps of the paper's
#: scenario take days; a smaller ``dt`` is a typo, not a plan.
MAX_SIM_STEPS = 10**8
#: The smallest ``dt`` (s): a microsecond, a thousandth of the paper's step (smaller is a typo).
MIN_DT_S = 1e-6
#: At most this many route waypoints (a corridor of 99 segments is already a long flight plan).
MAX_WAYPOINTS = 100

_SPEED = Bound(0.0, PX4_MAX_HORIZONTAL_M_S, why="PX4's MPC_XY_VEL_MAX default: faster "
               "setpoints are clipped")
_COUNT = Bound(1, MAX_ROBOTS, low_inclusive=True, why="the documented ceiling of the swarm")

#: The meaning of each controller parameter (their names, defaults and domain:
#: :mod:`vtube_fleet.core.params`).
_CONTROLLER_MEANINGS: Mapping[str, tuple[str, str]] = {
    "v": ("speed of the line-approaching term u1''", "m/s"),
    "v_max_prime": ("v'_max, the bound of the saturated repulsive part", "m/s"),
    "k2": ("gain of the robot–robot barrier (Vmij)", ""),
    "k3": ("gain of the tube-leg barriers (Vtli1)/(Vtri1)", ""),
    "k_t": ("width factor of the L/R areas (≥ 1)", ""),
    "eps_m": ("ε_m of (Vmij) (in [1e-12, 1])", ""),
    "eps_t": ("ε_t of (Vtli1)/(Vtri1) (in [1e-12, 1])", ""),
    "eps_s": ("ε_s of the smooth saturation s(·) (in [1e-12, 0.1])", ""),
    "eps_0": ("ε_0 of (TraCondition): a robot exits when −n_cᵀ(p − p_r1) ≤ ε_0", "m"),
    "k4": ("gain of Appendix C's obstacle potential (`--controller apf` only)", ""),
    "eps_o": ("ε_o of Appendix C's obstacle potential (`--controller apf` only, in "
              "[1e-12, 1])", ""),
}
_DOMAIN = "then the `ControllerParams` domain check (core/params.py)"


def _controller_key(name: str) -> Key:
    meaning, unit = _CONTROLLER_MEANINGS[name]
    speed = name in ("v", "v_max_prime")
    return Key(name, "number", meaning, unit, CONTROLLER_DEFAULTS.get(name),
               required=name in CONTROLLER_REQUIRED, bound=_SPEED if speed else POSITIVE,
               bound_note=_DOMAIN)


#: Every scenario key, section by section (``"robots.grid"``: the inline table ``[robots].grid``):
#: type, unit, default, bounds, meaning. The one source of the parser and of the table in
#: docs/config.md (:func:`scenario_keys_table`).
SCENARIO_KEYS: Mapping[str, tuple[Key, ...]] = {
    "tube": (
        Key("p_h0", "point", "start of the left leg", "m", required=True),
        Key("p_h1", "point", "end of the left leg", "m", required=True),
        Key("p_r0", "point", "start of the right leg", "m", required=True),
        Key("p_r1", "point", "end of the right leg", "m", required=True),
    ),
    "route": (
        Key("waypoints", "other", "the route's waypoints, in order (2 or more; instead of "
            "`[tube]`); waypoints i and i + 1 make segment i (docs/route.md)",
            type_label="array of tables", default_text="`[tube]` instead",
            bound_note=f"2 to {MAX_WAYPOINTS} waypoints"),
    ),
    "route.waypoints": (
        Key("position", "point", "waypoint position c_i (the middle of its base lines)", "m",
            default_text="one of `position`/`lat_lon`"),
        Key("lat_lon", "other", "waypoint position as WGS84 latitude and longitude (mission "
            "files only: their `[mission]` anchor puts it in the tube frame)", "deg",
            type_label="`[lat, lon]`", default_text="one of `position`/`lat_lon`",
            bound_note="latitude in (-90, 90), longitude in [-180, 180]"),
        Key("half_width", "number", "w_i: the corridor's half-width at the waypoint, measured "
            "perpendicular to each adjacent segment", "m", required=True, bound=POSITIVE),
        Key("heading_deg", "number", "direction of flight across the base lines of the "
            "segment starting here, counter-clockwise from the frame's x axis (the last "
            "waypoint's must equal its segment's)", "deg",
            bound=Bound(-360.0, 360.0, low_inclusive=True, interval=True),
            default_text="towards the next waypoint"),
        Key("bearing_deg", "number", "the same as a compass bearing, clockwise from true "
            "north (mission files only; instead of `heading_deg`)", "deg",
            bound=Bound(-360.0, 360.0, low_inclusive=True, interval=True),
            default_text="towards the next waypoint"),
        Key("overlap_m", "number", "e_i: how far both segments are prolonged at this "
            "waypoint's bend (the hand-over overlap, docs/route.md)", "m", bound=NON_NEGATIVE,
            default_text="the mitre w_i tan(|θ_i|/2)"),
    ),
    "obstacles": (
        Key("center", "point", "obstacle centre p_o,k", "m", required=True),
        Key("radius", "number", "obstacle radius r_o,k", "m", required=True, bound=POSITIVE),
        Key("apex_distance", "number", "h_k = ‖p_oth,k − p_o,k‖ of the circumscribed triangle; "
            '`"auto"`: chosen by the planner jointly with the other `"auto"` ones', "m",
            bound=POSITIVE, also=(APEX_AUTO,), bound_note="and > `radius`",
            default_text="`[partition].apex_distance`"),
    ),
    "partition": (
        Key("apex_distance", "choice", "the apex distance of every obstacle that has none of "
            'its own: `"auto"` lets the planner choose them all jointly, `"default"` is '
            "1.3 h_min", default="default", choices=(APEX_AUTO, "default")),
    ),
    "robots": (
        Key("model", "choice", "(Single), or a unicycle driven through (NID)",
            default="single_integrator", choices=MODELS),
        Key("r_s", "number", "safety radius", "m", required=True, bound=POSITIVE),
        Key("r_a", "number", "avoidance radius", "m", required=True, bound=POSITIVE,
            bound_note="and > `r_s`"),
        Key("v_min", "number", "minimum permitted speed", "m/s", required=True,
            bound=Bound(0.0, PX4_MAX_HORIZONTAL_M_S, low_inclusive=True, why=_SPEED.why)),
        Key("v_max", "number", "maximum permitted speed", "m/s", required=True, bound=_SPEED,
            bound_note="and > `v_min`"),
        Key("grid", "other", "`{ origin = [x0, y0], rows = R, cols = C, spacing = s }` (below)",
            type_label="table", default_text="one of `grid`/`positions`"),
        Key("positions", "other", "explicit initial positions", "m",
            type_label="array of `[x, y]`", default_text="one of `grid`/`positions`",
            bound_note=f"1 to {MAX_ROBOTS} points"),
        Key("nid_distance", "number", "s of (NID): the control point is p + s[cos θ, sin θ] "
            "(unicycles only)", "m", bound=POSITIVE, default_text="required for unicycles"),
        Key("headings", "other", "initial headings θ_i (unicycles only)", "rad",
            type_label="number or array of M numbers", default_text="facing n_c",
            bound_note="finite"),
    ),
    "robots.grid": (
        Key("origin", "point", "position (x0, y0) of robot 0", "m", required=True),
        Key("rows", "integer", "R, robots along x", required=True, bound=_COUNT),
        Key("cols", "integer", "C, robots along y", required=True, bound=_COUNT,
            bound_note=f"and rows × cols <= {MAX_ROBOTS}"),
        Key("spacing", "number", "s, the distance between neighbours of the grid", "m",
            required=True, bound=POSITIVE),
    ),
    "controller": tuple(_controller_key(n) for n in (*CONTROLLER_REQUIRED,
                                                     *CONTROLLER_DEFAULTS)),
    "sim": (
        Key("dt", "number", "time step", "s", DEFAULT_DT_S,
            bound=Bound(MIN_DT_S, 1.0, low_inclusive=True,
                        why="a second: the barriers need many steps per crossing"),
            bound_note=f"in a file also `duration / dt` <= {MAX_SIM_STEPS:.0e}".replace(
                "e+0", "e")),
        Key("duration", "number", "simulated time; the run also stops when every robot has "
            "exited", "s", DEFAULT_DURATION_S,
            bound=Bound(0.0, 86400.0, why="a day of simulated time")),
        Key("record_every", "integer", "keep every K-th step in `trajectory.npz`",
            bound=Bound(1, low_inclusive=True), default_text="automatic"),
        Key("integrator", "choice", "`adaptive`, `rk4` or `euler` (see [Integrators]"
            "(#integrators))", default=DEFAULT_INTEGRATOR, choices=INTEGRATORS),
    ),
}


def _section_title(section: str) -> str:
    return {"obstacles": "[[obstacles]]", "robots.grid": "[robots].grid",
            "route.waypoints": "[[route.waypoints]]"}.get(section, f"[{section}]")


def scenario_key(section: str, name: str) -> Key:
    """The declared key ``name`` of ``section`` (``"sim"``, ``"robots.grid"`` …)."""
    for k in SCENARIO_KEYS[section]:
        if k.name == name:
            return k
    raise KeyError(f"{section}.{name}")


def scenario_keys_table() -> str:
    """The table of docs/config.md, generated from :data:`SCENARIO_KEYS`: one row per key,
    named ``[section].key``."""
    rows = []
    for section, keys in SCENARIO_KEYS.items():
        title = _section_title(section)
        rows += [dataclasses.replace(k, name=f"{title}.{k.name}") for k in keys]
    return markdown_table(rows)


@dataclass(frozen=True, eq=False)
class RobotsConfig:
    """The swarm: model, initial positions (config order) and the robot-level parameters.

    ``positions`` (M, 2) are robot centres in the tube frame. For ``model == "unicycle"``,
    ``headings`` (M,) are the initial headings θ_i in radians and ``nid_distance`` is s of
    (NID), the distance of the control point ahead of the centre; both are ``None`` otherwise.
    """

    model: str
    positions: np.ndarray
    r_s: float
    r_a: float
    v_min: float
    v_max: float
    headings: np.ndarray | None = None
    nid_distance: float | None = None

    @property
    def count(self) -> int:
        """M, the number of robots."""
        return int(self.positions.shape[0])

    def control_points(self) -> np.ndarray:
        """Points where the controller is evaluated: centres, or p + s[cos θ, sin θ] (NID)."""
        if self.model != "unicycle":
            return self.positions.copy()
        assert self.headings is not None and self.nid_distance is not None
        h = self.headings
        return self.positions + self.nid_distance * np.stack([np.cos(h), np.sin(h)], axis=-1)


@dataclass(frozen=True)
class SimConfig:
    """[sim]: step ``dt`` (s), simulated ``duration`` (s), optional decimation, and the
    ``integrator`` (:data:`vtube_fleet.core.integrate.INTEGRATORS`)."""

    dt: float = DEFAULT_DT_S
    duration: float = DEFAULT_DURATION_S
    record_every: int | None = None
    integrator: str = DEFAULT_INTEGRATOR


@dataclass(frozen=True, eq=False)
class Scenario:
    """A parsed scenario: ``geometry`` (the segments of its route: one for a ``[tube]``),
    ``obstacles`` (config order), robots, controller, sim. ``extra`` holds the raw tables of the
    allowed extra sections. :attr:`corridor` is the geometry with its obstacles, the one object
    the checks, the simulator and the recorder take."""

    geometry: RouteGeometry
    obstacles: tuple[Obstacle, ...]
    robots: RobotsConfig
    controller: ControllerParams
    sim: SimConfig
    source: str = "<config>"
    extra: Mapping[str, Any] = field(default_factory=dict)
    #: :func:`content_hash` of the parsed document (comments and formatting do not count)
    content_hash: str = ""

    @cached_property
    def corridor(self) -> Corridor:
        """The route's geometry and the obstacles (each owned by its segment)."""
        return Corridor(self.geometry, tuple(self.obstacles))

    @property
    def tube(self) -> Trapezoid:
        """The one trapezoid of a ``[tube]`` scenario; a route of several segments refuses
        (:class:`~vtube_fleet.core.route.RouteError`, one ``error:`` line) where a caller
        still expects one tube."""
        return self.corridor.tube

    @property
    def is_route(self) -> bool:
        """More than one segment."""
        return not self.geometry.is_single

    def with_robots(self, n: int) -> Scenario:
        """The same scenario keeping only the first ``n`` robots (config order)."""
        m = self.robots.count
        if not (isinstance(n, int) and 1 <= n <= m):
            raise ConfigError(f"{self.source}: --robots must be between 1 and {m}, got {n}")
        r = self.robots
        robots = dataclasses.replace(
            r,
            positions=_frozen(r.positions[:n]),
            headings=None if r.headings is None else _frozen(r.headings[:n]),
        )
        return dataclasses.replace(self, robots=robots)

    def with_sim(self, **changes: Any) -> Scenario:
        """The same scenario with some [sim] fields replaced (``dt``, ``duration``...)."""
        return dataclasses.replace(self, sim=dataclasses.replace(self.sim, **changes))


# ----------------------------------------------------------------------------------------
# entry points
# ----------------------------------------------------------------------------------------


def load_scenario(path: str | os.PathLike[str], extra_sections: Iterable[str] = ()) -> Scenario:
    """Read and parse a TOML scenario file (see :func:`parse_scenario`)."""
    source = os.fspath(path)
    try:
        with open(source, "rb") as fh:
            raw = fh.read()
    except FileNotFoundError:
        raise ConfigError(f"{source}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{source}: is a directory, expected a TOML file") from None
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read: {exc.strerror or exc}") from None
    try:  # a leading byte-order mark (Windows editors write one) is not part of the text
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{source}: not UTF-8 text (byte {exc.start})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        msg = " ".join(str(exc).split())
        raise ConfigError(f"{source}: invalid TOML: {msg}") from None
    return parse_scenario(data, source, extra_sections=extra_sections)


def parse_scenario(
    data: Mapping[str, Any], source: str = "<config>", extra_sections: Iterable[str] = ()
) -> Scenario:
    """Build a :class:`Scenario` from an already-decoded TOML document.

    ``source`` prefixes every error message (normally the file name). Top-level tables named in
    ``extra_sections`` are accepted unparsed and returned in :attr:`Scenario.extra`.
    """
    p = _Parser(source)
    extra_names = tuple(extra_sections)
    known = ("tube", "route", "obstacles", "robots", "controller", "sim", "partition",
             *extra_names)
    p.check_keys(data, known, "")
    if "route" in data:
        if "tube" in data:
            raise p.error("[route]", "give either [tube] (one trapezoid) or [route] (waypoints), "
                                     "not both")
        geometry = p.parse_route(p.table(data, "route", ""), data)
    else:
        geometry = RouteGeometry.single(p.parse_tube(p.table(data, "tube", "")))
    apex_default = p.parse_partition(p.table(data, "partition", "", required=False))
    obstacles = p.parse_obstacles(data.get("obstacles", []), apex_default)
    robots = p.parse_robots(p.table(data, "robots", ""), geometry.segments[0])
    controller = p.parse_controller(p.table(data, "controller", ""), robots)
    sim = p.parse_sim(p.table(data, "sim", "", required=False))
    extra = {}
    for name in extra_names:
        if name in data:
            extra[name] = p.table(data, name, "")
    return Scenario(
        geometry=geometry,
        obstacles=obstacles,
        robots=robots,
        controller=controller,
        sim=sim,
        source=source,
        extra=extra,
        content_hash=content_hash(data),
    )


def content_hash(data: Mapping[str, Any]) -> str:
    """Hash of a parsed TOML document (canonical JSON; comments and formatting do not count):
    16 hex digits of SHA-256. Two files with the same hash configure the same run."""
    canonical = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(canonical.encode()).hexdigest()[:16]


def grid_positions(
    origin: tuple[float, float] | np.ndarray, rows: int, cols: int, spacing: float
) -> np.ndarray:
    """Robots at (x0 + i·spacing, y0 + j·spacing), i < rows, j < cols; index = i·cols + j."""
    i, j = np.divmod(np.arange(rows * cols), cols)
    return np.stack([origin[0] + i * spacing, origin[1] + j * spacing], axis=-1).astype(float)


# ----------------------------------------------------------------------------------------
# implementation
# ----------------------------------------------------------------------------------------


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


#: a point ``[x, y]`` (positions of ``[robots].positions``)
_POINT = Key("point", "point", "a point", "m")


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


class _Parser:
    def __init__(self, source: str) -> None:
        self.source = source

    # ----- primitives -------------------------------------------------------------------
    def error(self, where: str, message: str) -> ConfigError:
        return ConfigError(f"{self.source}: {where}: {message}" if where else
                           f"{self.source}: {message}")

    @staticmethod
    def name(section: str, key: str) -> str:
        if not section:
            return f"[{key}]"
        return f"{section}.{key}"

    def check_keys(self, table: Mapping[str, Any], allowed: Iterable[str], section: str) -> None:
        allowed = tuple(allowed)
        for key in table:
            if key not in allowed:
                where = f"[{key}]" if not section else self.name(section, key)
                raise self.error(
                    where, f"unknown key (allowed: {', '.join(allowed)})"
                )

    def table(
        self, data: Mapping[str, Any], key: str, section: str, required: bool = True
    ) -> Mapping[str, Any]:
        where = self.name(section, key)
        if key not in data:
            if required:
                raise self.error(where, "missing required table")
            return {}
        value = data[key]
        if not isinstance(value, dict):
            raise self.error(where, f"expected a table, got {show_value(value)}")
        return value

    def value(self, table: Mapping[str, Any], key: Key, section: str) -> Any:
        """``table[key.name]`` checked against its declaration (:data:`SCENARIO_KEYS`): its
        default when absent, ``missing required key`` when required."""
        where = self.name(section, key.name)
        if key.name not in table:
            if key.required:
                raise self.error(where, "missing required key")
            return key.default
        try:
            return key.parse(table[key.name])
        except ValueError as exc:
            raise self.error(where, str(exc)) from None

    def section_values(self, table: Mapping[str, Any], section: str, sec: str,
                       skip: Iterable[str] = ()) -> dict[str, Any]:
        """Check ``table``'s keys against ``SCENARIO_KEYS[section]`` and parse each declared
        (non-structured) key not in ``skip``: name → value."""
        keys = SCENARIO_KEYS[section]
        self.check_keys(table, (k.name for k in keys), sec)
        skip = tuple(skip)
        return {k.name: self.value(table, k, sec) for k in keys
                if k.kind != "other" and k.name not in skip}

    def point_value(self, value: Any, where: str) -> np.ndarray:
        try:
            return np.array(_POINT.parse(value), dtype=float)
        except ValueError as exc:
            raise self.error(where, str(exc)) from None

    # ----- sections ---------------------------------------------------------------------
    def parse_tube(self, t: Mapping[str, Any]) -> Trapezoid:
        sec = "[tube]"
        v = self.section_values(t, "tube", sec)
        pts = {k: np.array(x, dtype=float) for k, x in v.items()}
        try:
            return Trapezoid(pts["p_h0"], pts["p_h1"], pts["p_r0"], pts["p_r1"])
        except UserError as exc:
            raise self.error(sec, str(exc)) from None

    def parse_route(self, t: Mapping[str, Any], data: Mapping[str, Any]) -> RouteGeometry:
        """[route]: ``[[route.waypoints]]`` → the segments (:class:`RouteGeometry`); waypoints
        in latitude/longitude go through the mission's geodetic anchor."""
        self.check_keys(t, [k.name for k in SCENARIO_KEYS["route"]], "[route]")
        wsec = "[[route.waypoints]]"
        raw = t.get("waypoints")
        if raw is None:
            raise self.error("[route].waypoints", "missing required key")
        if not isinstance(raw, list) or not all(isinstance(w, dict) for w in raw):
            raise self.error("[route].waypoints", f"expected an array of tables "
                                                  f"([[route.waypoints]]), got {show_value(raw)}")
        if not 2 <= len(raw) <= MAX_WAYPOINTS:
            raise self.error("[route].waypoints", f"a route needs 2 to {MAX_WAYPOINTS} "
                                                  f"waypoints, got {len(raw)}")
        frame = None
        wps = []
        for i, w in enumerate(raw):
            sec = f"{wsec}[{i}]"
            v = self.section_values(w, "route.waypoints", sec)
            has_pos, has_geo = "position" in w, "lat_lon" in w
            if has_pos == has_geo:
                raise self.error(sec, "give exactly one of position = [x, y] (metres) and "
                                      "lat_lon = [lat, lon] (degrees)")
            if "heading_deg" in w and "bearing_deg" in w:
                raise self.error(sec, "give heading_deg or bearing_deg, not both")
            if has_geo or "bearing_deg" in w:
                if frame is None:
                    frame = self.anchor(data, self.name(sec, "lat_lon" if has_geo
                                                        else "bearing_deg"))
            if has_geo:
                lat, lon = self.lat_lon(w["lat_lon"], self.name(sec, "lat_lon"))
                x, y, _ = frame.geodetic_to_tube(lat, lon, frame.alt0_m)
                pos = np.array([float(x), float(y)])
            else:
                pos = np.array(v["position"], dtype=float)
            heading = None
            if v["heading_deg"] is not None:
                heading = math.radians(v["heading_deg"])
            elif v["bearing_deg"] is not None:  # frame x is at compass heading_deg, y left
                heading = math.radians(frame.heading_deg - v["bearing_deg"])
            try:
                wps.append(Waypoint(pos, v["half_width"], heading, v["overlap_m"]))
            except UserError as exc:  # pragma: no cover - the keys' bounds come first
                raise self.error(sec, str(exc)) from None
        try:
            return RouteGeometry.from_waypoints(wps)
        except UserError as exc:
            raise self.error("[route]", str(exc)) from None

    def anchor(self, data: Mapping[str, Any], where: str) -> Any:
        """The tube frame of the file's ``[mission]`` anchor (lat/lon waypoints need it)."""
        from vtube_fleet.config.mission import MISSION_KEYS  # (mission imports this module)
        from vtube_fleet.frames import TubeFrame

        m = data.get("mission")
        if not isinstance(m, dict):
            raise self.error(where, "latitude/longitude need the geodetic anchor of a "
                                    "[mission] table (origin_lat_deg, origin_lon_deg, "
                                    "origin_alt_m, heading_deg): give position = [x, y] in "
                                    "metres instead")
        keys = {k.name: k for k in MISSION_KEYS}
        vals = {}
        for name in ("origin_lat_deg", "origin_lon_deg", "origin_alt_m", "heading_deg"):
            if name not in m:
                raise self.error(f"[mission].{name}", "missing required key (the anchor of "
                                                      f"{where})")
            try:
                vals[name] = keys[name].parse(m[name])
            except ValueError as exc:
                raise self.error(f"[mission].{name}", str(exc)) from None
        try:
            return TubeFrame(vals["origin_lat_deg"], vals["origin_lon_deg"],
                             vals["origin_alt_m"], vals["heading_deg"])
        except UserError as exc:  # pragma: no cover - the keys' bounds come first
            raise self.error("[mission]", str(exc)) from None

    def lat_lon(self, value: Any, where: str) -> tuple[float, float]:
        try:
            lat, lon = _POINT.parse(value)
        except ValueError:
            raise self.error(where, f"expected [lat, lon] in degrees, got {show_value(value)}"
                             ) from None
        if not -90.0 < lat < 90.0:
            raise self.error(where, f"latitude must be within (-90, 90), got {lat:g}")
        if not -180.0 <= lon <= 180.0:
            raise self.error(where, f"longitude must be within [-180, 180], got {lon:g}")
        return lat, lon

    def parse_partition(self, t: Mapping[str, Any]) -> str | None:
        """[partition]: ``apex_distance = "auto" | "default"``, the apex distance of every
        obstacle without its own (``"default"``: 1.3 h_min; ``"auto"``: core/plan.py)."""
        v = self.section_values(t, "partition", "[partition]")
        return APEX_AUTO if v["apex_distance"] == APEX_AUTO else None

    def parse_obstacles(self, value: Any, apex_default: str | None = None
                        ) -> tuple[Obstacle, ...]:
        if not isinstance(value, list) or not all(isinstance(o, dict) for o in value):
            raise self.error(
                "[[obstacles]]", f"expected an array of tables, got {show_value(value)}"
            )
        out = []
        for idx, o in enumerate(value):
            sec = f"[[obstacles]][{idx}]"
            v = self.section_values(o, "obstacles", sec)
            radius = v["radius"]
            apex: float | str | None = apex_default if v["apex_distance"] is None \
                else v["apex_distance"]
            if isinstance(apex, float) and apex <= radius:
                raise self.error(
                    self.name(sec, "apex_distance"),
                    f"must exceed the radius {radius:g}, got {apex:g}",
                )
            out.append(Obstacle(center=np.array(v["center"], dtype=float), radius=radius,
                                apex_distance=apex))
        return tuple(out)

    def parse_robots(self, r: Mapping[str, Any], tube: Trapezoid) -> RobotsConfig:
        sec = "[robots]"
        v = self.section_values(r, "robots", sec, skip=("nid_distance",))
        model, r_s, r_a = v["model"], v["r_s"], v["r_a"]
        v_min, v_max = v["v_min"], v["v_max"]
        robot_values = {"r_s": r_s, "r_a": r_a, "v_min": v_min, "v_max": v_max}
        problems = parameter_problems(robot_values)  # the one domain check (core/params.py)
        if problems:  # its messages start with the parameter's name: the key to blame
            key = problems[0].split(" ", 1)[0]
            raise self.error(self.name(sec, key) if key in robot_values else sec,
                             "; ".join(problems))

        has_grid, has_pos = "grid" in r, "positions" in r
        if has_grid and has_pos:
            raise self.error(sec, "give either grid or positions, not both")
        if not (has_grid or has_pos):
            raise self.error(self.name(sec, "grid"), "missing required key (or positions)")
        if has_grid:
            gsec = self.name(sec, "grid")
            g = r["grid"]
            if not isinstance(g, dict):
                raise self.error(gsec, f"expected a table, got {show_value(g)}")
            gv = self.section_values(g, "robots.grid", gsec)
            if gv["rows"] * gv["cols"] > MAX_ROBOTS:
                raise self.error(self.name(gsec, "cols"),
                                 f"rows × cols must be <= {MAX_ROBOTS} (the documented ceiling "
                                 f"of the swarm), got {gv['rows']} × {gv['cols']}")
            positions = grid_positions(gv["origin"], gv["rows"], gv["cols"], gv["spacing"])
        else:
            psec = self.name(sec, "positions")
            pv = r["positions"]
            if not isinstance(pv, list) or not pv:
                raise self.error(psec, "expected a non-empty array of [x, y], got "
                                 f"{show_value(pv)}")
            if len(pv) > MAX_ROBOTS:
                raise self.error(psec, f"at most {MAX_ROBOTS} robots (the documented ceiling of "
                                       f"the swarm), got {len(pv)}")
            positions = np.array(
                [self.point_value(v, f"{psec}[{i}]") for i, v in enumerate(pv)], dtype=float
            )
        m = positions.shape[0]

        headings = nid = None
        if model == "unicycle":
            nid = self.value(r, scenario_key("robots", "nid_distance"), sec)
            if nid is None:
                raise self.error(self.name(sec, "nid_distance"), "missing required key")
            hv = r.get("headings")
            hsec = self.name(sec, "headings")
            if hv is None:
                # default: every robot faces along n_c (towards the finishing line)
                headings = np.full(m, math.atan2(tube.n_c[1], tube.n_c[0]))
            elif _is_number(hv):
                if not math.isfinite(hv):
                    raise self.error(hsec, f"expected a finite number, got {show_value(hv)}")
                headings = np.full(m, float(hv))
            elif isinstance(hv, list):
                if len(hv) != m or not all(_is_number(h) for h in hv):
                    raise self.error(
                        hsec, f"expected a number or {m} numbers (one per robot), got "
                        f"{show_value(hv)}"
                    )
                headings = np.array(hv, dtype=float)
                if not np.all(np.isfinite(headings)):
                    raise self.error(hsec, f"expected finite numbers, got {show_value(hv)}")
            else:
                raise self.error(hsec, f"expected a number or an array, got {show_value(hv)}")
        else:
            for key in ("nid_distance", "headings"):
                if key in r:
                    raise self.error(
                        self.name(sec, key), f'only allowed with model = "unicycle" (got {model})'
                    )
        return RobotsConfig(
            model=model,
            positions=_frozen(positions),
            r_s=r_s,
            r_a=r_a,
            v_min=v_min,
            v_max=v_max,
            headings=None if headings is None else _frozen(headings),
            nid_distance=nid,
        )

    def parse_controller(self, c: Mapping[str, Any], robots: RobotsConfig) -> ControllerParams:
        sec = "[controller]"
        values = self.section_values(c, "controller", sec)
        problems = parameter_problems(
            {"r_s": robots.r_s, "r_a": robots.r_a, "v_min": robots.v_min, "v_max": robots.v_max,
             **values})
        if problems:  # the one domain check (core/params.py), reported here with the file
            raise self.error(sec, "; ".join(problems))
        return ControllerParams(
            r_s=robots.r_s, r_a=robots.r_a, v_min=robots.v_min, v_max=robots.v_max, **values
        )

    def parse_sim(self, s: Mapping[str, Any]) -> SimConfig:
        sec = "[sim]"
        v = self.section_values(s, "sim", sec)
        steps = v["duration"] / v["dt"]
        if steps > MAX_SIM_STEPS:
            raise self.error(self.name(sec, "dt"),
                             f"duration / dt must be <= {MAX_SIM_STEPS:.0e} steps, got "
                             f"{v['duration']:g} / {v['dt']:g} = {steps:.3g}")
        return SimConfig(dt=v["dt"], duration=v["duration"], record_every=v["record_every"],
                         integrator=v["integrator"])
