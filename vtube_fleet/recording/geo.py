"""The map of a recording: the mission's static geometry as WGS84 polylines (no rerun here).

Everything is drawn in the tube frame first and converted with the mission's geodetic anchor,
:meth:`vtube_fleet.frames.TubeFrame.tube_to_geodetic` — the conversion the fleet uses for the
fence it uploads (``fleet/onboard.fence_items``) — so the map shows exactly the fence PX4 got:

* the outline of the tube (:func:`outline_polylines`: one closed polyline per tube; a route of
  several segments adds one per segment and nothing else changes);
* each obstacle O_k as a circle of radius r_o;
* the PX4 geofence (:meth:`vtube_fleet.config.mission.Mission.fence_geometry`): its inclusion
  polygon and an exclusion circle of radius r_o + r_s per obstacle;
* each start slot as a circle of radius r_s.

The writer (:mod:`vtube_fleet.recording.writer`) logs each :class:`MapLayer` as one static
``GeoLineStrings`` entity, and converts the vehicles' positions with the same frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from vtube_fleet.recording.layout import (
    E_MAP_FENCE,
    E_MAP_OBSTACLES,
    E_MAP_OUTLINE,
    E_MAP_SLOTS,
    MAP_FENCE_COLOR,
    MAP_OBSTACLE_COLOR,
    MAP_OUTLINE_COLOR,
    MAP_SLOT_COLOR,
)

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.config.mission import MissionConfig
    from vtube_fleet.config.scenario import Scenario

__all__ = [
    "MAX_MAP_ZOOM",
    "MapLayer",
    "circle",
    "closed",
    "map_layers",
    "map_zoom",
    "outline_polylines",
    "to_lat_lon",
]

#: The deepest zoom of the map view's OpenStreetMap tiles (rerun's map view refuses a deeper
#: one and then stays at its default, 16: a 100 m tube a few pixels tall).
MAX_MAP_ZOOM = 19.0
#: Web-Mercator ground resolution at zoom 0 on the equator (m per pixel, 256-pixel tiles).
_M_PER_PX_Z0 = 156543.03392


def closed(poly: np.ndarray) -> np.ndarray:
    """A polygon (K, 2) as a closed polyline (K + 1, 2)."""
    poly = np.asarray(poly, dtype=float)
    return np.vstack([poly, poly[:1]])


def circle(center: np.ndarray, radius: float, n: int = 48) -> np.ndarray:
    """A closed polyline (n + 1, 2) around ``center``."""
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    return np.asarray(center, dtype=float) + radius * np.stack([np.cos(a), np.sin(a)], axis=-1)


@dataclass(frozen=True, eq=False)
class MapLayer:
    """One static map entity: polylines (each (K, 2) of lat_deg, lon_deg), a colour (RGBA) and
    a line width (UI points); ``names``: what each polyline is (the recording's metadata)."""

    entity: str
    strips: list[np.ndarray]
    names: list[str]
    color: int
    width_pt: float


class GeodeticFrame(Protocol):
    """What the map needs of the mission's frame (``MissionConfig.frame``, a
    :class:`vtube_fleet.frames.TubeFrame`)."""

    def tube_to_geodetic(self, x_m: Any, y_m: Any, up_m: Any = 0.0
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


def to_lat_lon(frame: GeodeticFrame, strips: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Tube-frame polylines → (K, 2) lat_deg, lon_deg each, in ONE vectorized conversion."""
    if not strips:
        return []
    flat = np.concatenate([np.asarray(s, dtype=float).reshape(-1, 2) for s in strips])
    lat, lon, _ = frame.tube_to_geodetic(flat[:, 0], flat[:, 1], 0.0)
    ll = np.stack(np.broadcast_arrays(lat, lon), axis=-1).reshape(-1, 2)
    cuts = np.cumsum([len(s) for s in strips])[:-1]
    return list(np.split(ll, cuts))


def outline_polylines(scenario: Scenario) -> list[tuple[str, np.ndarray]]:
    """(name, closed tube-frame polyline) of every tube the vehicles fly: the tube T, or each
    segment of a route (``S1`` …)."""
    segments = scenario.corridor.segments
    if len(segments) == 1:
        tube = segments[0]
        return [(getattr(tube, "name", "") or "tube T", closed(tube.polygon()))]
    return [(f"S{s + 1}", closed(t.polygon())) for s, t in enumerate(segments)]


def map_layers(scenario: Scenario, mission: MissionConfig, *, fence: bool = True
               ) -> list[MapLayer]:
    """The map's static layers of ``scenario`` flown with ``mission`` (module docstring);
    ``fence=False`` (``--no-fence``: nothing uploaded) leaves the fence out."""
    from vtube_fleet.config.mission import Mission

    m = Mission(scenario, mission)
    frame = mission.frame
    r_s = float(scenario.controller.r_s)
    layers: list[tuple[str, list[tuple[str, np.ndarray]], int, float]] = [
        (E_MAP_OUTLINE, outline_polylines(scenario), MAP_OUTLINE_COLOR, 2.0)]
    obstacles = list(scenario.obstacles)
    if obstacles:
        layers.append((E_MAP_OBSTACLES, [(f"O{k + 1}", circle(o.center, float(o.radius)))
                                         for k, o in enumerate(obstacles)],
                       MAP_OBSTACLE_COLOR, 2.0))
    if fence:
        geom = m.fence_geometry()
        multi = len(geom.polygons) > 1
        parts = [(f"fence polygon S{s + 1}" if multi else "fence polygon", closed(poly))
                 for s, poly in enumerate(geom.polygons)]
        parts += [(f"fence exclusion O{k + 1}", circle(c, float(r)))
                  for k, (c, r) in enumerate(zip(geom.circle_centers, geom.circle_radii,
                                                 strict=True))]
        layers.append((E_MAP_FENCE, parts, MAP_FENCE_COLOR, 1.5))
    slots = np.asarray(m.slots, dtype=float).reshape(-1, 2)
    if len(slots):
        layers.append((E_MAP_SLOTS, [(f"slot {i}", circle(p, r_s, 16))
                                     for i, p in enumerate(slots)], MAP_SLOT_COLOR, 1.0))
    out = []
    for entity, named, color, width in layers:
        out.append(MapLayer(entity, to_lat_lon(frame, [s for _, s in named]),
                            [n for n, _ in named], color, width))
    return out


def map_zoom(layers: Sequence[MapLayer], panel_px: float = 450.0) -> float | None:
    """The map zoom that shows every layer within ``panel_px`` pixels (Web Mercator at the
    layers' mean latitude), at most :data:`MAX_MAP_ZOOM`; None without geometry."""
    pts = [s for layer in layers for s in layer.strips if len(s)]
    if not pts:
        return None
    ll = np.concatenate(pts)
    lat0 = float(np.radians(ll[:, 0].mean()))
    span_m = max(float(np.ptp(ll[:, 0])) * 111_320.0,
                 float(np.ptp(ll[:, 1])) * 111_320.0 * np.cos(lat0), 1.0)
    z = float(np.log2(_M_PER_PX_Z0 * np.cos(lat0) * panel_px / span_m))
    return round(min(MAX_MAP_ZOOM, max(1.0, z)), 2)
