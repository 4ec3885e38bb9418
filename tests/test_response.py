"""core/response.py: a velocity step's lag and crossings and the model's first order, against
closed forms; the response check's model and rule (fleet/response_check.py) and the response
watch (fleet/budget.py) — pure, fast."""

from __future__ import annotations

import bisect
import math

import numpy as np
import pytest

from vtube_fleet.core.response import (
    StepResponse,
    model_follow,
    model_lag_s,
    share_crossing,
    step_lag_s,
    step_response,
)
from vtube_fleet.fleet.budget import (
    RESPONSE_PERSIST_TICKS,
    RESPONSE_WATCH_HOLDS,
    ResponseModel,
    ResponseWatch,
)
from vtube_fleet.fleet.response_check import ResponseReport


def first_order(t: np.ndarray, delay_s: float, t63_s: float, gain: float = 1.0) -> np.ndarray:
    """Share of a unit step at t = 0: nothing for ``delay_s``, then a first order."""
    return gain * np.where(t > delay_s, -np.expm1(-(t - delay_s) / t63_s), 0.0)


def test_model_lag_closed_form() -> None:
    assert model_lag_s(0.2, 0.3, 1.0) == pytest.approx(0.2)  # within the delay: all of it
    assert model_lag_s(2.0, 0.5, 1.0) == pytest.approx(0.5 + 1.0 - math.exp(-1.5))
    assert model_lag_s(100.0, 0.3, 1.0) == pytest.approx(1.3)  # long window: τ_d + t63
    assert model_lag_s(2.0, 0.4, 0.0) == pytest.approx(0.4)


def test_lag_of_a_first_order_matches_the_model_for_many_vehicles() -> None:
    t = np.arange(0.0, 2.5, 0.05)
    delays = np.array([0.2, 0.3, 0.5])
    t63s = np.array([0.5, 1.0, 1.5])
    share = np.stack([first_order(t, d, c) for d, c in zip(delays, t63s, strict=True)], axis=1)
    tt = np.repeat(t[:, None], 3, axis=1)
    lag = step_lag_s(tt, share, 0.0, 2.0)
    want = [model_lag_s(2.0, d, c) for d, c in zip(delays, t63s, strict=True)]
    np.testing.assert_allclose(lag, want, atol=0.01)


def test_one_vehicle_is_a_table_of_one_column() -> None:
    t = np.arange(0.0, 2.5, 0.05)
    v = first_order(t, 0.3, 1.0)
    one = step_response(t, v, 0.0, 0.0, 1.0, 2.0)
    many = step_response(np.repeat(t[:, None], 4, 1), np.repeat(v[:, None], 4, 1), 0.0, 0.0,
                         1.0, 2.0)
    assert one.lag_s.shape == (1,)
    np.testing.assert_allclose(many.lag_s, one.lag_s[0])


def test_crossings_and_the_share_reached() -> None:
    t = np.arange(0.0, 3.0, 0.02)
    v = 2.0 * first_order(t, 0.3, 1.0)  # a 0 → 2 m/s step
    r = step_response(t, v, 0.0, 0.0, 2.0, 3.0, smooth=1)
    assert r.rise_s[0] == pytest.approx(1.3, abs=0.02)  # τ_d + t63
    assert r.dead_time_s[0] == pytest.approx(0.3 + -math.log(0.95), abs=0.02)
    assert r.share_end[0] == pytest.approx(1 - math.exp(-(t[-1] - 0.3)), abs=0.01)


def test_a_slow_vehicle_lags_more_and_never_reaches_63_percent() -> None:
    t = np.arange(0.0, 2.5, 0.05)
    v = np.stack([first_order(t, 0.3, 1.0), first_order(t, 0.3, 1.0, gain=0.4)], axis=1)
    r = step_response(np.repeat(t[:, None], 2, 1), v, 0.0, 0.0, 1.0, 2.16)
    assert math.isnan(r.rise_s[1]) and math.isfinite(r.rise_s[0])
    assert r.lag_s[1] > r.lag_s[0] + 0.6


def test_a_stop_is_measured_against_the_command() -> None:
    """A stop from 1 m/s: the share is (1 − v) / 1; a vehicle that does not slow lags the
    whole window."""
    t = np.arange(0.0, 2.0, 0.05)
    slowing = 1.0 - first_order(t, 0.2, 0.5)
    flying_on = np.ones_like(t)
    r = step_response(np.repeat(t[:, None], 2, 1), np.stack([slowing, flying_on], axis=1),
                      0.0, 1.0, 0.0, 1.9)
    assert r.lag_s[0] == pytest.approx(model_lag_s(1.9, 0.2, 0.5), abs=0.01)
    assert r.lag_s[1] == pytest.approx(1.9, abs=1e-9)


