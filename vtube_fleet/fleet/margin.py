"""The margin of a mission's safety budget: how far the measured link latency L and the
reported position accuracy σ may go before the mission no longer validates on its start slots
(``vtube-fleet check`` prints it; docs/config.md, "The margin").

δ grows with L and σ (``fleet/budget.py``), and with δ the flown radii r_s', r_a'. The mission
stays valid while

* the inflated scenario validates on the slots: :func:`slot_violations`, the one check that
  ``check``'s verdict is, the same conditions as the supervisor's preflight
  (``validate_route`` with the slots as the planner's keep-out points, the apex
  look-ahead) and the budget's own refusals (L + ``latency_headroom_s`` > ``max_latency_s``,
  σ > ``max_position_accuracy_m``);
* that is, while δ ≤ δ_max, found by bisection over δ (the geometry alone) and checked on a
  grid below it, so that a mission whose validity is not monotone in δ is not given a margin
  it does not have.

:func:`mission_margin` gives δ_max, the largest L (σ as assumed) and the largest σ (L as
assumed), each found by bisection with :func:`slot_violations` itself and printed rounded
down, so that the printed figures validate. :func:`margin_note` turns a refused measurement
into the sentence that names the figure past the margin; :func:`refusal_note` is that for the
supervisor's preflight refusal (check's default assumptions).

L here is what the links measure (position age + setpoint delay) and what ``check
--latency-s`` takes: the budget adds ``latency_headroom_s`` to it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from vtube_fleet.config.mission import Mission
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.partition import Violation
from vtube_fleet.core.route import Route
from vtube_fleet.core.validation import (
    RouteValidation,
    bisect_edge,
    flown_symbols,
    validate_route,
)
from vtube_fleet.fleet.budget import (
    PX4_SITL_ACCURACY_M,
    PX4_SITL_LATENCY_S,
    LinkMeasurement,
    SafetyBudget,
    budget_problems,
    mission_budget,
)

__all__ = [
    "BudgetMargin",
    "assumed_measurement",
    "lookahead_violations",
    "margin_note",
    "mission_margin",
    "refusal_note",
    "slot_violations",
]

#: Bisection resolution of δ (m): below the printed 1 mm (the L and σ margins derived from
#: δ_max are confirmed by the full check, on their own grid).
_TOL = 1e-4
#: The margins of L (s) and σ (m) are found on this grid, exactly: valid at the figure
#: printed, invalid one step past it.
_STEP = 1e-3
#: Grid points below δ_max at which validity is checked again (a hole below the bisection's
#: end point would otherwise be missed).
_GRID = 8


def assumed_measurement(latency_s: float | None = None, accuracy_m: float | None = None
                        ) -> LinkMeasurement:
    """What ``check`` assumes the vehicles will measure: ``latency_s`` (default: the L real
    PX4 SITL measured, :data:`~vtube_fleet.fleet.budget.PX4_SITL_LATENCY_S`) and
    ``accuracy_m`` (default: the σ it reported, :data:`~vtube_fleet.fleet.budget.
    PX4_SITL_ACCURACY_M`)."""
    return LinkMeasurement(
        position_age_s=PX4_SITL_LATENCY_S if latency_s is None else float(latency_s),
        setpoint_delay_s=0.0,
        accuracy_m=PX4_SITL_ACCURACY_M if accuracy_m is None else float(accuracy_m))


def lookahead_violations(route: Route, positions: np.ndarray,
                         names: Sequence[str] | None = None) -> list[Violation]:
    """Slots (or vehicles, ``names``) that the apex look-ahead (a mission flies it) puts into a
    side tube at most r_s' from its legs: they would start inside the barrier (``check``'s
    verdict and the fleet's preflight, on the ground and at altitude, refuse them)."""
    positions = np.asarray(positions, dtype=float).reshape(-1, 2)
    if not len(positions) or not route.lookahead:
        return []
    flat = dataclasses.replace(route, lookahead=False)
    seg0, k0 = flat.locate(positions)
    _, k1 = route.locate(positions, seg0)
    out = []
    for i in np.flatnonzero(k0 != k1):
        t = route.sub_tubes[int(k1[i])]
        d = min(float(t.d_Th(positions[i])), float(t.d_Tr(positions[i])))
        if d <= route.params.r_s:
            who = f"slot {i}" if names is None else names[i]
            out.append(Violation("Assumption1", (
                f"Assumption1 violated: {who} at ({positions[i, 0]:.3f}, "
                f"{positions[i, 1]:.3f}) is in the look-ahead zone of an apex: it would fly "
                f"{t.name} with {d:.2f} m to its legs ≤ r_s' = {route.params.r_s:.2f} m (move "
                f"the slot upstream or the obstacle downstream)")))
    return out


