"""The control tick (fleet/tick.py): ONE implementation for one vehicle and for a thousand.

* the neighbour classification by its rule, on random tables;
* the fleet's compensation bank and residual tracker against straightforward per-vehicle
  references;
* an MQTT agent's tick (a table of one row, its neighbours from a bus) and the supervisor's
  (the whole fleet's table) send the same setpoints, bit for bit, through 160 ticks with faults
  (a vehicle that does not follow, one that leaves OFFBOARD, one disarmed, a stopped one, a
  stall of our own loop);
* a fault rule added in one place acts for every vehicle, of the fleet and of an agent.
"""

from __future__ import annotations

import asyncio
import math
from bisect import bisect_right
from collections import deque
from itertools import pairwise

import numpy as np
import pytest
from memory_fleet import MemoryLink, fly_telemetry, memory_fleet

from vtube_fleet.fleet.compensation import (
    RESIDUAL_WINDOW_S,
    CompensatorBank,
    ResidualTracker,
)
from vtube_fleet.fleet.neighbour_view import States, classify, states_of
from vtube_fleet.fleet.pilot import VehiclePilot
from vtube_fleet.fleet.supervisor import Supervisor
from vtube_fleet.fleet.table import PHASE_CODE, FleetTable
from vtube_fleet.fleet.tick import FAULT_RULES, Tick
from vtube_fleet.state import AIRBORNE_PHASES, STOPPED_PHASES, TUBE_PHASES, NeighbourState, Phase

WALL = 1.7e9  # wall clock = monotonic + WALL


def test_classify_sorts_every_state_by_the_rule() -> None:
    """Random tables (phases, ages, NaN positions, a stall, per-state silence limits): each id
    lands in the bucket the rule names, at its own position, sorted by id."""
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
        limit = np.where(rng.random(n) < 0.3, math.inf, 1.5)
        view = classify(states_of(states), now, max_age_s=0.5, lost_after_s=limit,
                        heard_since_s=heard)
        want: dict[str, list[NeighbourState]] = {"live": [], "static": [], "lost": []}
        for st, lim in zip(states, limit.tolist(), strict=True):
            if not math.isfinite(st.x_m):
                continue
            age = now - st.stamp_s
            silence = age if heard is None else min(age, now - heard)
            if st.phase == Phase.LOST or st.phase in STOPPED_PHASES:
                want["lost"].append(st)
            elif st.phase in AIRBORNE_PHASES:
                which = "lost" if silence > lim else "static" if age > 0.5 else "live"
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
    estimates large enough to be clipped: each row of the bank, and a vehicle's own bank of one
    row, follow the straightforward formula."""
    rng = np.random.default_rng(4)
    m = 12
    bank = CompensatorBank(m, window_s=0.4, limit_m_s=1.0)
    alone = [CompensatorBank(1, window_s=0.4, limit_m_s=1.0) for _ in range(m)]
    zero = np.zeros(1, np.int64)
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
            alone[r].add(zero, *(np.array([v]) for v in sample))
        for r in range(m):
            want = refs[r][1]
            got = (float(bank.dx_m_s[r]), float(bank.dy_m_s[r]))
            assert (float(alone[r].dx_m_s[0]), float(alone[r].dy_m_s[0])) == got
            assert got == pytest.approx(want["d"], rel=1e-9, abs=1e-12), (k, r)
            assert int(bank.clipped[r]) == want["clipped"]
    assert bank.clipped.sum() > 100 and (bank.max_m_s > 1.0).all()
    assert bank.max_m_s == pytest.approx([r[1]["max"] for r in refs], rel=1e-12)


class _Bus:
    """A perfect bus for the agents: the other vehicles' states as the fleet's tick computed
    them this tick (what each agent would have published)."""

    def __init__(self, own: int) -> None:
        self.own = own
        self.fleet: States = States.empty()
        #: the waiting teammates' status stages: id → times released without a path
        self.waiting: dict[int, int] = {}

    def states(self, now_wall: float) -> States:
        keep = self.fleet.ids != self.own
        f = self.fleet
        return States(f.ids[keep], f.pos[keep], f.vel[keep], f.phase[keep], f.stamps_s[keep])

    def problem(self, now_wall: float) -> str | None:
        return None

    def tube_stages(self, now_wall: float) -> tuple[bool, dict[int, int]]:
        """Every teammate's state is heard here, so only the waiting stages add anything."""
        return False, {i: k for i, k in self.waiting.items() if i != self.own}