def test_missing_samples_and_samples_outside_the_window() -> None:
    t = np.arange(-0.5, 3.0, 0.05)
    v = first_order(t, 0.3, 1.0)
    v_gappy = v.copy()
    v_gappy[(t > 0.8) & (t < 1.0)] = np.nan  # a few lost samples barely change the integral
    tt = np.repeat(t[:, None], 3, 1)
    vv = np.stack([v, v_gappy, np.full_like(v, np.nan)], axis=1)
    r = step_response(tt, vv, 0.0, 0.0, 1.0, 2.0)
    assert r.lag_s[1] == pytest.approx(r.lag_s[0], abs=0.02)
    assert r.lag_s[0] == pytest.approx(model_lag_s(2.0, 0.3, 1.0), abs=0.01)
    assert math.isnan(r.lag_s[2]) and math.isnan(r.rise_s[2])


def test_the_crossing_is_interpolated_between_samples() -> None:
    t = np.array([[0.0], [1.0], [2.0]])
    s = np.array([[0.0], [0.5], [1.0]])
    assert share_crossing(t, s, 0.75)[0] == pytest.approx(1.5)
    assert math.isnan(share_crossing(t, s, 1.5)[0])


def test_noise_averages_out_of_the_lag() -> None:
    """The lag is an integral: 0.05 m/s of white noise on the samples moves it by far less
    than it moves a single crossing."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 2.2, 0.05)
    clean = first_order(t, 0.3, 1.0)
    noisy = clean[:, None] + rng.normal(0.0, 0.05, (t.size, 200))
    r = step_response(np.repeat(t[:, None], 200, 1), noisy, 0.0, 0.0, 1.0, 2.16)
    assert np.std(r.lag_s) < 0.02
    assert abs(np.mean(r.lag_s) - model_lag_s(2.16, 0.3, 1.0)) < 0.02


def test_a_step_needs_a_change() -> None:
    with pytest.raises(ValueError, match="non-zero change"):
        step_response(np.zeros(3), np.zeros(3), 0.0, 1.0, 1.0, 1.0)


# ----------------------------------------------------------------------------------------------
# fleet/response_check.py: the model, the rule and its texts (no flight)
# ----------------------------------------------------------------------------------------------
def _model(sigma_m: float = 0.29) -> ResponseModel:
    return ResponseModel(period_s=0.05, latency_s=0.11, dead_time_s=0.3, t63_s=1.0,
                         sigma_m=sigma_m)


def test_the_model_holds_each_step_past_its_response_and_allows_its_own_lag() -> None:
    m = _model()
    assert m.delay_s == pytest.approx(0.46)
    assert m.hold_s == pytest.approx(0.46 + 1.0 + 0.7)
    start, stop = m.allowed_lag_s()
    assert start == pytest.approx(model_lag_s(m.hold_s, 0.46, 1.0))
    # the stop follows the start: 2 lag(H) − lag(2H), less than the start's
    assert stop == pytest.approx(2 * start - model_lag_s(2 * m.hold_s, 0.46, 1.0))
    assert 0 < stop < start
    assert m.tolerance_s(1.0) == pytest.approx(0.29) and m.tolerance_s(2.0) == pytest.approx(0.145)
    assert m.reach_m(1.0) == pytest.approx(2 * m.hold_s)


def test_the_model_lags_what_a_first_order_vehicle_would() -> None:
    """A vehicle that is exactly the model, flown through the start and the stop steps, lags
    the model's allowances (the rule refuses only what is slower)."""
    m = _model()
    h, dt = m.hold_s, 0.01
    t = np.arange(0.0, 2 * h + dt / 2, dt)
    y = first_order(t, m.delay_s, m.t63_s) - first_order(t - h, m.delay_s, m.t63_s)
    start = step_lag_s(t[:, None], y[:, None], 0.0, h)
    stop = step_lag_s(t[:, None], (1.0 - y)[:, None], h, h)
    np.testing.assert_allclose([start[0], stop[0]], m.allowed_lag_s(), atol=0.005)


def _report(start_lag: list[float], stop_lag: list[float]) -> ResponseReport:
    n = len(start_lag)
    nan = np.full(n, np.nan)
    r = ResponseReport(1.0, _model(), list(range(n)))
    r.start = StepResponse(np.array(start_lag, float), nan, nan, np.full(n, 0.5))
    r.stop = StepResponse(np.array(stop_lag, float), nan, nan, nan)
    return r


