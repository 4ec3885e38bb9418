"""sim_stub's estimator profiles against real PX4 SITL: estimate vs truth in the fleet flights.

The real figures come from ``data/px4_sitl/fleet_truth`` (PX4's estimate and the simulator's
ground truth side by side, ``fleet_truth.py``); the simulated ones from
:class:`sim_stub.estimator.EstimatorErrors` and the mock's dynamics, pure numpy (no sockets).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from fleet_truth import DT, FLIGHTS, error_stats, flight_series, reported_accuracy

from sim_stub.dynamics import QuadState
from sim_stub.estimator import ESTIMATOR_PROFILES, EstimatorErrors, estimator_profile
from sim_stub.telemetry import STRUCTS
from sim_stub.vehicle import MockVehicle


@pytest.fixture(scope="module")
def real() -> dict[str, object]:
    stats, drifts, accuracy = [], [], []
    for flight in FLIGHTS:
        for sysid in (1, 2, 3):
            s = flight_series(flight, sysid)
            a = s.airborne
            if flight != "mavlink_backend_takeoff_abort":
                stats.append(error_stats(s.pos_err[a], s.vel_err[a]))
            i0 = int(np.argmax(s.up_m > 0.05))
            i4 = int(np.argmax(s.up_m > 4.0))
            drifts.append(float(np.hypot(*(s.truth_ne[i4] - s.truth_ne[i0]))))
            accuracy.append(reported_accuracy(flight, sysid))
    return {"stats": stats, "drift": drifts, "accuracy": accuracy}


def simulate_errors(profile: str, seed: int, airborne_s: float = 36.0, dt: float = 0.01
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Errors of one vehicle that lifts off at t = 0 and flies ``airborne_s``, sampled at DT."""
    est = EstimatorErrors(1, seed)
    est.configure(0, estimator_profile(profile))
    est.start(0)
    air = np.ones(1, dtype=bool)
    every = int(round(DT / dt))
    ep, ev = [], []
    for k in range(int(airborne_s / dt)):
        est.step(dt, air)
        if k % every == 0:
            ep.append(est.e_p[0, :2].copy())
            ev.append(est.e_v[0, :2].copy())
    return np.array(ep), np.array(ev)


def within_half(sim: float, real: float) -> bool:
    return 0.5 * real <= sim <= 1.5 * real


def test_px4_sih_errors_match_the_fleet_truth_flights(real: dict) -> None:
    """Position and velocity estimate errors (p50, p95, max) and the velocity error's 1 s
    autocorrelation of the px4-sih profile are within ±50 % of the real flights' medians."""
    ref = {k: float(np.median([s[k] for s in real["stats"]])) for k in real["stats"][0]}
    sims = [error_stats(*simulate_errors("px4-sih", seed)) for seed in range(24)]
    sim = {k: float(np.median([s[k] for s in sims])) for k in sims[0]}
    print("\nreal  " + " ".join(f"{k} {v:.2f}" for k, v in ref.items()))
    print("mock  " + " ".join(f"{k} {v:.2f}" for k, v in sim.items()))
    bad = {k: (sim[k], ref[k]) for k in ref if not within_half(sim[k], ref[k])}
    assert not bad, f"outside ±50 % of the real flights (sim, real): {bad}"


def mock_reported(estimator: str, up_s: float = 60.0) -> dict[str, float]:
    """What a mock vehicle of that profile reports ``up_s`` after its start: the payloads its
    ESTIMATOR_STATUS and GPS_RAW_INT builders send, decoded with pymavlink's own field order."""
    from pymavlink.dialects.v20 import common

    v = MockVehicle(0, clock=lambda: 0.0, estimator=estimator)
    now = v.t0 + up_s
    out = {}
    for name, cls, payload in (
            ("ESTIMATOR_STATUS", common.MAVLink_estimator_status_message,
             v._b_estimator_status(now)),
            ("GPS_RAW_INT", common.MAVLink_gps_raw_int_message, v._b_gps_raw_int(now))):
        assert STRUCTS[name].format == cls.unpacker.format  # the wire order pymavlink reads
        out.update(zip(cls.ordered_fieldnames, cls.unpacker.unpack(payload), strict=True))
    return out