def _agents(sup, count: int, t0: float):
    """One agent per vehicle: a one-row table, a pilot, a tick with the bus; their links are
    in-memory copies of the fleet's (same state, their own setpoints)."""
    agents = []
    for i, fleet_link in enumerate(sup.pilots):
        link = MemoryLink(fleet_link.link.endpoint.url, i % 255 + 1)
        link.state = fleet_link.link.state.copy()
        tab = FleetTable([i], sup.mission)
        tab.takeoff_xy[0] = sup.table.takeoff_xy[i]
        pilot = VehiclePilot(link, tab, 0, sup.mission)
        pilot.set_phase(sup.pilots[i].phase)
        bus = _Bus(i)

        def hold(exc, view, pilot=pilot) -> None:  # as the supervisor's abort does
            if pilot.phase in TUBE_PHASES | {Phase.EXITED}:
                pilot.reason = pilot.reason or f"mission aborted: {exc}"
                pilot.begin_hold("mission aborted")

        tick = Tick(tab, [pilot], sup.mission, sup.plan, neighbours=bus, publish=lambda m: None,
                    on_replan_failed=hold, t0_s=sup.t0)
        agents.append((tick, pilot, link, bus))
    return agents


def _why(reason: str | None) -> str | None:
    """A reason to compare: the supervisor's abort names the other vehicles' reasons too."""
    return "mission aborted" if reason and reason.startswith("mission aborted") else reason


def _inject(k: int, links) -> None:
    """Faults on tick ``k``: 9 disarms, 1 leaves OFFBOARD; 7 no longer follows (below)."""
    for i, link in enumerate(links):
        s = link.state
        if i == 9 and k == 20:
            s.armed = False
        if i == 1 and k == 40:
            s.flight_mode = "POSCTL"


async def test_an_agents_one_row_tick_sends_what_the_fleet_tick_sends() -> None:
    """The same vehicles, the same telemetry: the supervisor's tick over its fleet table, and
    one agent per vehicle running the same tick over a table of one row with the others'
    states from a bus: the same setpoints, commands, phases and reasons, bit for bit, through
    every fault rule, the re-partitions around them, the vehicles they trap (which wait), and
    once the tube can no longer be re-partitioned, those that fly partitions of their own,
    the releases one at a time and the landings of those with no way out."""
    count, t0 = 10, 5000.0
    sup, links = memory_fleet(count, now_s=t0, spacing_m=6.0)
    agents = _agents(sup, count, t0)
    sup.pilots[4].begin_hold("a test")  # a stopped vehicle: an obstacle, a transition
    agents[4][1].begin_hold("a test")
    a_links = [a[2] for a in agents]
    period = sup.cfg.period_s
    now = t0
    jitter = np.random.default_rng(6)
    waited: set[int] = set()
    flew_own: set[int] = set()
    apart = False
    for k in range(160):
        now += period * (1.0 + 0.3 * jitter.random())
        listening = now - 1.0 if k == 60 else None  # a stall of our own loop once
        for world in (links, a_links):
            if k > 10:  # vehicle 7 no longer follows its setpoints
                world[7].v_ned = (0.0, 0.0, world[7].v_ned[2])
            if k % 2 == 0:
                fly_telemetry(world, 2 * period, now)
            _inject(k, world)
        fleet = sup.ticker(now, now + WALL, listening)
        stages = {i: int(a[0].table.step_tries[0]) for i, a in enumerate(agents)
                  if a[1].phase == Phase.WAITING}  # (as the agents announced them)
        for tick, _pilot, _link, bus in agents:
            bus.fleet, bus.waiting = fleet.states, stages
            tick(now, now + WALL, listening)
        await asyncio.sleep(0)  # the hold's transition task
        waited |= {i for i, x in enumerate(sup.pilots) if x.phase == Phase.WAITING}
        if sup.ticker.apart is not None:
            apart = True
            flew_own |= set(sup.ticker.own_plans)
        assert [lk.v_ned for lk in links] == [lk.v_ned for lk in a_links], f"tick {k}"
        assert [p.phase for p in sup.pilots] == [a[1].phase for a in agents], k
        assert [_why(p.reason) for p in sup.pilots] == [_why(a[1].reason) for a in agents], k
        got = [None if p.cmd_xy is None else p.cmd_xy.tobytes() for p in sup.pilots]
        assert got == [None if a[1].cmd_xy is None else a[1].cmd_xy.tobytes()
                       for a in agents], k
    p = sup.pilots
    assert p[4].phase == Phase.HOLDING and sup.partitions >= 3
    assert p[9].phase == Phase.LOST and p[9].reason == "disarmed in the air"
    assert p[1].phase == Phase.LOST and p[1].reason.startswith("left OFFBOARD unexpectedly")
    assert p[7].phase == Phase.LOST and p[7].reason.startswith("not following its setpoints")
    # the vehicles the re-partitions trapped waited; the tube then could no longer be
    # re-partitioned: those past the stopped ones flew partitions of their own, the waiting
    # ones were released one at a time, found no way into a sub-tube (twice) and landed
    assert apart and flew_own
    assert waited and all(p[i].phase == Phase.LANDING for i in waited)
    assert all(p[i].phase in (Phase.IN_TUBE, Phase.EXITED) for i in flew_own)
    res = sup.table.residuals.residuals()
    assert res.size == sum(a[1].table.residuals.residuals().size for a in agents) > 0