def test_a_vehicle_is_refused_beyond_the_model_and_the_tolerance_on_either_step() -> None:
    start, stop = _model().allowed_lag_s()
    r = _report([1.0, start + 0.28, start + 0.30, 1.0, math.nan],
                [0.6, 0.6, 0.6, stop + 0.30, 0.6])
    assert r.refused() == [2, 3, 4]  # a step without samples is refused too
    text = r.refusal([f"slot {i}" for i in range(5)])
    assert text.startswith("response check failed before the tube: 3 of 5 vehicle(s)")
    assert "slot 2: lag" in text and "slot 0:" not in text and "no sample" in text
    assert "tracking_dead_time_s, tracking_t63_s" in text and "0.29 s the estimate" in text
    d = r.as_dict()
    assert d["refused"] == [2, 3, 4] and d["lag_start_s"][4] is None
    assert d["allowed_lag_s"] == [round(start, 3), round(stop, 3)]


def test_a_skipped_check_refuses_nobody_and_says_why() -> None:
    r = ResponseReport(1.0, _model(), [0, 1])
    r.skipped = "response_check = false in the mission"
    assert r.refused() == []
    assert r.describe() == "response check skipped: response_check = false in the mission"
    assert r.as_dict()["lag_start_s"] == [] and r.as_dict()["skipped"] == r.skipped


# ----------------------------------------------------------------------------------------------
# the model's first order and the response watch (fleet/budget.py)
# ----------------------------------------------------------------------------------------------
def test_model_follow_is_the_exact_first_order_in_any_steps() -> None:
    y1, dx = model_follow(np.zeros((1, 2)), np.array([[1.0, -2.0]]), 0.5, 1.0)
    a = -math.expm1(-0.5)
    np.testing.assert_allclose(y1, [[a, -2 * a]])
    np.testing.assert_allclose(dx, [[0.5 - a, -2 * (0.5 - a)]])  # ∫ (1 − e^(−t)) dt
    y, x = np.zeros((1, 2)), np.zeros((1, 2))
    for _ in range(50):  # the same half second in 50 steps
        y, d = model_follow(y, np.array([[1.0, -2.0]]), 0.01, 1.0)
        x += d
    np.testing.assert_allclose(y, y1, atol=1e-12)
    np.testing.assert_allclose(x, dx, atol=1e-12)
    y0, d0 = model_follow(np.zeros((1, 2)), np.array([[1.0, 0.0]]), 0.2, 0.0)
    np.testing.assert_allclose(y0, [[1.0, 0.0]])  # t63 = 0: at once
    np.testing.assert_allclose(d0, [[0.2, 0.0]])


def _watch_model() -> ResponseModel:
    return ResponseModel(period_s=0.05, latency_s=0.11, dead_time_s=0.3, t63_s=1.0,
                         sigma_m=0.29, disturbance_m_s=0.25)


def _fly(watch: ResponseWatch, gains: list[float], *, seconds: float = 24.0,
         watched_from_s: float = 1.0, dead: list[float] | None = None) -> list[str]:
    """Vehicles hover, then from ``watched_from_s`` are sent 1 m/s along x (turning to y at
    12 s); vehicle i answers as the model with a steady ``gains[i]`` (and its own dead
    time); returns the hold reasons."""
    m = watch.model
    n = len(gains)
    dt = m.period_s
    delays = dead or [m.delay_s] * n
    hist: list[tuple[float, np.ndarray]] = []
    y = np.zeros((n, 2))
    xy = np.zeros((n, 2))
    ids = np.arange(10, 10 + n)
    out = []
    sub = 50  # the vehicles fly in 1 ms steps, each command acting its own delay after it
    times: list[float] = []
    for k in range(int(seconds / dt)):
        t = k * dt
        for j in range(sub if hist else 0):  # each its own delay, the first order, its gain
            tau = t - dt + j * dt / sub
            u = np.zeros((n, 2))
            for i in range(n):
                at = bisect.bisect_right(times, tau - delays[i] + 1e-12) - 1
                u[i] = gains[i] * hist[at][1][i] if at >= 0 else 0.0
            y, d = model_follow(y, u, dt / sub, m.t63_s)
            xy = xy + d
        sent = np.zeros((n, 2))
        if t >= watched_from_s:
            sent[:, 0 if t < 12.0 else 1] = 1.0
        hist.append((t, sent))
        times.append(t)
        why = watch.update(t, sent, xy, np.full(n, t >= watched_from_s), ids)
        if why:
            out.append(why)
    return out


