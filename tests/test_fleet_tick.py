"""The supervisor's vectorized tick does what each pilot's own steps do, vehicle by vehicle.

The supervisor runs its fleet's per-tick steps for all vehicles at once (issue 16):
:func:`~vtube_fleet.fleet.pilot.sense_all`, :func:`~vtube_fleet.fleet.pilot.check_faults_all`,
:func:`~vtube_fleet.fleet.pilot.fleet_states` with :func:`~vtube_fleet.fleet.agent.classify_arrays`,
:func:`~vtube_fleet.fleet.pilot.actuate_all`, and the fleet's
:class:`~vtube_fleet.fleet.compensation.CompensatorBank` and
:class:`~vtube_fleet.fleet.compensation.ResidualTracker`. The standalone agent
runs the same steps per vehicle (:meth:`VehiclePilot.tick`). Here two identical in-memory
fleets fly the same ticks with faults injected (a silent vehicle, one that does not follow,
one that leaves OFFBOARD, one disarmed, a stopped one), one through the fleet functions, one
pilot by pilot, and everything they send, decide and report must agree: bit for bit, except
the residuals, which are ``np.hypot`` against ``math.hypot`` (last bit).
"""

from __future__ import annotations

import asyncio
import math
from bisect import bisect_right
from collections import deque
from itertools import pairwise

import numpy as np
import pytest
from memory_fleet import fly_telemetry, memory_fleet

from vtube_fleet.fleet.agent import classify, classify_arrays, fleet_setpoints
from vtube_fleet.fleet.compensation import (
    RESIDUAL_WINDOW_S,
    CompensatorBank,
    EstimateCompensator,
    ResidualTracker,
)
from vtube_fleet.fleet.pilot import (
    actuate_all,
    check_faults_all,
    fleet_states,
    sense_all,
)
from vtube_fleet.state import AIRBORNE_PHASES, STOPPED_PHASES, NeighbourState, Phase

WALL = 1.7e9  # wall clock = monotonic + WALL