#: nine vehicles in three rows 3 to 12 m before the bend of a route of two segments (14 m, a
#: 60° bend to the left, 20 m)
ROUTE_SLOTS = [[x, y] for x in (2.0, 6.5, 11.0) for y in (-4.5, 0.0, 4.5)]


async def test_a_route_is_flown_alike_by_the_fleet_and_by_its_agents() -> None:
    """A route (two segments, a 60° bend): the supervisor's tick over its fleet and one agent
    per vehicle over a table of one row hand over at the same tick and send the same
    setpoints, bit for bit, until every vehicle flies the second segment; each vehicle's
    segment only ever goes forward (S1 → S2), its commands stay in [v_min, v_max], and none
    exits before the LAST finishing line."""
    from missions import route_mission

    count, t0 = len(ROUTE_SLOTS), 7000.0
    sup, links = memory_fleet(count, now_s=t0, text=route_mission(14.0, 60.0, 20.0,
                                                                  ROUTE_SLOTS))
    assert sup.plan.route.S == 2
    agents = _agents(sup, count, t0)
    a_links = [a[2] for a in agents]
    period = sup.cfg.period_s
    flown = sup.plan.flown
    now = t0
    jitter = np.random.default_rng(8)
    segs = []
    for k in range(700):
        now += period * (1.0 + 0.3 * jitter.random())
        for world in (links, a_links):
            if k % 2 == 0:
                fly_telemetry(world, 2 * period, now)
        fleet = sup.ticker(now, now + WALL)
        for tick, _pilot, _link, bus in agents:
            bus.fleet = fleet.states
            tick(now, now + WALL)
        await asyncio.sleep(0)
        assert [lk.v_ned for lk in links] == [lk.v_ned for lk in a_links], f"tick {k}"
        seg = sup.table.segment.copy()
        assert seg.tolist() == [int(a[1].table.segment[0]) for a in agents], f"tick {k}"
        segs.append(seg)
        cmd = [p.cmd_xy for p in sup.pilots if p.cmd_in_tube]
        speed = np.hypot(*np.array(cmd).T) if cmd else np.zeros(0)
        assert (speed >= flown.v_min - 1e-9).all() and (speed <= flown.v_max + 1e-9).all()
        if (seg == 1).all():
            break
    segs = np.array(segs)
    assert (segs[-1] == 1).all(), f"not every vehicle reached S2: {segs[-1].tolist()}"
    assert (np.diff(segs, axis=0) >= 0).all() and set(np.unique(segs)) == {0, 1}
    # each starts in the segment its slot lies in (the three slots deep in S2's prolonged
    # start, 4.5 m left of the axis or 3 m from the waypoint, start in S2)
    start = sup.plan.route.start_segments(np.array(ROUTE_SLOTS))
    assert segs[0].tolist() == start.tolist() and 0 < start.sum() < count
    assert all(p.phase == Phase.IN_TUBE for p in sup.pilots)  # not exited at the junction
    handed = [int(np.argmax(segs[:, i] == 1)) for i in range(count)]
    assert len(set(handed)) > 1  # each at its own tick, where its position says


async def test_each_fault_rule_finds_its_vehicle() -> None:
    """One tick, many faults at once: every rule finds its vehicle, each takes the first rule
    it hits; a vehicle arming FAILS instead; holding vehicles on the ground are LANDED."""
    sup, links = memory_fleet(12, now_s=100.0)
    p = sup.pilots
    for i in (6, 7, 8, 9):
        sup.table.offboard_seen[i] = True  # confirmed once, as in flight
    p[1].set_phase(Phase.ARMING)
    p[2].set_phase(Phase.HOLDING)
    s = [lk.state for lk in links]
    s[0].last_position_s = 98.0  # silent for 2 s > lost_after_s
    s[1].last_position_s = 98.0  # … while arming: failed
    s[2].landed_state, s[2].armed = "ON_GROUND", False  # holding, touched down
    s[6].flight_mode = "POSCTL"  # left OFFBOARD
    s[7].armed = False  # disarmed in the air
    s[8].flight_mode, s[8].armed = "POSCTL", False  # both: the first rule wins
    now = 100.05
    sup.ticker(now, now + WALL)
    phases = [x.phase for x in p]
    assert phases[:3] == [Phase.LOST, Phase.FAILED, Phase.LANDED]
    assert [phases[i] for i in (6, 7, 8)] == [Phase.LOST] * 3
    assert p[0].reason.startswith("no telemetry for more than lost_after_s = 1 s")
    assert p[1].reason.startswith("no telemetry")
    assert p[6].reason.startswith("left OFFBOARD unexpectedly (mode POSCTL")
    assert p[7].reason == "disarmed in the air"
    assert p[8].reason.startswith("left OFFBOARD")
    # no rule for the others (they hold: the losses near the start cannot be re-planned)
    assert not any(x.phase in (Phase.LOST, Phase.FAILED, Phase.LANDED)
                   for x in [p[3], p[4], p[5], *p[9:]])


