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

Pure: :class:`EstimateCompensator` per vehicle, :class:`ResidualTracker` vectorized over
vehicles; positions and velocities in the tube frame (x, y), times in seconds.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

__all__ = [
    "DEFAULT_LIMIT_M_S",
    "DEFAULT_WINDOW_S",
    "RESIDUAL_HISTORY",
    "RESIDUAL_WINDOW_S",
    "EstimateCompensator",
    "ResidualTracker",
]

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


#: d̂ entries per vehicle the residual looks back in (ticks: 12.8 s at 20 Hz).
RESIDUAL_HISTORY = 256
#: Averaging time (s) of the residual compared with the budgeted D in flight.
RESIDUAL_WINDOW_S = 1.0
#: Entries :meth:`ResidualTracker.track` looks at first (newest first); older only if needed.
_NEAR = 16


class ResidualTracker:
    """The compensation's residual of ``m`` vehicles: how much d̂ changed over its own delay
    Δ = W/2 + T + L (what PX4 cannot have been told yet), one value per tracked tick, and its
    mean over :data:`RESIDUAL_WINDOW_S` against the budgeted D (the budget integrates D over
    time, so single-tick spikes are harmless; a residual that stays above D is not).

    Each vehicle keeps its newest :data:`RESIDUAL_HISTORY` (tick time, d̂) entries; Δ is
    looked back from the newest entry. Vectorized over the vehicles tracked in one call."""

    def __init__(self, m: int, period_s: float, budget_m_s: float,
                 history: int = RESIDUAL_HISTORY) -> None:
        self.period_s = float(period_s)
        self.budget_m_s = float(budget_m_s)
        self.history = int(history)
        self._times = np.full((m, self.history), np.nan)
        self._hist = np.zeros((m, self.history, 2))
        self._count = np.zeros(m, dtype=np.int64)
        self.mean_m_s = np.zeros(m)  #: each vehicle's residual averaged over RESIDUAL_WINDOW_S
        self.warned = np.zeros(m, dtype=bool)  #: its mean has exceeded the budget once
        self._rows: list[np.ndarray] = []  # per call: the vehicles with a residual …
        self._values: list[np.ndarray] = []  # … and their residuals

    def track(self, rows: np.ndarray, now_s: float, d_m_s: np.ndarray,
              lag_s: np.ndarray) -> np.ndarray:
        """Vehicles ``rows`` (distinct) at tick time ``now_s`` with d̂ ``d_m_s`` (k, 2) and
        delays Δ ``lag_s`` (k,): store, then the residual |d̂ − d̂(newest entry ≤ now − Δ)|
        where one exists. Returns the rows whose mean has just exceeded the budget (each once)."""
        h = self.history
        n = self._count[rows]
        slot = n % h
        self._times[rows, slot] = now_s
        self._hist[rows, slot] = d_m_s
        n = n + 1
        self._count[rows] = n
        thr = now_s - lag_s
        avail = np.minimum(n, h)
        near = min(_NEAR, h)
        back = np.arange(near)
        cols = (n[:, None] - 1 - back) % h
        ok = (self._times[rows[:, None], cols] <= thr[:, None]) & (back < avail[:, None])
        found = ok.any(axis=1)
        pick = cols[np.arange(len(rows)), ok.argmax(axis=1)]
        for k in np.flatnonzero(~found & (avail > near)).tolist():  # Δ beyond the near entries
            back_all = np.arange(avail[k])
            c_all = (n[k] - 1 - back_all) % h
            hit = np.flatnonzero(self._times[rows[k], c_all] <= thr[k])
            if hit.size:
                found[k], pick[k] = True, c_all[hit[0]]
        if not found.any():
            return rows[:0]
        r = rows[found]
        old = self._hist[r, pick[found]]
        d = d_m_s[found]
        residual = np.hypot(d[:, 0] - old[:, 0], d[:, 1] - old[:, 1])
        self._rows.append(r)
        self._values.append(residual)
        gain = min(1.0, self.period_s / RESIDUAL_WINDOW_S)
        mean = self.mean_m_s[r]
        mean += gain * (residual - mean)
        self.mean_m_s[r] = mean
        crossed = r[(mean > self.budget_m_s) & ~self.warned[r]]
        self.warned[crossed] = True
        return crossed

    def residuals(self, row: int | None = None) -> np.ndarray:
        """Every residual so far (m/s): of vehicle ``row``, or of all vehicles."""
        if not self._values:
            return np.zeros(0)
        values = np.concatenate(self._values)
        if row is None:
            return values
        return values[np.concatenate(self._rows) == row]
