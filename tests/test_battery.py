"""Batteries (issue 34, part 5): the mock's battery, the links' battery field, the mission's
battery keys, the check before arming and the low-battery landing in flight.

* the mock's battery: PX4 SITL's simulated battery by default (drain while armed, a floor,
  full again when disarmed), per-vehicle drain and the ``battery_low`` fault;
* the mission's expected airborne time and the charge it needs, derived from the mission;
* on the mock, judged by the mock's GROUND TRUTH (``truth.py``): a vehicle whose battery does
  not cover the mission keeps the fleet on the ground (one line naming it, with the numbers;
  no vehicle left the ground); a vehicle whose battery drops below the reserve mid-tube lands
  where it is, the others pass it (truth-clean), and the event and the summary say why.

No sleeps as synchronisation and no timing asserts: the flights wait on conditions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fleet_ports import free_ports
from missions import straight_mission, write_mission
from truth import TruthLog, assert_true_clearance

from sim_stub import Faults, MockFleet
from sim_stub.battery import Battery
from sim_stub.errors import SimStubError
from sim_stub.faults import parse_fault_spec
from vtube_fleet.config.mission import PX4_LAND_SPEED_M_S, load_mission
from vtube_fleet.errors import ConfigError
from vtube_fleet.fleet.launch import fly, mock_fleet
from vtube_fleet.fleet.supervisor import Supervisor

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------------------------
# the mock's battery
# ----------------------------------------------------------------------------------------------
def test_the_mock_battery_is_px4_sitls_and_configurable_per_vehicle() -> None:
    """PX4 SITL's battery (100 % a minute while armed, floor 50 %, full when disarmed); a
    vehicle's own drain and pack; the battery_low fault at its time, kept after disarming."""
    b = Battery(Faults())
    assert b.update(0.0, 0.0, armed=False) == 100.0 and b.voltage_mv == 16200  # capture: 16.2 V
    assert b.update(6.0, 6.0, armed=True) == pytest.approx(90.0)  # 6 s armed: -10 %
    assert b.update(60.0, 60.0, armed=True) == 50.0  # SIM_BAT_MIN_PCT
    assert b.update(61.0, 61.0, armed=False) == 100.0  # PX4 SITL: full again when disarmed
    own = Battery(Faults(battery_pct=60.0, drain_pct_per_min=6.0, battery_floor_pct=0.0))
    assert own.update(0.0, 0.0, armed=False) == 60.0
    assert own.update(300.0, 300.0, armed=True) == pytest.approx(30.0)  # 5 min at 6 %/min
    low = Battery(Faults(battery_low_pct=15.0, battery_low_at_s=20.0))
    assert low.update(0.0, 0.0, armed=True) == 100.0  # (integrated from the first report on)
    assert low.update(10.0, 10.0, armed=True) == pytest.approx(100.0 - 100.0 * 10 / 60)
    assert low.update(20.0, 20.0, armed=True) == 15.0  # the fault, below the floor
    assert low.update(30.0, 30.0, armed=False) == 15.0  # a depleted pack stays depleted
    assert (low.remaining_pct, low.charge_state) == (15, 1)
    low.drop_to(6.0)
    assert (low.remaining_pct, low.charge_state) == (6, 3)  # below BAT_CRIT_THR 7 %
    assert parse_fault_spec("2:battery=40,drain=8,battery_low=12,battery_low_at=30") == (
        2, Faults(battery_pct=40.0, drain_pct_per_min=8.0, battery_low_pct=12.0,
                  battery_low_at_s=30.0))
    with pytest.raises(SimStubError, match=r"battery_pct must be in \[0, 100\] %, got 120"):
        parse_fault_spec("battery=120")
    with pytest.raises(SimStubError, match="'battery_low'"):
        parse_fault_spec("batery_low=3")  # the error lists the keys


