"""Compensation of the estimate disturbance: make the estimated position follow the command.

PX4's velocity controller drives its **estimated** velocity v̂ to the setpoint. When that
estimate is wrong (PX4 SITL: 0.25-0.33 m/s typical, up to 0.8 m/s, for seconds), the vehicle —
and with it the estimated position p̂, which the controller closes its loop on — moves at
v̂ − (v̂ − dp̂/dt): the paper's single integrator (Single) sees an unmodelled velocity
disturbance

    d = v̂ − dp̂/dt,

as large as the avoidance authority v'_max or larger (the real SITL flights crossed a leg while
commanded the full lateral push away from it). ``d`` is observable from what PX4 reports: its
velocity estimate and its position estimate. :class:`CompensatorBank` measures it over a
short window ``W`` of telemetry samples,

    d̂ = (∫ v̂ dt − (p̂(t) − p̂(t − W))) / W       (trapezoid rule over the samples),

and the pilot sends ``v_c + d̂`` instead of the controller's ``v_c``, so that PX4's loop drives
v̂ to v_c + d̂ and p̂ moves at ≈ v_c: the estimated position follows the single integrator again.
The residual is the change of d over the compensation delay (W/2 + link latency + control
period); it is budgeted (``SafetyBudget.disturbance_m_s``) and measured in flight.

Pure and vectorized over vehicles (:class:`CompensatorBank`, :class:`ResidualTracker`: one
vehicle is a bank of one row); positions and velocities in the tube frame
(x, y), times in seconds.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "BANK_CAPACITY",
    "DEFAULT_LIMIT_M_S",
    "DEFAULT_WINDOW_S",
    "RESIDUAL_HISTORY",
    "RESIDUAL_WINDOW_S",
    "CompensatorBank",
    "ResidualTracker",
]

#: Averaging window of the disturbance estimate (s): long enough to average the estimate's
#: sample noise, short against the disturbance's ~2-5 s correlation time.
DEFAULT_WINDOW_S = 0.4
#: Largest correction sent (m/s); larger estimates are clipped (and counted).
DEFAULT_LIMIT_M_S = 1.0


#: Samples a :class:`CompensatorBank` keeps per vehicle at most (the window holds a few: the
#: pilots add at most one per control tick); beyond it the oldest is dropped.
BANK_CAPACITY = 64


class CompensatorBank:
    """d̂ of ``m`` vehicles from their telemetry samples (module docstring), vectorized over
    the vehicles given to one :meth:`add`.

    Each vehicle keeps its samples (t, x, y) of the last ``window_s`` (at least two) with each
    one's trapezoid increments of ∫ v̂ dt towards its predecessor, computed once on arrival; an
    update sums the window's increments oldest first (the same operations in the same order as
    for one vehicle alone; |d̂| is ``np.hypot``)."""

    def __init__(self, m: int, window_s: float = DEFAULT_WINDOW_S,
                 limit_m_s: float = DEFAULT_LIMIT_M_S, capacity: int = BANK_CAPACITY) -> None:
        if not (math.isfinite(window_s) and window_s > 0):
            raise ValueError(f"compensation window must be > 0 s, got {window_s}")
        if not (math.isfinite(limit_m_s) and limit_m_s >= 0):
            raise ValueError(f"compensation limit must be >= 0 m/s, got {limit_m_s}")
        self.window_s = float(window_s)
        self.limit_m_s = float(limit_m_s)
        self.capacity = int(capacity)
        shape = (m, self.capacity)
        #: per sample: time, position, the increments of ∫v̂ dt since the previous one, v̂
        self._t, self._x, self._y = np.zeros(shape), np.zeros(shape), np.zeros(shape)
        self._ix, self._iy = np.zeros(shape), np.zeros(shape)
        self._vx, self._vy = np.zeros(shape), np.zeros(shape)
        self._head = np.zeros(m, dtype=np.int64)  # slot of each vehicle's oldest sample
        self._count = np.zeros(m, dtype=np.int64)
        self.dx_m_s = np.zeros(m)  #: d̂ (m/s), to be added to the commanded velocity
        self.dy_m_s = np.zeros(m)
        self.clipped = np.zeros(m, dtype=np.int64)  #: estimates larger than ``limit_m_s``
        self.max_m_s = np.zeros(m)  #: the largest |d̂| seen

    def d_hat_m_s(self, rows: np.ndarray) -> np.ndarray:
        """d̂ (k, 2) of ``rows`` (m/s, tube frame)."""
        return np.stack((self.dx_m_s[rows], self.dy_m_s[rows]), axis=1)

    def reset(self, rows: np.ndarray) -> None:
        """Forget the history of ``rows`` (after a jump of the estimate, a mode change, …)."""
        self._count[rows] = 0
        self.dx_m_s[rows] = 0.0
        self.dy_m_s[rows] = 0.0

    def add(self, rows: np.ndarray, t_s: np.ndarray, x_m: np.ndarray, y_m: np.ndarray,
            vx_m_s: np.ndarray, vy_m_s: np.ndarray) -> None:
        """A new telemetry sample (estimated position and velocity at time ``t_s``) for each
        of ``rows`` (distinct); samples with a non-finite value or not newer than the
        vehicle's last are ignored. Then each vehicle's d̂ is updated."""
        cap = self.capacity
        rows = np.asarray(rows, dtype=np.int64)
        ok = (np.isfinite(t_s) & np.isfinite(x_m) & np.isfinite(y_m) & np.isfinite(vx_m_s)
              & np.isfinite(vy_m_s))
        cnt = self._count[rows]
        last = (self._head[rows] + cnt - 1) % cap
        prev_t = self._t[rows, last]
        had = cnt > 0
        ok &= ~had | (t_s > prev_t)
        if not ok.all():
            rows, t_s, x_m, y_m, vx_m_s, vy_m_s = (a[ok] for a in (rows, t_s, x_m, y_m, vx_m_s,
                                                                    vy_m_s))
            cnt, last, prev_t, had = cnt[ok], last[ok], prev_t[ok], had[ok]
        if not rows.size:
            return
        dt = t_s - prev_t
        ix = np.where(had, 0.5 * (vx_m_s + self._vx[rows, last]) * dt, 0.0)
        iy = np.where(had, 0.5 * (vy_m_s + self._vy[rows, last]) * dt, 0.0)
        head = self._head[rows]
        full = cnt >= cap  # (a vehicle adds one sample per tick: never in practice)
        head = np.where(full, (head + 1) % cap, head)
        cnt = np.where(full, cnt, cnt + 1)
        slot = (head + cnt - 1) % cap
        for arr, val in ((self._t, t_s), (self._x, x_m), (self._y, y_m), (self._ix, ix),
                         (self._iy, iy), (self._vx, vx_m_s), (self._vy, vy_m_s)):
            arr[rows, slot] = val
        window = self.window_s
        while True:  # drop samples older than the window, keeping two
            drop = (cnt > 2) & (t_s - self._t[rows, (head + 1) % cap] >= window)
            if not drop.any():
                break
            head = np.where(drop, (head + 1) % cap, head)
            cnt = cnt - drop
        self._head[rows] = head
        self._count[rows] = cnt
        self._update(rows, head, cnt)

    def _update(self, rows: np.ndarray, head: np.ndarray, cnt: np.ndarray) -> None:
        cap = self.capacity
        first = head
        last = (head + cnt - 1) % cap
        span = self._t[rows, last] - self._t[rows, first]
        use = (cnt >= 2) & ~(span < 0.5 * self.window_s)
        if not use.any():
            return
        rows, first, last, cnt, span = rows[use], first[use], last[use], cnt[use], span[use]
        # the window's increments after its first sample (whose reach back before it), oldest
        # first, summed in that order: the last column of a running sum (np.cumsum adds
        # strictly left to right) over the (vehicles, samples) table padded with zeros
        j = np.arange(1, max(int(cnt.max()), 2))
        slots = (first[:, None] + j) % cap
        inside = j < cnt[:, None]
        ix = np.cumsum(np.where(inside, self._ix[rows[:, None], slots], 0.0), axis=1)[:, -1]
        iy = np.cumsum(np.where(inside, self._iy[rows[:, None], slots], 0.0), axis=1)[:, -1]
        dx = (ix - (self._x[rows, last] - self._x[rows, first])) / span
        dy = (iy - (self._y[rows, last] - self._y[rows, first])) / span
        n = np.hypot(dx, dy)
        self.max_m_s[rows] = np.fmax(self.max_m_s[rows], n)
        over = n > self.limit_m_s  # (> 0)
        if over.any():
            self.clipped[rows[over]] += 1
            scale = self.limit_m_s / n[over]
            dx[over] *= scale
            dy[over] *= scale
        self.dx_m_s[rows] = dx
        self.dy_m_s[rows] = dy


#: d̂ entries per vehicle the residual looks back in (ticks: 12.8 s at 20 Hz).
RESIDUAL_HISTORY = 256
#: Averaging time (s) of the residual compared with the budgeted D in flight.
RESIDUAL_WINDOW_S = 1.0


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
        # the newest entry <= thr: entries j back from the newest have decreasing times (one
        # per call; callers pass a monotonic now_s), so "<= thr" holds from some j on: bisect
        lo = np.zeros(len(rows), np.int64)
        hi = avail.copy()
        while True:
            active = lo < hi
            if not active.any():
                break
            mid = (lo + hi) // 2
            left = self._times[rows, (n - 1 - mid) % h] <= thr
            hi = np.where(active & left, mid, hi)
            lo = np.where(active & ~left, mid + 1, lo)
        found = lo < avail
        pick = (n - 1 - lo) % h
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
