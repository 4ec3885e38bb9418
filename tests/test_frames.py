"""Tube frame and PX4 local frames, incl. a check against the real PX4 SITL captures."""

from __future__ import annotations

import bisect
import math
from pathlib import Path

import numpy as np
import pymap3d
import pytest

from vtube_fleet.errors import UserError
from vtube_fleet.frames import (
    FrameError,
    TubeFrame,
    geodetic_to_local_ned,
    local_ned_to_geodetic,
)

CAPTURES = Path(__file__).parent / "data" / "px4_sitl"  # real PX4 SITL captures
LAT0, LON0, ALT0 = 47.3977459, 8.5455930, 489.056  # sysid 1's GPS_GLOBAL_ORIGIN (captures)


def test_heading_0_x_north_y_west() -> None:
    f = TubeFrame(LAT0, LON0, ALT0, 0.0)
    lat, lon, alt = f.tube_to_geodetic(100.0, 0.0, 0.0)
    assert lat > LAT0 and lon == pytest.approx(LON0, abs=1e-9)
    assert (lat - LAT0) * 111_180 == pytest.approx(100.0, rel=2e-3)  # ~111.18 km/deg at 47.4°
    x, y, up = f.geodetic_to_tube(LAT0, LON0 + 0.001, ALT0)  # a point east
    assert y < -70 and abs(x) < 0.01  # east is to the right of north-facing x: negative y
    assert up == pytest.approx(-(y**2) / (2 * 6.37e6), abs=2e-4)  # curvature drop only


def test_heading_90_x_east_y_north() -> None:
    f = TubeFrame(LAT0, LON0, ALT0, 90.0)
    n, e = f.tube_velocity_to_ned(2.0, 0.0)
    assert (float(n), float(e)) == pytest.approx((0.0, 2.0), abs=1e-12)
    n, e = f.tube_velocity_to_ned(0.0, 1.0)
    assert (float(n), float(e)) == pytest.approx((1.0, 0.0), abs=1e-12)
    x, y, _ = f.geodetic_to_tube(LAT0, LON0 + 0.001, ALT0)
    assert x > 70 and abs(y) < 0.01
    x, y, _ = f.geodetic_to_tube(LAT0 + 0.001, LON0, ALT0)
    assert y > 100 and abs(x) < 0.01


@pytest.mark.parametrize("heading", [0.0, 30.0, 90.0, 180.0, 247.5, -45.0])
def test_velocity_rotation_round_trip_and_handedness(heading: float) -> None:
    f = TubeFrame(LAT0, LON0, ALT0, heading)
    rng = np.random.default_rng(1)
    vx, vy = rng.normal(size=(2, 50))
    n, e = f.tube_velocity_to_ned(vx, vy)
    assert np.allclose(np.hypot(n, e), np.hypot(vx, vy))
    bx, by = f.ned_velocity_to_tube(n, e)
    assert np.allclose(bx, vx) and np.allclose(by, vy)
    # x along the heading; y = x rotated 90° counter-clockwise seen from above (to the left)
    psi = math.radians(heading)
    n, e = f.tube_velocity_to_ned(1.0, 0.0)
    assert (float(n), float(e)) == pytest.approx((math.cos(psi), math.sin(psi)))
    n, e = f.tube_velocity_to_ned(0.0, 1.0)
    left = (math.cos(psi - math.pi / 2), math.sin(psi - math.pi / 2))
    assert (float(n), float(e)) == pytest.approx(left)


def test_geodetic_round_trip_sub_mm_at_100m_vectorized() -> None:
    f = TubeFrame(LAT0, LON0, ALT0 + 5.0, 33.0)
    rng = np.random.default_rng(2)
    x = rng.uniform(-100, 100, 400)
    y = rng.uniform(-100, 100, 400)
    up = rng.uniform(-5, 30, 400)
    lat, lon, alt = f.tube_to_geodetic(x, y, up)
    assert lat.shape == lon.shape == alt.shape == (400,)
    x2, y2, up2 = f.geodetic_to_tube(lat, lon, alt)
    assert np.abs(x2 - x).max() < 1e-6 and np.abs(y2 - y).max() < 1e-6
    assert np.abs(up2 - up).max() < 1e-6
    # broadcasting: (3, 1) against (4,)
    X, Y, _ = f.geodetic_to_tube(lat[:3, None], lon[:4], alt[:3, None])
    assert X.shape == Y.shape == (3, 4)
    # scalar in, 0-d out
    sx, sy, su = f.geodetic_to_tube(LAT0, LON0, ALT0 + 5.0)
    assert np.ndim(sx) == 0 and abs(float(sx)) < 1e-9 and abs(float(su)) < 1e-9


def test_px4_local_projection_round_trip_and_sphere() -> None:
    rng = np.random.default_rng(3)
    n = rng.uniform(-500, 500, 200)
    e = rng.uniform(-500, 500, 200)
    d = rng.uniform(-50, 1, 200)
    lat, lon, alt = local_ned_to_geodetic(n, e, d, LAT0, LON0, ALT0)
    n2, e2, d2 = geodetic_to_local_ned(lat, lon, alt, LAT0, LON0, ALT0)
    assert np.abs(n2 - n).max() < 1e-6 and np.abs(e2 - e).max() < 1e-6
    assert np.allclose(alt, ALT0 - d) and np.allclose(d2, d)
    # 1 m north on PX4's 6371 km sphere is exactly 1/6371000 rad of latitude
    lat1, lon1, _ = local_ned_to_geodetic(1.0, 0.0, 0.0, LAT0, LON0, ALT0)
    assert math.radians(float(lat1) - LAT0) * 6371000.0 == pytest.approx(1.0, rel=1e-9)
    assert float(lon1) == pytest.approx(LON0, abs=1e-12)
    # zero offset stays at the origin
    lat0, lon0, _ = local_ned_to_geodetic(0.0, 0.0, 0.0, LAT0, LON0, ALT0)
    assert (float(lat0), float(lon0)) == pytest.approx((LAT0, LON0), abs=1e-12)


