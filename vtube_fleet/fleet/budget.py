"""The safety budget: how much the runtime inflates r_s and r_a so that the *true* clearance
keeps the paper's limits on real vehicles (``docs/fleet.md``, "The safety budget").

The paper's guarantee (Theorems 1, 2) is for continuous time, exact positions and a vehicle
whose velocity *is* the command. A PX4 fleet breaks all three; the budget covers each part with
a term of its own:

* **lag** — positions are L old when used and the setpoint takes another link delay to arrive
  (L = position age + setpoint delay, measured as the round trip), each command is held for
  a control period T, and PX4 follows a velocity step only after a dead time τ_d and with a
  first-order lag t63. Only the saturated part of (ModifiedVectorField), sat(u2 + u3' + u4',
  v'_max), reacts to neighbours, legs and triangle sides, so one vehicle's unmodelled excursion
  towards anything is at most ``v'_max · (T + L + τ_d + t63)``;
* **estimate** — the controller sees PX4's *estimated* position, which is off the truth by up
  to ``k · σ``: σ the horizontal accuracy the vehicles report (ESTIMATOR_STATUS
  ``pos_horiz_accuracy``, 1 σ), k the confidence factor (default 2: on real PX4 SITL the
  reported σ was 0.29 m and the largest error 0.53 m = 1.83 σ);
* **disturbance** — PX4 tracks its *estimated* velocity, so the vehicle moves where nobody
  commanded; the pilot compensates what it can observe (:mod:`~vtube_fleet.fleet.
  compensation`); the rest, at most D m/s, acts like the avoidance terms over the same delay:
  ``D · (T + L + τ_d + t63)``.

So the controller is flown with

    δ = (v'_max + D)·(T + L + τ_d + t63) + k σ,    r_s' = r_s + δ,    r_a' = r_a + δ

With **reference tracking** (``tracking = "reference"``) the controller works on reference
positions r, each vehicle's commands integrated, which are the paper's single integrator (up
to the period T and the neighbours' age L); a position loop holds each vehicle's estimate p̂
to its own r, and |p̂ − r| is measured every tick against its budgeted bound e
(``tracking_error_m``: the tube holds beyond it). PX4's response and the estimate disturbance
then no longer enter as assumed lags; they are inside the measured e:

    δ = v'_max·(T + L) + e + k σ

(2 r_s' between two vehicles leaves 2 r_s after both err; a leg clearance r_s' leaves r_s; an
obstacle clearance r_o + r_s' leaves r_o + r_s). The inflated scenario must itself satisfy the
paper's conditions; the runtime checks that before arming and refuses with the numbers.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from vtube_fleet.config.mission import DEFAULT_ACCURACY_FACTOR
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.response import model_follow, model_lag_s

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.config.mission import Mission, MissionConfig

__all__ = [
    "BudgetWatch",
    "LOOP_CHECK_S",
    "LOOP_MIN_S",
    "LOOP_ON_TIME_MIN",
    "LOOP_RATE_MIN",
    "LinkMeasurement",
    "PX4_SITL_ACCURACY_M",
    "PX4_SITL_LATENCY_S",
    "RESPONSE_MARGIN_S",
    "RESPONSE_PERSIST_TICKS",
    "RESPONSE_WATCH_HOLDS",
    "ResponseModel",
    "ResponseWatch",
    "SafetyBudget",
    "TRACKING_PERSIST_TICKS",
    "WorstOver",
    "achieved_rate_hz",
    "budget_latency_s",
    "budget_problems",
    "latency_over",
    "loop_problem",
    "mission_budget",
    "on_time_share",
]

#: The σ PX4 SITL (SIH) reports: ESTIMATOR_STATUS ``pos_horiz_accuracy`` 0.29-0.30 m before
#: arming in 13 flights of ``run`` on real PX4 SITL (the built-in mock's default ``px4-sih``
#: profile reports 0.29 m); the worst of them. ``vtube-fleet check`` assumes it for a mission
#: before any vehicle has reported its own; a run measures σ instead. (The MQTT coordinator's
#: run budget assumes a ceiling above it, ``distributed.coordinator.ASSUMED_ACCURACY_M``, that
#: every agent's vehicle must stay under.)
PX4_SITL_ACCURACY_M = 0.30
#: The link latency L (position age p95 + setpoint delay, before ``latency_headroom_s``) that
#: ``run`` measured before arming on real PX4 SITL (SIH, one 2-core machine, 3-6 instances):
#: 0.098-0.124 s over the same 13 flights; the worst of them. ``vtube-fleet check`` assumes it
#: (docs/config.md), so that it predicts what ``run`` accepts there.
PX4_SITL_LATENCY_S = 0.124


@dataclass(frozen=True)
class SafetyBudget:
    """δ and its terms (module docstring), or a fixed override (``overridden``, from
    ``override_source``).

    ``period_s`` T, ``latency_s`` L (position age + setpoint delay), ``dead_time_s`` τ_d and
    ``t63_s`` of PX4's velocity tracking, ``v_max_prime`` of the controller, ``accuracy_m`` σ
    (the worst reported horizontal accuracy), ``accuracy_factor`` k, ``disturbance_m_s`` D;
    ``delta_m`` the inflation used; ``tracking_error_m`` e with reference tracking (None:
    velocity tracking, the module docstring's first formula).
    """

    period_s: float
    latency_s: float
    dead_time_s: float
    t63_s: float
    v_max_prime: float
    delta_m: float
    accuracy_m: float = 0.0
    accuracy_factor: float = DEFAULT_ACCURACY_FACTOR
    disturbance_m_s: float = 0.0
    overridden: bool = False
    override_source: str = "safety_margin_m from the mission file"
    tracking_error_m: float | None = None

    @property
    def reference(self) -> bool:
        """Reference tracking: e is budgeted instead of PX4's response (module docstring)."""
        return self.tracking_error_m is not None

    @property
    def delay_s(self) -> float:
        """The effective delay T + L + τ_d + t63 (reference tracking: T + L)."""
        if self.reference:
            return self.period_s + self.latency_s
        return self.period_s + self.latency_s + self.dead_time_s + self.t63_s

    @property
    def lag_m(self) -> float:
        return self.v_max_prime * self.delay_s

    @property
    def estimate_m(self) -> float:
        return self.accuracy_factor * self.accuracy_m

    @property
    def disturbance_m(self) -> float:
        return self.disturbance_m_s * self.delay_s

    @property
    def tracking_m(self) -> float:
        """e (0 with velocity tracking)."""
        return self.tracking_error_m or 0.0

    @classmethod
    def compute(
        cls,
        params: ControllerParams,
        *,
        period_s: float,
        latency_s: float,
        dead_time_s: float,
        t63_s: float,
        accuracy_m: float = 0.0,
        accuracy_factor: float = DEFAULT_ACCURACY_FACTOR,
        disturbance_m_s: float = 0.0,
        override_m: float | None = None,
        override_source: str = "safety_margin_m from the mission file",
        tracking_error_m: float | None = None,
    ) -> SafetyBudget:
        """δ of the module docstring: velocity tracking, or reference tracking when
        ``tracking_error_m`` (e) is given (then τ_d, t63 and D are not budgeted: they act
        inside the measured e)."""
        for name, value in (("period_s", period_s), ("latency_s", latency_s),
                            ("dead_time_s", dead_time_s), ("t63_s", t63_s),
                            ("accuracy_m", accuracy_m), ("accuracy_factor", accuracy_factor),
                            ("disturbance_m_s", disturbance_m_s),
                            ("tracking_error_m", tracking_error_m or 0.0)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"safety budget: {name} must be finite and >= 0, got {value}")
        if tracking_error_m is not None:
            dead_time_s = t63_s = disturbance_m_s = 0.0
        b = cls(period_s, latency_s, dead_time_s, t63_s, float(params.v_max_prime), 0.0,
                accuracy_m, accuracy_factor, disturbance_m_s, override_m is not None,
                override_source, tracking_error_m)
        delta = (b.lag_m + b.disturbance_m + b.tracking_m + b.estimate_m
                 if override_m is None else float(override_m))
        return dataclasses.replace(b, delta_m=delta)

    def inflate(self, params: ControllerParams) -> ControllerParams:
        """The controller parameters actually flown: r_s' = r_s + δ, r_a' = r_a + δ."""
        return dataclasses.replace(params, r_s=params.r_s + self.delta_m,
                                   r_a=params.r_a + self.delta_m)

    def describe(self, params: ControllerParams | None = None) -> str:
        """One line with the formula and the numbers."""
        if self.overridden:
            text = f"δ = {self.delta_m:.3f} m ({self.override_source})"
        elif self.reference:
            text = (
                f"δ = v'_max·(T + L) + e + k σ = {self.v_max_prime:g}·({self.period_s:.3f} + "
                f"{self.latency_s:.3f}) + {self.tracking_m:.3f} + {self.accuracy_factor:g}·"
                f"{self.accuracy_m:.3f} = {self.delta_m:.3f} m (reference tracking)"
            )
        else:
            text = (
                f"δ = (v'_max + D)·(T + L + τ_d + t63) + k σ = ({self.v_max_prime:g} + "
                f"{self.disturbance_m_s:g})·({self.period_s:.3f} + {self.latency_s:.3f} + "
                f"{self.dead_time_s:.3f} + {self.t63_s:.3f}) + {self.accuracy_factor:g}·"
                f"{self.accuracy_m:.3f} = {self.delta_m:.3f} m"
            )
        if params is not None:
            text += (f" → r_s' = {params.r_s + self.delta_m:.3f} m, "
                     f"r_a' = {params.r_a + self.delta_m:.3f} m")
        return text

    def as_dict(self) -> dict[str, Any]:
        return {
            "delta_m": self.delta_m,
            "lag_m": self.lag_m,
            "estimate_m": self.estimate_m,
            "disturbance_m": self.disturbance_m,
            "period_s": self.period_s,
            "latency_s": self.latency_s,
            "dead_time_s": self.dead_time_s,
            "t63_s": self.t63_s,
            "v_max_prime": self.v_max_prime,
            "accuracy_m": self.accuracy_m,
            "accuracy_factor": self.accuracy_factor,
            "disturbance_m_s": self.disturbance_m_s,
            "tracking": "reference" if self.reference else "velocity",
            "tracking_error_m": self.tracking_error_m,
            "overridden": self.overridden,
        }


#: Each step of the response check is held this long past the budget's response time T + L +
#: τ_d + t63 (the lag is read over the whole hold); the response watch's window is as long.
RESPONSE_MARGIN_S = 0.7
#: The response watch: ticks in a row some vehicle may be off the model's path by more than
#: the tolerance before the tube holds (one tick over may be a single jumping sample).
RESPONSE_PERSIST_TICKS = 2
#: … and its window, in holds H: 4 H (8.6 s on the mock mission). Real PX4 SITL's own answer
#: leaves the τ_d, t63 model's path by up to 0.97 m over one H (its slow velocity integrator on
#: a sideways command: the captures, replayed through the watch; docs/fleet.md, "The response
#: watch"), about as much as a vehicle following 55 % of its commands; over 4 H a steady
#: shortfall grows four times while PX4's own lag does not (1.96 m), so the two part.
RESPONSE_WATCH_HOLDS = 4


@dataclass(frozen=True)
class ResponseModel:
    """The budget's model of PX4's answer to a velocity change: nothing for ``delay_s`` = T + L
    + τ_d after the tick that sends it, then a first order with ``t63_s``; ``sigma_m`` the
    reported accuracy σ, ``disturbance_m_s`` the budget's D. τ_d and t63 are the mission's
    (``tracking_dead_time_s``, ``tracking_t63_s``), also with reference tracking, whose budget
    does not count them."""

    period_s: float
    latency_s: float
    dead_time_s: float
    t63_s: float
    sigma_m: float
    disturbance_m_s: float = 0.0
    accuracy_factor: float = DEFAULT_ACCURACY_FACTOR

    @classmethod
    def of(cls, budget: SafetyBudget, cfg: MissionConfig) -> ResponseModel:
        return cls(budget.period_s, budget.latency_s, cfg.tracking_dead_time_s,
                   cfg.tracking_t63_s,
                   budget.accuracy_m if math.isfinite(budget.accuracy_m) else 0.0,
                   cfg.disturbance_residual_m_s, budget.accuracy_factor)

    @property
    def delay_s(self) -> float:
        return self.period_s + self.latency_s + self.dead_time_s

    @property
    def hold_s(self) -> float:
        """H = T + L + τ_d + t63 + :data:`RESPONSE_MARGIN_S`: how long each step of the
        response check is held (the response watch's window is a multiple of it)."""
        return self.delay_s + self.t63_s + RESPONSE_MARGIN_S

    def allowed_lag_s(self) -> tuple[float, float]:
        """The model's lag (:func:`~vtube_fleet.core.response.model_lag_s`) on the start step
        over its hold H, and on the stop step that follows it: 2 lag(H) − lag(2 H) (the
        model's start response goes on under the stop's)."""
        h = self.hold_s
        one = model_lag_s(h, self.delay_s, self.t63_s)
        return one, 2.0 * one - model_lag_s(2.0 * h, self.delay_s, self.t63_s)

    def tolerance_s(self, step_m_s: float) -> float:
        """What the check cannot tell from the estimate's own drift: σ of position over the
        step (the estimate error moves by about σ / 3 over a hold on the mock's px4-sih
        profile)."""
        return self.sigma_m / step_m_s

    @property
    def watch_window_s(self) -> float:
        """The response watch's window W = :data:`RESPONSE_WATCH_HOLDS` H."""
        return RESPONSE_WATCH_HOLDS * self.hold_s

    def watch_tolerance_m(self) -> float:
        """How far, over its window W, a vehicle's estimated path may leave the model's answer
        to its commands in flight: D W (the compensation's residual the budget allows) + k σ
        (the estimate error's change over W: its autocorrelation crosses zero after 3-7 s)."""
        return self.disturbance_m_s * self.watch_window_s + self.accuracy_factor * self.sigma_m

    def reach_m(self, step_m_s: float) -> float:
        """How far ahead the check may take a vehicle: the step's speed over both holds (an
        upper bound: PX4 does not overshoot the command by more than it lags it)."""
        return 2.0 * step_m_s * self.hold_s

    def describe(self) -> str:
        return (f"T + L + τ_d = {self.period_s:.2f} + {self.latency_s:.2f} + "
                f"{self.dead_time_s:g} s, then t63 = {self.t63_s:g} s: tracking_dead_time_s, "
                f"tracking_t63_s")


class WorstOver:
    """The worst of a per-vehicle figure, tick by tick (the response watch, the reference
    tracking watch): its largest value with the time and vehicle (``max_m``, ``max_at``), and
    ``over``: the ticks in a row it has been over the bound (0: not over now)."""

    def __init__(self) -> None:
        self.max_m = math.nan
        self.max_at: tuple[float, int] | None = None  # (time, vehicle)
        self.over = 0

    def judge(self, t_s: float, values: np.ndarray, vehicle_ids: np.ndarray,
              bound: float) -> tuple[int, float]:
        """One tick's values (k,) of the vehicles ``vehicle_ids`` (k,) against ``bound``:
        (index of the worst, its value)."""
        k = int(np.argmax(values))
        worst = float(values[k])
        if not worst <= self.max_m:
            self.max_m, self.max_at = worst, (t_s, int(vehicle_ids[k]))
        self.over = 0 if worst <= bound else self.over + 1
        return k, worst


class ResponseWatch:
    """The response watch (velocity tracking, in flight; docs/fleet.md, "The response watch"):
    every tick, the model's answer (:class:`ResponseModel`) to the velocities each vehicle was
    sent is flown as a path of its own (:func:`~vtube_fleet.core.response.model_follow`, the
    commands ``delay_s`` late), and each watched vehicle's estimated displacement over the
    last W (:attr:`ResponseModel.watch_window_s`) is compared with the model path's over the
    same ticks. PX4 answering more slowly than the budget's τ_d and t63 (a weaker motor, a
    heavier payload) leaves the model behind; the lag term then no longer covers the vehicle.
    :meth:`update` returns the hold reason once some vehicle has been further off than
    :meth:`ResponseModel.watch_tolerance_m` for :data:`RESPONSE_PERSIST_TICKS` ticks in a row.

    A vehicle is judged only on a window it was watched through (in the tube, flying the
    controller's commands) that starts at least ``settle_s`` = T + L + τ_d + 3 t63 into the
    watched spell, with a fresh sample at both ends (a silent vehicle is the lost-vehicle
    rule's). The model runs for every row from the first tick the watch is fed (the first
    vehicle in the tube). Vectorized over the ``n`` rows of a table; pure (no I/O)."""

    def __init__(self, model: ResponseModel, n: int) -> None:
        self.model = model
        self.window_s = model.watch_window_s
        self.settle_s = model.delay_s + 3.0 * model.t63_s  #: a spell's start, not judged
        self.tolerance_m = model.watch_tolerance_m()
        self._cmds: deque[tuple[float, np.ndarray]] = deque()  # (time, velocities sent)
        self._y = np.zeros((n, 2))  # the model's velocity
        self._x = np.zeros((n, 2))  # … and its path
        self._t = math.nan
        self._hist: deque[tuple[float, np.ndarray, np.ndarray]] = deque()  # (t, path, p̂)
        self._since = np.full(n, np.nan)  # when each row's watched spell began
        self.offset_m = np.full(n, np.nan)  #: each row's offset at the last tick (NaN: unjudged)
        self.worst = WorstOver()  #: the largest offset judged, and the ticks in a row over

    def update(self, t_s: float, sent_m_s: np.ndarray, xy: np.ndarray, watched: np.ndarray,
               vehicle_ids: np.ndarray, fresh: np.ndarray | None = None) -> str | None:
        """One tick at time ``t_s`` (s): the velocities sent (n, 2; NaN: none, flown as
        zero: PX4 holds), the estimated positions (n, 2), which rows are ``watched`` and which
        of them have a ``fresh`` sample (None: all; a stale one is not compared, its spell
        goes on). A gap of more than 2 T + 0.1 s since the last call (the watch was not fed:
        no vehicle in the tube, an agent's untrusted tick) restarts every spell."""
        m = self.model
        if math.isfinite(self._t) and t_s > self._t:
            if t_s - self._t > 2.0 * m.period_s + 0.1:
                self._since[:] = np.nan
            self._advance(t_s)
        self._t = t_s
        self._cmds.append((t_s, np.nan_to_num(np.asarray(sent_m_s, float))))
        ok = watched & np.isfinite(xy).all(axis=1)
        self._since[~ok] = np.nan
        self._since[ok & np.isnan(self._since)] = t_s
        now_ok = ok if fresh is None else ok & fresh
        self._hist.append((t_s, self._x.copy(),
                           np.where(now_ok[:, None], np.asarray(xy, float), np.nan)))
        cut = t_s - self.window_s
        while len(self._hist) > 1 and self._hist[1][0] <= cut:
            self._hist.popleft()
        t0, x0, p0 = self._hist[0]
        # a whole window inside the spell, after the model's start has settled (its state at
        # a spell's start is the model's, not the vehicle's: e^-3 of it is left after 3 t63)
        judged = (now_ok & np.isfinite(p0).all(axis=1) & (t0 <= cut)
                  & (self._since <= t0 - self.settle_s))
        self.offset_m[:] = np.nan
        if not judged.any():
            self.worst.over = 0
            return None
        rows = np.flatnonzero(judged)
        off = (xy[rows] - p0[rows]) - (self._x[rows] - x0[rows])
        dev = np.hypot(off[:, 0], off[:, 1])
        self.offset_m[rows] = dev
        k, worst = self.worst.judge(t_s, dev, vehicle_ids[rows], self.tolerance_m)
        if self.worst.over < RESPONSE_PERSIST_TICKS:
            return None
        return (f"safety budget exceeded in flight: vehicle {int(vehicle_ids[rows[k]])} flew "
                f"{worst:.2f} m off the path PX4's budgeted response gives its commands over the "
                f"last {self.window_s:.1f} s > {self.tolerance_m:.2f} m (D·W + k σ = "
                f"{m.disturbance_m_s:g}·{self.window_s:.2f} + {m.accuracy_factor:g}·"
                f"{m.sigma_m:.2f}; "
                f"{RESPONSE_PERSIST_TICKS} ticks in a row; PX4 follows more slowly than "
                f"τ_d = {m.dead_time_s:g} s, t63 = {m.t63_s:g} s, which the partition was "
                f"built for)")

    def _advance(self, t_to: float) -> None:
        """The model from the last tick to ``t_to``: each command sent at t_k acts from
        t_k + ``delay_s`` exactly (a tick's interval is cut where one starts to act)."""
        cmds, d, t = self._cmds, self.model.delay_s, self._t
        while t < t_to:
            while len(cmds) > 1 and cmds[1][0] + d <= t:
                cmds.popleft()
            if cmds and cmds[0][0] + d <= t:
                u, nxt = cmds[0][1], (cmds[1][0] + d if len(cmds) > 1 else math.inf)
            else:  # nothing sent yet that acts: the hover
                u, nxt = np.zeros_like(self._y), (cmds[0][0] + d if cmds else math.inf)
            end = min(t_to, nxt)
            self._y, dx = model_follow(self._y, u, end - t, self.model.t63_s)
            self._x = self._x + dx
            t = end

    @property
    def max_m(self) -> float:
        """The largest offset judged (NaN: none)."""
        return self.worst.max_m

    @property
    def max_at(self) -> tuple[float, int] | None:
        """(time, vehicle) of :attr:`max_m`."""
        return self.worst.max_at

    def as_dict(self) -> dict[str, Any]:
        return {"window_s": round(self.window_s, 3), "tolerance_m": round(self.tolerance_m, 3),
                "max_m": None if not math.isfinite(self.max_m) else round(self.max_m, 3),
                "max_at": (None if self.max_at is None else
                           {"t_s": round(self.max_at[0], 2), "vehicle": self.max_at[1]})}


@dataclass(frozen=True)
class LinkMeasurement:
    """What the safety budget needs from the links, measured before arming.

    ``position_age_s``: p95 over the fleet of the position samples' age when used (downlink
    latency + time since arrival); ``setpoint_delay_s``: the worst one-way uplink delay (half
    the largest measured round trip); ``accuracy_m``: the worst reported horizontal position
    accuracy (1 σ; NaN if no vehicle reports one), ``accuracies_m`` per pilot.
    """

    position_age_s: float
    setpoint_delay_s: float
    accuracy_m: float
    accuracies_m: tuple[float, ...] = ()

    @property
    def latency_s(self) -> float:
        """L: position age + setpoint delay (the measured round trip of a command)."""
        return self.position_age_s + self.setpoint_delay_s


def budget_latency_s(mission: Mission, measured: LinkMeasurement | None) -> float:
    """The L a mission's budget is built on: its ``latency_s``, else the measured position age
    + setpoint delay + ``latency_headroom_s`` (0 before a measurement)."""
    cfg = mission.config
    if cfg.latency_s is not None:
        return cfg.latency_s
    if measured is None:
        return 0.0
    return measured.latency_s + cfg.latency_headroom_s


def latency_over(mission: Mission, measured: LinkMeasurement) -> bool:
    """The MEASURED L is above ``max_latency_s`` (a fixed ``latency_s`` is not measured: never
    worth measuring again)."""
    cfg = mission.config
    return cfg.latency_s is None and budget_latency_s(mission, measured) > cfg.max_latency_s


def mission_budget(mission: Mission, measured: LinkMeasurement | None = None, *,
                   extra_latency_s: float = 0.0) -> SafetyBudget:
    """THE budget of a mission (supervisor and MQTT agents alike): L = the mission's
    ``latency_s``, else the measured position age + setpoint delay + ``latency_headroom_s``;
    σ = the mission's ``position_accuracy_m``, else the worst measured accuracy (0 before a
    measurement); ``extra_latency_s`` adds what the caller's data path adds (the MQTT agents:
    the neighbour states' allowed age)."""
    cfg = mission.config
    latency = budget_latency_s(mission, measured)
    sigma = cfg.position_accuracy_m
    if sigma is None:
        sigma = (measured.accuracy_m if measured is not None
                 and math.isfinite(measured.accuracy_m) else 0.0)
    return SafetyBudget.compute(
        mission.scenario.controller, period_s=cfg.period_s,
        latency_s=latency + extra_latency_s, dead_time_s=cfg.tracking_dead_time_s,
        t63_s=cfg.tracking_t63_s, accuracy_m=sigma, accuracy_factor=cfg.accuracy_factor,
        disturbance_m_s=cfg.disturbance_residual_m_s, override_m=cfg.safety_margin_m,
        tracking_error_m=cfg.tracking_error_m if cfg.tracking == "reference" else None)


def budget_problems(mission: Mission, measured: LinkMeasurement) -> list[str]:
    """Why the measured links cannot be flown at all, whatever the geometry: L above
    ``max_latency_s``; no accuracy reported and none configured."""
    cfg = mission.config
    out = []
    latency = budget_latency_s(mission, measured)
    if latency > cfg.max_latency_s:
        how = ("latency_s from the mission file" if cfg.latency_s is not None else
               f"position age p95 {measured.position_age_s * 1000:.0f} ms + setpoint delay "
               f"{measured.setpoint_delay_s * 1000:.0f} ms + headroom "
               f"{cfg.latency_headroom_s * 1000:.0f} ms")
        out.append(f"link latency L = {latency * 1000:.0f} ms ({how}) > max_latency_s = "
                   f"{cfg.max_latency_s * 1000:.0f} ms: the safety budget does not cover this "
                   f"link")
    if cfg.position_accuracy_m is None and not math.isfinite(measured.accuracy_m):
        out.append("no vehicle reports its position accuracy (ESTIMATOR_STATUS or GPS_RAW_INT "
                   "h_acc); set [mission].position_accuracy_m")
    return out


#: Before arming, the control ticks of the last :data:`LOOP_CHECK_S` seconds must have kept at
#: least this share of the rate (:func:`loop_problem`): a healthy loop keeps ~100 %, one that
#: takes 1.6 periods a tick keeps 62 % (a tick after falling behind is not made up:
#: Supervisor._clock).
LOOP_RATE_MIN = 0.8
#: … and at least this share of them must have started on time. A healthy loop keeps ~99 %; a
#: loop whose telemetry receive fills the gaps between ticks a few percent (1,000 vehicles on
#: one 2 GHz core: 0 %).
LOOP_ON_TIME_MIN = 0.5
#: The stretch of wall time :func:`loop_problem` judges, s (shorter when the clock has run
#: less, but at least :data:`LOOP_MIN_S`).
LOOP_CHECK_S = 5.0
#: The least clock time a judgement covers, s.
LOOP_MIN_S = 2.0


def on_time_share(lateness_s: Sequence[float] | np.ndarray, period_s: float) -> float | None:
    """The share of ticks that started on time: within half a period of their schedule
    (``lateness_s``: actual minus scheduled start of each tick); None without ticks."""
    late = np.asarray(lateness_s, dtype=float)
    return float(np.mean(late <= period_s / 2)) if late.size else None


def achieved_rate_hz(starts_s: Sequence[float] | np.ndarray) -> float:
    """The tick rate from the ticks' start times (s): ticks per second between the first and
    the last; NaN under two ticks. (Not from the lateness: a loop that falls more than a
    period behind drops the ticks it missed and restarts its schedule.)"""
    if len(starts_s) < 2:
        return math.nan
    span = float(starts_s[-1]) - float(starts_s[0])
    return (len(starts_s) - 1) / span if span > 0 else math.nan


def loop_problem(starts_s: Sequence[float], lateness_s: Sequence[float],
                 durations_s: Sequence[float], period_s: float, vehicles: int, *,
                 now_s: float, window_s: float = LOOP_CHECK_S) -> str | None:
    """Why the control loop must not arm its fleet, or None: the ticks that started in the
    ``window_s`` up to ``now_s`` (start times, lateness and durations, s, one per tick; the
    same clock as ``now_s``) were fewer than :data:`LOOP_RATE_MIN` of the rate, or fewer than
    :data:`LOOP_ON_TIME_MIN` of them started on time. Such a loop sends its setpoints late, in
    bursts or not at all, which the budget's T + L does not cover. Counted in wall time, so a
    loop too slow to tick at all is judged too."""
    k = bisect.bisect_left(starts_s, now_s - window_s)
    count = len(starts_s) - k
    rate = count / window_s
    share = on_time_share(lateness_s[k:], period_s) or 0.0  # None: no tick in the window
    if share >= LOOP_ON_TIME_MIN and rate >= LOOP_RATE_MIN / period_s:
        return None
    d = np.asarray(durations_s[k:], dtype=float) * 1000.0
    ticks = (f"tick p50 {float(np.percentile(d, 50)):.1f} ms, p99 "
             f"{float(np.percentile(d, 99)):.1f} ms" if d.size else "no tick finished")
    return (f"the control loop cannot keep up with {vehicles} vehicles on this computer: over "
            f"the last {window_s:.1f} s it ticked at {rate:.2f} Hz of {1.0 / period_s:g} Hz "
            f"(at least {LOOP_RATE_MIN / period_s:g} Hz needed) with {share:.1%} of its "
            f"ticks started on time (at least {LOOP_ON_TIME_MIN:.0%}; {ticks}, plus the "
            f"telemetry received in between): fly fewer vehicles per supervisor or a lower "
            f"rate_hz")


#: Reference tracking: the ticks in a row a vehicle may be further than e from its reference
#: before the tube holds (one tick over may be a single late or jumping sample).
TRACKING_PERSIST_TICKS = 2
#: … and the resolution (m) and range of the tracking errors kept for the summary.
TRACKING_BIN_M = 0.01
TRACKING_BINS = 500


class BudgetWatch:
    """The in-flight check of a budget's inputs (supervisor and MQTT agent alike; pure).

    Feed it the position ages as they are used (:meth:`add_ages`, with the vehicles they
    belong to); once a second :meth:`check` compares L (p95 of the last ``window_s`` of ages
    + the worst uplink delay)
    and σ (the worst reported accuracy) with what ``budget`` was built for: L more than one
    control period over, σ more than 25 % (+2 cm) over. It returns ``(warning, hold)``: a
    warning text the first second over, and a hold reason after ``persist_s`` seconds in a row.
    Overridden budgets and the mission's own ``latency_s`` / ``position_accuracy_m`` are not
    second-guessed. With velocity tracking, :meth:`check_response` feeds the response watch
    (:class:`ResponseWatch`; its model from ``response_budget`` when given).

    A vehicle that falls silent is a fault, not a slow link: the lost-vehicle path handles
    it. So an age counts only once the sample it was measured on has been superseded (the
    vehicle spoke again: then its silence was the link's), judged from the arrival times of
    the newest samples given to :meth:`check`; :meth:`forget` drops a lost vehicle's ages.
    One dying vehicle (plus a stall of our own loop) does not make the whole fleet hold; a
    slow or sparse link still does, one sample interval later.

    The gaps between control ticks are fed too (:meth:`add_tick_gap`): while our own loop
    stalls, the vehicles fly their last setpoint, so a gap longer than the budgeted T + L
    delays every command beyond what δ covers. That counts as over whatever the mission fixed
    (``latency_s`` describes the link, an override the margin; neither covers our own loop).
    """

    def __init__(self, mission: Mission, budget: SafetyBudget, *, window_s: float = 3.0,
                 persist_s: int = 2, response_budget: SafetyBudget | None = None) -> None:
        self.cfg = mission.config
        self.budget = budget
        self.window_s = window_s
        self.persist_s = persist_s
        # (time, finite ages, [their vehicle ids, their samples' arrival times] or None) per
        # add_ages call: one array per tick, not one tuple per age (1,000 vehicles at 20 Hz
        # keep 60,000 ages in 3 s)
        self._ages: deque[tuple[float, np.ndarray, np.ndarray | None]] = deque()
        self._checked_s = -math.inf
        self._over = 0
        self._worst_gap_s = 0.0  # the longest tick gap since the last check
        self.longest_tick_gap_s = -math.inf  # … and ever (the summaries' loop health)
        # reference tracking: ticks in a row with a vehicle beyond e, and every error seen
        # (a histogram of TRACKING_BIN_M bins: a thousand vehicles for an hour stay small)
        self._tracking = WorstOver()
        self.tracking_counts = np.zeros(TRACKING_BINS, np.int64)
        # velocity tracking: PX4's answer to the commands against the budget's model (created
        # at the first tick, for the table's rows; None with reference tracking, which
        # watches e, and for an override, which is not second-guessed)
        # (``response_budget``: the vehicle's own link, when ``budget``'s L has more in it:
        # an MQTT agent's neighbour age)
        # (without the estimate compensation p̂ drifts by the estimate disturbance, up to D
        # over the whole window: the watch is off)
        self._response_model = (None if budget.reference or budget.overridden
                                or not self.cfg.response_watch
                                or not self.cfg.compensate_estimate
                                else ResponseModel.of(response_budget or budget, self.cfg))
        self.response: ResponseWatch | None = None

    def add_ages(self, t_s: float, ages: Sequence[float],
                 vehicle_ids: Sequence[int] | None = None,
                 sample_s: Sequence[float] | None = None) -> None:
        """The position ages used at ``t_s`` (s), with the vehicle of each and the arrival
        time of the sample it was measured on (s, the clock of :meth:`check`'s
        ``newest_sample_s``). Without them (an agent's own ages) every age counts at once."""
        a = np.asarray(ages, dtype=float)
        ok = np.isfinite(a)
        who = None
        if vehicle_ids is not None and sample_s is not None:
            who = np.stack([np.asarray(vehicle_ids, dtype=float)[ok],
                            np.asarray(sample_s, dtype=float)[ok]])
        a = a[ok]
        if a.size:
            self._ages.append((t_s, a, who))

    def forget(self, vehicle_ids: Sequence[int]) -> None:
        """Drop the ages of these vehicles (declared lost: their silence was a fault, handled
        as one, not the link's latency)."""
        gone = np.asarray(vehicle_ids, dtype=int)
        if not gone.size:
            return
        kept: deque[tuple[float, np.ndarray, np.ndarray | None]] = deque()
        for t_s, a, who in self._ages:
            if who is not None:
                keep = ~np.isin(who[0], gone)
                a, who = a[keep], who[:, keep]
            if a.size:
                kept.append((t_s, a, who))
        self._ages = kept

    def add_tick_gap(self, gap_s: float) -> None:
        """The time between two control ticks (the period when on time)."""
        if math.isfinite(gap_s):
            self._worst_gap_s = max(self._worst_gap_s, gap_s)
            self.longest_tick_gap_s = max(self.longest_tick_gap_s, gap_s)

    @property
    def max_tick_gap_s(self) -> float:
        """The longest tick gap the budget covers: T + L (the delay of a fresh command)."""
        return self.budget.period_s + self.budget.latency_s

    def due(self, t_s: float) -> bool:
        """A :meth:`check` at ``t_s`` would judge (once a second); before that it returns
        (None, None) whatever it is given."""
        return t_s - self._checked_s >= 1.0

    def check(self, t_s: float, uplink_s: float, accuracies_m: Sequence[float],
              newest_sample_s: np.ndarray | None = None) -> tuple[str | None, str | None]:
        """Judge once a second (see the class). ``newest_sample_s``: per vehicle id, the
        arrival time of its newest sample (NaN: none); an age given with a vehicle counts once
        its sample is older than that."""
        if not self.due(t_s):
            return None, None
        self._checked_s = t_s
        while self._ages and self._ages[0][0] < t_s - self.window_s:
            self._ages.popleft()
        b, cfg = self.budget, self.cfg
        over = []
        gap, self._worst_gap_s = self._worst_gap_s, 0.0
        if gap > self.max_tick_gap_s:
            over.append(f"control loop stalled {gap * 1000:.0f} ms > budgeted T + L = "
                        f"{self.max_tick_gap_s * 1000:.0f} ms (the vehicles flew their last "
                        f"setpoint)")
        if b.overridden:
            return self._judge(over)
        latency = 0.0
        ages = self._settled_ages(newest_sample_s)
        if ages.size:
            k = int(0.95 * (ages.size - 1))  # the element sorted(ages)[k], without the sort
            latency = float(np.partition(ages, k)[k]) + uplink_s
        acc = [a for a in accuracies_m if math.isfinite(a)]
        sigma = max(acc, default=0.0)
        if cfg.latency_s is None and latency > b.latency_s + cfg.period_s:
            over.append(f"link latency L = {latency * 1000:.0f} ms (last {self.window_s:g} s) "
                        f"> budgeted {b.latency_s * 1000:.0f} ms + one period")
        if cfg.position_accuracy_m is None and sigma > 1.25 * b.accuracy_m + 0.02:
            over.append(f"reported position accuracy σ = {sigma:.2f} m > budgeted "
                        f"{b.accuracy_m:.2f} m (+25 %)")
        return self._judge(over)

    def check_tracking(self, errors_m: np.ndarray, vehicle_ids: np.ndarray,
                       t_s: float = math.nan) -> str | None:
        """Reference tracking, every tick (mission time ``t_s``): the in-tube vehicles'
        |p̂ − r| (m; NaN: none) with their ids. Returns a hold reason once some vehicle has been
        further than the budgeted e in :data:`TRACKING_PERSIST_TICKS` ticks in a row (its
        true position may then be outside what δ covers; the reason names the worst of the
        last tick), else None; every finite error is kept for the summary (to 5 m: the
        percentiles of larger errors say 5 m, the maximum is exact)."""
        e = self.budget.tracking_error_m
        ok = np.isfinite(errors_m)
        if e is None or not ok.any():
            self._tracking.over = 0
            return None
        err, ids = errors_m[ok], vehicle_ids[ok]
        self.tracking_counts += np.bincount(
            np.minimum((err / TRACKING_BIN_M).astype(np.int64), TRACKING_BINS - 1),
            minlength=TRACKING_BINS)
        k, worst = self._tracking.judge(t_s, err, ids, e)
        if self._tracking.over < TRACKING_PERSIST_TICKS:
            return None
        return (f"safety budget exceeded in flight: vehicle {int(ids[k])} is {worst:.2f} m "
                f"from its reference > the budgeted tracking error e = {e:.2f} m "
                f"({TRACKING_PERSIST_TICKS} ticks in a row; PX4 follows more slowly than the "
                f"partition was built for)")

    def check_response(self, t_s: float, sent_m_s: np.ndarray, xy: np.ndarray,
                       watched: np.ndarray, vehicle_ids: np.ndarray,
                       fresh: np.ndarray | None = None) -> str | None:
        """Velocity tracking, every tick: :meth:`ResponseWatch.update` (the velocities sent,
        the estimated positions, the rows watched, their ids, the rows with a fresh sample);
        None when not watched."""
        if self._response_model is None:
            return None
        if self.response is None:
            self.response = ResponseWatch(self._response_model, len(vehicle_ids))
        return self.response.update(t_s, sent_m_s, xy, watched, vehicle_ids, fresh)

    @property
    def tracking_max_m(self) -> float:
        """Reference tracking: the largest |p̂ − r| seen (NaN: none)."""
        return self._tracking.max_m

    @property
    def tracking_max_at(self) -> tuple[float, int] | None:
        """(mission time, vehicle) of :attr:`tracking_max_m`."""
        return self._tracking.max_at

    def tracking_percentile_m(self, q: float) -> float:
        """The ``q`` percentile of the tracking errors seen (to :data:`TRACKING_BIN_M`, the
        upper edge of its bin); NaN: none."""
        total = int(self.tracking_counts.sum())
        if not total:
            return math.nan
        k = int(np.searchsorted(np.cumsum(self.tracking_counts), q / 100.0 * total))
        return min((k + 1) * TRACKING_BIN_M, self.tracking_max_m)

    def _settled_ages(self, newest_sample_s: np.ndarray | None) -> np.ndarray:
        """The window's ages whose samples have been superseded (or carry no vehicle)."""
        parts = []
        for _, a, who in self._ages:
            if who is not None:
                ids = who[0].astype(int)
                newest = np.full(ids.size, np.nan)
                if newest_sample_s is not None:
                    known = ids < newest_sample_s.size
                    newest[known] = newest_sample_s[ids[known]]
                a = a[newest > who[1]]  # (NaN: never superseded)
            parts.append(a)
        return np.concatenate(parts) if parts else np.empty(0)

    def _judge(self, over: list[str]) -> tuple[str | None, str | None]:
        """(warning the first second over, hold reason after ``persist_s`` seconds in a row)."""
        if not over:
            self._over = 0
            return None, None
        self._over += 1
        text = "; ".join(over)
        warning = f"safety budget exceeded: {text}" if self._over == 1 else None
        hold = None
        if self._over >= self.persist_s:
            hold = (f"safety budget exceeded in flight for {self.persist_s} s ({text}): the "
                    f"partition was built for the smaller δ")
        return warning, hold