async def test_a_fault_rule_added_in_one_place_acts_for_every_vehicle() -> None:
    """One rule of the tick's rules (FAULT_RULES' last: a battery below the mission's
    ``battery_reserve_pct``, action "land"): every vehicle of a 12-vehicle fleet that hits it
    and an agent's one vehicle act on it alike (here: land, an obstacle for the others)."""
    assert FAULT_RULES[-1].name == "battery_low" and FAULT_RULES[-1].action == "land"
    sup, links = memory_fleet(12, now_s=100.0)
    assert sup.cfg.battery_reserve_pct == 20.0
    agents = _agents(sup, 12, 100.0)
    low = {2, 5, 6, 11}
    for world in (links, [a[2] for a in agents]):
        for i, link in enumerate(world):
            link.state.battery_remaining = 0.1 if i in low else 0.9
    now = 100.05
    fleet = sup.ticker(now, now + WALL)
    for tick, _pilot, _link, bus in agents:
        bus.fleet = fleet.states
        tick(now, now + WALL)
    for group in (sup.pilots, [a[1] for a in agents]):
        landing = {p.vehicle_id for p in group if p.phase == Phase.LANDING}
        assert low == landing  # (those they trap, inside the new partition's region, wait)
        assert all(p.reason.startswith("battery 10 % < battery_reserve_pct = 20 %: lands")
                   for p in group if p.vehicle_id in low)
    assert ({p.vehicle_id for p in sup.pilots if p.phase == Phase.LANDING}
            == {a[1].vehicle_id for a in agents if a[1].phase == Phase.LANDING})
    await asyncio.sleep(0)
    # the next tick: the landing vehicles are obstacles (stopped) for the others
    now += 0.05
    fleet = sup.ticker(now, now + WALL)
    assert fleet.view is not None and low <= set(fleet.view.lost_ids.tolist())
    assert (sup.table.phase == PHASE_CODE[Phase.LANDING]).sum() >= len(low)


async def test_a_re_partition_is_planned_off_the_control_loop() -> None:
    """With a worker (the supervisor and the agents): the tick that first sees a stopped
    vehicle does not plan (the control loop goes on with the current plan, the stopped one a
    point of the pair barrier); a tick after the worker is done adopts the plan, and stops
    the vehicles it traps (they wait): the same outcome as planning in the tick itself."""
    from concurrent.futures import ThreadPoolExecutor

    low = {2, 5}

    def fleet():
        sup, links = memory_fleet(12, now_s=100.0)
        for i, link in enumerate(links):
            link.state.battery_remaining = 0.1 if i in low else 0.9
        return sup

    now = 100.05
    sup = fleet()
    worker = ThreadPoolExecutor(1)
    sup.ticker.replan_worker = worker
    replans: list[float] = []
    sup.ticker.on_replan = lambda plan, t: replans.append(t)
    try:
        sup.ticker(now, now + WALL)  # the low ones land: stopped, not yet a plan's obstacle
        sup.ticker(now + 0.05, now + 0.05 + WALL)  # the re-partition is handed to the worker
        assert sup.ticker.plan is sup.ticker.root and not replans
        assert {p.vehicle_id for p in sup.pilots if p.phase == Phase.LANDING} == low
        worker.submit(lambda: None).result()  # the worker is done with what it was given
        sup.ticker(now + 0.10, now + 0.10 + WALL)
        assert len(replans) == 1 and sup.ticker.plan is not sup.ticker.root
    finally:
        worker.shutdown()
    # planned in the tick (after: the plans share their cache): the same vehicles land
    inline = fleet()
    inline.ticker(now, now + WALL)
    inline.ticker(now + 0.05, now + 0.05 + WALL)
    want = {p.vehicle_id for p in inline.pilots if p.phase == Phase.WAITING}
    assert want and inline.ticker.plan is not inline.ticker.root
    assert {p.vehicle_id for p in sup.pilots if p.phase == Phase.WAITING} == want


async def test_airborne_pairs_count_from_the_take_off_on() -> None:
    """``min_pair_distance_airborne_m`` takes every airborne pair from the take-off on (docs/
    fleet.md, summary keys), not only once the tube has started."""
    sup, _links = memory_fleet(4, phase="takeoff", spacing_m=5.0, now_s=100.0)
    assert sup.tube_start_s is None
    sup._step(100.05, 100.05 + WALL, None)
    got = sup.summary()["min_pair_distance_airborne_m"]
    assert got is not None and got == pytest.approx(5.0, abs=0.01)


def test_the_coordinators_airborne_pairs_count_from_the_take_off_on() -> None:
    """The MQTT coordinator's judge (RunMonitor) takes airborne pairs from the take-off on
    too, as ``run`` does: three vehicles climbing 4 m apart, no tube started yet."""
    import tempfile
    from pathlib import Path

    from missions import COMPACT_12, write_mission

    from vtube_fleet.fleet.distributed.monitor import RunMonitor

    with tempfile.TemporaryDirectory() as tmp:
        mission = write_mission(Path(tmp), COMPACT_12)
    mon = RunMonitor(mission, 3)
    states = {i: NeighbourState(i, 4.0 * i, 0.0, 0.0, 0.0, Phase.TAKEOFF, 10.0, 1)
              for i in range(3)}
    mon.sample(states, 10.05)
    assert mon.tube_start_s is None and mon.min_pair_airborne == pytest.approx(4.0)