def _geometry(mission: Mission, budget: SafetyBudget
              ) -> tuple[ControllerParams, RouteValidation, list[Violation]]:
    sc = mission.scenario
    flown = budget.inflate(sc.controller)
    res = validate_route(sc.corridor, flown, mission.slots, keep_out=mission.slots,
                         lookahead=True)
    violations = [dataclasses.replace(v, message=flown_symbols(v.message))
                  for v in res.violations]
    if res.route is not None:
        violations += lookahead_violations(res.route, mission.slots)
    return flown, res, violations


def slot_violations(mission: Mission, measured: LinkMeasurement
                    ) -> tuple[SafetyBudget, ControllerParams, RouteValidation, list[Violation]]:
    """(budget, flown parameters, the route's validation (its planned route, junction checks),
    violations) of ``mission`` on its start slots with the links ``measured`` (module
    docstring): what ``check``'s verdict and the margin judge. Violations of the budget itself
    come first (condition ``Budget``)."""
    cfg = mission.config
    budget = mission_budget(mission, measured)
    extra = [Violation("Budget", f"Budget refused: {p}")
             for p in budget_problems(mission, measured)]
    sigma = measured.accuracy_m
    if cfg.position_accuracy_m is None and math.isfinite(sigma) \
            and sigma > cfg.max_position_accuracy_m:
        extra.append(Violation("Budget", (
            f"Budget refused: σ = {sigma:g} m > max_position_accuracy_m = "
            f"{cfg.max_position_accuracy_m:g} m: the vehicles would wait for a better fix "
            f"until ready_timeout_s = {cfg.ready_timeout_s:g} s and be refused")))
    flown, res, violations = _geometry(mission, budget)
    return budget, flown, res, extra + violations


def _largest(valid: Callable[[float], bool], lo: float, hi: float) -> float:
    """The largest x in [lo, hi) found valid by bisection, given ``valid(lo)`` and not
    ``valid(hi)``."""
    return bisect_edge(valid, lo, hi, tol=_TOL)


def _largest_step(valid: Callable[[float], bool], lo: float, hi: float) -> float:
    """The largest multiple of :data:`_STEP` in [lo, hi) found valid by bisection, given
    ``valid`` at the step at or below ``lo`` and not at ``hi``."""
    a, b = math.floor(lo / _STEP + 1e-9), math.ceil(hi / _STEP - 1e-9)
    while b - a > 1:
        m = (a + b) // 2
        if valid(m * _STEP):
            a = m
        else:
            b = m
    return round(a * _STEP, 9)


def _first_problem(violations: list[Violation]) -> str:
    return violations[0].message if violations else ""