def _view_equal(a, b) -> None:
    for name in ("live_ids", "live_pos", "live_vel", "static_ids", "static_pos", "lost_ids",
                 "lost_pos"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape and np.array_equal(x, y), name


def test_classify_sorts_every_state_by_the_rule() -> None:
    """Random tables (phases, ages, NaN positions, a stall): each id lands in the bucket the
    rule names, at its own position, sorted by id."""
    rng = np.random.default_rng(1)
    phases = list(Phase)
    for _ in range(50):
        n = int(rng.integers(0, 40))
        ids = rng.permutation(200)[:n]
        now = 1000.0
        heard = None if rng.random() < 0.5 else now - rng.uniform(0.0, 2.0)
        states = [NeighbourState(int(i), *(rng.normal(size=4) if rng.random() > 0.1
                                           else (math.nan, 1.0, 0.5, 0.5)),
                                 phases[int(rng.integers(len(phases)))],
                                 now - rng.uniform(0.0, 3.0), 1) for i in ids]
        exclude = int(ids[0]) if n and rng.random() < 0.5 else None
        view = classify(states, now, max_age_s=0.5, lost_after_s=1.5, exclude=exclude,
                        heard_since_s=heard)
        want: dict[str, list[NeighbourState]] = {"live": [], "static": [], "lost": []}
        for st in states:
            if st.vehicle_id == exclude or not math.isfinite(st.x_m):
                continue
            age = now - st.stamp_s
            silence = age if heard is None else min(age, now - heard)
            if st.phase == Phase.LOST or st.phase in STOPPED_PHASES:
                want["lost"].append(st)
            elif st.phase in AIRBORNE_PHASES:
                which = "lost" if silence > 1.5 else "static" if age > 0.5 else "live"
                want[which].append(st)
        for which, ids_got, pos_got in (("live", view.live_ids, view.live_pos),
                                        ("static", view.static_ids, view.static_pos),
                                        ("lost", view.lost_ids, view.lost_pos)):
            rows = sorted(want[which], key=lambda s: s.vehicle_id)
            assert ids_got.tolist() == [s.vehicle_id for s in rows], which
            assert pos_got.tolist() == [[s.x_m, s.y_m] for s in rows], which
        assert view.live_vel.tolist() == [[s.vx_m_s, s.vy_m_s] for s in
                                          sorted(want["live"], key=lambda s: s.vehicle_id)]


def test_residual_tracker_matches_a_lookup_per_vehicle() -> None:
    """Vehicles tracked on different ticks, with delays beyond the first entries looked at:
    the same residuals, means and warnings as a bisect over each vehicle's own history."""
    rng = np.random.default_rng(2)
    m, period, budget = 7, 0.05, 0.25
    tracker = ResidualTracker(m, period, budget, history=40)
    hist: list[list[tuple[float, float, float]]] = [[] for _ in range(m)]
    mean = [0.0] * m
    warned = [False] * m
    want: list[list[float]] = [[] for _ in range(m)]
    t = 0.0
    for _ in range(300):
        t += period * rng.uniform(0.5, 3.0)
        rows = np.flatnonzero(rng.random(m) < 0.7)
        if not rows.size:
            continue
        d = rng.normal(size=(rows.size, 2)) * np.where(rows < 4, 0.3, 0.02)[:, None]  # 4-6 calm
        lag = np.where(rows == 3, 1.4, rng.uniform(0.2, 0.5, rows.size))  # row 3: > 16 back
        crossed = tracker.track(rows, t, d, lag)
        expect = []
        for k, r in enumerate(rows.tolist()):
            h = hist[r]
            h.append((t, float(d[k, 0]), float(d[k, 1])))
            recent = h[-40:]
            j = bisect_right([e[0] for e in recent], t - lag[k]) - 1
            if j < 0:
                continue
            res = math.hypot(d[k, 0] - recent[j][1], d[k, 1] - recent[j][2])
            want[r].append(res)
            mean[r] += min(1.0, period / RESIDUAL_WINDOW_S) * (res - mean[r])
            if mean[r] > budget and not warned[r]:
                warned[r] = True
                expect.append(r)
        assert sorted(crossed.tolist()) == sorted(expect)
    assert any(len(w) > 100 for w in want) and any(warned) and not all(warned)
    for r in range(m):
        np.testing.assert_allclose(tracker.residuals(r), want[r], rtol=1e-15, atol=1e-16)
        assert tracker.mean_m_s[r] == pytest.approx(mean[r], rel=1e-12, abs=1e-15)
    assert tracker.residuals().size == sum(len(w) for w in want)


def _deque_compensator(window_s: float, limit_m_s: float):
    """d̂ of one vehicle written straightforwardly (a deque of samples, the module docstring's
    formula): the reference for :class:`CompensatorBank`."""
    q: deque[tuple[float, float, float, float, float]] = deque()
    out = {"d": (0.0, 0.0), "clipped": 0, "max": 0.0}

    def add(t: float, x: float, y: float, vx: float, vy: float) -> None:
        if not all(math.isfinite(v) for v in (t, x, y, vx, vy)) or (q and t <= q[-1][0]):
            return
        q.append((t, x, y, vx, vy))
        while len(q) > 2 and t - q[1][0] >= window_s:
            q.popleft()
        span = q[-1][0] - q[0][0]
        if len(q) < 2 or span < 0.5 * window_s:
            return
        s = list(q)
        ix = sum(0.5 * (b[3] + a[3]) * (b[0] - a[0]) for a, b in pairwise(s))
        iy = sum(0.5 * (b[4] + a[4]) * (b[0] - a[0]) for a, b in pairwise(s))
        dx, dy = (ix - (s[-1][1] - s[0][1])) / span, (iy - (s[-1][2] - s[0][2])) / span
        n = math.hypot(dx, dy)
        out["max"] = max(out["max"], n)
        if n > limit_m_s:
            out["clipped"] += 1
            dx, dy = dx * limit_m_s / n, dy * limit_m_s / n
        out["d"] = (dx, dy)

    return add, out


def test_compensator_bank_matches_one_deque_per_vehicle() -> None:
    """Vehicles with samples on different ticks, some late or not finite (ignored), and
    estimates large enough to be clipped: each row of the bank, and a vehicle's own
    EstimateCompensator, follow the straightforward formula."""
    rng = np.random.default_rng(4)
    m = 12
    bank = CompensatorBank(m, window_s=0.4, limit_m_s=1.0)
    alone = [EstimateCompensator(window_s=0.4, limit_m_s=1.0) for _ in range(m)]
    refs = [_deque_compensator(0.4, 1.0) for _ in range(m)]
    t = np.zeros(m)
    for k in range(600):
        rows = np.flatnonzero(rng.random(m) < 0.8)
        t[rows] += rng.uniform(0.01, 0.12, rows.size)
        tt = t[rows].copy()
        x, y = rng.normal(size=rows.size), rng.normal(size=rows.size)
        vx, vy = rng.normal(size=rows.size) * 2.0, rng.normal(size=rows.size)
        if k % 37 == 0 and rows.size:
            tt[0] -= 0.5  # older than that vehicle's last sample
            x[-1] = np.nan
        bank.add(rows, tt, x, y, vx, vy)
        for j, r in enumerate(rows.tolist()):
            sample = (float(tt[j]), float(x[j]), float(y[j]), float(vx[j]), float(vy[j]))
            refs[r][0](*sample)
            alone[r].add(*sample)
        for r in range(m):
            want = refs[r][1]
            got = (float(bank.dx_m_s[r]), float(bank.dy_m_s[r]))
            assert alone[r].correction == got
            assert got == pytest.approx(want["d"], rel=1e-9, abs=1e-12), (k, r)
            assert int(bank.clipped[r]) == want["clipped"]
    assert bank.clipped.sum() > 100 and (bank.max_m_s > 1.0).all()
    assert bank.max_m_s == pytest.approx([r[1]["max"] for r in refs], rel=1e-12)


def _inject(k: int, links, rng) -> None:
    """Faults on tick ``k``: vehicle 3 falls silent, 7 stops following, 11 leaves OFFBOARD,
    13 disarms; telemetry noise on everyone."""
    for i, link in enumerate(links):
        s = link.state
        if i == 11 and k == 30:
            s.flight_mode = "POSCTL"
        if i == 13 and k == 45:
            s.armed = False
        s.vn_m_s += 0.01 * rng.standard_normal()


@pytest.mark.parametrize("count", [40])
async def test_the_fleet_functions_fly_like_each_pilot_alone(count: int) -> None:
    t0 = 5000.0
    fleets = [memory_fleet(count, now_s=t0) for _ in range(2)]
    events: list[list[tuple[str, int | None, str]]] = [[], []]
    for (sup, _), ev in zip(fleets, events, strict=True):
        for p in sup.pilots:
            p.on_event = lambda text, vid, level, ev=ev: ev.append((text, vid, level))
        sup.pilots[20].begin_hold("a test")  # a stopped vehicle: an obstacle, a transition
    rngs = [np.random.default_rng(5), np.random.default_rng(5)]
    period = fleets[0][0].cfg.period_s
    now = t0
    jitter = np.random.default_rng(6)
    for k in range(160):
        now += period * (1.0 + 0.3 * jitter.random())
        listening = now - 1.0 if k == 60 else None  # a stall of our own loop once
        out = []
        for f, ((sup, links), rng) in enumerate(zip(fleets, rngs, strict=True)):
            pilots = sup.pilots
            if k > 10:  # vehicle 7 no longer follows its setpoints
                links[7].v_ned = (0.0, 0.0, links[7].v_ned[2])
            if k % 2 == 0:
                fly_telemetry([lk for i, lk in enumerate(links) if not (i == 3 and k > 20)],
                              2 * period, now)
            _inject(k, links, rng)
            if f == 0:
                sense_all(pilots, sup.frame)
            else:
                for p in pilots:
                    p.sense()
            if f == 0:
                check_faults_all(pilots, now, listening)
                fs = fleet_states(pilots, now, now + WALL)
                view = classify_arrays(fs.ids, fs.pos, fs.vel, fs.phases, fs.stamps_s,
                                       now + WALL, max_age_s=sup.cfg.neighbour_max_age_s,
                                       lost_after_s=math.inf)
            else:
                for p in pilots:
                    p.check_faults(now, listening)
                states = [s for p in pilots if (s := p.state(now, now + WALL)) is not None]
                view = classify(states, now + WALL, max_age_s=sup.cfg.neighbour_max_age_s,
                                lost_after_s=math.inf)
            flying = [p for p in pilots if p.phase == Phase.IN_TUBE and p.has_position()]
            index = {int(v): j for j, v in enumerate(view.ids())}
            cmd_pilots = [p for p in flying if p.vehicle_id in index]
            rows = [index[p.vehicle_id] for p in cmd_pilots]
            cmds = (fleet_setpoints(sup.plan, view.points(), rows) if rows
                    else np.zeros((0, 2)))
            if f == 0:
                actuate_all(pilots, now, cmd_pilots, cmds, view)
            else:
                by_id = dict(zip((p.vehicle_id for p in cmd_pilots), cmds, strict=True))
                for p in pilots:
                    p.actuate(now, by_id.get(p.vehicle_id), view)
            out.append((view, [lk.v_ned for lk in links], [p.phase for p in pilots],
                        [p.reason for p in pilots], [p._still_since for p in pilots],
                        [None if p.cmd_xy is None else tuple(p.cmd_xy) for p in pilots],
                        [p.cmd_in_tube for p in pilots], [p.setpoints_sent for p in pilots]))
        await asyncio.sleep(0)  # the hold's transition task
        a, b = out
        _view_equal(a[0], b[0])
        assert a[1:] == b[1:], f"tick {k}"
    assert events[0] == events[1]
    phases = out[0][2]
    assert phases[3] == phases[7] == phases[11] == phases[13] == Phase.LOST
    assert phases[20] == Phase.HOLDING
    assert sum(ph == Phase.IN_TUBE for ph in phases) == count - 5
    sup_a, sup_b = fleets[0][0], fleets[1][0]
    for pa, pb in zip(sup_a.pilots, sup_b.pilots, strict=True):
        np.testing.assert_allclose(pa.disturbance_residual_m_s, pb.disturbance_residual_m_s,
                                   rtol=1e-15, atol=1e-16)
    # the pilots of fleet 0 share the supervisor's tracker, those of fleet 1 each used
    # their own calls into it: every residual was tracked once
    assert sup_a.residuals.residuals().size == sup_b.residuals.residuals().size > 0


async def test_sense_all_feeds_compensators_of_their_own_like_each_pilot() -> None:
    """Pilots that are not one fleet's (each its own compensator): sense_all gives each its
    sample as its own sense() would."""
    fleets = [memory_fleet(6, now_s=100.0) for _ in range(2)]
    for sup, links in fleets:
        for k, (p, link) in enumerate(zip(sup.pilots, links, strict=True)):
            p.compensator = EstimateCompensator()
            link.v_ned = (1.0, 0.1 * k, 0.0)
    now = 100.0
    for _ in range(30):
        now += 0.05
        for f, (sup, links) in enumerate(fleets):
            fly_telemetry(links, 0.05, now)
            for link in links:
                link.state.vn_m_s += 0.3  # the estimate's velocity is off: d̂ ≈ 0.3 m/s
            if f == 0:
                assert sense_all(sup.pilots, sup.frame) == 6
            else:
                assert all(p.sense() for p in sup.pilots)
    got = [[p.compensator.correction for p in sup.pilots] for sup, _ in fleets]
    assert got[0] == got[1]
    assert all(abs(math.hypot(*d) - 0.3) < 0.05 for d in got[0])
    assert [p.xy.tolist() for p in fleets[0][0].pilots] == [p.xy.tolist()
                                                              for p in fleets[1][0].pilots]


def test_the_tables_phase_column_follows_the_agent_however_its_phase_is_set() -> None:
    """The fleet steps read phases from the table: a phase set on the agent directly (its
    public API) reaches the column as one set through the pilot does."""
    from vtube_fleet.fleet.table import PHASE_CODE

    sup, _ = memory_fleet(3, now_s=10.0)
    p0, p1, p2 = sup.pilots
    p0.set_phase(Phase.HOLDING, "through the pilot")
    p1.agent.set_phase(Phase.LOST)
    p2.agent.phase = Phase.EXITED
    assert sup.table.phase.tolist() == [PHASE_CODE[Phase.HOLDING], PHASE_CODE[Phase.LOST],
                                        PHASE_CODE[Phase.EXITED]]
    assert [p.phase for p in sup.pilots] == [Phase.HOLDING, Phase.LOST, Phase.EXITED]
