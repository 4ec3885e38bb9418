"""The supervisor's ``summary.json``: what a fleet run did, measured, and how it ended.

:func:`fleet_summary` builds it from a :class:`~vtube_fleet.fleet.supervisor.Supervisor` at any
moment (the interim summaries while flying, the final one at the end) on top of the run's
:class:`~vtube_fleet.core.metrics.SummaryAccumulator` — the simulator's own accumulator, fed every
tick from **telemetry** positions: the ``""`` stream holds the vehicles in the tube (and lost
vehicles at their frozen positions) with the *commanded* horizontal velocities, so
``min_speed_m_s``/``max_speed_m_s`` are the commanded speeds in the tube; the measured speeds
are ``min_measured_speed_m_s``/``max_measured_speed_m_s``; ``min_pair_distance_airborne_m`` also
counts vehicles that have exited. With ground truth the ``*_truth`` keys are the same figures
from the vehicles' true positions (:func:`~vtube_fleet.core.metrics.truth_keys`).
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from vtube_fleet.core.metrics import finite_or_none, percentile_or_none, truth_keys
from vtube_fleet.fleet.budget import achieved_rate_hz, on_time_share
from vtube_fleet.state import Phase

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.fleet.supervisor import Supervisor

__all__ = ["fleet_summary", "signing_summary", "telemetry_summary"]

log = logging.getLogger(__name__)


def signing_summary(sup: Supervisor) -> dict[str, Any]:
    """Whether the links signed (docs/security.md) and what they refused, by reason."""
    refused: dict[str, int] = {}
    for p in sup.pilots:
        for why, n in getattr(p.link, "signing_refused", {}).items():
            refused[why] = refused.get(why, 0) + int(n)
    return {"enabled": bool(sup.cfg.signing_key_file), "refused": refused}


def telemetry_summary(sup: Supervisor) -> dict[str, Any]:
    """What the links refused of the vehicles' telemetry, by reason (docs/security.md:
    another system id, another source address, impossible speed or jump, time running
    backwards or jumping), the vehicles whose telemetry the link stopped trusting (``faults``:
    vehicle and why) and the addresses re-learned."""
    refused: dict[str, int] = {}
    faults = []
    changes = 0
    for p in sup.pilots:
        s = p.link.state
        for why, n in s.telemetry_refused.items():
            refused[why] = refused.get(why, 0) + int(n)
        if s.telemetry_fault is not None:
            faults.append({"vehicle": p.vehicle_id, "reason": s.telemetry_fault})
        changes += int(s.source_changes)
    return {"refused": refused, "faults": faults, "source_changes": changes}


def fleet_summary(sup: Supervisor) -> dict[str, Any]:
    """The run's summary so far (module docstring)."""
    cfg = sup.cfg
    clock = sup.clock
    mes = sup.measurement
    dur = np.asarray(clock.durations_s)
    flown = sup.plan.flown
    route = sup.plan.route
    segment = sup.table.segment
    vehicles = []
    for k, p in enumerate(sup.pilots):
        vehicles.append({
            "id": p.vehicle_id, "endpoint": p.link.endpoint.url, "phase": p.phase.value,
            "exit_s": finite_or_none(p.exit_time_s), "reason": p.reason,
            "last_position": None if not p.has_position() else [
                round(float(p.xy[0]), 3), round(float(p.xy[1]), 3)],
            "setpoints_sent": p.setpoints_sent,
            "battery_pct": finite_or_none(round(100.0 * p.link.state.battery_remaining, 1)),
        })
        if route.S > 1:  # the segment it flew last (S1, S2 …; None: never had a position)
            vehicles[-1]["segment"] = (f"S{int(segment[k]) + 1}" if segment[k] >= 0
                                       else None)
    last_exit = [p.exit_time_s for p in sup.pilots if p.exit_time_s is not None]
    extra: dict[str, Any] = {
        "kind": "fleet",
        "source": sup.mission.source,
        "backend": sup.backend,
        "outcome": sup.outcome,
        "reason": sup.reason,
        "onboard": dict(sup.onboard),  # the fence and the PX4 parameter audit
        "battery": sup.preflight.battery,  # the check before arming (fleet/preflight.py)
        "mavlink_signing": signing_summary(sup),
        "telemetry": telemetry_summary(sup),
        "vehicles": len(sup.pilots),
        "lost": [p.vehicle_id for p in sup.pilots if p.phase == Phase.LOST],
        # at the end: the vehicles not known to be on the ground (the reason says why)
        "not_down": sorted(set(sup.not_landed) | set(sup.unreachable) | set(sup.not_waited)
                           | set(sup.held_for_operator)),
        "r_s": sup.physical.r_s,
        "r_a": sup.physical.r_a,
        "r_s_flown": flown.r_s,
        "r_a_flown": flown.r_a,
        "segments": route.S,  # of the route flown (1: a [tube])
        "apex_distances_m": [  # h_k of the configured obstacles flown ("auto": core/plan.py)
            next((t.h for t in route.triangles if t.obstacle == i), None)
            for i in range(len(route.corridor.obstacles))],
        "pair_limit_m": mes.monitor.limits.pair_m,
        "safety_budget": sup.budget.as_dict(),
        "min_pair_distance_airborne_m": finite_or_none(mes.min_pair_airborne),
        "min_commanded_speed_m_s": finite_or_none(mes.cmd_speed[0]),
        "max_commanded_speed_m_s": finite_or_none(mes.cmd_speed[1]),
        "min_measured_speed_m_s": finite_or_none(mes.measured_speed[0]),
        "max_measured_speed_m_s": finite_or_none(mes.measured_speed[1]),
        "settle_s": mes.settle_s,
        "min_measured_speed_settled_m_s": finite_or_none(mes.settled_speed[0]),
        "max_measured_speed_settled_m_s": finite_or_none(mes.settled_speed[1]),
        "rate_hz": cfg.rate_hz,
        "achieved_rate_hz": finite_or_none(achieved_rate_hz(clock.starts_s)),
        "ticks": int(dur.size),
        "ticks_on_time_share": on_time_share(clock.lateness_s, cfg.period_s),
        "tick_duration_p50_s": finite_or_none(percentile_or_none(dur, 50)),
        "tick_duration_p99_s": finite_or_none(percentile_or_none(dur, 99)),
        "tick_duration_max_s": finite_or_none(float(dur.max()) if dur.size else math.nan),
        "link_latency_p50_s": finite_or_none(percentile_or_none(mes.latencies, 50)),
        "link_latency_p99_s": finite_or_none(percentile_or_none(mes.latencies, 99)),
        "position_age_p50_s": finite_or_none(percentile_or_none(mes.sample_ages, 50)),
        "position_age_p99_s": finite_or_none(percentile_or_none(mes.sample_ages, 99)),
        "tube_start_s": finite_or_none(sup.tube_start_s),
        "flight_time_s": (finite_or_none(max(last_exit) - sup.tube_start_s)
                          if last_exit and sup.tube_start_s is not None else None),
        "partitions": sup.partitions,
        "wall_s": round(sup.t_s(), 3),
        "vehicle_states": vehicles,
        "events": sup.events[-200:],
    }
    extra["first_violation"] = mes.violations.first
    if sup.truth:
        extra["truth"] = True
        extra["min_pair_distance_airborne_m_truth"] = finite_or_none(mes.min_pair_airborne_truth)
        # (→ truth_min_pair_distance_airborne_m, like every *_truth key)
    if sup.measured is not None:
        extra["measured"] = {
            "position_age_p95_s": sup.measured.position_age_s,
            "setpoint_delay_s": sup.measured.setpoint_delay_s,
            "accuracy_m": finite_or_none(sup.measured.accuracy_m),
            "accuracies_m": [finite_or_none(a) for a in sup.measured.accuracies_m]}
    bank = sup.table.compensator
    if bank is not None and bank.max_m_s.size:
        res = sup.table.residuals.residuals().tolist()
        extra["estimate_compensation"] = {
            "max_correction_m_s": float(bank.max_m_s.max()),
            "clipped": int(bank.clipped.sum()),
            "residual_p50_m_s": finite_or_none(percentile_or_none(res, 50)),
            "residual_p99_m_s": finite_or_none(percentile_or_none(res, 99)),
            "residual_max_m_s": finite_or_none(max(res) if res else math.nan),
            "budgeted_m_s": sup.budget.disturbance_m_s}
    if sup.response is not None:
        extra["response_check"] = sup.response.as_dict()
    watch = mes.watch
    if watch is not None and watch.response is not None:
        extra["response_watch"] = watch.response.as_dict()
    if sup.budget.reference and watch is not None:
        extra["reference_tracking"] = {
            "error_p50_m": finite_or_none(watch.tracking_percentile_m(50)),
            "error_p99_m": finite_or_none(watch.tracking_percentile_m(99)),
            "error_max_m": finite_or_none(watch.tracking_max_m),
            "error_max_at": (None if watch.tracking_max_at is None else
                             {"t_s": round(watch.tracking_max_at[0], 2),
                              "vehicle": watch.tracking_max_at[1]}),
            "budgeted_m": sup.budget.tracking_error_m,
            # the mock's truth: |p − r| ≤ e + k σ is what δ counts on
            "truth_offset_max_m": finite_or_none(mes.truth_reference_max_m),
            "budgeted_with_estimate_m": sup.budget.tracking_m + sup.budget.estimate_m,
            "gain_1_s": cfg.tracking_gain_1_s}
    try:
        out = mes.acc.summary(**extra)
    except Exception as exc:  # never lose the summary
        log.error("summary accumulator failed: %s", exc)
        return extra
    return truth_keys(out)
