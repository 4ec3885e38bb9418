"""The geodetic tube frame and PX4's per-vehicle local frames (all geodesy by pymap3d).

**Tube frame.** The mission anchors the paper's 2-D plane geodetically: origin
(``lat0_deg, lon0_deg, alt0_m``, WGS84, altitude AMSL as PX4 reports it) and ``heading_deg``, the
direction of the tube's x axis measured clockwise from true north. The frame is right-handed with
x forward (along ``heading_deg``), **y 90° to the left of x** and z (``up_m``) up, i.e. it is the
local ENU tangent frame at the origin rotated about "up" so that x points along the heading:

    x =  n cos ψ + e sin ψ            north = x cos ψ + y sin ψ
    y =  n sin ψ − e cos ψ            east  = x sin ψ − y cos ψ

(ψ = heading; heading 0 → x north, y west; heading 90 → x east, y north). Positions go through
``pymap3d.geodetic2enu``/``enu2geodetic`` on WGS84; ``up_m`` is ENU up (it includes the Earth's
curvature drop, ≈ d²/2R = 0.8 mm at 100 m).

**PX4 local frames.** Each PX4 vehicle's LOCAL_POSITION_NED is relative to *its own*
GPS_GLOBAL_ORIGIN (its first GNSS fix; the captures show two vehicles whose origins are 10.9 m
apart), so equal local coordinates on two vehicles are different places. PX4 maps local x/y to
lat/lon with an azimuthal-equidistant projection on a sphere of radius 6371000 m about the origin
(``map_projection``), and ``alt = origin_alt − z``. :func:`local_ned_to_geodetic` /
:func:`geodetic_to_local_ned` reproduce that with pymap3d's Vincenty direct/inverse solutions on
that sphere (``pymap3d.vincenty.vreckon``/``vdist``; a geodesic from the origin with distance d and
azimuth α *is* the azimuthal-equidistant point (d cos α, d sin α)). The captures confirm: local
x/y = projection of GLOBAL_POSITION_INT within ±0.02 m (``tests/test_frames.py``). Using WGS84 ENU
instead would be off by ~0.3 % of the distance east-west at 47° N (0.3 m per 100 m).

**Velocities.** A 2-D tube velocity becomes north/east with the rotation above; each vehicle's
LOCAL_NED axes point to true north/east at *its* origin, which differs from the tube origin's
north by the meridian convergence (Δlon · sin lat: 0.0077° for vehicles 1 km apart at 47° N),
which is ignored.

All functions accept scalars or numpy arrays (broadcast together) and return numpy arrays
(0-d for scalar input).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymap3d
from numpy.typing import ArrayLike
from pymap3d.vincenty import vdist, vreckon

from vtube_fleet.errors import ConfigError

__all__ = [
    "PX4_EARTH_RADIUS_M",
    "PX4_SPHERE",
    "WGS84",
    "FrameError",
    "TubeFrame",
    "local_ned_to_geodetic",
    "geodetic_to_local_ned",
]

#: Radius of the sphere PX4's map projection uses (``CONSTANTS_RADIUS_OF_EARTH``).
PX4_EARTH_RADIUS_M = 6371000.0
#: That sphere as a pymap3d ellipsoid.
PX4_SPHERE = pymap3d.Ellipsoid(PX4_EARTH_RADIUS_M, PX4_EARTH_RADIUS_M, name="px4-sphere")
WGS84 = pymap3d.Ellipsoid.from_name("wgs84")


class FrameError(ConfigError):
    """An invalid geodetic anchor (latitude outside ±90°, non-finite value …)."""


def _arr(v: ArrayLike) -> np.ndarray:
    return np.asarray(v, dtype=float)


def local_ned_to_geodetic(
    north_m: ArrayLike,
    east_m: ArrayLike,
    down_m: ArrayLike,
    origin_lat_deg: ArrayLike,
    origin_lon_deg: ArrayLike,
    origin_alt_m: ArrayLike,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PX4 LOCAL_POSITION_NED (about GPS_GLOBAL_ORIGIN) → (lat_deg, lon_deg, alt_m), as PX4
    computes GLOBAL_POSITION_INT: azimuthal-equidistant on the 6371 km sphere, ``alt = o_alt − d``.
    """
    n, e, d = np.broadcast_arrays(_arr(north_m), _arr(east_m), _arr(down_m))
    lat0, lon0, alt0 = np.broadcast_arrays(
        _arr(origin_lat_deg), _arr(origin_lon_deg), _arr(origin_alt_m)
    )
    shape = np.broadcast_shapes(n.shape, lat0.shape)
    n, e, d, lat0, lon0, alt0 = (np.broadcast_to(a, shape) for a in (n, e, d, lat0, lon0, alt0))
    dist = np.hypot(n, e)
    az = np.degrees(np.arctan2(e, n))
    lat, lon = vreckon(lat0, lon0, dist, az, ell=PX4_SPHERE)
    lon = (np.asarray(lon, dtype=float) + 180.0) % 360.0 - 180.0
    return np.asarray(lat, dtype=float), lon, alt0 - d


