"""Estimate-vs-truth series from the real PX4 SITL fleet flights in ``data/px4_sitl/fleet_truth``.

:func:`flight_series` aligns, on a 0.1 s grid by the tlog timestamps (``HIL_STATE_QUATERNION``
has ``time_usec`` 0), PX4's estimate (LOCAL_POSITION_NED for velocity, GLOBAL_POSITION_INT for
position) with the simulator's truth (HIL_STATE_QUATERNION), horizontally in metres about the
mission anchor, and marks the airborne samples (truth more than 1 m above the first second).
:func:`error_stats` gives the figures the sim_stub estimator profile is fitted to.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

FLEET_TRUTH = Path(__file__).parent / "data" / "px4_sitl" / "fleet_truth"
FLIGHTS = ("mavlink_backend_flight", "mavsdk_backend_flight", "mavlink_backend_takeoff_abort")
ANCHOR = (47.397742, 8.545594)
R_EARTH = 6371000.0
DT = 0.1


@dataclass
class Series:
    t: np.ndarray  # (K,) s from the first aligned sample
    truth_ne: np.ndarray  # (K, 2)
    truth_v: np.ndarray  # (K, 2)
    est_ne: np.ndarray  # (K, 2)
    est_v: np.ndarray  # (K, 2)
    up_m: np.ndarray  # (K,) truth height above the first second
    airborne: np.ndarray  # (K,) bool

    @property
    def pos_err(self) -> np.ndarray:
        return self.est_ne - self.truth_ne

    @property
    def vel_err(self) -> np.ndarray:
        return self.est_v - self.truth_v


def _ne(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    lat0, lon0 = ANCHOR
    return np.stack((np.radians(lat - lat0) * R_EARTH,
                     np.radians(lon - lon0) * R_EARTH * np.cos(np.radians(lat0))), axis=1)


def flight_series(flight: str, sysid: int) -> Series:
    m = mavutil.mavlink_connection(str(FLEET_TRUTH / flight / f"sys{sysid}_gcs_link.tlog"))
    truth, gpi, lpn = [], [], []
    while (msg := m.recv_match()) is not None:
        kind = msg.get_type()
        if kind == "HIL_STATE_QUATERNION":
            truth.append((msg._timestamp, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3,
                          msg.vx / 100.0, msg.vy / 100.0))
        elif kind == "GLOBAL_POSITION_INT":
            gpi.append((msg._timestamp, msg.lat * 1e-7, msg.lon * 1e-7))
        elif kind == "LOCAL_POSITION_NED":
            lpn.append((msg._timestamp, msg.vx, msg.vy))
    tr, g, lp = np.array(truth), np.array(gpi), np.array(lpn)
    grid = np.arange(max(tr[0, 0], g[0, 0], lp[0, 0]), min(tr[-1, 0], g[-1, 0], lp[-1, 0]), DT)

    def at(t: np.ndarray, x: np.ndarray) -> np.ndarray:
        return np.interp(grid, t, x)

    tne, gne = _ne(tr[:, 1], tr[:, 2]), _ne(g[:, 1], g[:, 2])
    up = at(tr[:, 0], tr[:, 3])
    up = up - up[: int(1.0 / DT)].mean()
    return Series(
        t=grid - grid[0],
        truth_ne=np.stack((at(tr[:, 0], tne[:, 0]), at(tr[:, 0], tne[:, 1])), axis=1),
        truth_v=np.stack((at(tr[:, 0], tr[:, 4]), at(tr[:, 0], tr[:, 5])), axis=1),
        est_ne=np.stack((at(g[:, 0], gne[:, 0]), at(g[:, 0], gne[:, 1])), axis=1),
        est_v=np.stack((at(lp[:, 0], lp[:, 1]), at(lp[:, 0], lp[:, 2])), axis=1),
        up_m=up,
        airborne=up > 1.0,
    )


def reported_accuracy(flight: str, sysid: int) -> dict[str, float]:
    """What PX4 *reported* about its accuracy in that flight: the medians of
    ``ESTIMATOR_STATUS.pos_horiz_accuracy`` (m) and of ``GPS_RAW_INT`` eph (cm), h_acc (mm),
    vel_acc (mm/s) and fix_type over the whole log."""
    m = mavutil.mavlink_connection(str(FLEET_TRUTH / flight / f"sys{sysid}_gcs_link.tlog"))
    acc, gps = [], []
    while (msg := m.recv_match(type=["ESTIMATOR_STATUS", "GPS_RAW_INT"])) is not None:
        if msg.get_type() == "ESTIMATOR_STATUS":
            acc.append(msg.pos_horiz_accuracy)
        else:
            gps.append((msg.eph, msg.h_acc, msg.vel_acc, msg.fix_type))
    g = np.median(np.array(gps, dtype=float), axis=0)
    return {"pos_horiz_accuracy": float(np.median(acc)), "eph": float(g[0]),
            "h_acc": float(g[1]), "vel_acc": float(g[2]), "fix_type": float(g[3])}


def acf(x: np.ndarray, lag: int) -> float:
    x = x - x.mean()
    return float((x[:-lag] * x[lag:]).mean() / (x * x).mean())


def error_stats(pos_err: np.ndarray, vel_err: np.ndarray) -> dict[str, float]:
    """p50/p95/max of the horizontal position and velocity errors (airborne samples, (K, 2)),
    and the velocity error's autocorrelation at 1 s (mean of the two axes)."""
    ep = np.hypot(*pos_err.T)
    ev = np.hypot(*vel_err.T)
    lag = int(round(1.0 / DT))
    return {
        "pos_p50": float(np.percentile(ep, 50)), "pos_p95": float(np.percentile(ep, 95)),
        "pos_max": float(ep.max()),
        "vel_p50": float(np.percentile(ev, 50)), "vel_p95": float(np.percentile(ev, 95)),
        "vel_max": float(ev.max()),
        "vel_acf_1s": float(np.mean([acf(vel_err[:, k], lag) for k in range(2)])),
    }
