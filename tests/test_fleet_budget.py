"""The safety budget's parts, pure: the mission's budget from a measurement, the refusals, the
in-flight watch, and the estimate-disturbance compensation against the mock's own dynamics and
PX4 SITL-like estimate errors (no sockets)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from missions import COMPACT_12, write_mission

from sim_stub.dynamics import QuadState
from sim_stub.estimator import ESTIMATOR_PROFILES, EstimatorErrors
from vtube_fleet.fleet.budget import (
    LOOP_CHECK_S,
    BudgetWatch,
    LinkMeasurement,
    achieved_rate_hz,
    budget_problems,
    loop_problem,
    mission_budget,
    on_time_share,
)
from vtube_fleet.fleet.compensation import CompensatorBank
from vtube_fleet.fleet.preflight import MEASURE_TRIES, measure_budget_links


@pytest.fixture()
def mission(tmp_path):
    return write_mission(tmp_path, COMPACT_12)


def test_mission_budget_from_a_measurement(mission) -> None:
    m = LinkMeasurement(position_age_s=0.04, setpoint_delay_s=0.02, accuracy_m=0.29)
    b = mission_budget(mission, m)
    cfg = mission.config
    assert b.latency_s == pytest.approx(0.04 + 0.02 + cfg.latency_headroom_s)
    assert b.accuracy_m == pytest.approx(0.29) and b.accuracy_factor == cfg.accuracy_factor
    assert b.disturbance_m_s == cfg.disturbance_residual_m_s
    vmp = mission.scenario.controller.v_max_prime
    expect = (vmp + b.disturbance_m_s) * b.delay_s + 2.0 * 0.29
    assert b.delta_m == pytest.approx(expect)
    # the MQTT agents add the neighbour states' allowed age to L
    assert mission_budget(mission, m, extra_latency_s=0.15).latency_s == pytest.approx(
        b.latency_s + 0.15)
    assert budget_problems(mission, m) == []


def test_budget_refusals_name_the_numbers(mission) -> None:
    slow = LinkMeasurement(position_age_s=0.18, setpoint_delay_s=0.15, accuracy_m=0.3)
    (p,) = budget_problems(mission, slow)
    assert "link latency L = 380 ms" in p and "max_latency_s = 250 ms" in p
    blind = LinkMeasurement(0.02, 0.01, math.nan)
    (p,) = budget_problems(mission, blind)
    assert "position_accuracy_m" in p


def test_the_watch_holds_only_after_two_seconds_over(mission) -> None:
    b = mission_budget(mission, LinkMeasurement(0.03, 0.01, 0.29))
    w = BudgetWatch(mission, b)
    t = 0.0
    for _ in range(5):  # within the budget: nothing
        w.add_ages(t, [0.03] * 10)
        assert w.check(t, 0.01, [0.29]) == (None, None)
        t += 1.0
    w.add_ages(t, [0.5] * 50)  # latency far above L + T
    warning, hold = w.check(t, 0.01, [0.29])
    assert warning and "link latency" in warning and hold is None
    t += 1.0
    w.add_ages(t, [0.5] * 50)
    warning, hold = w.check(t, 0.01, [0.29])
    assert warning is None and hold and "safety budget exceeded in flight" in hold
    # the accuracy: 25 % above the budgeted σ
    w2 = BudgetWatch(mission, b)
    assert w2.check(0.0, 0.01, [0.40])[0] is not None
    assert w2.check(1.0, 0.01, [0.40])[1] is not None
    w3 = BudgetWatch(mission, b)
    assert w3.check(0.0, 0.01, [0.36]) == (None, None)  # within 25 % + 2 cm


def _fly(compensate: bool, seed: int, seconds: float = 40.0) -> float:
    """One vehicle flying a constant 1 m/s command with px4-sih estimate errors, through the
    mock's PX4 velocity response; the worst drift of the ESTIMATED position from the error-free
    flight over any 5 s."""
    dt = 0.01
    runs = []
    for errors in (True, False):
        q = QuadState(1, nominal_dt=dt)
        q.p[0, 2] = -5.0  # in the air (on the ground the mock's friction stops it)
        est = EstimatorErrors(1, seed)
        est.configure(0, ESTIMATOR_PROFILES["px4-sih" if errors else "ideal"])
        est.start(0)
        comp = CompensatorBank(1)
        row = np.zeros(1, np.int64)
        air, frozen = np.ones(1, bool), np.zeros(1, bool)
        u = np.zeros((1, 3))
        out = []
        for k in range(int(seconds / dt)):
            est.step(dt, air)
            q.step(dt, u - est.e_v, air, frozen, np.full(1, np.nan), np.zeros(1))
            q.p[0, 2] = -5.0
            p = q.p[0, :2] + est.e_p[0, :2]
            v = q.v[0, :2] + est.e_v[0, :2]
            if k % 5 == 0:  # the fleet's control tick (20 Hz) sees a fresh sample
                comp.add(row, np.array([k * dt]), p[:1], p[1:2], v[:1], v[1:2])
                dx, dy = ((float(comp.dx_m_s[0]), float(comp.dy_m_s[0]))
                          if (compensate and errors) else (0.0, 0.0))
                u[0] = (1.0 + dx, dy, 0.0)
            out.append(p.copy())
        runs.append(np.array(out))
    d = runs[0] - runs[1]
    w = int(5.0 / dt)
    return float(np.hypot(*(d[w:] - d[:-w]).T).max())


def test_compensation_makes_the_estimate_follow_the_command() -> None:
    """Without compensation PX4 SITL's velocity-estimate error carries the estimated position
    metres off the command (the real flights' 5 s drifts: 1.3-2.5 m); with it, a few dm."""
    raw = [_fly(False, s) for s in range(4)]
    comp = [_fly(True, s) for s in range(4)]
    print(f"\nworst 5 s drift of the estimate: without compensation {max(raw):.2f} m, with "
          f"{max(comp):.2f} m")
    assert min(raw) > 1.0
    assert max(comp) < 0.5 and max(comp) < 0.3 * min(raw)


def test_compensator_window_and_clip() -> None:
    c = CompensatorBank(1, window_s=0.4, limit_m_s=1.0)
    row, zero = np.zeros(1, np.int64), np.zeros(1)
    # the estimate says 2 m/s east while the estimated position does not move: d = 2, clipped
    for k in range(20):
        c.add(row, np.array([0.05 * k]), zero, zero, zero, np.array([2.0]))
    assert (c.dx_m_s[0], c.dy_m_s[0]) == pytest.approx((0.0, 1.0)) and c.clipped[0] > 0
    assert c.max_m_s[0] == pytest.approx(2.0)
    with pytest.raises(ValueError):
        CompensatorBank(1, window_s=0.0)


class _Link:
    """A link that takes every setpoint (what :func:`actuate` needs of one)."""

    closed = False
    latency_s = None

    def __init__(self) -> None:
        from vtube_fleet.link.base import VehicleState

        self.state = VehicleState(endpoint="udpin://127.0.0.1:24999")
        self.sent = 0

    def send_velocity_ned(self, north_m_s: float, east_m_s: float, down_m_s: float,
                          yaw_deg: float | None = None) -> None:
        self.sent += 1

    @classmethod
    def _send_velocities(cls, links, north, east, down):
        for lk in links:
            lk.send_velocity_ned(0.0, 0.0, 0.0)
        return [None] * len(links)


def test_a_lasting_residual_above_d_warns_once_a_spike_does_not(mission) -> None:
    """The budget covers D integrated over time: one tick's jump of d̂ is not a warning, a
    residual that stays above D is, once per vehicle (the tick's actuation tracks it)."""
    from vtube_fleet.fleet.flight_plan import FlightPlan
    from vtube_fleet.fleet.table import PHASE_CODE, FleetTable
    from vtube_fleet.fleet.tick import actuate, read_links
    from vtube_fleet.state import Phase

    sc = mission.scenario
    plan = FlightPlan.build(sc.corridor, sc.controller)
    tab = FleetTable([0], mission)
    tab.phase[0] = PHASE_CODE[Phase.IN_TUBE]
    link = _Link()
    period, d = mission.config.period_s, mission.config.disturbance_residual_m_s
    bank = tab.compensator
    assert bank is not None

    def tick(t: float, dx: float) -> list[int]:
        bank.dx_m_s[0] = dx
        act = actuate(tab, read_links([link]), [link], mission, plan, t,
                      np.zeros(1, np.int64), np.array([[1.0, 0.0]]), None)
        return act.residual_over.tolist()

    t = 0.0
    warned: list[int] = []
    for k in range(200):  # a single spike of 3 D, then calm
        warned += tick(t, 3 * d if k == 100 else 0.0)
        t += period
    assert tab.residuals.residuals(0).max() > d and not warned
    for k in range(200):  # d̂ drifting at 2 D per compensation delay: the residual stays > D
        warned += tick(t, 2 * d * k * period / (0.5 * bank.window_s + period))
        t += period
    assert warned == [0] and link.sent == 400


def test_the_watch_counts_stalls_of_our_own_loop(mission, tmp_path) -> None:
    """A control loop that stalls beyond T + L flies the vehicles on stale setpoints: counted
    over budget even when the mission fixes latency_s (that describes the link, not us)."""
    b = mission_budget(mission, LinkMeasurement(0.03, 0.01, 0.29))
    w = BudgetWatch(mission, b)
    t = 0.0
    for _ in range(3):  # ticks on time, and one a little late: nothing
        w.add_tick_gap(b.period_s)
        w.add_tick_gap(b.period_s + 0.5 * b.latency_s)
        w.add_ages(t, [0.03] * 10)
        assert w.check(t, 0.01, [0.29]) == (None, None)
        t += 1.0
    w.add_tick_gap(w.max_tick_gap_s + 0.1)  # one stall: a warning with the numbers
    warning, hold = w.check(t, 0.01, [0.29])
    assert warning and "control loop stalled" in warning and hold is None
    t += 1.0
    assert w.check(t, 0.01, [0.29]) == (None, None)  # not again: the gap was judged once
    for _ in range(2):  # stalls in two seconds in a row: hold
        t += 1.0
        w.add_tick_gap(w.max_tick_gap_s + 0.1)
        warning, hold = w.check(t, 0.01, [0.29])
    assert hold and "control loop stalled" in hold
    fixed = write_mission(tmp_path, COMPACT_12.replace("[mission]", "[mission]\nlatency_s = 0.25",
                                                       1), name="fixed.toml")
    assert fixed.config.latency_s == 0.25
    wf = BudgetWatch(fixed, mission_budget(fixed, LinkMeasurement(0.03, 0.01, 0.29)))
    wf.add_tick_gap(wf.max_tick_gap_s + 0.1)
    assert "control loop stalled" in (wf.check(0.0, 0.01, [0.29])[0] or "")



def test_a_vehicle_that_falls_silent_is_not_link_latency(mission) -> None:
    """The sequence of a real CI run: our loop stalls, then one of 4 vehicles falls silent. Its
    growing age (counted up to neighbour_max_age_s, as the supervisor does) is a fault, not the
    link's latency: its sample is never superseded, so the ages do not count, and once it is
    declared lost (lost_after_s) the watch forgets them. Counted at once, the same ages make
    the whole fleet hold; a slow or a sparse link still does."""
    cfg = mission.config
    b = mission_budget(mission, LinkMeasurement(0.03, 0.01, 0.29))
    stall_s, death_s = 0.30, 1.40

    def run(*, settle: bool = True, link_s: float = 0.03, every_s: float = b.period_s
            ) -> list[tuple[str | None, str | None]]:
        w = BudgetWatch(mission, b)
        arrived = np.zeros(4)  # the arrival time of each vehicle's newest sample
        out = []
        for k in range(int(6.0 / b.period_s)):
            t = k * b.period_s
            if stall_s <= t < stall_s + 0.1:  # the stall: nothing read, then the backlog
                pass
            elif t - arrived[1] >= every_s - 1e-9:  # (vehicle 1 never dies)
                arrived[:] = t
            if t >= death_s:
                arrived[0] = min(arrived[0], death_s)  # vehicle 0: silent
            ids = np.arange(4)
            ages = link_s + (t - arrived)
            used = ages <= cfg.neighbour_max_age_s  # older: handled as a fault
            if t - arrived[0] > cfg.lost_after_s:
                w.forget([0])  # declared lost (again and again: harmless)
            w.add_tick_gap(0.28 + b.period_s if abs(t - stall_s) < 1e-9 else b.period_s)
            w.add_ages(t, ages[used], ids[used] if settle else None, arrived[used])
            if w.due(t):
                out.append(w.check(t, 0.01, [0.29], arrived.copy()))
        return out

    checks = run()
    assert "control loop stalled" in (checks[1][0] or "")  # the stall is still reported
    assert [hold for _, hold in checks] == [None] * len(checks)
    assert any(hold and "link latency" in hold for _, hold in run(settle=False))
    # a slow link on every vehicle, or a sparse one (2 Hz), is latency all the same
    assert any(hold and "link latency" in hold for _, hold in run(link_s=0.25))
    assert any(hold and "link latency" in hold for _, hold in run(every_s=0.5))

# -- the control loop before arming (loop_problem) ----------------------------------------------
T = 0.05  # s, the control period of these ticks


def every(dt_s: float, n: int) -> list[float]:
    """The start times of ``n`` ticks ``dt_s`` apart."""
    return list(dt_s * np.arange(n))


def test_on_time_and_rate() -> None:
    assert on_time_share([], T) is None and math.isnan(achieved_rate_hz([0.0]))
    assert on_time_share([0.0, 0.025, 0.026, 0.2], T) == 0.5  # within half a period
    assert achieved_rate_hz(every(T, 21)) == pytest.approx(20.0)
    assert achieved_rate_hz(every(0.08, 11)) == pytest.approx(12.5)


def judge(starts: list[float], late: list[float], dur: list[float], vehicles: int = 12,
          **kw) -> str | None:
    """loop_problem half a period after the last tick's start."""
    return loop_problem(starts, late, dur, T, vehicles, now_s=starts[-1] + T / 2, **kw)


def test_a_healthy_loop_passes() -> None:
    n = round(LOOP_CHECK_S / T)
    assert judge(every(T, n), [0.002] * n, [0.01] * n) is None
    # a stall long ago is forgotten: only the last LOOP_CHECK_S of ticks count
    starts = every(0.3, 300) + list(90.0 + T * np.arange(n))
    assert judge(starts, [0.3] * 300 + [0.002] * n, [0.01] * (300 + n)) is None
    # one tick in two starts 30 ms late, at the full rate: 50 % on time passes
    assert judge(every(T, n), [0.0, 0.03] * (n // 2), [0.01] * n) is None
    # a shorter window (the clock has run 2 s)
    assert judge(every(T, 40), [0.0] * 40, [0.01] * 40, window_s=2.0) is None


def test_a_loop_that_cannot_keep_up_is_named_with_its_numbers() -> None:
    n = round(LOOP_CHECK_S / T)
    # the telemetry receive fills the gaps: the rate is kept, but no tick starts on time
    late = [0.002] * 300 + [0.03] * n
    text = judge(every(T, 300 + n), late, [0.045] * len(late), 1000)
    assert text is not None
    assert text.startswith("the control loop cannot keep up with 1000 vehicles on this computer")
    assert ("over the last 5.0 s it ticked at 20.00 Hz of 20 Hz (at least 16 Hz needed) with "
            "0.0% of its ticks started on time (at least 50%; tick p50 45.0 ms, p99 45.0 ms") \
        in text and "lower rate_hz" in text
    # every tick takes 1.6 periods: the clock drops the missed ticks, so one in two starts on
    # time (the one after the restart of its schedule), at 12.5 of 20 Hz
    text = judge(every(0.08, n), [0.03, 0.0] * (n // 2), [0.08] * n, 3)
    assert text is not None and "it ticked at 12.60 Hz of 20 Hz" in text
    # a loop too slow to tick often is judged by the time it took: 1 tick a second
    text = judge(every(1.0, 10), [0.0] * 10, [0.9] * 10, 3)
    assert text is not None and "it ticked at 1.00 Hz of 20 Hz" in text
    # no tick at all in the window
    text = loop_problem([0.0], [0.0], [0.01], T, 3, now_s=10.0)
    assert text is not None and "0.00 Hz" in text and "no tick finished" in text


async def test_one_stall_before_arming_is_judged_again_not_refused() -> None:
    """Preflight.check_loop: a 1.3 s stall in the judged window fails the first judgement
    (13.5 Hz); the next LOOP_CHECK_S of a 20 Hz clock pass, so the fleet may arm."""
    import asyncio
    from types import SimpleNamespace

    from vtube_fleet.fleet.preflight import Preflight

    loop = asyncio.get_running_loop()
    t0 = loop.time()
    starts = [t for t in (t0 - 4.0 + T * k for k in range(80)) if not t0 - 2.3 < t < t0 - 1.0]
    events: list[str] = []
    clock = SimpleNamespace(starts_s=starts, lateness_s=[0.0] * len(starts),
                            durations_s=[0.005] * len(starts))
    pre = Preflight([SimpleNamespace(name=f"slot {i}") for i in range(3)],
                    SimpleNamespace(config=SimpleNamespace(period_s=T)),  # type: ignore[arg-type]
                    event=lambda text, level="info": events.append(f"{level}: {text}"))

    async def ticking() -> None:
        # a clock that keeps 20 Hz exactly: each wake-up records every tick due by then, so a
        # loaded machine's late wake-ups do not make this healthy clock look slow
        next_t = t0 + T
        while True:
            await asyncio.sleep(T)
            while next_t <= loop.time():
                clock.starts_s.append(next_t)
                clock.lateness_s.append(0.0)
                clock.durations_s.append(0.005)
                next_t += T

    task = asyncio.create_task(ticking())
    try:
        await pre.check_loop(clock)  # type: ignore[arg-type]  # raises if judged twice slow
    finally:
        task.cancel()
    assert len(events) == 1 and events[0].startswith("warning: the control loop cannot keep up")
    assert "over the last 4.0 s it ticked at 13." in events[0] and "once more" in events[0]


class _SlowThenFastLink:
    """A link whose round trip is measured once per measurement (the counter)."""

    latency_s = None

    def __init__(self) -> None:
        self.measurements = 0

    async def measure_round_trip_s(self) -> float:
        self.measurements += 1
        return 0.02


class _Pilot:
    """What :func:`measure_links` reads of a pilot: its link, its samples' age, σ."""

    def __init__(self, slow_measurements: int) -> None:
        self.link = _SlowThenFastLink()
        self.slow = slow_measurements

    def sample_age_s(self, now_mono: float) -> float:
        return 0.4 if self.link.measurements <= self.slow else 0.02  # s

    def position_accuracy_m(self, allow_gnss: bool = True) -> float:
        return 0.29


async def test_a_start_up_burst_of_latency_is_measured_again_not_refused(mission) -> None:
    """A second of load when every process starts at once is not the link: measured again."""
    pilot = _Pilot(slow_measurements=2)
    measured, problems = await measure_budget_links([pilot], mission, duration_s=0.05)
    assert problems == [] and pilot.link.measurements == 3
    assert measured.position_age_s == pytest.approx(0.02)  # the budget is built on the last


async def test_a_latency_that_stays_high_is_refused_naming_every_try(mission) -> None:
    pilot = _Pilot(slow_measurements=99)
    measured, problems = await measure_budget_links([pilot], mission, duration_s=0.05)
    assert pilot.link.measurements == MEASURE_TRIES == 3
    assert len(problems) == 2 and "max_latency_s = 250 ms" in problems[0]
    assert "the same in 3 measurements of 0.05 s (L = 460, 460, 460 ms)" in problems[1]
    assert measured.position_age_s == pytest.approx(0.4)


@pytest.mark.parametrize(("slow", "refused"), [(1, False), (99, True)])
async def test_an_agent_measures_again_before_it_refuses_the_runs_delta(slow: int,
                                                                          refused: bool) -> None:
    """The MQTT agent: an L the run's δ does not cover (below max_latency_s) is measured
    again too; the refusal names the run's δ and every try."""
    from missions import MOCK_FLEET

    from vtube_fleet.bus.codec import MissionConfigMsg
    from vtube_fleet.fleet.distributed.coordinator import bus_safety_budget
    from vtube_fleet.fleet.distributed.vehicle_agent import AgentProcess, AgentRefused

    agent = AgentProcess(MOCK_FLEET, 0)
    run_delta = bus_safety_budget(agent.mission, None, agent.max_age_s).delta_m
    agent.run_cfg = MissionConfigMsg("m", "r", agent.hash, 12, 0.0, max_age_s=agent.max_age_s,
                                     delta_m=run_delta)

    class AgentPilot(_Pilot):
        def sample_age_s(self, now_mono: float) -> float:  # 150 ms: < max_latency_s, > run's
            return 0.15 if self.link.measurements <= self.slow else 0.02

        def position_accuracy_m(self, allow_gnss: bool = True) -> float:
            return 0.35  # the coordinator's assumed σ: then L decides

    from types import SimpleNamespace

    pilot = AgentPilot(slow)
    control = SimpleNamespace(pilot=pilot, set_plan=lambda plan: None, watch=None)
    if not refused:
        await agent.measure_budget(control)  # type: ignore[arg-type]
        assert pilot.link.measurements == 2 and agent.budget.delta_m == pytest.approx(run_delta)
        return
    with pytest.raises(AgentRefused) as err:
        await agent.measure_budget(control)  # type: ignore[arg-type]
    text = str(err.value)
    assert pilot.link.measurements == MEASURE_TRIES
    assert f"more than the run's δ = {run_delta:.3f} m" in text
    assert "the same in 3 measurements of 1 s (L = 210, 210, 210 ms)" in text, text


def test_flying_on_past_the_finish_stops_before_the_fence(mission) -> None:
    """``after_exit = "continue"``: an exited vehicle flies on at v, but holds a stopping
    distance before the fence's exit (core/fence.exit_room_m), not at PX4's fence failsafe
    (a vehicle stuck in the tube kept the others flying on until the fence caught them)."""
    from vtube_fleet.core.fence import exit_room_m
    from vtube_fleet.fleet.flight_plan import FlightPlan
    from vtube_fleet.fleet.table import PHASE_CODE, FleetTable
    from vtube_fleet.fleet.tick import actuate, read_links
    from vtube_fleet.state import Phase

    assert mission.config.after_exit == "continue"
    sc = mission.scenario
    plan = FlightPlan.build(sc.corridor, sc.controller)
    tube = plan.route.segments[-1].tube
    room = exit_room_m(tube.length, mission.config.exit_clear_m)
    n_c = np.asarray(tube.n_c, float)
    finish = 0.5 * (np.asarray(tube.p_h1, float) + np.asarray(tube.p_r1, float))

    def fly_at(past_m: float) -> tuple[list, np.ndarray]:
        tab = FleetTable([0], mission)
        tab.phase[0] = PHASE_CODE[Phase.EXITED]
        tab.xy[0] = finish + past_m * n_c
        tab.has[0] = True
        link = _Link()
        act = actuate(tab, read_links([link]), [link], mission, plan, 0.0,
                      np.zeros(0, np.int64), np.zeros((0, 2)), None)
        return act.hold, tab.cmd[0].copy()

    hold, cmd = fly_at(1.0)  # just past the line: flies on along n_c
    assert hold == [] and float(cmd @ n_c) > 0.0
    hold, cmd = fly_at(room - 0.5)  # within a stopping distance of the fence's exit: holds
    assert len(hold) == 1 and hold[0][0] == 0
    assert "before the fence's exit" in hold[0][1] and np.allclose(cmd, 0.0)