def geodetic_to_local_ned(
    lat_deg: ArrayLike,
    lon_deg: ArrayLike,
    alt_m: ArrayLike,
    origin_lat_deg: ArrayLike,
    origin_lon_deg: ArrayLike,
    origin_alt_m: ArrayLike,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`local_ned_to_geodetic`: (north_m, east_m, down_m) in the PX4 local frame
    whose GPS_GLOBAL_ORIGIN is given."""
    lat, lon, alt = np.broadcast_arrays(_arr(lat_deg), _arr(lon_deg), _arr(alt_m))
    lat0, lon0, alt0 = np.broadcast_arrays(
        _arr(origin_lat_deg), _arr(origin_lon_deg), _arr(origin_alt_m)
    )
    shape = np.broadcast_shapes(lat.shape, lat0.shape)
    lat, lon, alt, lat0, lon0, alt0 = (
        np.broadcast_to(a, shape) for a in (lat, lon, alt, lat0, lon0, alt0)
    )
    dist, az = vdist(lat0, lon0, lat, lon, ell=PX4_SPHERE)
    az = np.radians(np.asarray(az, dtype=float))
    dist = np.asarray(dist, dtype=float)
    return dist * np.cos(az), dist * np.sin(az), alt0 - alt


@dataclass(frozen=True)
class TubeFrame:
    """Geodetic anchor of the tube's 2-D frame (x along ``heading_deg``, y to the left, z up).

    Parameters: origin ``lat0_deg``, ``lon0_deg`` (WGS84), ``alt0_m`` (AMSL) and ``heading_deg``
    (x axis, clockwise from true north). See the module docstring for the formulas.
    """

    lat0_deg: float
    lon0_deg: float
    alt0_m: float
    heading_deg: float

    def __post_init__(self) -> None:
        for name in ("lat0_deg", "lon0_deg", "alt0_m", "heading_deg"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise FrameError(f"tube frame {name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise FrameError(f"tube frame {name} must be finite, got {value}")
        if not -90.0 < self.lat0_deg < 90.0:
            raise FrameError(f"tube frame lat0_deg = {self.lat0_deg} outside (-90, 90)")
        if not -180.0 <= self.lon0_deg <= 360.0:
            raise FrameError(f"tube frame lon0_deg = {self.lon0_deg} outside [-180, 360]")
        if not -1000.0 <= self.alt0_m <= 20000.0:
            raise FrameError(f"tube frame alt0_m = {self.alt0_m} m outside [-1000, 20000] (AMSL)")
        psi = math.radians(self.heading_deg)
        object.__setattr__(self, "_cos", math.cos(psi))
        object.__setattr__(self, "_sin", math.sin(psi))

    # -- rotations -------------------------------------------------------------------------
    def ned_velocity_to_tube(
        self, north_m_s: ArrayLike, east_m_s: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray]:
        """(north, east) → (x, y) components; same formula for positions and velocities."""
        return self._flip(_arr(north_m_s), _arr(east_m_s))

    def tube_velocity_to_ned(
        self, vx_m_s: ArrayLike, vy_m_s: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray]:
        """Tube-frame (vx, vy) → (north_m_s, east_m_s) for SET_POSITION_TARGET_LOCAL_NED."""
        return self._flip(_arr(vx_m_s), _arr(vy_m_s))

    def _flip(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The NED ↔ tube map: a reflection (its own inverse), (a c + b s, a s − b c)."""
        c, s = self._cos, self._sin  # type: ignore[attr-defined]
        return a * c + b * s, a * s - b * c

    # -- positions -------------------------------------------------------------------------
    def geodetic_to_tube(
        self, lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lat, lon, alt AMSL) → (x_m, y_m, up_m) via ``pymap3d.geodetic2enu`` (WGS84)."""
        e, n, u = pymap3d.geodetic2enu(
            _arr(lat_deg), _arr(lon_deg), _arr(alt_m),
            self.lat0_deg, self.lon0_deg, self.alt0_m, ell=WGS84,
        )
        x, y = self.ned_velocity_to_tube(n, e)
        return x, y, np.asarray(u, dtype=float)

    def tube_to_geodetic(
        self, x_m: ArrayLike, y_m: ArrayLike, up_m: ArrayLike = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x_m, y_m, up_m) → (lat_deg, lon_deg, alt_m AMSL) via ``pymap3d.enu2geodetic``."""
        n, e = self.tube_velocity_to_ned(x_m, y_m)
        lat, lon, alt = pymap3d.enu2geodetic(
            e, n, _arr(up_m), self.lat0_deg, self.lon0_deg, self.alt0_m, ell=WGS84
        )
        return np.asarray(lat, float), np.asarray(lon, float), np.asarray(alt, float)

    def local_ned_to_tube(
        self,
        north_m: ArrayLike,
        east_m: ArrayLike,
        down_m: ArrayLike,
        origin_lat_deg: ArrayLike,
        origin_lon_deg: ArrayLike,
        origin_alt_m: ArrayLike,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A vehicle's LOCAL_POSITION_NED plus its GPS_GLOBAL_ORIGIN → (x_m, y_m, up_m).

        Goes through PX4's own projection (:func:`local_ned_to_geodetic`), so it agrees with
        :meth:`geodetic_to_tube` of that vehicle's GLOBAL_POSITION_INT. Origins may be arrays
        (one per vehicle).
        """
        lat, lon, alt = local_ned_to_geodetic(
            north_m, east_m, down_m, origin_lat_deg, origin_lon_deg, origin_alt_m
        )
        return self.geodetic_to_tube(lat, lon, alt)

    def tube_to_local_ned(
        self,
        x_m: ArrayLike,
        y_m: ArrayLike,
        up_m: ArrayLike,
        origin_lat_deg: ArrayLike,
        origin_lon_deg: ArrayLike,
        origin_alt_m: ArrayLike,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse of :meth:`local_ned_to_tube`: a tube point in a vehicle's local frame."""
        lat, lon, alt = self.tube_to_geodetic(x_m, y_m, up_m)
        return geodetic_to_local_ned(lat, lon, alt, origin_lat_deg, origin_lon_deg, origin_alt_m)

    def mission_down_m(self, height_m: ArrayLike, origin_alt_m: ArrayLike) -> np.ndarray:
        """Local ``down`` (z) that puts a vehicle at ``alt0_m + height_m`` AMSL, given its
        GPS_GLOBAL_ORIGIN altitude: ``origin_alt − (alt0 + height)`` (PX4: alt = o_alt − z)."""
        return _arr(origin_alt_m) - (self.alt0_m + _arr(height_m))