@pytest.mark.slow
@pytest.mark.timeout(120)
@pytest.mark.parametrize("backend", ["mavlink", "mavsdk"])
async def test_both_links_report_the_battery(backend: str) -> None:
    """``VehicleState.battery_remaining`` (0..1): SYS_STATUS with the mavlink backend, MAVSDK's
    battery (BATTERY_STATUS) with mavsdk; a drop on the vehicle shows."""
    from vtube_fleet.link import open_links

    faults = [Faults(battery_pct=42.0), None]
    async with (MockFleet(2, spacing_m=5.0, port_scheme=free_ports(2), boot_time_scale=0.3,
                          faults=faults) as fleet,
                open_links(fleet.endpoints, backend, sysids=[1, 2]) as links):
        for link in links:
            await link.connect(30.0)
        for link, want in zip(links, (0.42, 1.0), strict=True):
            await link.wait_until(lambda s, w=want: abs(s.battery_remaining - w) < 1e-9, 20.0,
                                  f"battery {want:.0%}")
        fleet.vehicles[1].set_battery(17.0)
        await links[1].wait_until(lambda s: abs(s.battery_remaining - 0.17) < 1e-9, 20.0,
                                  "battery 17 %")


# ----------------------------------------------------------------------------------------------
# the mission's keys
# ----------------------------------------------------------------------------------------------
def test_the_missions_expected_airborne_time_and_needed_charge(tmp_path: Path) -> None:
    """Derived: the climb + the longest slot's path (plus exit_clear_m) at v_min + the descent
    at PX4's land speed; a declared expected_airborne_s wins; more than a full pack is refused
    when the mission is loaded."""
    m = load_mission(ROOT / "configs" / "px4_sitl_3.toml")
    cfg = m.config
    path = 34.0 - 3.0 + cfg.exit_clear_m  # slots at x = 3, the finishing line at x = 34
    want = (cfg.altitude_m / cfg.climb_speed_m_s + path / m.scenario.robots.v_min
            + cfg.altitude_m / PX4_LAND_SPEED_M_S)
    assert m.expected_airborne_s == pytest.approx(want)
    assert m.battery_needed_pct == pytest.approx(20.0 + 5.0 * want / 60.0)
    text = straight_mission(30.0, [[2.0, 0.0]], extra="expected_airborne_s = 600.0\n"
                            "battery_drain_pct_per_min = 8.0\n")
    fixed = write_mission(tmp_path, text)
    assert fixed.expected_airborne_s == 600.0 and fixed.battery_needed_pct == 100.0
    with pytest.raises(ConfigError, match=r"battery_reserve_pct: the reserve 20 % \+ "
                       r"battery_drain_pct_per_min 9 %/min × the expected 600 s in the air "
                       r"= 110 % of a full pack"):
        write_mission(tmp_path, text.replace("= 8.0", "= 9.0"))


# ----------------------------------------------------------------------------------------------
# on the mock, judged by truth
# ----------------------------------------------------------------------------------------------
def _boot(count: int, seed: int, **kw) -> dict:
    return {"boot_time_scale": 0.3, "port_scheme": free_ports(count), "seed": seed, **kw}


@pytest.mark.slow
@pytest.mark.timeout(120)
async def test_a_battery_that_does_not_cover_the_mission_keeps_the_fleet_on_the_ground(
        tmp_path: Path) -> None:
    positions = [[2.0, 4.5], [2.0, 0.0], [2.0, -4.5]]
    mission = write_mission(tmp_path, straight_mission(30.0, positions))
    need = mission.battery_needed_pct
    holder: list[Supervisor] = []
    faults = [None, Faults(battery_pct=25.0), None]  # a quarter-charged pack in slot 1
    async with mock_fleet(mission, **_boot(3, 5, faults=faults)) as fleet:
        log = TruthLog(fleet, mission)

        def hook(tick: int, sup: Supervisor) -> None:
            if not holder:
                holder.append(sup)
            log(tick, sup)

        result = await fly(mission, endpoints=fleet.endpoints, sysids=[1, 2, 3],
                           out_dir=tmp_path, tick_hook=hook)
        armed = [v.armed or any(c == 400 for _, c, *_ in v.command_log) for v in fleet.vehicles]
    assert result.outcome == "failed" and result.exit_code == 2
    reason = result.reason
    print(f"\nrefusal: {reason}")
    assert reason.startswith("preflight failed, nothing armed: 1 of 3 vehicles' batteries do not "
                             "cover the mission (battery_reserve_pct 20 % + "
                             "battery_drain_pct_per_min 5 %/min × ")
    assert reason.endswith(f": slot 1 ({fleet.endpoints[1]}): battery 25 % < {need:.1f} % "
                           f"needed")
    assert "\n" not in reason
    # the truth: nobody was even told to arm, nobody left the ground
    assert armed == [False] * 3
    assert log.up and max(float(np.max(u)) for u in log.up) < 0.5
    b = result.summary["battery"]
    assert b["at_arming_pct"] == [100.0, 25.0, 100.0] and b["needed_pct"] == round(need, 1)
    assert [v["battery_pct"] for v in result.summary["vehicle_states"]] == [100.0, 25.0, 100.0]


