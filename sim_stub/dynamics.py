"""Multicopter velocity-response model fitted to the PX4 SIH captures (pure numpy, vectorized).

The model maps a commanded NED velocity ``u`` (what PX4's position controller is asked to fly:
an offboard velocity setpoint, or the output of the mock's position loops) to the vehicle's
velocity, for ``N`` vehicles at once (arrays of shape ``(N, 3)``). Per axis group:

1. pure dead time ``delay`` (a ring buffer of past commands),
2. a first-order command filter ``cmd_tau``,
3. the velocity is the sum of a *fast* part tracking ``fast_gain·c`` with ``fast_tau`` and a *slow*
   part tracking ``slow_gain·c`` with ``slow_tau`` (this reproduces the captures' slow tail: a
   2 m/s step reaches 1.23 m/s after 1 s but only ~1.6 after 4 s, and a stop leaves ~0.15 m/s
   for seconds),
4. an acceleration limit on the total velocity change.

Vertically the gains differ by direction: climbing tracks ``z_up_fast_gain + z_up_slow_gain``
(0.85) of the command, descending ``z_down_gain`` (0.81): the captures climb at -1.2..-1.4 m/s
for a -1.5 command and descend at 0.72-0.83 m/s for +1.0. The parameters below were fitted by
least squares to LOCAL_POSITION_NED (49 Hz) of offboard_flight_i0 and three_vehicles_i0..2
(horizontal: RMS error 0.063 m/s over the 0→2→0 m/s steps) and of those plus offboard_loss
(vertical, from arming through the descent: RMS 0.067 m/s). The ground phase (motor spool-up,
takeoff ramp, "Takeoff detected" before lift-off) is handled by the vehicle logic, which keeps a
vehicle ``grounded`` until lift-off.

Not modelled: SIH's estimator artefacts (z drift on the ground, home altitude jumps), wind,
cross-coupling noise, overshoot, battery drain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["DynamicsParams", "QuadState", "GRAVITY"]

GRAVITY = 9.80665


@dataclass(frozen=True)
class DynamicsParams:
    """Velocity-response parameters (defaults: least-squares fit to the captures)."""

    xy_delay_s: float = 0.15
    xy_cmd_tau_s: float = 0.18
    xy_fast_gain: float = 0.65
    xy_fast_tau_s: float = 0.28
    xy_slow_tau_s: float = 4.5
    xy_accel_max: float = 2.3  # capture: max 2.2-2.7 m/s² (0.1 s finite difference)
    z_delay_s: float = 0.05
    z_cmd_tau_s: float = 0.05
    z_fast_tau_s: float = 0.14
    z_up_fast_gain: float = 0.70
    z_up_slow_gain: float = 0.15
    z_slow_tau_s: float = 1.3
    z_down_gain: float = 0.81
    z_accel_up_max: float = 1.45
    z_accel_down_max: float = 4.5  # capture: 4.5-4.7 m/s² when stopping a climb
    ground_friction_tau_s: float = 0.1
    yaw_tau_s: float = 0.3
    yaw_rate_max: float = math.radians(45.0)  # MPC_YAWRAUTO_MAX
    attitude_tau_s: float = 0.05


class QuadState:
    """State of ``n`` vehicles; ``step`` advances all of them by ``dt``.

    Positions are NED metres relative to each vehicle's own origin (its start point on the
    ground, ``z = 0`` is the ground, up is negative).
    """

    def __init__(self, n: int, params: DynamicsParams | None = None, nominal_dt: float = 0.01):
        self.n = n
        self.prm = params or DynamicsParams()
        self.nominal_dt = nominal_dt
        self.p = np.zeros((n, 3))
        self.v = np.zeros((n, 3))
        self.vf = np.zeros((n, 3))
        self.vs = np.zeros((n, 3))
        self.c = np.zeros((n, 3))
        self.acc = np.zeros((n, 3))
        self.yaw = np.zeros(n)
        self.yaw_rate = np.zeros(n)
        self.roll = np.zeros(n)
        self.pitch = np.zeros(n)
        self.roll_rate = np.zeros(n)
        self.pitch_rate = np.zeros(n)
        self.contact = np.ones(n, dtype=bool)
        self._dxy = max(0, round(self.prm.xy_delay_s / nominal_dt))
        self._dz = max(0, round(self.prm.z_delay_s / nominal_dt))
        self._hist = np.zeros((max(self._dxy, self._dz) + 1, n, 3))
        self._k = 0

    def step(
        self,
        dt: float,
        u: np.ndarray,
        airborne: np.ndarray,
        frozen: np.ndarray,
        yaw_sp: np.ndarray,
        yaw_rate_sp: np.ndarray,
    ) -> None:
        """Advance by ``dt`` seconds with commanded NED velocity ``u`` (n, 3).

        ``airborne`` (n,) False keeps a vehicle on the ground (motors idle or spooling: all
        motion zero). ``frozen`` (n,) True holds a vehicle exactly where it is (fault
        "freeze"). ``yaw_sp`` (n,) NaN means hold the current heading; ``yaw_rate_sp`` is used
        where ``yaw_sp`` is NaN (NaN → 0). ``contact`` is True where the vehicle touches the
        ground after the step.
        """
        prm = self.prm
        dt = float(min(max(dt, 1e-4), 0.1))
        hist = self._hist
        K = hist.shape[0]
        self._k = k = (self._k + 1) % K
        hist[k] = u
        c = self.c
        u_xy = hist[(k - self._dxy) % K, :, :2]
        u_z = hist[(k - self._dz) % K, :, 2]
        c[:, :2] += (u_xy - c[:, :2]) * (1.0 - math.exp(-dt / prm.xy_cmd_tau_s))
        c[:, 2] += (u_z - c[:, 2]) * (1.0 - math.exp(-dt / prm.z_cmd_tau_s))

        up = c[:, 2] < 0.0
        tf = np.empty_like(c)
        ts = np.empty_like(c)
        tf[:, :2] = prm.xy_fast_gain * c[:, :2]
        ts[:, :2] = (1.0 - prm.xy_fast_gain) * c[:, :2]
        tf[:, 2] = np.where(up, prm.z_up_fast_gain, prm.z_down_gain) * c[:, 2]
        ts[:, 2] = np.where(up, prm.z_up_slow_gain, 0.0) * c[:, 2]

        af = np.array(
            [1.0 - math.exp(-dt / prm.xy_fast_tau_s)] * 2 + [1.0 - math.exp(-dt / prm.z_fast_tau_s)]
        )
        asl = np.array(
            [1.0 - math.exp(-dt / prm.xy_slow_tau_s)] * 2 + [1.0 - math.exp(-dt / prm.z_slow_tau_s)]
        )
        dvf = (tf - self.vf) * af
        dvs = (ts - self.vs) * asl
        dv = dvf + dvs
        # acceleration limits: horizontal norm, vertical by direction
        lim_xy = prm.xy_accel_max * dt
        nxy = np.hypot(dv[:, 0], dv[:, 1])
        s_xy = np.minimum(1.0, lim_xy / np.maximum(nxy, 1e-12))
        lim_z = np.where(dv[:, 2] < 0.0, prm.z_accel_up_max, prm.z_accel_down_max) * dt
        s_z = np.minimum(1.0, lim_z / np.maximum(np.abs(dv[:, 2]), 1e-12))
        scale = np.stack((s_xy, s_xy, s_z), axis=1)
        v_old = self.v
        self.vf += dvf * scale
        self.vs += dvs * scale
        v = self.vf + self.vs
        p = self.p
        p_frozen = p[frozen]
        p += 0.5 * (v + v_old) * dt

        # ground contact: cannot sink below z = 0; horizontal motion dies out on the ground
        below = p[:, 2] >= 0.0
        if below.any():
            p[below, 2] = 0.0
            hit = below & (v[:, 2] > 0.0)
            for arr in (v, self.vf, self.vs):
                arr[hit, 2] = 0.0
            c[hit, 2] = np.minimum(c[hit, 2], 0.0)
            fr = math.exp(-dt / prm.ground_friction_tau_s)
            for arr in (v, self.vf, self.vs, c):
                arr[below, :2] *= fr
        self.contact = below

        # grounded (not airborne) and frozen vehicles do not move at all
        still = ~airborne | frozen
        if still.any():
            for arr in (v, self.vf, self.vs, c):
                arr[still] = 0.0
            grounded = ~airborne & ~frozen
            p[grounded, 2] = 0.0
            self.contact = self.contact | grounded
            hist[:, still] = 0.0
            p[frozen] = p_frozen

        acc_raw = (v - v_old) / dt
        a_att = 1.0 - math.exp(-dt / prm.attitude_tau_s)
        self.acc += (acc_raw - self.acc) * a_att
        self.v = v

        # heading
        yaw = self.yaw
        has_sp = ~np.isnan(yaw_sp)
        err = np.where(
            has_sp, (np.nan_to_num(yaw_sp) - yaw + math.pi) % (2 * math.pi) - math.pi, 0.0
        )
        rate_cmd = np.where(
            has_sp,
            np.clip(err / prm.yaw_tau_s, -prm.yaw_rate_max, prm.yaw_rate_max),
            np.nan_to_num(yaw_rate_sp),
        )
        rate_cmd = np.where(airborne & ~frozen, rate_cmd, 0.0)
        self.yaw_rate += (rate_cmd - self.yaw_rate) * (1.0 - math.exp(-dt / 0.1))
        self.yaw = (yaw + self.yaw_rate * dt + math.pi) % (2 * math.pi) - math.pi

        # tilt from horizontal acceleration in the heading frame (small-angle multicopter)
        cy, sy = np.cos(self.yaw), np.sin(self.yaw)
        a_fwd = cy * self.acc[:, 0] + sy * self.acc[:, 1]
        a_right = -sy * self.acc[:, 0] + cy * self.acc[:, 1]
        pitch = -np.arctan(a_fwd / GRAVITY)
        roll = np.arctan(a_right / GRAVITY)
        self.pitch_rate = (pitch - self.pitch) / dt
        self.roll_rate = (roll - self.roll) / dt
        self.pitch = pitch
        self.roll = roll