async def test_a_vehicle_past_the_stopped_ones_flies_on_with_a_partition_of_its_own() -> None:
    """Vehicles 2 and 5 land (low battery) and become obstacles; the common re-partition
    takes vehicle 6, beside vehicle 5 and past vehicle 2, into its region. Vehicle 6 has
    passed vehicle 2's O' (and every command moves it forward), so it is given a partition
    without it (FlightPlan.past) and flies on to the finishing line instead of landing:
    every command in [v_min, v_max], never within r_o + r_s of a stopped vehicle (the
    physical radii). Vehicle 1, right behind vehicle 2, passed nothing: it waits; once
    nobody flies the tube behind it or within reach (those ahead only move away) it steps
    aside into a sub-tube and flies on to the finishing line too, as far from the stopped
    ones."""
    sup, links = memory_fleet(12, now_s=100.0)
    low = {2, 5}
    for i, link in enumerate(links):
        link.state.battery_remaining = 0.1 if i in low else 0.9
    p6 = sup.pilots[6]
    sc = sup.mission.scenario
    radius = sc.controller.r_s + sup.cfg.lost_obstacle_margin_m + sc.controller.r_s
    period, now = sup.cfg.period_s, 100.0
    own_seen, speeds = False, []
    paths: dict[int, list[np.ndarray]] = {1: [], 6: []}
    stopped: dict[int, np.ndarray] = {}
    p1 = sup.pilots[1]
    phases1: list[Phase] = []
    stepped_with_others = False
    flying = (Phase.IN_TUBE, Phase.EXITED, Phase.WAITING, Phase.STEPPING)
    for _ in range(6000):  # (the tube is 104 m long)
        now += period
        for i, p in enumerate(sup.pilots):
            if p.phase not in flying:  # PX4 holds, then lands
                links[i].v_ned = (0.0, 0.0, 0.0)
                stopped.setdefault(i, sup.table.xy[i].copy())
        fly_telemetry(links, period, now)
        sup.ticker(now, now + WALL)
        await asyncio.sleep(0)
        own_seen |= 6 in sup.ticker.own_plans
        if not phases1 or phases1[-1] != p1.phase:
            phases1.append(p1.phase)
        if p1.phase == Phase.WAITING:  # (an obstacle for 6 meanwhile)
            stopped.setdefault(1, sup.table.xy[1].copy())
        for i in (1, 6):
            if sup.pilots[i].phase in (Phase.IN_TUBE, Phase.STEPPING):
                paths[i].append(sup.table.xy[i].copy())
        if p6.phase == Phase.IN_TUBE and p6.cmd_xy is not None:
            speeds.append(float(np.hypot(*p6.cmd_xy)))
        if p1.phase not in (Phase.IN_TUBE, Phase.WAITING, Phase.STEPPING):
            break
        if p1.phase == Phase.STEPPING:  # everyone still flying the tube is ahead, out of reach
            xi = sup.plan.route.xi(sup.table.xy, np.zeros(12, np.intp))
            ahead = [xi[i] - xi[1] for i, q in enumerate(sup.pilots) if q.phase == Phase.IN_TUBE]
            assert all(d > sup.plan.neighbour_radius_m for d in ahead), ahead
            stepped_with_others |= bool(ahead)
    # (6 exited, then held before the fence's exit while 1 was still in the tube)
    assert own_seen and p6.exit_time_s is not None, (p6.phase, p6.reason)
    assert not p6.reason or "cannot pass" not in p6.reason
    assert any(e["vehicle"] == p6.vehicle_id and "flies on with a partition of its own" in
               e["text"] and "past the obstacle(s) at (1.5, 2.5)" in e["text"]
               for e in sup.events)
    # vehicle 1 waited until every other vehicle had left the tube, then stepped aside
    assert phases1 == [Phase.WAITING, Phase.STEPPING, Phase.IN_TUBE, Phase.EXITED], (
        phases1, p1.reason)
    assert stepped_with_others  # (released while those ahead still flew the tube)
    assert all(p.phase not in (Phase.IN_TUBE, Phase.WAITING, Phase.STEPPING)
               for p in sup.pilots)
    assert any(e["vehicle"] == 1 and e["text"].startswith("steps aside") for e in sup.events)
    assert not p1.reason
    for v in (1, 6):
        path_a = np.array(paths[v])
        for i in (2, 5) if v == 1 else (1, 2, 5):
            assert float(np.min(np.hypot(*(path_a - stopped[i]).T))) > radius, (v, i)
    assert sc.controller.v_min - 1e-9 <= min(speeds) and max(speeds) <= sc.controller.v_max