@dataclass(frozen=True)
class BudgetMargin:
    """How far L and σ may go (module docstring). ``assumed``: the figures ``check`` assumed
    (``latency_s`` / ``accuracy_m`` of a :class:`LinkMeasurement`); ``delta_m`` δ there;
    ``delta_max_m`` the largest δ the slots validate with (None: not even δ = 0);
    ``latency_max_s`` the largest measured L with σ as assumed and ``accuracy_max_m`` the
    largest σ with L as assumed (None when the mission fixes that figure, ``latency_s`` /
    ``position_accuracy_m``, or when the mission is invalid at the assumed figures); the
    ``*_why`` texts: what refuses just past each."""

    assumed: LinkMeasurement
    delta_m: float
    delta_max_m: float | None
    delta_why: str
    latency_max_s: float | None
    latency_why: str
    accuracy_max_m: float | None
    accuracy_why: str
    fixed_latency_s: float | None = None
    fixed_accuracy_m: float | None = None
    overridden: bool = False

    @property
    def ok(self) -> bool:
        """The mission validates at the assumed figures."""
        return self.delta_max_m is not None and self.delta_m <= self.delta_max_m \
            and self.latency_max_s is not None and self.accuracy_max_m is not None

    @staticmethod
    def _down(x: float) -> float:
        """Rounded down to 1 ms / 1 mm: the printed figure validates."""
        return math.floor(x * 1000.0 + 1e-9) / 1000.0

    @property
    def latency_shown_s(self) -> float | None:
        return None if self.latency_max_s is None else self._down(self.latency_max_s)

    @property
    def accuracy_shown_m(self) -> float | None:
        return None if self.accuracy_max_m is None else self._down(self.accuracy_max_m)

    @property
    def delta_shown_m(self) -> float | None:
        return None if self.delta_max_m is None else self._down(self.delta_max_m)

    def _l_text(self) -> str:
        if self.fixed_latency_s is not None:
            return f"L = {self.fixed_latency_s:g} s fixed (latency_s)"
        return f"L ≤ {self.latency_shown_s:.3f} s"

    def _s_text(self) -> str:
        if self.fixed_accuracy_m is not None:
            return f"σ = {self.fixed_accuracy_m:g} m fixed (position_accuracy_m)"
        return f"σ ≤ {self.accuracy_shown_m:.3f} m"

    def lines(self) -> list[str]:
        """What ``check`` prints: ``margin: valid up to L ≤ … s, σ ≤ … m`` and what refuses
        just past each figure (or why there is no margin)."""
        a = self.assumed
        if not self.ok:
            if self.delta_max_m is None:
                return ["margin: none: the slots do not validate even with δ = 0 (the "
                        "physical radii)"]
            return [f"margin: none at the assumed figures (L = {a.latency_s:.3f} s, σ = "
                    f"{a.accuracy_m:.3f} m → δ = {self.delta_m:.3f} m): the slots validate "
                    f"only while δ ≤ {self.delta_shown_m:.3f} m"]
        out = [f"margin: valid up to {self._l_text()}, {self._s_text()} (each with the other "
               f"as assumed: L = {a.latency_s:.3f} s, σ = {a.accuracy_m:.3f} m; both together "
               f"while δ ≤ {self.delta_shown_m:.3f} m"
               + (", δ fixed by safety_margin_m" if self.overridden else "") + ")"]
        if self.latency_why:
            out.append(f"  past L ≤ {self.latency_shown_s:.3f} s: {self.latency_why}")
        if self.accuracy_why:
            out.append(f"  past σ ≤ {self.accuracy_shown_m:.3f} m: {self.accuracy_why}")
        return out

    def as_dict(self) -> dict[str, Any]:
        return {"latency_max_s": self.latency_shown_s, "accuracy_max_m": self.accuracy_shown_m,
                "delta_max_m": self.delta_shown_m, "assumed_latency_s": self.assumed.latency_s,
                "assumed_accuracy_m": self.assumed.accuracy_m, "delta_m": self.delta_m}


