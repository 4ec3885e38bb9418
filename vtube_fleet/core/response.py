"""PX4's measured answer to a velocity step (pure numpy, vectorized over vehicles;
docs/fleet.md, "The response check").

The safety budget's lag term (docs/fleet.md, eq. δ) models PX4's answer to a commanded velocity
change as a first-order response: nothing for the delay T + L + τ_d, then 63 % after t63 more.
What the term budgets is the distance a vehicle falls behind the commanded path, which is the
step's **lag**: the integral of the share of the change not yet flown,

    lag(W) = ∫_0^W (1 − share(t)) dt,

over a window W after the step (a position error of Δv · lag). For the model it is
:func:`model_lag_s`; the runtime flies every vehicle one step in the hover and reads its
measured lag (:func:`step_response`) — an integral, so the estimate's sample noise averages
out, where the time of a single crossing of 63 % would not (PX4's slow velocity integrator puts
that crossing on a plateau). The times to :data:`DEAD_SHARE` (τ_d) and :data:`RISE_SHARE`
(τ_d + t63) are read too, for the report.

Samples are a table: times ``t_s`` and velocities along the step ``v_m_s``, both (K, N) — K
samples of N vehicles, NaN where a vehicle has none — one column per vehicle, so that one
vehicle and a thousand take the same path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DEAD_SHARE", "RISE_SHARE", "StepResponse", "model_follow", "model_lag_s",
           "share_crossing", "step_lag_s", "step_response"]

#: The share of a step that marks the end of the dead time τ_d.
DEAD_SHARE = 0.05
#: The share of a step reached after τ_d + t63 (a first-order response: 1 − 1/e).
RISE_SHARE = 0.63
#: Samples averaged (centred) before a crossing is read: 3 ticks, against estimate noise.
SMOOTH_SAMPLES = 3


@dataclass(frozen=True)
class StepResponse:
    """Per vehicle (N,): the step's lag over the window (``lag_s``, :func:`step_lag_s`),
    seconds from the step to :data:`DEAD_SHARE` (``dead_time_s``) and to :data:`RISE_SHARE`
    (``rise_s``) of the commanded change — NaN: not reached in the samples — and the share
    reached at the last sample (``share_end``)."""

    lag_s: np.ndarray
    dead_time_s: np.ndarray
    rise_s: np.ndarray
    share_end: np.ndarray


def model_lag_s(window_s: float, delay_s: float, t63_s: float) -> float:
    """The lag over ``window_s`` of the budget's model: nothing for ``delay_s``, then a first
    order with time constant ``t63_s`` (tends to delay + t63 for a long window)."""
    if window_s <= delay_s:
        return float(window_s)
    if t63_s <= 0:
        return float(delay_s)
    return float(delay_s + t63_s * -np.expm1(-(window_s - delay_s) / t63_s))


def model_follow(y: np.ndarray, u: np.ndarray, dt_s: float, t63_s: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The model's first order over ``dt_s`` with the (already delayed) command ``u`` held:
    the new velocity y' = u + (y − u) e^(−dt/t63) and the distance flown meanwhile, exactly
    u dt − t63 (y' − y) (both (N, 2); t63 = 0: y' = u at once)."""
    if t63_s <= 0:
        return u.copy(), u * dt_s
    y1 = u + (y - u) * np.exp(-dt_s / t63_s)
    return y1, u * dt_s - t63_s * (y1 - y)


def step_lag_s(t_s: np.ndarray, share: np.ndarray, step_at_s: np.ndarray | float,
               window_s: float) -> np.ndarray:
    """Per column of (K, N): ∫ (1 − share) dt from ``step_at_s`` over ``window_s``, by the
    trapezoid rule from the step (share 0) through the samples in the window, the last
    sample's share held to the window's end; NaN for a column without samples in it."""
    t = np.asarray(t_s, float)
    s = np.asarray(share, float)
    n = s.shape[1]
    cols = np.arange(n)
    t0 = np.broadcast_to(np.asarray(step_at_s, float), (n,))
    end = t0 + window_s
    ok = np.isfinite(t) & np.isfinite(s) & (t >= t0) & (t <= end)
    tt = np.vstack((t0[None, :], np.where(ok, t, np.nan), end[None, :]))
    ss = np.vstack((np.ones((1, n)), np.where(ok, 1.0 - s, np.nan), np.full((1, n), np.nan)))
    rows = np.arange(tt.shape[0])[:, None]
    # a missing sample repeats the one before it (a zero-width trapezoid)
    tt = tt[np.maximum.accumulate(np.where(np.isfinite(tt), rows, 0), axis=0), cols]
    ss = ss[np.maximum.accumulate(np.where(np.isfinite(ss), rows, 0), axis=0), cols]
    area = 0.5 * (ss[1:] + ss[:-1]) * np.diff(tt, axis=0)
    return np.where(ok.any(axis=0), area.sum(axis=0), np.nan)


