"""PX4's state estimate beside the truth: estimator error profiles (pure numpy, vectorized).

A real PX4 vehicle flies on its *estimate*. Its velocity controller drives the **estimated**
velocity to the setpoint, so when the estimate is wrong the vehicle truly moves where nobody
commanded; its position controllers (Hold, Land, …) and every message it sends use the estimated
position. This module models that error for ``n`` vehicles at once, per horizontal axis:

* **velocity-estimate error** ``e_v``: a stationary second-order Gauss-Markov process (natural
  frequency ``omega_rad_s``, damping ``zeta``, standard deviation ``sigma_v_m_s`` per axis), plus
  a **take-off transient** after each lift-off: ``kick_m_s · u · (s/τ) e^(1 − s/τ)`` with a random
  unit direction ``u`` and ``s`` the time since lift-off (peak ``kick_m_s`` at ``s = τ``). On the
  ground the process is scaled by ``ground_scale``;
* **position-estimate error** ``e_p``: the estimate integrates its own velocity and is pulled back
  to GNSS with gain ``pull_1_s``: ``ė_p = coupling · e_v − pull · e_p + √q w`` (white ``w``);
* the vehicle's true velocity is what PX4's velocity loop makes of ``setpoint − e_v``
  (``sim_stub.scheduler``), so ``v_est = v_true + e_v`` and ``p_est = p_true + e_p``;
* the GNSS receiver itself (GPS_RAW_INT) reports ``p_true + e_gnss`` with its own small error.

The ``px4-sih`` constants were fitted to three real PX4 SITL (SIH) fleet flights with PX4's
ground truth beside its estimate (``docs/sim_stub.md``, "Estimate and truth"): the regression of
the measured ``ė_p`` on ``e_v`` and ``e_p`` gave coupling 0.31-0.60 and pull 0.37-0.81 /s; the
velocity error's autocorrelation is 0.78-0.99 at 1 s and crosses zero after 3-7 s. Simulated
flights (median of 24 seeds, 36 s airborne) give horizontal ``|e_p|`` p50/p95/max 0.23/0.45/0.52 m
and ``|e_v|`` 0.32/0.67/0.78 m/s, autocorrelation 0.88 at 1 s (the flights' medians: 0.21/0.45/
0.50 m, 0.29/0.66/0.78 m/s, 0.86), and a take-off drift of the truth (lift-off to 4 m, under the
climb the flights flew) of 1.06 m median, 0.18-2.07 m (flights: 1.23 m, 0.36-1.29 m);
``tests/test_sim_stub_estimator.py`` checks this.

Profiles (:data:`ESTIMATOR_PROFILES`): ``px4-sih`` (like the captures; the default), ``rtk``
(cm-level, RTK fixed) and ``ideal`` (the estimate *is* the truth; for unit tests only). Errors are
independent across vehicles unless ``shared`` (SIH gives every instance the same noise sequence:
the captures show cross-instance correlation 0.92-0.99 in two flights).

The vertical axis is not perturbed (the tube is 2-D; altitude is held by a separate loop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["ESTIMATOR_PROFILES", "EstimatorProfile", "EstimatorErrors", "estimator_profile"]


@dataclass(frozen=True)
class EstimatorProfile:
    """Error model constants of one estimator profile (see the module docstring) and the
    accuracy the vehicle reports for it (ESTIMATOR_STATUS, GPS_RAW_INT)."""

    name: str
    sigma_v_m_s: float  #: stationary std of the velocity-estimate error, per axis
    omega_rad_s: float
    zeta: float
    kick_m_s: float  #: peak of the take-off transient of the velocity error
    kick_tau_s: float
    coupling: float  #: ė_p = coupling·e_v − pull·e_p + noise
    pull_1_s: float
    pos_noise_m_sqrt_s: float
    ground_scale: float  #: error scale while on the ground (before and after flight)
    gnss_sigma_m: float  #: GNSS receiver position error (GPS_RAW_INT), per axis
    gnss_tau_s: float
    gnss_vel_sigma_m_s: float
    # reported accuracy
    pos_horiz_accuracy_m: float  #: ESTIMATOR_STATUS.pos_horiz_accuracy
    pos_vert_accuracy_m: float
    eph_cm: int  #: GPS_RAW_INT.eph (HDOP × 100)
    epv_cm: int
    h_acc_mm: int
    v_acc_mm: int
    vel_acc_mm_s: int
    fix_type: int  #: 3 = 3D fix, 6 = RTK fixed
    satellites: int

    @property
    def perturbs(self) -> bool:
        """False for the ``ideal`` profile (no error at all)."""
        return self.sigma_v_m_s > 0 or self.kick_m_s > 0 or self.pos_noise_m_sqrt_s > 0


ESTIMATOR_PROFILES: dict[str, EstimatorProfile] = {
    p.name: p
    for p in (
        # fitted to the fleet flights with PX4 SITL ground truth (module docstring); reported
        # accuracy as PX4 SIH reported it there (ESTIMATOR_STATUS p50 0.29 m; GPS_RAW_INT eph
        # 70, h_acc 0.90 m, vel_acc 0.40 m/s, fix 3, 10 satellites)
        EstimatorProfile(
            "px4-sih", sigma_v_m_s=0.23, omega_rad_s=0.55, zeta=0.35, kick_m_s=0.7,
            kick_tau_s=2.5, coupling=0.5, pull_1_s=0.6, pos_noise_m_sqrt_s=0.03,
            ground_scale=0.25, gnss_sigma_m=0.15, gnss_tau_s=3.0, gnss_vel_sigma_m_s=0.05,
            pos_horiz_accuracy_m=0.29, pos_vert_accuracy_m=0.32, eph_cm=70, epv_cm=110,
            h_acc_mm=900, v_acc_mm=1780, vel_acc_mm_s=400, fix_type=3, satellites=10,
        ),
        # RTK fixed: a few cm (drone-show class receivers, 1-2 cm)
        EstimatorProfile(
            "rtk", sigma_v_m_s=0.02, omega_rad_s=0.55, zeta=0.35, kick_m_s=0.02,
            kick_tau_s=2.5, coupling=0.5, pull_1_s=1.0, pos_noise_m_sqrt_s=0.003,
            ground_scale=0.25, gnss_sigma_m=0.01, gnss_tau_s=3.0, gnss_vel_sigma_m_s=0.01,
            pos_horiz_accuracy_m=0.02, pos_vert_accuracy_m=0.03, eph_cm=50, epv_cm=80,
            h_acc_mm=14, v_acc_mm=20, vel_acc_mm_s=20, fix_type=6, satellites=22,
        ),
        # the estimate is the truth (the mock's behaviour before estimator profiles existed)
        EstimatorProfile(
            "ideal", sigma_v_m_s=0.0, omega_rad_s=0.55, zeta=0.35, kick_m_s=0.0,
            kick_tau_s=2.5, coupling=0.0, pull_1_s=1.0, pos_noise_m_sqrt_s=0.0,
            ground_scale=1.0, gnss_sigma_m=0.0, gnss_tau_s=3.0, gnss_vel_sigma_m_s=0.0,
            pos_horiz_accuracy_m=0.29, pos_vert_accuracy_m=0.32, eph_cm=70, epv_cm=110,
            h_acc_mm=900, v_acc_mm=1780, vel_acc_mm_s=400, fix_type=3, satellites=10,
        ),
    )
}


def estimator_profile(name: str) -> EstimatorProfile:
    """The profile called ``name``; ``ValueError`` naming the choices otherwise."""
    try:
        return ESTIMATOR_PROFILES[name]
    except KeyError:
        raise ValueError(f"estimator profile must be one of "
                         f"{', '.join(ESTIMATOR_PROFILES)}, got {name!r}") from None


class EstimatorErrors:
    """Estimate errors of ``n`` vehicle slots (horizontal NED axes), advanced by :meth:`step`.

    Per slot: a ``profile`` (set with :meth:`configure`) and whether the vehicle is airborne
    (take-off transients start at each lift-off). ``e_v`` and ``e_p`` are (n, 3) arrays (the
    third, vertical, column stays 0); ``e_gnss`` is the GNSS receiver error (n, 3). One random
    generator (``seed``) serves all independent slots; slots configured ``shared`` all take
    the same draws from a second generator (SIH-like).
    """

    def __init__(self, n: int, seed: int = 0, *, stream: int = 0) -> None:
        self.n = n
        self.e_v = np.zeros((n, 3))
        self.e_p = np.zeros((n, 3))
        self.e_gnss = np.zeros((n, 3))
        self.e_gnss_v = np.zeros((n, 3))
        self._x = np.zeros((n, 2))  # stationary velocity-error state
        self._xd = np.zeros((n, 2))
        self._kick_dir = np.zeros((n, 2))
        self._air_s = np.full(n, -1.0)  # seconds since lift-off, -1 on the ground
        self._profiles: list[EstimatorProfile] = [ESTIMATOR_PROFILES["ideal"]] * n
        # stream k > 0: an independent sequence (a fleet split over processes), same shared one
        self._rng = np.random.default_rng(seed if stream == 0 else (seed, stream))
        self._shared = np.zeros(n, dtype=bool)
        self._running = np.zeros(n, dtype=bool)
        self._active = np.zeros(n, dtype=bool)
        self._shared_rng = np.random.default_rng(seed + 1)
        self._params = np.zeros((n, 12))
        self._k: tuple | None = None  # step()'s per-slot constants (_constants)
        self._refresh()

    # -- configuration -------------------------------------------------------------------
    def configure(self, slot: int, profile: EstimatorProfile, shared: bool = False) -> None:
        """Give slot ``slot`` the ``profile``; ``shared`` slots take common draws. The errors
        stay 0 until :meth:`start` (PX4 reports exactly (0, 0, 0) after boot, capture)."""
        self._profiles[slot] = profile
        self._running[slot] = False
        self._shared[slot] = shared
        rng = np.random.default_rng(0) if shared else self._rng
        p = profile
        self.e_v[slot] = self.e_p[slot] = self.e_gnss[slot] = self.e_gnss_v[slot] = 0.0
        # start in the stationary distribution (scaled for the ground)
        self._x[slot] = rng.standard_normal(2) * p.sigma_v_m_s
        self._xd[slot] = rng.standard_normal(2) * p.sigma_v_m_s * p.omega_rad_s
        self.e_gnss[slot, :2] = rng.standard_normal(2) * p.gnss_sigma_m
        self._kick_dir[slot] = 0.0
        self._air_s[slot] = -1.0
        self._refresh(slot)

    def start(self, slot: int) -> None:
        """The errors of ``slot`` start evolving (the mock calls this at the first arming)."""
        if not self._running[slot]:
            self._running[slot] = True
            self._refresh(slot)

    def release(self, slot: int) -> None:
        """The slot is free: no errors."""
        self._running[slot] = False
        self._profiles[slot] = ESTIMATOR_PROFILES["ideal"]
        self._shared[slot] = False
        self.e_v[slot] = self.e_p[slot] = self.e_gnss[slot] = self.e_gnss_v[slot] = 0.0
        self._refresh(slot)

    def profile(self, slot: int) -> EstimatorProfile:
        return self._profiles[slot]

    def _refresh(self, slot: int | None = None) -> None:
        prm = self._params
        slots = range(self.n) if slot is None else (slot,)
        for i in slots:
            p = self._profiles[i]
            prm[i] = (p.sigma_v_m_s, p.omega_rad_s, p.zeta, p.kick_m_s, p.kick_tau_s,
                      p.coupling, p.pull_1_s, p.pos_noise_m_sqrt_s, p.ground_scale,
                      p.gnss_sigma_m, p.gnss_tau_s, p.gnss_vel_sigma_m_s)
            self._active[i] = p.perturbs and bool(self._running[i])
        self._k = None  # the per-slot constants of step() are derived again

    def _constants(self) -> tuple:
        """Per-slot constants of :meth:`step` that only change with the profiles (the same
        expressions step() used to evaluate every tick, so the results are bit for bit the
        same)."""
        prm = self._params
        sig, w, z, kick, ktau = prm[:, 0], prm[:, 1], prm[:, 2], prm[:, 3], prm[:, 4]
        coup, pull, qn, ground = prm[:, 5], prm[:, 6], prm[:, 7], prm[:, 8]
        gsig, gtau, gvsig = prm[:, 9], prm[:, 10], prm[:, 11]
        active = self._active
        inactive = ~active
        self._k = k = (
            bool(active.any()), active.copy(), inactive, bool(inactive.any()),
            bool(self._shared.any()),
            (-2.0 * z * w)[:, None], (w * w)[:, None], 4.0 * z * w ** 3 * sig ** 2,
            ktau.copy(), np.maximum(ktau, 1e-9), kick.copy(), ground.copy(), 1.0 - ground,
            coup[:, None], pull[:, None], qn.copy(), np.maximum(gtau, 1e-9), gsig.copy(),
            gvsig[:, None],
        )  # fmt: skip
        return k

    # -- time ----------------------------------------------------------------------------
    def _noise(self, k: int, shared: bool | None = None) -> np.ndarray:
        """(n, k) standard normal draws, the same row for shared slots."""
        out = self._rng.standard_normal((self.n, k))
        if self._shared.any() if shared is None else shared:
            out[self._shared] = self._shared_rng.standard_normal(k)
        return out

    def step(self, dt: float, airborne: np.ndarray, frozen: np.ndarray | None = None,
             any_frozen: bool | None = None) -> None:
        """Advance every slot by ``dt`` s; ``airborne`` (n,) bool (lift-off starts a kick);
        ``frozen`` (n,) slots keep their errors unchanged (a frozen vehicle's state does not
        change; ``any_frozen``: whether any is, if the caller knows)."""
        k = self._k if self._k is not None else self._constants()
        (any_active, active, inactive, any_inactive, any_shared, m2zw, ww, q, ktau, ktau_pos,
         kick, ground, ground_c, coup, pull, qn, gtau_pos, gsig, gvsig) = k  # fmt: skip
        if not any_active or dt <= 0.0:
            return
        keep = None
        if frozen is not None and (frozen.any() if any_frozen is None else any_frozen):
            keep = (frozen, self.e_v[frozen].copy(), self.e_p[frozen].copy(),
                    self.e_gnss[frozen].copy(), self.e_gnss_v[frozen].copy())
        noise = self._noise(10, any_shared)
        # lift-off: a new take-off transient with a random direction
        air = np.asarray(airborne, dtype=bool) & active
        air_s = self._air_s
        lift = air & (air_s < 0.0)
        if lift.any():
            d = noise[lift, 0:2]
            nrm = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
            self._kick_dir[lift] = d / nrm[:, None]
            air_s[lift] = 0.0
        air_s[air] += dt
        air_s[~air] = -1.0
        # stationary second-order process: x'' = -2 z w x' - w² x + sqrt(4 z w³ σ²) ξ
        xdd = m2zw * self._xd - ww * self._x + np.sqrt(q / dt)[:, None] * noise[:, 2:4]
        self._xd += xdd * dt
        self._x += self._xd * dt
        s = air_s
        on = s > 0.0
        env = np.where(on, (s / ktau) * np.exp(1.0 - s / ktau_pos), 0.0)
        scale = np.where(air, np.minimum(1.0, ground + ground_c * np.maximum(s, 0.0)), ground)
        ev = scale[:, None] * self._x + (kick * env)[:, None] * self._kick_dir
        self.e_v[:, :2] = ev
        ep = self.e_p[:, :2]
        ep += dt * (coup * ev - pull * ep) + (qn * math.sqrt(dt))[:, None] * noise[:, 4:6]
        # GNSS receiver error: first-order Gauss-Markov
        a = np.exp(-dt / gtau_pos)
        g = self.e_gnss[:, :2]
        g *= a[:, None]
        g += (gsig * np.sqrt(1.0 - a * a))[:, None] * noise[:, 6:8]
        self.e_gnss_v[:, :2] = gvsig * noise[:, 8:10]
        if keep is not None:
            m, ev0, ep0, g0, gv0 = keep
            self.e_v[m], self.e_p[m], self.e_gnss[m], self.e_gnss_v[m] = ev0, ep0, g0, gv0
        if any_inactive:
            self.e_v[inactive] = self.e_p[inactive] = 0.0
            self.e_gnss[inactive] = self.e_gnss_v[inactive] = 0.0
