"""The response check: PX4's answer to a velocity step, measured per vehicle in the hover
before the tube (docs/fleet.md, "The response check").

The safety budget's lag term models PX4's answer to a commanded velocity change as nothing for
T + L + τ_d after the tick that sends it, then a first order with t63 (:class:`ResponseModel`).
After the climb, every hovering vehicle flies the same steps at once: zero for
:data:`SETTLE_S` (a still start), the cruise speed v along the first segment's n_c for a hold
H (:attr:`ResponseModel.hold_s`), then zero for as long. The tick samples how fast each
estimated position moves along n_c (:meth:`ResponseProbe.moving_m_s`), and
:func:`~vtube_fleet.core.response.step_response` reads each step's lag: how far, in seconds of
the change, the vehicle fell behind the commanded path over the step. A vehicle whose lag on
either step exceeds the model's over the same window (:meth:`ResponseModel.allowed_lag_s`) by
more than the estimate can tell apart (:meth:`ResponseModel.tolerance_s`) is refused, with the
numbers, and the mission aborts (every vehicle lands) before any enters the tube. Otherwise
every vehicle flies back to its take-off spot (:data:`RETURN_GAIN_1_S`, at most v, until each
is within :data:`RETURN_TOL_M`): the steps move the vehicles apart by their differences in
lag, and the tube starts from the formation the preflight validated.

All vehicles fly the same command, so the pairs keep their spacing up to their differences in
response; the room ahead (every vehicle moved by :meth:`ResponseModel.reach_m`) is checked
against the partition first, and without it the check is skipped, said in the events and the
summary.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vtube_fleet.core.response import StepResponse, step_response
from vtube_fleet.fleet.budget import ResponseModel
from vtube_fleet.fleet.table import FleetTable
from vtube_fleet.fleet.tick import toward_m_s

__all__ = ["SETTLE_S", "ResponseProbe", "ResponseReport", "run_response_check"]

#: The hover is first made still: zero (plus d̂) for this long before the step, so that the
#: step starts from a settled velocity (after the climb PX4's estimate still converges and the
#: take-off spot's hold chases it).
SETTLE_S = 1.5
#: The way back to the take-off spots: gain (1/s) on the offset, at most the step's speed, until
#: every vehicle is within RETURN_TOL_M of its spot, or RETURN_TIMEOUT_S have passed (then
#: Assumption 1 at altitude judges where they are).
RETURN_GAIN_1_S = 1.0
RETURN_TOL_M = 0.2
RETURN_TIMEOUT_S = 10.0
#: Extra seconds a step may wait for its ticks before the check gives up (a stalled loop).
TICK_WAIT_EXTRA_S = 5.0


@dataclass
class ResponseProbe:
    """Samples, after each tick, the velocity along ``direction`` of the table's ``rows``; the
    first tick after :meth:`start` is the step's time (the tick that sends it), ``hold_s``
    the current phase's length."""

    table: FleetTable
    rows: np.ndarray
    direction: np.ndarray
    hold_s: float = 0.0
    step_at_s: float | None = None
    #: flying back to the take-off spots at most this fast (None: a step)
    return_m_s: float | None = None
    done: asyncio.Event = field(default_factory=asyncio.Event)
    _t: list[np.ndarray] = field(default_factory=list)
    _v: list[np.ndarray] = field(default_factory=list)

    def start(self, velocity_m_s: np.ndarray, hold_s: float) -> None:
        """Send ``velocity_m_s`` (2,) to every row from the next tick on, for ``hold_s``
        (:attr:`done` then); samples restart."""
        self.hold_s = hold_s
        self.table.probe_vel[self.rows] = velocity_m_s
        self.step_at_s = None
        self.done.clear()
        self._t.clear()
        self._v.clear()

    def start_return(self, max_m_s: float) -> None:
        """Fly every row back to its take-off spot from the next tick on (:meth:`on_tick`)."""
        self.return_m_s = max_m_s
        self.done.clear()
        self._steer_back()

    def _steer_back(self) -> bool:
        """Set each row's velocity towards its take-off spot; True once all are there."""
        tab, r = self.table, self.rows
        assert self.return_m_s is not None
        tab.probe_vel[r] = toward_m_s(tab.takeoff_xy[r], tab.xy[r], tab.has[r], RETURN_GAIN_1_S,
                                      self.return_m_s)
        off = np.hypot(*(tab.xy[r] - tab.takeoff_xy[r]).T)
        return bool(np.all(~tab.has[r] | (off <= RETURN_TOL_M)))

    def on_tick(self, now_mono: float) -> None:
        """The supervisor's hook after each tick (the tick has just sent the step)."""
        if self.return_m_s is not None:
            if self._steer_back():
                self.done.set()
            return
        if self.step_at_s is None:
            self.step_at_s = now_mono
        tab = self.table
        self._t.append(tab.sample_s[self.rows].copy())
        self._v.append(self.moving_m_s())
        if now_mono - self.step_at_s >= self.hold_s:
            self.done.set()

    def moving_m_s(self) -> np.ndarray:
        """How fast each row's estimated position moves along the direction: PX4's velocity
        estimate v̂ less the estimate disturbance d̂ (fleet/compensation.py: v̂ − d̂ ≈ dp̂/dt;
        PX4 drives v̂ to the setpoint plus d̂, so this is what follows the command)."""
        tab = self.table
        v = tab.vel[self.rows]
        bank = tab.compensator
        if bank is not None:
            v = v - bank.d_hat_m_s(self.rows)
        return v @ self.direction

    def response(self, v_from_m_s: float, v_to_m_s: float) -> StepResponse:
        """This step's response (:func:`~vtube_fleet.core.response.step_response`) over the
        hold, against the commanded change."""
        if not self._t or self.step_at_s is None:
            nan = np.full(self.rows.size, np.nan)
            return StepResponse(nan, nan.copy(), nan.copy(), nan.copy())
        return step_response(np.stack(self._t), np.stack(self._v), self.step_at_s,
                             v_from_m_s, v_to_m_s, self.hold_s)

    def finish(self) -> None:
        """Stop: each row holds its take-off spot again (the climb's hold)."""
        self.table.probe_vel[self.rows] = np.nan
        self.return_m_s = None


