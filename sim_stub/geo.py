"""PX4's local-frame map projection (azimuthal equidistant on a sphere, R = 6371000 m).

PX4 converts between its LOCAL_POSITION_NED frame (origin = GPS_GLOBAL_ORIGIN) and
GLOBAL_POSITION_INT with ``map_projection_project``/``reproject`` on this sphere; the README of the
captures checked that projecting GLOBAL_POSITION_INT about the origin with it reproduces local x/y
within ±0.02 m. Scalar pure functions, fast enough to call per message.
"""

from __future__ import annotations

import math

__all__ = ["EARTH_RADIUS_M", "reproject", "project"]

EARTH_RADIUS_M = 6371000.0


def reproject(lat0_deg: float, lon0_deg: float, x: float, y: float) -> tuple[float, float]:
    """Local north ``x`` / east ``y`` [m] about the reference → (lat, lon) [deg]."""
    lat0 = math.radians(lat0_deg)
    x_rad = x / EARTH_RADIUS_M
    y_rad = y / EARTH_RADIUS_M
    c = math.sqrt(x_rad * x_rad + y_rad * y_rad)
    if c == 0.0:
        return lat0_deg, lon0_deg
    sin_c, cos_c = math.sin(c), math.cos(c)
    sin_lat0, cos_lat0 = math.sin(lat0), math.cos(lat0)
    lat = math.asin(cos_c * sin_lat0 + (x_rad * sin_c * cos_lat0) / c)
    lon = math.radians(lon0_deg) + math.atan2(
        y_rad * sin_c, c * cos_lat0 * cos_c - x_rad * sin_lat0 * sin_c
    )
    return math.degrees(lat), math.degrees(lon)


def project(
    lat0_deg: float, lon0_deg: float, lat_deg: float, lon_deg: float
) -> tuple[float, float]:
    """(lat, lon) [deg] → local north ``x`` / east ``y`` [m] about the reference."""
    lat0 = math.radians(lat0_deg)
    lat = math.radians(lat_deg)
    dlon = math.radians(lon_deg - lon0_deg)
    sin_lat0, cos_lat0 = math.sin(lat0), math.cos(lat0)
    sin_lat, cos_lat = math.sin(lat), math.cos(lat)
    cos_dlon = math.cos(dlon)
    arg = max(-1.0, min(1.0, sin_lat0 * sin_lat + cos_lat0 * cos_lat * cos_dlon))
    c = math.acos(arg)
    k = c / math.sin(c) if abs(c) > 0.0 else 1.0
    x = k * (cos_lat0 * sin_lat - sin_lat0 * cos_lat * cos_dlon) * EARTH_RADIUS_M
    y = k * cos_lat * math.sin(dlon) * EARTH_RADIUS_M
    return x, y