@pytest.mark.slow
@pytest.mark.timeout(240)
async def test_a_low_battery_mid_tube_lands_and_the_others_pass(tmp_path: Path) -> None:
    """Vehicle 0 flies ahead of the others; mid-tube its battery drops to 15 % (the mock's
    ``battery_low`` fault on demand), below the 20 % reserve: it lands where it is (PX4 LAND),
    an obstacle for the others while it comes down, the tube re-partitioned around it; the
    others pass it and exit; the run is incomplete (exit 3) and says why."""
    positions = [[12.0, 0.0], [2.0, 4.5], [2.0, 0.0], [2.0, -4.5]]
    mission = write_mission(tmp_path, straight_mission(32.0, positions, on_complete="hold"))
    holder: list[Supervisor] = []
    dropped: list[np.ndarray] = []
    seen: list[tuple[np.ndarray, np.ndarray]] = []  # vehicle 0 landing: (estimate, obstacle)
    async with mock_fleet(mission, **_boot(4, 4)) as fleet:
        log = TruthLog(fleet, mission)

        def hook(tick: int, sup: Supervisor) -> None:
            if not holder:
                holder.append(sup)
            log(tick, sup)
            p = sup.pilots[0]
            if not dropped and p.phase.value == "in_tube" and p.xy[0] > 18.0:
                dropped.append(p.xy.copy())
                fleet.vehicles[0].set_battery(15.0)  # THE FAULT
            if p.phase.value == "landing" and sup.plan.lost:
                seen.append((p.xy.copy(), sup.plan.lost[0].center.copy()))

        result = await fly(mission, endpoints=fleet.endpoints, sysids=[1, 2, 3, 4],
                           out_dir=tmp_path, keep_trace=True, tick_hook=hook)
        modes = [m for _, m, _ in fleet.vehicles[0].mode_log]
    sup = holder[0]
    assert dropped, "vehicle 0 never reached x = 18 m"
    s = result.summary
    print(f"\nlow battery: {result.outcome}: {result.reason}; partitions {s['partitions']}")
    assert result.outcome == "incomplete" and result.exit_code == 3
    assert s["exited"] == 3 and s["lost"] == []
    why = "battery 15 % < battery_reserve_pct = 20 %: lands where it is"
    v0 = s["vehicle_states"][0]
    assert v0["phase"] == "landed" and v0["reason"].startswith(why) and v0["battery_pct"] == 15
    assert f"{sup.names[0]} landed ({why}" in result.reason
    events = [e for e in s["events"] if e["vehicle"] == 0 and "in_tube → landing" in e["text"]]
    assert len(events) == 1 and why in events[0]["text"] and events[0]["level"] == "warning"
    assert "AUTO.LAND" in modes  # PX4 was told to land, not to hold
    # an obstacle while it comes down: the others flew a partition around it, which followed it
    # only in steps of the anchor distance (not every tick as its estimate wandered)
    assert seen, "no partition around the landing vehicle"
    est = np.array([e for e, _ in seen])
    centre = np.array([c for _, c in seen])
    anchor = sup.ticker.anchor_m
    # (+ what the estimate drifts while the new anchor's partition is planned off the loop:
    # up to a few hundred ms at the landing's drift of at most 0.3 m/s)
    assert float(np.hypot(*(est - centre).T).max()) <= anchor + 0.15
    steps = int((np.hypot(*np.diff(centre, axis=0).T) > 0).sum())
    path = float(np.hypot(*np.diff(est, axis=0).T).sum())
    assert steps <= path / anchor + 1  # each step: the estimate moved more than the anchor
    assert s["partitions"] >= 2
    # the truth: it came down near where its battery failed, and the others passed it
    k0 = next(k for k, ph in enumerate(log.phases) if ph[0] == "landing")
    down = [k for k, ph in enumerate(log.phases) if ph[0] in ("landing", "landed")]
    track = np.array([log.xy[k][0] for k in down])
    drift = float(np.hypot(*(track - log.xy[k0][0]).T).max())
    assert float(log.up[-1][0]) < 0.3  # on the ground
    air = [k for k in down if log.up[k][0] > 0.5]  # vehicle 0 still in the air
    clearance = min(float(np.hypot(*(log.xy[k][1:] - log.xy[k][0]).T)[
        np.isin(np.array(log.phases[k][1:]), ["in_tube", "exited"])].min(initial=np.inf))
        for k in air)
    assert clearance > 2 * mission.scenario.robots.r_s
    passed = max(float(log.xy[k][1:, 0].max()) for k in down)
    assert passed > float(log.xy[k0][0][0]) + 3.0  # they did pass it
    truth = assert_true_clearance(log)
    print(f"TRUE: pair {truth['pair']:.3f} m, legs {truth['left_leg']:.3f} / "
          f"{truth['right_leg']:.3f} m; vehicle 0 drifted {drift:.3f} m while landing (its "
          f"obstacle followed it in {steps} steps of > {anchor:g} m); the others' closest "
          f"approach while it was in the air {clearance:.3f} m")