@dataclass
class ResponseReport:
    """What the check measured: per checked vehicle (``ids``) the start and the stop step's
    response, against the ``model``'s lags on the two steps plus its tolerance for a
    ``step_m_s`` step; or why it was skipped."""

    step_m_s: float
    model: ResponseModel
    ids: list[int]
    start: StepResponse | None = None
    stop: StepResponse | None = None
    skipped: str | None = None
    #: seconds the way back to the take-off spots took (None: not flown, or not all within
    #: RETURN_TOL_M after RETURN_TIMEOUT_S)
    return_s: float | None = None

    @property
    def allowed_s(self) -> tuple[float, float]:
        return self.model.allowed_lag_s()

    @property
    def tolerance_s(self) -> float:
        return self.model.tolerance_s(self.step_m_s)

    def over_s(self) -> np.ndarray:
        """Per vehicle: by how much the worse of its two steps lags more than the model
        (inf: a step without samples; NaN: not measured)."""
        if self.start is None or self.stop is None:
            return np.full(len(self.ids), np.nan)
        a = np.where(np.isnan(self.start.lag_s), np.inf, self.start.lag_s - self.allowed_s[0])
        b = np.where(np.isnan(self.stop.lag_s), np.inf, self.stop.lag_s - self.allowed_s[1])
        return np.maximum(a, b)

    def refused(self) -> list[int]:
        """The indices (into ``ids``) of the vehicles that lag more than the model and the
        tolerance."""
        if self.skipped is not None:
            return []
        return np.flatnonzero(self.over_s() > self.tolerance_s).tolist()

    def describe(self) -> str:
        """One line for the events: the ranges measured against the budget."""
        if self.skipped is not None:
            return f"response check skipped: {self.skipped}"
        assert self.start is not None and self.stop is not None
        return (f"response check: {len(self.ids)} vehicle(s), a {self.step_m_s:g} m/s step: lag "
                f"{_span(self.start.lag_s)} (start; the budget's model "
                f"{self.allowed_s[0]:.2f} s), {_span(self.stop.lag_s)} (stop; model "
                f"{self.allowed_s[1]:.2f} s), tolerance {self.tolerance_s:.2f} s; 63 % after "
                f"{_span(self.start.rise_s)}, 5 % after {_span(self.start.dead_time_s)}"
                + ("" if self.refused() else
                   f"; back at the take-off spots after {self.return_s:.1f} s"
                   if self.return_s is not None else
                   f"; not all back within {RETURN_TOL_M:g} m of their take-off spots after "
                   f"{RETURN_TIMEOUT_S:g} s"))

    def refusal(self, names: Sequence[str]) -> str:
        """The abort's text: each refused vehicle with its numbers, and the model's."""
        assert self.start is not None and self.stop is not None
        hold = self.model.hold_s
        parts = []
        for k in self.refused():
            a, b = float(self.start.lag_s[k]), float(self.stop.lag_s[k])
            share = float(self.start.share_end[k])
            parts.append(f"{names[self.ids[k]]}: lag {_s(a)} (start; at {share:.0%} of the step "
                         f"after {hold:.2f} s), {_s(b)} (stop)")
        return (f"response check failed before the tube: {len(parts)} of {len(self.ids)} "
                f"vehicle(s) follow a {self.step_m_s:g} m/s velocity step more slowly than the "
                f"safety budget assumes: its model ({self.model.describe()}) lags "
                f"{self.allowed_s[0]:.2f} s (start) and {self.allowed_s[1]:.2f} s (stop) over "
                f"{hold:.2f} s, plus {self.tolerance_s:.2f} s the estimate cannot tell apart "
                f"(σ / step): " + "; ".join(parts))

    def as_dict(self) -> dict[str, Any]:
        """The summary's ``response_check``."""

        def col(r: StepResponse | None, name: str) -> list[float | None]:
            if r is None:
                return []
            return [round(float(v), 3) if math.isfinite(v) else None for v in getattr(r, name)]

        return {"step_m_s": self.step_m_s,
                "allowed_lag_s": [round(self.allowed_s[0], 3), round(self.allowed_s[1], 3)],
                "tolerance_s": round(self.tolerance_s, 3),
                "vehicles": self.ids, "skipped": self.skipped,
                "lag_start_s": col(self.start, "lag_s"), "lag_stop_s": col(self.stop, "lag_s"),
                "rise_s": col(self.start, "rise_s"), "dead_time_s": col(self.start, "dead_time_s"),
                "share_end": col(self.start, "share_end"),
                "return_s": None if self.return_s is None else round(self.return_s, 2),
                "refused": [self.ids[k] for k in self.refused()]}