async def test_the_control_clock_switches_threads_often_while_it_runs() -> None:
    """While a control clock runs, the interpreter switches threads every GIL_SWITCH_S (the
    re-partition worker must not hold the loop back: bench/bench_gil.py); two clocks in one
    process (agents in a test) keep it until the last one ends; then it is restored."""
    import sys

    from vtube_fleet.fleet.tick import GIL_SWITCH_S, ControlClock

    before = sys.getswitchinterval()
    assert before > GIL_SWITCH_S
    seen: dict[str, list[float]] = {"a": [], "b": []}
    stops = {"a": asyncio.Event(), "b": asyncio.Event()}

    def step_of(name: str, ticks: int):
        def step(now_mono: float, now_wall: float, listening: float | None) -> None:
            seen[name].append(sys.getswitchinterval())
            if len(seen[name]) >= ticks:
                stops[name].set()
        return step

    a = asyncio.create_task(ControlClock(0.01, step_of("a", 12)).run(stops["a"]))
    await ControlClock(0.01, step_of("b", 3)).run(stops["b"])  # ends first
    await a
    assert len(seen["a"]) == 12 and len(seen["b"]) == 3
    assert all(x == pytest.approx(GIL_SWITCH_S) for x in seen["a"] + seen["b"])
    assert sys.getswitchinterval() == before


async def test_a_plan_of_its_own_is_planned_again_when_the_stopped_ones_return_to_an_earlier_set(
        ) -> None:
    """With the worker and ``on_trapped = "land"``: vehicles 2 and 5 land, vehicle 1
    (trapped) lands too, vehicle 6 flies
    a partition of its own. When vehicle 1 touches down it is no longer an obstacle and the
    set of stopped vehicles is {2, 5} again, whose common plan is cached: vehicle 6's own
    plan is planned again from where it is, and it flies on (it was landed when the cached
    plan came back alone)."""
    from concurrent.futures import ThreadPoolExecutor

    sup, links = memory_fleet(12, now_s=100.0, mission_keys='on_trapped = "land"\n')
    for i, link in enumerate(links):
        link.state.battery_remaining = 0.1 if i in (2, 5) else 0.9
    worker = ThreadPoolExecutor(1)
    sup.ticker.replan_worker = worker
    now = 100.0
    plans = []
    sup.ticker.on_replan = lambda plan, t: plans.append(plan)

    async def step() -> None:
        nonlocal now
        now += 0.05
        sup.ticker(now, now + WALL)
        await asyncio.sleep(0)
        worker.submit(lambda: None).result()  # the worker is done with what it was given

    try:
        for _ in range(6):
            await step()
        assert sup.pilots[1].phase == Phase.LANDING and 6 in sup.ticker.own_plans
        assert len(plans) == 2  # around {2, 5}, then around {2, 5, 1}
        links[1].state.landed_state, links[1].state.armed = "ON_GROUND", False
        for _ in range(6):
            await step()
        assert sup.pilots[1].phase == Phase.LANDED
        assert len(plans) == 3 and plans[2] is plans[0]  # {2, 5} again: the cached plan
        assert sup.pilots[6].phase == Phase.IN_TUBE and 6 in sup.ticker.own_plans
    finally:
        worker.shutdown()


async def _two_stop(phase: str = "tube") -> tuple[Supervisor, float]:
    """The 12-vehicle fleet of these tests (``phase``: in the tube or climbing) after three
    ticks in which vehicles 2 and 5 land for a low battery and the tube is re-partitioned
    around them (in the tick): (the supervisor, the time of the last tick)."""
    sup, links = memory_fleet(12, phase=phase, now_s=100.0)
    for i, link in enumerate(links):
        link.state.battery_remaining = 0.1 if i in (2, 5) else 0.9
    now = 100.0
    for _ in range(3):
        now += 0.05
        sup.ticker(now, now + WALL)
        await asyncio.sleep(0)
    return sup, now


async def test_a_stopped_vehicle_moving_within_its_obstacle_keeps_the_plan_flown(
        monkeypatch) -> None:
    """The fleet above re-partitioned around vehicles 2 and 5 (landing) and 1 (waiting);
    then vehicle 2 drifts and the re-partition around where it is now fails (THE FAULT).
    While it has moved less than its obstacle's margin (radius − r_s) the plan flown still
    holds its body: everyone flies on as before, nobody waits. Once it has moved farther, there is
    no common partition: the vehicles fly apart (on_trapped = "wait")."""
    from vtube_fleet.core.partition import PartitionError
    from vtube_fleet.fleet.flight_plan import FlightPlan

    sup, now = await _two_stop()
    plan = sup.ticker.plan
    assert len(plan.lost) == 3 and sup.ticker.apart is None  # (2, 5 and 1, waiting)
    phases = [p.phase for p in sup.pilots]
    tried = []

    def fails(self, lost):  # THE FAULT: no partition around the vehicles where they are now
        tried.append(len(lost))
        raise PartitionError(0, "a test")

    monkeypatch.setattr(FlightPlan, "with_lost", fails)
    margin = sup.mission.config.lost_obstacle_margin_m
    links = [p.link for p in sup.pilots]
    start = links[2].state.north_m
    for moved, holds in ((0.6 * margin, True), (1.4 * margin, False)):
        links[2].state.north_m = start + moved
        for _ in range(2):
            now += 0.05
            for link in links:
                link.state.last_position_s = now
            sup.ticker(now, now + WALL)
            await asyncio.sleep(0)
        assert tried, "no re-partition was tried"
        if holds:
            assert sup.ticker.plan is plan and sup.ticker.apart is None
            assert [p.phase for p in sup.pilots] == phases
        else:
            assert sup.ticker.apart is not None
        tried.clear()