def _smooth(x: np.ndarray, k: int) -> np.ndarray:
    """Centred moving mean over ``k`` rows of (K, N), NaN-aware (the ends average fewer)."""
    if k <= 1 or x.shape[0] < 2:
        return x
    ok = np.isfinite(x)
    z = np.where(ok, x, 0.0)
    pad = k // 2
    zc = np.cumsum(np.pad(z, ((pad + 1, pad), (0, 0))), axis=0)
    nc = np.cumsum(np.pad(ok.astype(float), ((pad + 1, pad), (0, 0))), axis=0)
    s = zc[k:] - zc[:-k]
    n = nc[k:] - nc[:-k]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok & (n > 0), s / np.where(n > 0, n, 1.0), np.nan)


def share_crossing(t_s: np.ndarray, share: np.ndarray, level: float) -> np.ndarray:
    """Per column of (K, N): the first time ``share`` reaches ``level``, linearly interpolated
    from the sample before (the crossing sample's own time when it is the first); NaN where it
    never does."""
    t = np.asarray(t_s, float)
    s = np.asarray(share, float)
    above = np.isfinite(s) & np.isfinite(t) & (s >= level)
    hit = above.any(axis=0)
    k = np.argmax(above, axis=0)
    cols = np.arange(s.shape[1])
    # the previous finite sample of each column (the samples are in time order)
    finite = np.isfinite(s) & np.isfinite(t)
    idx = np.where(finite, np.arange(s.shape[0])[:, None], -1)
    last_before = np.maximum.accumulate(idx, axis=0)
    prev = np.where(k > 0, last_before[np.maximum(k - 1, 0), cols], -1)
    t1, s1 = t[k, cols], s[k, cols]
    has_prev = prev >= 0
    pi = np.maximum(prev, 0)
    t0, s0 = t[pi, cols], s[pi, cols]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.clip((level - s0) / (s1 - s0), 0.0, 1.0)
    when = np.where(has_prev & (s1 > s0), t0 + frac * (t1 - t0), t1)
    return np.where(hit, when, np.nan)


def step_response(t_s: np.ndarray, v_m_s: np.ndarray, step_at_s: float | np.ndarray,
                  v_from_m_s: float | np.ndarray, v_to_m_s: float | np.ndarray,
                  window_s: float, *, smooth: int = SMOOTH_SAMPLES) -> StepResponse:
    """The response to a commanded velocity step ``v_from_m_s`` → ``v_to_m_s`` sent at
    ``step_at_s``, from the samples (K, N) of the velocity along the step's direction: its lag
    over ``window_s`` (:func:`step_lag_s`, on the raw samples) and the crossing times (on
    samples averaged over ``smooth``; module docstring).

    The share is measured against the *command*: a vehicle that settles short of it (PX4's
    steady shortfall) lags more, and reaches 63 % later or never (NaN)."""
    t = np.asarray(t_s, float)
    v = np.asarray(v_m_s, float)
    if t.ndim == 1:
        t, v = t[:, None], v[:, None]
    n = v.shape[1]
    v_from = np.broadcast_to(np.asarray(v_from_m_s, float), (n,))
    dv = np.broadcast_to(np.asarray(v_to_m_s, float), (n,)) - v_from
    if np.any(np.abs(dv) < 1e-9):
        raise ValueError("a step needs a non-zero change of the commanded velocity")
    start = np.broadcast_to(np.asarray(step_at_s, float), (n,))
    after = t >= start
    raw = np.where(after, (v - v_from) / dv, np.nan)
    share = np.where(after, (_smooth(v, smooth) - v_from) / dv, np.nan)
    finite = np.isfinite(raw)
    last = np.where(finite.any(axis=0),
                    share[np.maximum(finite.shape[0] - 1 - np.argmax(finite[::-1], axis=0), 0),
                          np.arange(n)], np.nan)
    return StepResponse(lag_s=step_lag_s(t, raw, start, window_s),
                        dead_time_s=share_crossing(t, share, DEAD_SHARE) - start,
                        rise_s=share_crossing(t, share, RISE_SHARE) - start,
                        share_end=last)