def test_px4_sih_reports_the_accuracy_px4_reported(real: dict) -> None:
    """The accuracy the mock *reports* (what the safety budget is built from) is what PX4 SIH
    reported in the fleet flights: ESTIMATOR_STATUS.pos_horiz_accuracy within ±10 % of every
    flight's median (the tlogs: 0.291–0.294 m); GPS_RAW_INT eph, h_acc, vel_acc and fix_type,
    constants in every tlog, equal."""
    assert len(real["accuracy"]) == 9
    mock = mock_reported("px4-sih")
    print(f"\nmock  pos_horiz_accuracy {mock['pos_horiz_accuracy']:.3f} m, eph {mock['eph']}, "
          f"h_acc {mock['h_acc']} mm, vel_acc {mock['vel_acc']} mm/s, fix {mock['fix_type']}")
    for k, acc in enumerate(real["accuracy"]):
        print("real  " + " ".join(f"{key} {val:g}" for key, val in acc.items()))
        assert 0.9 * acc["pos_horiz_accuracy"] <= mock["pos_horiz_accuracy"] \
            <= 1.1 * acc["pos_horiz_accuracy"], (k, acc, mock["pos_horiz_accuracy"])
        for key in ("eph", "h_acc", "vel_acc", "fix_type"):
            assert mock[key] == acc[key], (k, key, mock[key], acc[key])


def test_takeoff_drift_under_the_old_weak_hold_is_as_real(real: dict) -> None:
    """The truth drifts 0.4-1.3 m between lift-off and 4 m under the climb the real flights
    flew (climb 1.5 m/s, a horizontal hold on the *estimate* of gain 0.5 /s capped at
    0.3 m/s): the velocity-estimate error, its take-off transient and PX4 tracking the
    estimate. The mock's median drift is within ±50 % of the real one."""
    ref = float(np.median(real["drift"]))
    drifts = []
    for seed in range(24):
        q = QuadState(1, nominal_dt=0.01)
        est = EstimatorErrors(1, seed)
        est.configure(0, ESTIMATOR_PROFILES["px4-sih"])
        est.start(0)
        air = np.ones(1, dtype=bool)
        frozen = np.zeros(1, dtype=bool)
        u = np.zeros((1, 3))
        start = None
        for _ in range(2000):
            est.step(0.01, air)
            q.step(0.01, u - est.e_v, air, frozen, np.full(1, np.nan), np.zeros(1))
            p_est = q.p[0, :2] + est.e_p[0, :2]
            if start is None:
                start = (q.p[0, :2].copy(), p_est.copy())
            hold = 0.5 * (start[1] - p_est)
            n = float(np.hypot(*hold))
            if n > 0.3:
                hold *= 0.3 / n
            u[0] = (hold[0], hold[1], -1.5)
            if -q.p[0, 2] > 4.0:
                break
        drifts.append(float(np.hypot(*(q.p[0, :2] - start[0]))))
    sim = float(np.median(drifts))
    print(f"\ntake-off drift, truth, lift-off to 4 m: real median {ref:.2f} m "
          f"({min(real['drift']):.2f}..{max(real['drift']):.2f}), mock median {sim:.2f} m "
          f"({min(drifts):.2f}..{max(drifts):.2f})")
    assert within_half(sim, ref)


def test_rtk_is_centimetre_level_and_ideal_is_exact() -> None:
    ep, ev = simulate_errors("rtk", 1)
    assert np.hypot(*ep.T).max() < 0.06 and np.hypot(*ev.T).max() < 0.08
    ep, ev = simulate_errors("ideal", 1)
    assert not ep.any() and not ev.any()


def test_errors_are_independent_unless_shared() -> None:
    px4 = ESTIMATOR_PROFILES["px4-sih"]
    est = EstimatorErrors(4, seed=7)
    for slot in range(4):
        est.configure(slot, px4, shared=slot >= 2)
        est.start(slot)
    air = np.ones(4, dtype=bool)
    rows = []
    for _ in range(3000):
        est.step(0.01, air)
        rows.append(est.e_p[:, :2].copy())
    e = np.array(rows)  # (K, 4, 2)
    assert np.array_equal(e[:, 2], e[:, 3])  # shared: the same sequence
    corr = np.corrcoef(e[:, 0, 0], e[:, 1, 0])[0, 1]
    assert abs(corr) < 0.9 and not np.allclose(e[:, 0], e[:, 1])


def test_errors_stay_zero_until_armed_and_frozen_slots_keep_theirs() -> None:
    est = EstimatorErrors(2, seed=3)
    for slot in range(2):
        est.configure(slot, ESTIMATOR_PROFILES["px4-sih"])
    air = np.ones(2, dtype=bool)
    for _ in range(100):
        est.step(0.01, air)
    assert not est.e_p.any()  # PX4 reports (0, 0, 0) until armed (capture)
    est.start(0)
    est.start(1)
    for _ in range(300):
        est.step(0.01, air)
    kept = est.e_p[1].copy()
    frozen = np.array([False, True])
    for _ in range(100):
        est.step(0.01, air, frozen)
    assert np.array_equal(est.e_p[1], kept) and math.isfinite(float(est.e_p[0, 0]))


def test_unknown_profile_is_an_error_naming_the_choices() -> None:
    with pytest.raises(ValueError, match="px4-sih, rtk, ideal"):
        estimator_profile("gps")