def mission_margin(mission: Mission, assumed: LinkMeasurement | None = None) -> BudgetMargin:
    """The :class:`BudgetMargin` of ``mission`` around ``assumed`` (default:
    :func:`assumed_measurement`, what ``check`` assumes)."""
    a = assumed_measurement() if assumed is None else assumed
    cfg = mission.config

    def problems(m: LinkMeasurement) -> list[Violation]:
        return slot_violations(mission, m)[3]

    def valid(m: LinkMeasurement) -> bool:
        return not problems(m)

    here = mission_budget(mission, a)
    # δ_max: the geometry alone (a fixed δ through the budget's override)
    params = mission.scenario.controller

    def geometry_ok(delta: float) -> bool:
        b = SafetyBudget.compute(params, period_s=cfg.period_s, latency_s=0.0,
                                 dead_time_s=0.0, t63_s=0.0, override_m=delta)
        return not _geometry(mission, b)[2]

    delta_max: float | None = None
    delta_why = ""
    if geometry_ok(0.0):
        hi = max(2.0 * here.delta_m, 1.0)
        while geometry_ok(hi) and hi < 1e3:
            hi *= 2.0
        lo = _largest(geometry_ok, 0.0, hi)
        while True:  # a hole below the end point: the margin ends before it
            bad = [x for x in np.linspace(0.0, lo, _GRID + 1)[1:-1] if not geometry_ok(x)]
            if not bad:
                break
            prev = max([0.0] + [x for x in np.linspace(0.0, lo, _GRID + 1) if x < bad[0]])
            lo = _largest(geometry_ok, float(prev), float(bad[0]))
        delta_max = lo
        b = SafetyBudget.compute(params, period_s=cfg.period_s, latency_s=0.0, dead_time_s=0.0,
                                 t63_s=0.0, override_m=min(lo + 1e-3, hi))
        delta_why = _first_problem(_geometry(mission, b)[2])
    fixed_l = cfg.latency_s
    fixed_s = cfg.position_accuracy_m

    def edge(make: Callable[[float], LinkMeasurement], lo: float, hi: float
             ) -> tuple[float, str]:
        """The largest figure on the grid that validates, and what refuses one step past:
        first from δ_max (the budget alone: cheap), confirmed by the full check there and
        one step past; by bisection with the full check where that does not hold."""
        def quick(x: float) -> bool:
            m = make(x)
            return (delta_max is not None and mission_budget(mission, m).delta_m <= delta_max
                    and not budget_problems(mission, m) and not (
                        fixed_s is None and m.accuracy_m > cfg.max_position_accuracy_m))

        x = _largest_step(quick, lo, hi) if quick(math.floor(lo / _STEP + 1e-9) * _STEP) \
            else lo
        past = problems(make(x + _STEP))
        if not valid(make(x)) or not past:  # validity not monotone in δ here
            x = _largest_step(lambda y: valid(make(y)), lo, hi)
            past = problems(make(x + _STEP))
        return x, _first_problem(past)

    lat_max: float | None = None
    acc_max: float | None = None
    lat_why = acc_why = ""
    if valid(a):
        if fixed_l is None:
            lat_max, lat_why = edge(lambda x: LinkMeasurement(x, 0.0, a.accuracy_m),
                                    a.latency_s, cfg.max_latency_s + _STEP)
        else:
            lat_max = fixed_l
        if fixed_s is None:
            acc_max, acc_why = edge(
                lambda x: LinkMeasurement(a.position_age_s, a.setpoint_delay_s, x),
                a.accuracy_m, cfg.max_position_accuracy_m + _STEP)
        else:
            acc_max = fixed_s
    return BudgetMargin(a, here.delta_m, delta_max, delta_why, lat_max, lat_why, acc_max,
                        acc_why, fixed_l, fixed_s, cfg.safety_margin_m is not None)


def margin_note(margin: BudgetMargin, mission: Mission, measured: LinkMeasurement) -> str:
    """Which measured figure went past the margin ``check`` printed (one sentence), for a
    refusal of ``mission`` measured as ``measured``."""
    if not margin.ok:
        return ("check refuses this mission too at its assumed figures (L = "
                f"{margin.assumed.latency_s:.3f} s, σ = {margin.assumed.accuracy_m:.3f} m)")
    past = []
    L, sigma = measured.latency_s, measured.accuracy_m
    if margin.fixed_latency_s is None and L > (margin.latency_shown_s or 0.0):
        past.append(f"measured L = {L:.3f} s > the margin L ≤ {margin.latency_shown_s:.3f} s "
                    f"that check printed")
    if (margin.fixed_accuracy_m is None and math.isfinite(sigma)
            and sigma > (margin.accuracy_shown_m or 0.0)):
        past.append(f"measured σ = {sigma:.3f} m > the margin σ ≤ "
                    f"{margin.accuracy_shown_m:.3f} m that check printed")
    if past:
        return "; ".join(past)
    delta = mission_budget(mission, measured).delta_m
    if margin.delta_max_m is not None and delta > margin.delta_max_m:
        return (f"measured L = {L:.3f} s and σ = {sigma:.3f} m are each within the margin "
                f"check printed (L ≤ {margin.latency_shown_s:.3f} s, σ ≤ "
                f"{margin.accuracy_shown_m:.3f} m, each with the other as assumed) but "
                f"together give δ = {delta:.3f} m > δ ≤ {margin.delta_shown_m:.3f} m")
    return (f"measured L = {L:.3f} s and σ = {sigma:.3f} m are within the margin check "
            f"printed (L ≤ {margin.latency_shown_s:.3f} s, σ ≤ {margin.accuracy_shown_m:.3f} m,"
            f" δ = {delta:.3f} m ≤ {margin.delta_shown_m:.3f} m): what refuses is where the "
            f"vehicles are, not the link")


def refusal_note(mission: Mission, measured: LinkMeasurement) -> str:
    """:func:`margin_note` against the margin ``check MISSION`` prints by default (its
    assumed figures: :func:`assumed_measurement`); for the supervisor's preflight refusal.
    Costs some 60 validations of the mission (tens of ms): call it on the refusal path
    only."""
    return margin_note(mission_margin(mission), mission, measured)
