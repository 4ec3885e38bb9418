"""Robot models: single integrator (Single) and unicycle with the near-identity
diffeomorphism (NID) of the Robotarium experiment (Section V-C).

* (Single): ṗ_i = v_c,i, integrated with forward Euler: p ← p + dt v_c.
* Unicycle: ẋ = v cos θ, ẏ = v sin θ, θ̇ = ω. The controller is evaluated at the control
  point p + s [cos θ, sin θ] ahead of the robot (paper note 10), and (NID) maps the
  velocity command of the control point to the inputs

      [v; ω] = [[cos θ, sin θ], [−sin θ / s, cos θ / s]] v_c,

  which makes the control point move exactly with v_c (the map is the inverse of the control
  point's kinematics).

All functions are vectorized over robots (arrays of shape (M, 2) / (M,)) and return new arrays.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "control_point_velocity",
    "nid_control_point",
    "nid_inputs",
    "single_integrator_step",
    "unicycle_step",
    "wrap_angle",
]


def _positive(x: float) -> bool:
    """x is a positive finite real number (math.isfinite: ~20× cheaper than np.isfinite on a
    Python float)."""
    try:
        return math.isfinite(x) and x > 0
    except TypeError:  # not a real number (e.g. an array of several values)
        return False


def _check_dt(dt: float) -> None:
    if not _positive(dt):
        raise ValueError(f"dt must be a positive finite number, got {dt}")


def _check_s(s: float) -> None:
    if not _positive(s):
        raise ValueError(f"the control point distance s must be > 0, got {s}")


def single_integrator_step(p: np.ndarray, v_c: np.ndarray, dt: float,
                           out: np.ndarray | None = None) -> np.ndarray:
    """One forward-Euler step of (Single): p + dt v_c. ``p`` and ``v_c`` have shape (M, 2);
    ``out``: an optional (M, 2) float array receiving the result (it may be ``p``)."""
    _check_dt(dt)
    p = np.asarray(p, dtype=float)
    v_c = np.asarray(v_c, dtype=float)
    if p.shape != v_c.shape:
        raise ValueError(f"p {p.shape} and v_c {v_c.shape} must have the same shape")
    return _single_step(p, v_c, dt, out)


def _single_step(p: np.ndarray, v_c: np.ndarray, dt: float, out: np.ndarray | None = None
                 ) -> np.ndarray:
    """(Single) without argument checks, for a loop that checked them once (the simulator):
    float64 arrays of one shape, dt > 0. 2 numpy calls."""
    step = np.multiply(v_c, dt, out=None if out is None or out is p else out)
    return np.add(p, step, out=step if out is None else out)


def wrap_angle(theta: np.ndarray) -> np.ndarray:
    """Angles wrapped to [−π, π)."""
    return (np.asarray(theta, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


def nid_control_point(p: np.ndarray, theta: np.ndarray, s: float) -> np.ndarray:
    """(NID) control point p + s [cos θ, sin θ] of unicycles at ``p`` (M, 2), heading θ (M,)."""
    _check_s(s)
    p = np.asarray(p, dtype=float)
    theta = np.asarray(theta, dtype=float)
    return p + s * np.stack([np.cos(theta), np.sin(theta)], axis=-1)


def nid_inputs(theta: np.ndarray, v_c: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """(NID): linear and angular speed inputs (v, ω) of unicycles with heading θ (M,) from the
    command v_c (M, 2) of their control points: v = cos θ v_cx + sin θ v_cy,
    ω = (−sin θ v_cx + cos θ v_cy)/s.
    """
    _check_s(s)
    v_c = np.asarray(v_c, dtype=float)
    c, sn = np.cos(theta), np.sin(theta)
    v = c * v_c[..., 0] + sn * v_c[..., 1]
    omega = (-sn * v_c[..., 0] + c * v_c[..., 1]) / s
    return v, omega


def control_point_velocity(v: np.ndarray, omega: np.ndarray, theta: np.ndarray,
                           s: float) -> np.ndarray:
    """Velocity of the control point for unicycle inputs (v, ω): the inverse of (NID),
    v [cos θ, sin θ] + s ω [−sin θ, cos θ]."""
    _check_s(s)
    c, sn = np.cos(theta), np.sin(theta)
    return np.stack([v * c - s * omega * sn, v * sn + s * omega * c], axis=-1)


def unicycle_step(p: np.ndarray, theta: np.ndarray, v: np.ndarray, omega: np.ndarray,
                  dt: float) -> tuple[np.ndarray, np.ndarray]:
    """One forward-Euler step of the unicycle: p += dt v [cos θ, sin θ], θ += dt ω (wrapped
    to [−π, π)). Returns the new (p, θ)."""
    _check_dt(dt)
    p = np.asarray(p, dtype=float)
    theta = np.asarray(theta, dtype=float)
    v = np.asarray(v, dtype=float)
    step = (dt * v)[..., None] * np.stack([np.cos(theta), np.sin(theta)], axis=-1)
    return p + step, wrap_angle(theta + dt * np.asarray(omega, dtype=float))
