"""An abort in the air brings every vehicle down (issue 34, part 1), judged by the mock's TRUTH:
what every vehicle is doing when the program returns.

* the budget watch holds the fleet mid-tube (our own control loop stalls past T + L for
  seconds): every vehicle holds, then lands in place; the run waits for touch-down; every mock
  vehicle is on the ground and disarmed when ``fly`` returns; exit 3, the reason in the summary;
* the same with one vehicle that drops its Hold (DO_SET_MODE never acknowledged, a mock fault):
  it is landed by LAND, named in the events;
* a vehicle that answers nothing any more (frozen, in OFFBOARD, hovering): it is sent LAND again
  until ``land_timeout_s`` and reported by name, in red; the run ends with exit 3, never
  "completed", the others on the ground;
* ``on_abort = "hold"``: the operator's choice, said in red, the vehicles named.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from fleet_ports import free_ports
from missions import straight_mission

from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.launch import fly
from vtube_fleet.fleet.supervisor import Supervisor
from vtube_fleet.state import Phase

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

POSITIONS = [[2.0, 5.0], [2.0, 0.0], [2.0, -5.0]]


def _mission(tmp_path: Path, extra: str = "", land_timeout_s: float = 25.0):
    path = tmp_path / "m.toml"
    path.write_text(straight_mission(40.0, POSITIONS, heading_deg=90.0,
                                     extra=f"land_timeout_s = {land_timeout_s}\n" + extra))
    return load_mission(path)


def _stall_in_tube(after_s: float, log: dict):
    """A tick hook: ``after_s`` into the tube, our own loop stalls 0.3 s on every tick (the
    event loop runs on: the vehicles' telemetry still arrives) until the fleet holds — longer
    than the budgeted T + L for more than the watch's 2 s."""

    def hook(tick: int, sup: Supervisor):
        log.setdefault("sup", sup)
        if sup.tube_start_s is None or sup.stage != "tube":
            return None
        if sup.t_s() - sup.tube_start_s < after_s or sup._abort_reason is not None:
            return None
        log["stalled"] = log.get("stalled", 0) + 1
        return asyncio.sleep(0.3)  # THE FAULT: the control loop stalls (not a synchronisation)

    return hook


def _on_the_ground(fleet) -> list[tuple[bool, str]]:
    """Each mock vehicle's TRUE state: (armed, "ON_GROUND" / "IN_AIR")."""
    from sim_stub.px4 import LANDED_ON_GROUND

    return [(bool(v.armed), "ON_GROUND" if v.landed_state == LANDED_ON_GROUND else "IN_AIR")
            for v in fleet.vehicles]


@pytest.mark.parametrize("mode_fault", ["", "drop"])
async def test_a_budget_exceeded_mid_tube_lands_everyone(tmp_path: Path, mode_fault: str) -> None:
    from sim_stub.faults import Faults
    from vtube_fleet.fleet.launch import mock_fleet

    mission = _mission(tmp_path)
    log: dict = {}
    faults = {1: Faults(mode_fault=mode_fault)} if mode_fault else None
    async with mock_fleet(mission, boot_time_scale=0.3, port_scheme=free_ports(3), seed=3,
                          faults=faults) as fleet:
        result = await fly(mission, endpoints=fleet.endpoints, sysids=[1, 2, 3],
                           out_dir=tmp_path, tick_hook=_stall_in_tube(3.0, log))
        truth = _on_the_ground(fleet)  # what every vehicle does when the program returns
        modes = [m[3] for m in fleet.vehicles[1].command_log if m[1] == 176][-3:]  # results
    sup: Supervisor = log["sup"]
    assert log.get("stalled"), f"never stalled: {result.outcome} {result.reason}"
    assert result.outcome == "aborted" and result.exit_code == 3, result.reason
    assert "safety budget exceeded in flight" in result.reason, result.reason
    assert result.summary["reason"] == result.reason and result.summary["complete"] is True
    assert truth == [(False, "ON_GROUND")] * 3, truth
    assert [p.phase for p in sup.pilots] == [Phase.LANDED] * 3
    texts = [e["text"] for e in result.summary["events"]]
    assert any("every vehicle holds, then lands in place" in t for t in texts), texts
    if mode_fault:
        assert modes == [-1, -1, -1], modes  # the Hold's three tries dropped
        hold = [e for e in result.summary["events"] if e["vehicle"] == 1
                and "Hold not acknowledged" in e["text"]]
        assert hold and "LAND instead" in hold[0]["text"], texts
    print(f"\nbudget exceeded ({mode_fault or 'no fault'}): {result.reason}; truth {truth}")


async def test_a_vehicle_that_answers_nothing_is_reported_by_name(tmp_path: Path) -> None:
    """Vehicle 2 freezes mid-tube: it hovers in OFFBOARD, streams telemetry, acknowledges
    nothing. The budget watch aborts (our loop stalls), the others land; vehicle 2 is sent LAND
    until land_timeout_s and named in red; exit 3."""
    from sim_stub.faults import Faults
    from vtube_fleet.fleet.launch import mock_fleet

    mission = _mission(tmp_path, land_timeout_s=8.0)
    log: dict = {}
    async with mock_fleet(mission, boot_time_scale=0.3, port_scheme=free_ports(3), seed=4,
                          faults={2: Faults(die_at_s=1e6, die_how="freeze")}) as fleet:
        def freeze_then_stall(tick: int, sup: Supervisor):
            if (sup.tube_start_s is not None and sup.t_s() - sup.tube_start_s > 2.0
                    and "frozen" not in log):
                log["frozen"] = True
                fleet.vehicles[2].kill("freeze")
            return stall(tick, sup)

        stall = _stall_in_tube(4.0, log)
        result = await fly(mission, endpoints=fleet.endpoints, sysids=[1, 2, 3],
                           out_dir=tmp_path, tick_hook=freeze_then_stall)
        truth = _on_the_ground(fleet)
    assert log.get("frozen")
    assert result.exit_code == 3 and result.outcome != "completed", result.reason
    assert truth[0] == truth[1] == (False, "ON_GROUND"), truth
    assert truth[2][1] == "IN_AIR"  # the frozen one: still hovering, and said so
    assert "slot 2" in result.reason and "NOT on the ground" in result.reason, result.reason
    red = [e["text"] for e in result.summary["events"] if e["level"] == "error"]
    assert any(t.startswith("NOT BROUGHT DOWN") and "slot 2" in t for t in red), red
    print(f"\nfrozen vehicle: {result.reason}")


async def test_on_abort_hold_leaves_them_to_an_operator_in_red(tmp_path: Path) -> None:
    from vtube_fleet.fleet.launch import mock_fleet

    mission = _mission(tmp_path, 'on_abort = "hold"\n')
    log: dict = {}
    async with mock_fleet(mission, boot_time_scale=0.3, port_scheme=free_ports(3),
                          seed=5) as fleet:
        result = await fly(mission, endpoints=fleet.endpoints, sysids=[1, 2, 3],
                           out_dir=tmp_path, tick_hook=_stall_in_tube(3.0, log))
        truth = _on_the_ground(fleet)
        modes = [v.mode.name for v in fleet.vehicles]
    assert result.outcome == "aborted" and result.exit_code == 3, result.reason
    assert truth == [(True, "IN_AIR")] * 3 and modes == ["AUTO.LOITER"] * 3, (truth, modes)
    assert "left holding in the air (on_abort = hold)" in result.reason, result.reason
    red = [e["text"] for e in result.summary["events"] if e["level"] == "error"]
    assert any("LEFT HOLDING IN THE AIR" in t and "slot 0" in t for t in red), red


AUTO_APEX = """
[tube]
p_h0 = [0.0, 10.0]
p_h1 = [40.0, 10.0]
p_r0 = [0.0, -10.0]
p_r1 = [40.0, -10.0]

[partition]
apex_distance = "auto"

[[obstacles]]
center = [20.0, 0.5]
radius = 0.6

[robots]
r_s = 0.3
r_a = 1.0
v_min = 0.3
v_max = 1.6
positions = [[2.0, 5.0], [2.0, 0.0], [2.0, -5.0]]

[controller]
v = 1.0
v_max_prime = 0.5

[mission]
origin_lat_deg = 47.397742
origin_lon_deg = 8.545594
origin_alt_m = 488.0
heading_deg = 90.0
altitude_m = 3.0
climb_speed_m_s = 1.5
"""


async def test_no_tick_gap_at_tube_entry_on_an_auto_apex_mission(tmp_path: Path,
                                                                  monkeypatch) -> None:
    """Issue 34: with ``apex_distance = "auto"`` the partition was planned again on the event
    loop once the vehicles were at altitude (real PX4, 10 instances on 2 cores: 165-275 ms
    stalls at "stage: tube"). Now it is planned before the climb (in a worker thread) and only
    the flown positions are checked at altitude: no partition is planned from the take-off on,
    and no gap between two ticks from the take-off to 3 s into the tube exceeds T + L."""
    import vtube_fleet.core.validation as validation
    from vtube_fleet.fleet.launch import mock_fleet

    planned: list[str] = []
    plan_partition = validation.partition

    def counted(*args, **kwargs):
        planned.append(log["sup"].stage if "sup" in log else "set-up")
        return plan_partition(*args, **kwargs)

    monkeypatch.setattr(validation, "partition", counted)

    path = tmp_path / "auto.toml"
    path.write_text(AUTO_APEX)
    mission = load_mission(path)
    log: dict = {}

    def hook(tick: int, sup: Supervisor):
        if sup.stage in ("takeoff", "tube") and len(sup.clock.gaps_s) > 1:
            log.setdefault("first", len(sup.clock.gaps_s) - 1)
        if sup.tube_start_s is not None and sup.t_s() - sup.tube_start_s > 3.0:
            if "last" not in log:
                log["last"] = len(sup.clock.gaps_s)
                sup.interrupt("test")  # enough: land them
        log["sup"] = sup

    async with mock_fleet(mission, boot_time_scale=0.3, port_scheme=free_ports(3),
                          seed=6) as fleet:
        result = await fly(mission, endpoints=fleet.endpoints, sysids=[1, 2, 3],
                           out_dir=tmp_path, tick_hook=hook)
    sup: Supervisor = log["sup"]
    assert "last" in log, result.reason
    gaps = sup.clock.gaps_s[log["first"]:log["last"]]
    budget = sup.budget.period_s + sup.budget.latency_s
    assert len(gaps) > 40 and max(gaps) <= budget, (max(gaps), budget)
    assert "preflight" in planned and not {"takeoff", "tube"} & set(planned), planned
    assert result.summary["apex_distances_m"][0] is not None  # "auto": planned
    print(f"\nauto apex: {len(gaps)} ticks from take-off into the tube, longest gap "
          f"{1000 * max(gaps):.1f} ms <= T + L = {1000 * budget:.1f} ms")


async def test_the_touch_down_report_does_not_count_a_lost_vehicle_as_down() -> None:
    """The wait for touch-down waits for the LANDING vehicles only; a LOST one (frozen or
    silent: maybe in the air) is not said to be on the ground. A probe flight (a vehicle frozen
    at the route's bend) said "all vehicles on the ground" while it hovered at 3 m. Once its
    fresh telemetry says disarmed on the ground, it is."""
    import time

    from memory_fleet import memory_fleet

    sup, links = memory_fleet(3)
    for p in sup.pilots[:2]:
        p.set_phase(Phase.LANDING, "mission aborted")
        p.landed.set()
    sup.pilots[2].set_phase(Phase.LOST, "not following its setpoints")
    await sup._wait_landed()
    said = sup.events[-1]["text"]
    assert said != "all vehicles on the ground", said
    assert "2 landing vehicle(s) on the ground" in said and "lost: slot 2 (" in said, said
    s = links[2].state
    s.armed, s.landed_state, s.last_position_s = False, "ON_GROUND", time.monotonic()
    await sup._wait_landed()
    assert sup.events[-1]["text"] == "all vehicles on the ground", sup.events[-1]


async def test_a_silent_lost_vehicle_is_named_in_the_reason_of_an_abort() -> None:
    """A vehicle lost for silence cannot be landed by us: the run's reason (the last line of
    `run`) names it, not only an error event in the middle of the output. A probe flight lost
    a vehicle while the fleet held after an abort: it hovered on in Hold (PX4's NAV_DLL_ACT
    off), and the closing `error:` line did not name it."""
    import time

    from memory_fleet import memory_fleet

    sup, links = memory_fleet(3)
    for p in sup.pilots[:2]:
        p.set_phase(Phase.LANDED, "on the ground")
        s = p.link.state
        s.armed, s.landed_state, s.flight_mode = False, "ON_GROUND", "LAND"
    sup.pilots[2].set_phase(Phase.LOST, "no telemetry for more than lost_after_s = 1 s")
    links[2].state.last_packet_s = time.monotonic() - 5.0
    await sup._land_again()
    sup.reason = "safety budget exceeded in flight"
    sup._say_not_down()
    assert "NOT known to be down: 1 lost vehicle(s)" in sup.reason, sup.reason
    assert "slot 2 (udpin://127.0.0.1:30002)" in sup.reason, sup.reason


async def test_a_quick_second_ctrl_c_still_sends_land_and_names_who_is_in_the_air(
        tmp_path: Path) -> None:
    """Two Ctrl-C in quick succession mid-tube (an operator's reflex). The second stops the
    wait for touch-down, but not the LAND: it used to cancel the bring-down while the Holds
    were still going out, leaving the vehicles hovering in Hold (a probe flight: all 12 in the
    air at exit, and the run said "SIGINT: held, then landed" with exit 130 and no name).
    Judged by the mock's TRUTH when `fly` returns: every vehicle landing (PX4 LAND) or on the
    ground, none holding or in OFFBOARD; those in the air named in the reason and the summary."""
    from vtube_fleet.fleet.launch import mock_fleet

    mission = _mission(tmp_path)
    log: dict = {}

    def double_ctrl_c(tick: int, sup: Supervisor) -> None:
        if sup.tube_start_s is None or sup.t_s() - sup.tube_start_s < 2.0:
            return
        if "first" not in log:
            log["first"] = tick
            sup.interrupt("SIGINT")
        elif "second" not in log and tick > log["first"]:
            log["second"] = tick  # the very next tick: the Holds are still in flight
            sup.interrupt("SIGINT")

    async with mock_fleet(mission, boot_time_scale=0.3, port_scheme=free_ports(3),
                          seed=5) as fleet:
        result = await fly(mission, endpoints=fleet.endpoints, sysids=[1, 2, 3],
                           out_dir=tmp_path, tick_hook=double_ctrl_c)
        modes = [v.mode_name for v in fleet.vehicles]
        truth = _on_the_ground(fleet)
    assert "second" in log, log
    assert result.outcome == "interrupted" and result.exit_code == 130, result.reason
    for mode, (_, where) in zip(modes, truth, strict=True):
        assert where == "ON_GROUND" or mode == "AUTO.LAND", modes  # never left hovering
    in_air = [f"slot {i} (" for i, (_, where) in enumerate(truth) if where == "IN_AIR"]
    assert in_air, f"all down already: the test did not stop the wait ({modes})"
    assert "still in the air" in result.reason, result.reason
    for name in in_air:
        assert name in result.reason, result.reason
    assert len(result.summary["not_down"]) == len(in_air), result.summary["not_down"]


async def test_a_lost_vehicle_that_answers_but_stays_up_is_landed_again_and_named() -> None:
    """A lost vehicle that still answers gets LAND at the end; if it stays in the air (a probe
    flight: the fence's Hold caught it again while it landed outside the fence, 0.67 m up) it
    is sent LAND again until land_timeout_s and named, not left hovering unreported."""
    import dataclasses
    import time

    from memory_fleet import memory_fleet

    sup, links = memory_fleet(3)
    sup.cfg = dataclasses.replace(sup.cfg, land_timeout_s=1.0)
    for p in sup.pilots[:2]:
        p.set_phase(Phase.LANDED, "on the ground")
        s = p.link.state
        s.armed, s.landed_state, s.flight_mode = False, "ON_GROUND", "LAND"
    sup.pilots[2].set_phase(Phase.LOST, "left OFFBOARD unexpectedly (mode HOLD)")
    s = links[2].state
    s.armed, s.landed_state, s.flight_mode = True, "IN_AIR", "HOLD"
    s.last_packet_s = time.monotonic() + 60.0  # it keeps answering (MemoryLink's land: no-op)
    await sup._land_again()
    red = [e["text"] for e in sup.events if e["level"] == "error"]
    assert any(t.startswith("NOT BROUGHT DOWN") and "slot 2 (" in t and "lost, in HOLD" in t
               for t in red), red
    assert sup.not_landed == [sup.pilots[2].name], sup.not_landed