def test_per_vehicle_origins_vectorized() -> None:
    """Captures 1b: vehicle 3's origin is 10.91 m north of vehicles 1/2; all start at 0,0,0."""
    f = TubeFrame(LAT0, LON0, ALT0, 0.0)
    o_lat = np.array([47.3977459, 47.3977459, 47.3978440])
    o_lon = np.array([8.5455930, 8.5455930, 8.5455937])
    o_alt = np.array([489.056, 489.056, 489.067])
    x, y, up = f.local_ned_to_tube(np.zeros(3), np.zeros(3), np.zeros(3), o_lat, o_lon, o_alt)
    assert x[0] == pytest.approx(0.0, abs=1e-6) and x[1] == pytest.approx(0.0, abs=1e-6)
    assert x[2] == pytest.approx(10.91, abs=0.01)
    assert -y[2] == pytest.approx(0.05, abs=0.01)  # 0.05 m east = -y for heading 0
    n, e, d = f.tube_to_local_ned(x, y, up, o_lat, o_lon, o_alt)
    assert np.abs(np.stack([n, e, d])).max() < 1e-6


def test_mission_down() -> None:
    f = TubeFrame(LAT0, LON0, 480.0, 0.0)
    # mission height 10 m above alt0 = 490 m AMSL; origin at 489.056 → z = -0.944
    assert float(f.mission_down_m(10.0, 489.056)) == pytest.approx(-0.944)
    assert np.allclose(f.mission_down_m(10.0, np.array([489.0, 491.0])), [-1.0, 1.0])


@pytest.mark.parametrize(
    "args, fragment",
    [
        ((95.0, 8.0, 400.0, 0.0), "lat0_deg = 95.0 outside"),
        ((47.0, 8.0, 400.0, math.nan), "heading_deg must be finite"),
        ((47.0, 8.0, 1e6, 0.0), "alt0_m = 1000000.0 m outside"),
        ((47.0, "8", 400.0, 0.0), "lon0_deg must be a number"),
    ],
)
def test_invalid_frame(args: tuple, fragment: str) -> None:
    with pytest.raises(FrameError) as info:
        TubeFrame(*args)
    assert fragment in str(info.value) and isinstance(info.value, UserError)


# -- the captures ------------------------------------------------------------------------------
def _read_capture(name: str):
    from pymavlink import mavutil

    m = mavutil.mavlink_connection(str(CAPTURES / f"{name}_vehicle_to_gcs.tlog"), dialect="common")
    local, glob, origin = [], [], None
    while (msg := m.recv_msg()) is not None:
        t = msg.get_type()
        if t == "LOCAL_POSITION_NED":
            local.append((msg.time_boot_ms, msg.x, msg.y, msg.z))
        elif t == "GLOBAL_POSITION_INT":
            glob.append((msg.time_boot_ms, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3))
        elif t == "GPS_GLOBAL_ORIGIN":
            origin = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
    times = [row[0] for row in local]
    pairs = []
    for g in glob:  # README: compare with the LOCAL_POSITION_NED within ±30 ms
        i = bisect.bisect_left(times, g[0])
        j = min((k for k in (i - 1, i) if 0 <= k < len(times)), key=lambda k: abs(times[k] - g[0]))
        if abs(times[j] - g[0]) <= 30:
            pairs.append((local[j][1:], g[1:]))
    L = np.array([p[0] for p in pairs])
    G = np.array([p[1] for p in pairs])
    return L, G, origin


@pytest.mark.parametrize("name", ["offboard_flight_i0", "three_vehicles_i2", "offboard_loss"])
def test_local_and_global_paths_agree_on_px4_captures(name: str) -> None:
    """README: LOCAL_POSITION_NED = azimuthal projection of GLOBAL_POSITION_INT about
    GPS_GLOBAL_ORIGIN within ±0.02 m, alt = origin.alt - z within ±0.02 m."""
    L, G, origin = _read_capture(name)
    assert origin is not None and len(L) > 300
    n, e, d = geodetic_to_local_ned(G[:, 0], G[:, 1], G[:, 2], *origin)
    assert np.abs(n - L[:, 0]).max() < 0.02
    assert np.abs(e - L[:, 1]).max() < 0.02
    assert np.abs(d - L[:, 2]).max() < 0.02
    f = TubeFrame(47.3977, 8.5455, 480.0, 30.0)  # tube origin ~60 m away from the vehicles
    a = np.array(f.local_ned_to_tube(L[:, 0], L[:, 1], L[:, 2], *origin))
    b = np.array(f.geodetic_to_tube(G[:, 0], G[:, 1], G[:, 2]))
    assert np.abs(a - b).max() < 0.02


def test_wgs84_enu_is_not_px4s_local_frame() -> None:
    """Why local→geodetic goes through PX4's sphere: a WGS84 tangent plane about the origin
    misses the captured local east by more than the ±0.02 m the PX4 projection achieves."""
    L, G, origin = _read_capture("offboard_flight_i0")
    e, n, _ = pymap3d.geodetic2enu(G[:, 0], G[:, 1], G[:, 2], *origin)
    assert np.abs(e - L[:, 1]).max() > 0.025