def _s(x: float) -> str:
    return f"{x:.2f} s" if math.isfinite(x) else "no sample"


def _span(x: np.ndarray) -> str:
    f = x[np.isfinite(x)]
    if f.size == 0:
        return "not reached"
    lo, hi = float(f.min()), float(f.max())
    out = f"{lo:.2f} s" if hi - lo < 0.005 else f"{lo:.2f}-{hi:.2f} s"
    return out + ("" if f.size == x.size else f" ({x.size - f.size} not reached)")


async def run_response_check(probe: ResponseProbe, report: ResponseReport,
                             attach: Callable[[ResponseProbe | None], None],
                             aborted: Callable[[], bool]) -> None:
    """Fly the steps (module docstring) with ``probe`` attached to the tick (``attach``), then
    detach it, filling ``report``; stops early when ``aborted()`` (the report then says it was
    skipped)."""
    step_m_s = report.step_m_s
    step_hold_s = report.model.hold_s
    attach(probe)
    try:
        steps = []
        for v_from, v_to, hold in ((None, 0.0, SETTLE_S), (0.0, step_m_s, step_hold_s),
                                   (step_m_s, 0.0, step_hold_s)):
            probe.start(v_to * probe.direction, hold)
            try:
                async with asyncio.timeout(hold + TICK_WAIT_EXTRA_S):
                    await probe.done.wait()
            except TimeoutError:
                report.skipped = (f"the control loop did not tick for "
                                  f"{hold + TICK_WAIT_EXTRA_S:.1f} s")
                return
            if aborted():
                report.skipped = "the mission aborted meanwhile"
                return
            if v_from is not None:
                steps.append(probe.response(v_from, v_to))
        report.start, report.stop = steps
        if report.refused():
            return  # the mission aborts: every vehicle lands where it is
        t0 = asyncio.get_running_loop().time()
        probe.start_return(step_m_s)
        try:
            async with asyncio.timeout(RETURN_TIMEOUT_S):
                await probe.done.wait()
            report.return_s = asyncio.get_running_loop().time() - t0
        except TimeoutError:
            pass
    except asyncio.CancelledError:  # the flight was stopped meanwhile (an abort, a signal)
        if report.skipped is None and report.stop is None:
            report.skipped = "interrupted before its steps were flown"
        raise
    finally:
        attach(None)
        probe.finish()