async def test_a_climbing_vehicle_gets_no_plan_of_its_own() -> None:
    """The same fleet as above, still climbing: vehicle 6 is trapped as before, but a climbing
    vehicle flies towards its take-off spot (which may lie behind it along n_c), so nothing it
    has passed may be left out: it lands."""
    sup, now = await _two_stop(phase="takeoff")
    assert not sup.ticker.own_plans
    assert sup.pilots[6].phase == Phase.LANDING
    assert sup.pilots[6].reason.startswith("cannot pass the stopped vehicle")


async def test_a_vehicle_flying_its_own_plan_lands_when_its_residual_exceeds_D(
        monkeypatch) -> None:
    """Vehicle 6 flies a partition of its own (the first test's fleet); then its estimate
    compensation's residual exceeds the budget's D (the residual watch): it may no longer
    advance along n_c, so it lands, and says why."""
    import dataclasses as dc

    import vtube_fleet.fleet.tick as tick_module

    sup, now = await _two_stop()
    assert 6 in sup.ticker.own_plans and sup.pilots[6].phase == Phase.IN_TUBE
    real = tick_module.actuate

    def residual_of_6(*a, **k):  # THE FAULT: vehicle 6's residual crosses D
        return dc.replace(real(*a, **k), residual_over=np.array([6]))

    monkeypatch.setattr(tick_module, "actuate", residual_of_6)
    now += 0.05
    sup.ticker(now, now + WALL)
    await asyncio.sleep(0)
    assert 6 not in sup.ticker.own_plans and sup.pilots[6].phase == Phase.LANDING
    assert "flying a partition of its own, its estimate compensation's residual exceeds " \
           "disturbance_residual_m_s" in sup.pilots[6].reason


async def test_an_agent_releases_its_waiting_vehicle_only_when_the_fleet_lets_it() -> None:
    """An agent's waiting vehicle (one row; the others heard on its bus, all past the tube)
    is released only when its bus's fleet-wide statuses (``tube_stages``: states reach only
    nearby cells) say nobody else flies the tube, and — not hearing the others' states —
    only if it has the smallest id of those released as few times before; released, it
    steps aside (here 0 m: nothing stopped is left)."""
    sup, _links = memory_fleet(4, now_s=100.0)
    tick, pilot, _link, bus = _agents(sup, 4, 100.0)[1]
    pilot.set_phase(Phase.WAITING)
    others = sup.ticker(100.05, 100.05 + WALL).states
    bus.fleet = States(others.ids, others.pos, others.vel,
                       np.full(len(others), PHASE_CODE[Phase.EXITED], np.int8),
                       others.stamps_s)
    stages = {"now": (True, {})}
    bus.tube_stages = lambda now_wall: stages["now"]
    now = 100.1
    for want, stage in ((Phase.WAITING, (True, {})),  # someone out of earshot flies
                        (Phase.WAITING, (False, {0: 0})),  # vehicle 0 waits too: first
                        (Phase.STEPPING, (False, {0: 1, 3: 1}))):  # both released before
        stages["now"] = stage
        tick(now, now + WALL)
        now += 0.05
        assert pilot.phase == want, stage
    # the plan without it (here: nobody stopped) is flown: it is inside a sub-tube already
    tick(now, now + WALL)
    assert pilot.phase == Phase.IN_TUBE


async def test_a_released_vehicle_without_a_path_waits_again_once_then_lands(
        monkeypatch) -> None:
    """Released, a vehicle finds no path to step aside on (THE FAULT: the plan has none):
    while others wait too it waits again (they may leave the way free; its agent would say
    ``waiting again``), once; the second time, or when nobody else waits, it lands and says
    why."""
    from vtube_fleet.fleet.flight_plan import FlightPlan

    monkeypatch.setattr(FlightPlan, "step_aside", lambda self, p, segment=-1, **_: None)
    sup, _links = memory_fleet(3, now_s=100.0)
    tick, pilot = sup.ticker, sup.pilots[1]
    for others_wait, want, tries in ((True, Phase.WAITING, 1), (True, Phase.LANDING, 1)):
        pilot.set_phase(Phase.WAITING)
        pilot.begin_step("a test")
        tick._step_point(1, others_wait=others_wait)
        assert pilot.phase == want and sup.table.step_tries[1] == tries
    assert pilot.reason.startswith("cannot step aside from")
    sup2, _ = memory_fleet(3, now_s=100.0)
    sup2.pilots[1].set_phase(Phase.WAITING)
    sup2.pilots[1].begin_step("a test")
    sup2.ticker._step_point(1, others_wait=False)  # nobody else waits: it lands at once
    assert sup2.pilots[1].phase == Phase.LANDING and sup2.table.step_tries[1] == 0


