"""Scenario configuration: a TOML file → a frozen :class:`Scenario`.

A scenario is everything the paper's simulation needs (Section V-A): the main trapezoid virtual
tube T(p_h0, p_h1, p_r0, p_r1), the circular obstacles O_k (obstacle), the robots (model, initial
positions, r_s, r_a, v_min, v_max), the controller parameters of (ModifiedVectorField) and
(TraCondition), and the simulation settings. The format is documented in ``docs/config.md``.

Parsing is strict: an unknown key, a wrong type (``true`` is not a number), a missing required
key or a non-finite number raises :class:`~vtube_fleet.errors.ConfigError` whose message names
the file and the key, e.g. ``paper.toml: [robots].r_s: expected a number, got "abc"``.

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
from typing import Any

import numpy as np

from vtube_fleet.core.integrate import DEFAULT_INTEGRATOR, INTEGRATORS
from vtube_fleet.core.params import (
    CONTROLLER_DEFAULTS,
    CONTROLLER_REQUIRED,
    ControllerParams,
    parameter_problems,
)
from vtube_fleet.core.tube import APEX_AUTO, Obstacle, Trapezoid
from vtube_fleet.errors import ConfigError, UserError

__all__ = [
    "MODELS",
    "RobotsConfig",
    "Scenario",
    "SimConfig",
    "content_hash",
    "grid_positions",
    "load_scenario",
    "parse_scenario",
]

#: Robot models understood by the simulator: (Single) and the unicycle driven through (NID).
MODELS: tuple[str, ...] = ("single_integrator", "unicycle")

#: Defaults of the optional [sim] table.
DEFAULT_DT_S = 0.001
DEFAULT_DURATION_S = 60.0


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
    """A parsed scenario. ``extra`` holds the raw tables of the allowed extra sections."""

    tube: Trapezoid
    obstacles: tuple[Obstacle, ...]
    robots: RobotsConfig
    controller: ControllerParams
    sim: SimConfig
    source: str = "<config>"
    extra: Mapping[str, Any] = field(default_factory=dict)
    #: :func:`content_hash` of the parsed document (comments and formatting do not count)
    content_hash: str = ""

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
    try:
        text = raw.decode("utf-8")
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
    known = ("tube", "obstacles", "robots", "controller", "sim", "partition", *extra_names)
    p.check_keys(data, known, "")
    tube = p.parse_tube(p.table(data, "tube", ""))
    apex_default = p.parse_partition(p.table(data, "partition", "", required=False))
    obstacles = p.parse_obstacles(data.get("obstacles", []), apex_default)
    robots = p.parse_robots(p.table(data, "robots", ""), tube)
    controller = p.parse_controller(p.table(data, "controller", ""), robots)
    sim = p.parse_sim(p.table(data, "sim", "", required=False))
    extra = {}
    for name in extra_names:
        if name in data:
            extra[name] = p.table(data, name, "")
    return Scenario(
        tube=tube,
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


def _show(value: Any) -> str:
    """A value as the user wrote it (TOML-ish), for error messages."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, dict):
        return "a table"
    try:
        text = json.dumps(value, default=str)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


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
            raise self.error(where, f"expected a table, got {_show(value)}")
        return value

    def number(
        self,
        table: Mapping[str, Any],
        key: str,
        section: str,
        *,
        default: float | None = None,
        required: bool = True,
        positive: bool = False,
        nonnegative: bool = False,
    ) -> float:
        where = self.name(section, key)
        if key not in table:
            if default is not None or not required:
                return default  # type: ignore[return-value]
            raise self.error(where, "missing required key")
        value = table[key]
        if not _is_number(value):
            raise self.error(where, f"expected a number, got {_show(value)}")
        x = float(value)
        if not math.isfinite(x):
            raise self.error(where, f"expected a finite number, got {_show(value)}")
        if positive and not x > 0:
            raise self.error(where, f"must be > 0, got {_show(value)}")
        if nonnegative and not x >= 0:
            raise self.error(where, f"must be >= 0, got {_show(value)}")
        return x

    def integer(
        self, table: Mapping[str, Any], key: str, section: str, *, minimum: int = 1
    ) -> int:
        where = self.name(section, key)
        if key not in table:
            raise self.error(where, "missing required key")
        value = table[key]
        if not isinstance(value, int) or isinstance(value, bool):
            raise self.error(where, f"expected an integer, got {_show(value)}")
        if value < minimum:
            raise self.error(where, f"must be >= {minimum}, got {value}")
        return int(value)

    def point(self, table: Mapping[str, Any], key: str, section: str) -> np.ndarray:
        where = self.name(section, key)
        if key not in table:
            raise self.error(where, "missing required key")
        return self.point_value(table[key], where)

    def point_value(self, value: Any, where: str) -> np.ndarray:
        if (
            not isinstance(value, list)
            or len(value) != 2
            or not all(_is_number(v) for v in value)
        ):
            raise self.error(where, f"expected a point [x, y] of two numbers, got {_show(value)}")
        pt = np.array(value, dtype=float)
        if not np.all(np.isfinite(pt)):
            raise self.error(where, f"expected finite numbers, got {_show(value)}")
        return pt

    # ----- sections ---------------------------------------------------------------------
    def parse_tube(self, t: Mapping[str, Any]) -> Trapezoid:
        sec = "[tube]"
        keys = ("p_h0", "p_h1", "p_r0", "p_r1")
        self.check_keys(t, keys, sec)
        pts = {k: self.point(t, k, sec) for k in keys}
        try:
            return Trapezoid(pts["p_h0"], pts["p_h1"], pts["p_r0"], pts["p_r1"])
        except UserError as exc:
            raise self.error(sec, str(exc)) from None

    def parse_partition(self, t: Mapping[str, Any]) -> str | None:
        """[partition]: ``apex_distance = "auto" | "default"``, the apex distance of every
        obstacle without its own (``"default"``: 1.3 h_min; ``"auto"``: core/plan.py)."""
        sec = "[partition]"
        self.check_keys(t, ("apex_distance",), sec)
        v = t.get("apex_distance", "default")
        if v not in (APEX_AUTO, "default"):
            raise self.error(self.name(sec, "apex_distance"),
                             f'expected "auto" or "default", got {_show(v)}')
        return APEX_AUTO if v == APEX_AUTO else None

    def parse_obstacles(self, value: Any, apex_default: str | None = None
                        ) -> tuple[Obstacle, ...]:
        if not isinstance(value, list) or not all(isinstance(o, dict) for o in value):
            raise self.error(
                "[[obstacles]]", f"expected an array of tables, got {_show(value)}"
            )
        out = []
        for idx, o in enumerate(value):
            sec = f"[[obstacles]][{idx}]"
            self.check_keys(o, ("center", "radius", "apex_distance"), sec)
            center = self.point(o, "center", sec)
            radius = self.number(o, "radius", sec, positive=True)
            apex: float | str | None = apex_default
            if o.get("apex_distance") == APEX_AUTO:
                apex = APEX_AUTO
            elif "apex_distance" in o:
                apex = self.number(o, "apex_distance", sec, positive=True)
            if isinstance(apex, float) and apex <= radius:
                raise self.error(
                    self.name(sec, "apex_distance"),
                    f"must exceed the radius {radius:g}, got {apex:g}",
                )
            out.append(Obstacle(center=center, radius=radius, apex_distance=apex))
        return tuple(out)

    def parse_robots(self, r: Mapping[str, Any], tube: Trapezoid) -> RobotsConfig:
        sec = "[robots]"
        allowed = (
            "model", "r_s", "r_a", "v_min", "v_max", "grid", "positions",
            "nid_distance", "headings",
        )
        self.check_keys(r, allowed, sec)
        model = r.get("model", "single_integrator")
        if not isinstance(model, str) or model not in MODELS:
            raise self.error(
                self.name(sec, "model"),
                f"expected one of {', '.join(json.dumps(m) for m in MODELS)}, got {_show(model)}",
            )
        r_s = self.number(r, "r_s", sec, positive=True)
        r_a = self.number(r, "r_a", sec, positive=True)
        if not r_a > r_s:
            raise self.error(
                self.name(sec, "r_a"), f"must exceed r_s = {r_s:g} (paper: r_a > r_s), got {r_a:g}"
            )
        v_min = self.number(r, "v_min", sec, nonnegative=True)
        v_max = self.number(r, "v_max", sec, positive=True)
        if not v_max > v_min:
            raise self.error(
                self.name(sec, "v_max"), f"must exceed v_min = {v_min:g}, got {v_max:g}"
            )

        has_grid, has_pos = "grid" in r, "positions" in r
        if has_grid and has_pos:
            raise self.error(sec, "give either grid or positions, not both")
        if not (has_grid or has_pos):
            raise self.error(self.name(sec, "grid"), "missing required key (or positions)")
        if has_grid:
            gsec = self.name(sec, "grid")
            g = r["grid"]
            if not isinstance(g, dict):
                raise self.error(gsec, f"expected a table, got {_show(g)}")
            self.check_keys(g, ("origin", "rows", "cols", "spacing"), gsec)
            origin = self.point(g, "origin", gsec)
            rows = self.integer(g, "rows", gsec)
            cols = self.integer(g, "cols", gsec)
            spacing = self.number(g, "spacing", gsec, positive=True)
            positions = grid_positions(origin, rows, cols, spacing)
        else:
            psec = self.name(sec, "positions")
            pv = r["positions"]
            if not isinstance(pv, list) or not pv:
                raise self.error(psec, f"expected a non-empty array of [x, y], got {_show(pv)}")
            positions = np.array(
                [self.point_value(v, f"{psec}[{i}]") for i, v in enumerate(pv)], dtype=float
            )
        m = positions.shape[0]

        headings = nid = None
        if model == "unicycle":
            nid = self.number(r, "nid_distance", sec, positive=True)
            hv = r.get("headings")
            hsec = self.name(sec, "headings")
            if hv is None:
                # default: every robot faces along n_c (towards the finishing line)
                headings = np.full(m, math.atan2(tube.n_c[1], tube.n_c[0]))
            elif _is_number(hv):
                headings = np.full(m, float(self.number(r, "headings", sec)))
            elif isinstance(hv, list):
                if len(hv) != m or not all(_is_number(h) for h in hv):
                    raise self.error(
                        hsec, f"expected a number or {m} numbers (one per robot), got {_show(hv)}"
                    )
                headings = np.array(hv, dtype=float)
                if not np.all(np.isfinite(headings)):
                    raise self.error(hsec, f"expected finite numbers, got {_show(hv)}")
            else:
                raise self.error(hsec, f"expected a number or an array, got {_show(hv)}")
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
        self.check_keys(c, (*CONTROLLER_REQUIRED, *CONTROLLER_DEFAULTS), sec)
        values = {k: self.number(c, k, sec, positive=True) for k in CONTROLLER_REQUIRED}
        for k, d in CONTROLLER_DEFAULTS.items():
            values[k] = self.number(c, k, sec, default=d, positive=True)
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
        self.check_keys(s, ("dt", "duration", "record_every", "integrator"), sec)
        dt = self.number(s, "dt", sec, default=DEFAULT_DT_S, positive=True)
        duration = self.number(s, "duration", sec, default=DEFAULT_DURATION_S, positive=True)
        record_every = None
        if "record_every" in s:
            record_every = self.integer(s, "record_every", sec)
        integrator = s.get("integrator", DEFAULT_INTEGRATOR)
        if not isinstance(integrator, str) or integrator not in INTEGRATORS:
            raise self.error(
                self.name(sec, "integrator"),
                f"expected one of {', '.join(json.dumps(n) for n in INTEGRATORS)}, "
                f"got {_show(integrator)}")
        return SimConfig(dt=dt, duration=duration, record_every=record_every,
                         integrator=integrator)