@pytest.mark.slow
@pytest.mark.timeout(240)
async def test_an_mqtt_agent_whose_battery_does_not_cover_the_mission_refuses(
        tmp_path: Path) -> None:
    """The same check in an MQTT agent (the preflight's one implementation): before its vehicle
    is READY, the agent of a pack that covers the reserve but not the mission refuses with the
    numbers, the
    coordinator's start fails naming it, and no vehicle is ever told to arm."""
    import asyncio

    from broker import LocalBroker

    from vtube_fleet.fleet.distributed.coordinator import Coordinator, MissionRunError
    from vtube_fleet.fleet.distributed.vehicle_agent import AgentProcess, AgentRefused

    mission = write_mission(tmp_path, straight_mission(14.0, [[2.0, 3.0], [2.0, -3.0]]))
    path = tmp_path / "mission.toml"
    need = mission.battery_needed_pct
    assert 20.0 < 22.0 < need  # above the reserve, short of the mission
    faults = [None, Faults(battery_pct=22.0)]
    with LocalBroker() as broker:
        async with mock_fleet(mission, **_boot(2, 6, faults=faults)) as fleet:
            agents = [AgentProcess(path, v, broker=broker.url, join_timeout_s=60,
                                   endpoint=fleet.endpoints[v]) for v in range(2)]
            tasks = [asyncio.ensure_future(a.run()) for a in agents]
            async with Coordinator(path, broker.url, vehicles=2, say=lambda _: None) as coord:
                with pytest.raises(MissionRunError) as err:
                    await coord.start_run(asyncio.Event(), ready_timeout_s=120)
                with pytest.raises(AgentRefused) as refused:
                    await tasks[1]
                for a in agents:
                    a.interrupt("the test is over")
                await asyncio.gather(tasks[0], return_exceptions=True)
            armed = [any(c == 400 for _, c, *_ in v.command_log) for v in fleet.vehicles]
    print(f"\n{err.value}")
    assert str(refused.value) == (
        f"vehicle 1 refuses to fly: preflight failed, nothing armed: 1 of 1 vehicles' batteries "
        f"do not cover the mission (battery_reserve_pct 20 % + battery_drain_pct_per_min 5 %/min "
        f"× {mission.expected_airborne_s:.0f} s expected in the air = {need:.1f} %): slot 1 "
        f"({fleet.endpoints[1]}): battery 22 % < {need:.1f} % needed")
    assert "vehicle 1: preflight failed, nothing armed: 1 of 1 vehicles' batteries" in str(
        err.value)
    assert armed == [False, False]