def test_with_no_common_partition_each_vehicle_gets_one_of_its_own_or_none(tmp_path) -> None:
    """A lost vehicle across a 3 m wide tube blocks it: no common partition. With
    ``apart`` (on_trapped = "wait") the re-plan job says so with the plans of their own: the
    vehicle past the lost one has one (the lost one left out), whichever its phase (one
    stepping aside may still be inside a region of it); the one behind it, which passed
    nothing, has none. Without ``apart`` it is the plain partition error (the abort)."""
    from missions import straight_mission

    from vtube_fleet.config.mission import load_mission
    from vtube_fleet.core.partition import PartitionError, h_min
    from vtube_fleet.core.tube import Obstacle
    from vtube_fleet.fleet.flight_plan import LOST_APEX_FACTOR, FlightPlan
    from vtube_fleet.fleet.tick import NoCommonPartition, replan_job

    path = tmp_path / "narrow.toml"
    path.write_text(straight_mission(26.0, [[8.0, 0.0], [2.0, 0.0]], heading_deg=90.0)
                    .replace(", 10.0]", ", 1.5]").replace(", -10.0]", ", -1.5]"))
    mission = load_mission(path)
    root = FlightPlan.for_mission(mission, mission.scenario.controller)
    r = mission.scenario.controller.r_s + mission.config.lost_obstacle_margin_m
    lost = (Obstacle(np.array([12.0, 0.0]), r, LOST_APEX_FACTOR * h_min(r, root.flown)),)
    rows, xy, seg = np.array([3, 5]), np.array([[6.0, 0.0], [16.0, 0.5]]), np.array([0, 0])
    for stepping in (np.array([False, True]), np.array([False, False])):
        with pytest.raises(NoCommonPartition) as info:
            replan_job(root, lost, rows, xy, seg, 0.0, stepping, apart=True)
        own = info.value.own
        assert set(own) == {5}, own
        plan, left_out = own[5]
        np.testing.assert_allclose(left_out, [[12.0, 0.0]])
        assert not plan.cannot_pass(xy[1:], seg[1:])[0]  # outside every region of its own
        assert "blocks the tube" in str(info.value)
    with pytest.raises(PartitionError) as info:
        replan_job(root, lost, rows, xy, seg, 0.0, np.array([False, False]), apart=False)
    assert not isinstance(info.value, NoCommonPartition)


def test_the_exit_room_is_checked_for_a_one_lane_queue() -> None:
    """With ``after_exit = "continue"`` the exit area must hold the rest of the fleet in one
    lane (a loss that leaves one passage sends them all there), each a stopping distance
    behind the one ahead, the tail out of reach of the finishing line: exit_queue counts how
    many fit and what exit_clear_m holds them; the supervisor warns before arming when they
    do not fit, and not when they do."""
    import dataclasses as dc
    from pathlib import Path

    from vtube_fleet.fleet.flight_plan import exit_queue, exit_stop_m

    text = (Path(__file__).resolve().parents[1] / "configs" / "mock_fleet.toml").read_text()
    sup, _ = memory_fleet(12, now_s=100.0, text=text)
    cfg, plan = sup.cfg, sup.ticker.plan
    assert cfg.after_exit == "continue" and cfg.exit_clear_m == 25.0
    stop = exit_stop_m(plan, cfg)
    reach = sup.ticker.lost_radius_m + plan.flown.r_s
    length = plan.route.segments[-1].tube.length
    fits, need_m, stop_m = exit_queue(plan, cfg, sup.ticker.lost_radius_m, 11)
    # the k-th vehicle (1-based) holds L + exit_clear_m − k·stop past the line
    assert fits == math.floor((length + cfg.exit_clear_m - reach) / stop)
    assert need_m == pytest.approx(11 * stop + reach - length)
    assert fits >= 11 and need_m <= 25.0  # (the shipped mission holds them)
    assert stop_m == stop
    assert exit_queue(plan, dc.replace(cfg, exit_clear_m=need_m + 1e-6),
                      sup.ticker.lost_radius_m, 11)[0] >= 11
    for clear_m, warned in ((0.0, True), (need_m + 0.1, False)):
        sup.cfg = dc.replace(cfg, exit_clear_m=clear_m)
        sup.events.clear()
        sup._warn_exit_room(plan)
        said = [e["text"] for e in sup.events if e["text"].startswith("exit room:")]
        assert bool(said) == warned, (clear_m, said)
        if warned:
            assert f"exit_clear_m = {math.ceil(need_m)} m holds them" in said[0], said