def test_the_response_watch_leaves_a_vehicle_that_answers_as_the_model_alone() -> None:
    w = ResponseWatch(_watch_model(), 2)
    assert w.window_s == pytest.approx(RESPONSE_WATCH_HOLDS * _watch_model().hold_s)
    assert w.tolerance_m == pytest.approx(0.25 * w.window_s + 2 * 0.29)  # D W + k σ
    assert _fly(w, [1.0, 1.0]) == []
    assert w.max_m < 0.005  # the same model, each command acting exactly its delay later
    # not judged before the model's start has settled and a whole window has passed
    assert w.as_dict()["max_at"]["t_s"] > 1.0 + w.settle_s + w.window_s


def test_the_response_watch_holds_a_vehicle_that_follows_forty_percent() -> None:
    w = ResponseWatch(_watch_model(), 3)
    reasons = _fly(w, [1.0, 0.4, 1.0])
    assert reasons, "a vehicle following 40 % of its commands must hold the tube"
    assert reasons[0].startswith("safety budget exceeded in flight: vehicle 11 flew ")
    assert f"{RESPONSE_PERSIST_TICKS} ticks in a row" in reasons[0]
    assert "τ_d = 0.3 s, t63 = 1 s" in reasons[0]
    assert w.max_at is not None and w.max_at[1] == 11


def test_the_response_watch_holds_a_steady_shortfall_not_a_late_answer() -> None:
    """Over its window a steady shortfall grows and a late answer does not: a vehicle at
    60 % holds, one at 85 % does not, nor one that answers 1.2 s later than the model (the
    response check before the tube judges that)."""
    m = _watch_model()
    assert _fly(ResponseWatch(m, 1), [0.6]) != []
    assert _fly(ResponseWatch(m, 1), [0.85]) == []
    assert _fly(ResponseWatch(m, 1), [1.0], dead=[m.delay_s + 1.2]) == []


def test_the_response_watch_judges_only_whole_watched_windows() -> None:
    w = ResponseWatch(_watch_model(), 1)
    ids = np.array([0])
    # a vehicle that never moves, watched for less than a window at a time: never judged
    for k in range(200):
        t = k * 0.05
        watched = np.array([(k // 30) % 2 == 0])  # 1.5 s on, 1.5 s off
        assert w.update(t, np.array([[1.0, 0.0]]), np.zeros((1, 2)), watched, ids) is None
    assert math.isnan(w.max_m)
    # without a position (NaN) it is not watched either
    for k in range(200, 300):
        assert w.update(k * 0.05, np.array([[1.0, 0.0]]), np.full((1, 2), np.nan),
                        np.array([True]), ids) is None
    assert math.isnan(w.max_m)


def _cruise(w: ResponseWatch, t0: float, t1: float, x0: float, *, speed: float = 1.0,
            stale_at: float | None = None) -> tuple[list[str], float]:
    """Feed ``w`` a vehicle sent ``speed`` along x and flying it, from ``t0`` to ``t1`` at 20
    Hz starting at x = ``x0``; ``stale_at``: that tick's sample is stale. Returns (the hold
    reasons, x at the end)."""
    out, x, t = [], x0, t0
    while t < t1 - 1e-9:
        fresh = np.array([stale_at is None or abs(t - stale_at) > 1e-6])
        why = w.update(t, np.array([[speed, 0.0]]), np.array([[x, 0.0]]), np.array([True]),
                       np.array([7]), fresh)
        if stale_at is not None and not fresh[0]:
            assert math.isnan(w.offset_m[0])  # a stale sample is not compared …
        if why:
            out.append(why)
        t += 0.05
        x += speed * 0.05
    return out, x


def test_a_pause_in_the_watch_restarts_its_spells_and_a_stale_sample_is_skipped() -> None:
    """The watch not fed for 3 s (no vehicle in the tube, an agent's untrusted ticks) while the
    vehicle stood still: its model would have flown on, so the spell restarts and nothing is
    held; a single stale sample is skipped, the spell goes on."""
    w = ResponseWatch(_watch_model(), 1)
    held, x = _cruise(w, 0.0, 20.0, 0.0, stale_at=15.0)
    assert held == [] and 0.0 < w.max_m < 0.1
    assert np.isfinite(w.offset_m[0])  # … and the next ones are again
    held, _ = _cruise(w, 23.0, 45.0, x)  # 3 s unfed, standing still at x
    assert held == [], held
    assert w.max_m < 0.1
