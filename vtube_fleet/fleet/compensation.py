"""Compensation of the estimate disturbance: make the estimated position follow the command.

PX4's velocity controller drives its **estimated** velocity v̂ to the setpoint. When that
estimate is wrong (PX4 SITL: 0.25-0.33 m/s typical, up to 0.8 m/s, for seconds), the vehicle —
and with it the estimated position p̂, which the controller closes its loop on — moves at
v̂ − (v̂ − dp̂/dt): the paper's single integrator (Single) sees an unmodelled velocity
disturbance

    d = v̂ − dp̂/dt,

as large as the avoidance authority v'_max or larger (the real SITL flights crossed a leg while
commanded the full lateral push away from it). ``d`` is observable from what PX4 reports: its
velocity estimate and its position estimate. :class:`EstimateCompensator` measures it over a
short window ``W`` of telemetry samples,

    d̂ = (∫ v̂ dt − (p̂(t) − p̂(t − W))) / W       (trapezoid rule over the samples),

and the pilot sends ``v_c + d̂`` instead of the controller's ``v_c``, so that PX4's loop drives
v̂ to v_c + d̂ and p̂ moves at ≈ v_c: the estimated position follows the single integrator again.
The residual is the change of d over the compensation delay (W/2 + link latency + control
period); it is budgeted (``SafetyBudget.disturbance_m_s``) and measured in flight.

Pure and per vehicle: positions and velocities in the tube frame (x, y), times in seconds.
"""

from __future__ import annotations

import math
from collections import deque

__all__ = ["EstimateCompensator", "DEFAULT_WINDOW_S", "DEFAULT_LIMIT_M_S"]

#: Averaging window of the disturbance estimate (s): long enough to average the estimate's
#: sample noise, short against the disturbance's ~2-5 s correlation time.
DEFAULT_WINDOW_S = 0.4
#: Largest correction sent (m/s); larger estimates are clipped (and counted).
DEFAULT_LIMIT_M_S = 1.0


class EstimateCompensator:
    """d̂ of one vehicle from its telemetry samples (module docstring).

    The samples are kept as (t, x, y) with each one's trapezoid increments of ∫ v̂ dt towards
    its predecessor computed once on arrival, so an update sums a window of increments instead
    of redoing the products (the same operations in the same order: the same bits)."""

    def __init__(self, window_s: float = DEFAULT_WINDOW_S,
                 limit_m_s: float = DEFAULT_LIMIT_M_S) -> None:
        if not (math.isfinite(window_s) and window_s > 0):
            raise ValueError(f"compensation window must be > 0 s, got {window_s}")
        if not (math.isfinite(limit_m_s) and limit_m_s >= 0):
            raise ValueError(f"compensation limit must be >= 0 m/s, got {limit_m_s}")
        self.window_s = float(window_s)
        self.limit_m_s = float(limit_m_s)
        #: (t_s, x_m, y_m, ∫v̂x dt, ∫v̂y dt since the previous sample, vx, vy) per sample
        self._samples: deque[tuple[float, float, float, float, float, float, float]] = deque()
        self.dx_m_s = 0.0
        self.dy_m_s = 0.0
        self.clipped = 0  #: estimates larger than ``limit_m_s`` (clipped)
        self.max_m_s = 0.0  #: the largest |d̂| seen

    def reset(self) -> None:
        """Forget the history (after a jump of the estimate, a mode change, …)."""
        self._samples.clear()
        self.dx_m_s = self.dy_m_s = 0.0

    def add(self, t_s: float, x_m: float, y_m: float, vx_m_s: float, vy_m_s: float) -> None:
        """A new telemetry sample (estimated position and velocity at time ``t_s``)."""
        isfinite = math.isfinite
        if not (isfinite(t_s) and isfinite(x_m) and isfinite(y_m) and isfinite(vx_m_s)
                and isfinite(vy_m_s)):
            return
        q = self._samples
        if q:
            prev = q[-1]
            if t_s <= prev[0]:
                return
            dt = t_s - prev[0]
            q.append((t_s, x_m, y_m, 0.5 * (vx_m_s + prev[5]) * dt,
                      0.5 * (vy_m_s + prev[6]) * dt, vx_m_s, vy_m_s))
        else:
            q.append((t_s, x_m, y_m, 0.0, 0.0, vx_m_s, vy_m_s))
        window = self.window_s
        while len(q) > 2 and t_s - q[1][0] >= window:
            q.popleft()
        self._update()

    def _update(self) -> None:
        q = self._samples
        if len(q) < 2:
            return
        first, last = q[0], q[-1]
        span = last[0] - first[0]
        if span < 0.5 * self.window_s:
            return
        ix = iy = 0.0
        it = iter(q)
        next(it)  # the first sample's increments reach back before the window
        for s in it:
            ix += s[3]
            iy += s[4]
        dx = (ix - (last[1] - first[1])) / span
        dy = (iy - (last[2] - first[2])) / span
        n = math.hypot(dx, dy)
        if n > self.max_m_s:
            self.max_m_s = n
        if n > self.limit_m_s:
            self.clipped += 1
            scale = self.limit_m_s / n if n > 0 else 0.0
            dx, dy = dx * scale, dy * scale
        self.dx_m_s, self.dy_m_s = dx, dy

    @property
    def correction(self) -> tuple[float, float]:
        """(d̂_x, d̂_y) in m/s, to be added to the commanded velocity."""
        return self.dx_m_s, self.dy_m_s
