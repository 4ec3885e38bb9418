"""End-to-end: the supervisor flies sim_stub mock vehicles over real UDP.

Safety is asserted from the telemetry the vehicles reported (the supervisor's per-tick trace of
telemetry positions in the tube frame and of the commands it sent), recomputed here
independently: every pair of airborne vehicles ≥ 2 r_s apart, obstacle centre distance
≥ r_o + r_s, leg distances ≥ r_s and every commanded horizontal speed in [v_min, v_max] while
in the tube. No sleeps as synchronisation and no timing asserts: the tests wait on conditions.
The mock vehicles boot with ``boot_time_scale`` 0.3 (armable after ~1.2 s instead of ~4 s).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fleet_ports import free_ports

from vtube_fleet.fleet.mission import Mission, load_mission
from vtube_fleet.fleet.supervisor import Supervisor, TickTrace
from vtube_fleet.fleetcli import fly, mock_fleet

ROOT = Path(__file__).resolve().parents[1]


def boot(count: int) -> dict:
    return {"boot_time_scale": 0.3, "port_scheme": free_ports(count)}

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]


def check_safety(mission: Mission, trace: list[TickTrace], *, lost: tuple[int, ...] = ()
                 ) -> dict[str, float]:
    """Recompute the safety figures from the telemetry trace; assert them; return them."""
    sc = mission.scenario
    r_s = sc.robots.r_s
    tube = sc.tube
    assert trace, "no tick recorded"
    worst = {"pair": np.inf, "obstacle": np.inf, "leg": np.inf, "cmd_min": np.inf,
             "cmd_max": -np.inf, "in_tube_ticks": 0}
    for tk in trace:
        phases = np.array(tk.phases)
        airborne = np.isin(phases, ["in_tube", "exited", "lost"]) & np.isfinite(tk.pos[:, 0])
        q = tk.pos[airborne]
        if len(q) > 1:
            d = np.hypot(*(q[:, None, :] - q[None, :, :]).transpose(2, 0, 1))
            d = d[np.triu_indices(len(q), 1)]
            worst["pair"] = min(worst["pair"], float(d.min()))
        rows = tk.in_tube
        if rows.any():
            worst["in_tube_ticks"] += 1
            p = tk.pos[rows]
            for ob in sc.obstacles:
                dist = np.hypot(*(p - ob.center).T) - ob.radius
                worst["obstacle"] = min(worst["obstacle"], float(dist.min()))
            worst["leg"] = min(worst["leg"], float(tube.d_Th(p).min()), float(tube.d_Tr(p).min()))
            sp = np.hypot(*tk.cmd[rows].T)
            worst["cmd_min"] = min(worst["cmd_min"], float(sp.min()))
            worst["cmd_max"] = max(worst["cmd_max"], float(sp.max()))
    assert worst["in_tube_ticks"] > 0
    assert worst["pair"] >= 2 * r_s, f"pair distance {worst['pair']:.3f} m < 2 r_s"
    assert worst["obstacle"] >= r_s, f"obstacle clearance {worst['obstacle']:.3f} m < r_s"
    assert worst["leg"] >= r_s, f"leg distance {worst['leg']:.3f} m < r_s"
    assert worst["cmd_min"] >= sc.robots.v_min - 1e-9
    assert worst["cmd_max"] <= sc.robots.v_max + 1e-9
    return worst


def report(name: str, result, worst: dict[str, float]) -> None:
    s = result.summary
    print(f"\n{name}: {result.outcome}, exited {s['exited']}/{s['robots']}, pair "
          f"{worst['pair']:.3f} m (2 r_s = {s['pair_limit_m']:.2f}), obstacle clearance "
          f"{worst['obstacle']:.3f} m, legs {worst['leg']:.3f} m, commanded "
          f"{worst['cmd_min']:.3f}..{worst['cmd_max']:.3f} m/s, measured "
          f"{s['min_measured_speed_settled_m_s']}..{s['max_measured_speed_m_s']} m/s (settled "
          f"min), δ {s['safety_budget']['delta_m']:.3f} m, rate {s['achieved_rate_hz']:.2f} Hz, "
          f"tick p50/p99 {1000 * s['tick_duration_p50_s']:.2f}/"
          f"{1000 * s['tick_duration_p99_s']:.2f} ms, latency p50 "
          f"{1000 * (s['link_latency_p50_s'] or 0):.2f} ms, flight {s['flight_time_s']:.1f} s")


def keep(holder: list[Supervisor]):
    def hook(tick: int, sup: Supervisor) -> None:
        if not holder:
            holder.append(sup)
    return hook


def mission_file(tmp_path: Path, text: str) -> Mission:
    p = tmp_path / "mission.toml"
    p.write_text(text)
    return load_mission(p)


STRAIGHT = """
[tube]
p_h0 = [0.0, 5.0]
p_h1 = [{length}, 5.0]
p_r0 = [0.0, -5.0]
p_r1 = [{length}, -5.0]

[robots]
r_s = 0.3
r_a = 1.0
v_min = 0.3
v_max = 1.6
positions = {positions}

[controller]
v = 1.0
v_max_prime = 0.5

[mission]
origin_lat_deg = 47.397742
origin_lon_deg = 8.545594
origin_alt_m = 488.0
heading_deg = 20.0
altitude_m = 3.0
climb_speed_m_s = 1.5
on_complete = "{on_complete}"
mission_timeout_s = 120.0
"""


# ----------------------------------------------------------------------------------------------
async def test_mavlink_12_vehicles_fly_the_mock_fleet_mission(tmp_path: Path) -> None:
    mission = load_mission(ROOT / "configs" / "mock_fleet.toml")
    assert mission.count == 12
    holder: list[Supervisor] = []
    result = await fly(mission, backend="mavlink", out_dir=tmp_path, mock_kwargs=boot(12),
                       keep_trace=True, tick_hook=keep(holder))
    sup = holder[0]
    assert result.exit_code == 0, result.reason
    assert result.outcome == "completed"
    assert result.summary["exited"] == 12
    assert all(p.exit_time_s is not None for p in sup.pilots)
    assert [v["phase"] for v in result.summary["vehicle_states"]] == ["landed"] * 12
    worst = check_safety(mission, sup.trace)
    assert (tmp_path / "summary.json").is_file()
    report("mavlink x12", result, worst)


async def test_mavsdk_4_vehicles_fly_the_mock_fleet_mission(tmp_path: Path) -> None:
    text = (ROOT / "configs" / "mock_fleet.toml").read_text().replace(
        'on_complete = "land"', 'on_complete = "hold"')
    mission = mission_file(tmp_path, text).with_vehicles(4)
    holder: list[Supervisor] = []
    result = await fly(mission, backend="mavsdk", out_dir=tmp_path, mock_kwargs=boot(4),
                       keep_trace=True, tick_hook=keep(holder))
    sup = holder[0]
    assert result.exit_code == 0, result.reason
    assert result.summary["exited"] == 4
    assert [v["phase"] for v in result.summary["vehicle_states"]] == ["holding"] * 4
    # the vehicles themselves report Hold (telemetry), not just our phase
    assert all(p.link.state.flight_mode == "HOLD" for p in sup.pilots)
    worst = check_safety(mission, sup.trace)
    report("mavsdk x4", result, worst)


async def test_vehicle_dies_mid_tube_and_the_others_pass(tmp_path: Path) -> None:
    positions = [[4.0, 0.0], [1.5, 2.5], [1.5, 0.0], [1.5, -2.5]]
    mission = mission_file(tmp_path, STRAIGHT.format(length=24.0, positions=positions,
                                                     on_complete="hold"))
    holder: list[Supervisor] = []
    killed: list[np.ndarray] = []
    async with mock_fleet(mission, **boot(4)) as fleet:

        def hook(tick: int, sup: Supervisor) -> None:
            if not holder:
                holder.append(sup)
            p = sup.pilots[0]
            if not killed and p.phase.value == "in_tube" and p.xy[0] > 9.0:
                killed.append(p.xy.copy())
                fleet.kill(0, "silent")

        result = await fly(mission, endpoints=fleet.endpoints, sysids=[1, 2, 3, 4],
                           out_dir=tmp_path, keep_trace=True, tick_hook=hook)
    sup = holder[0]
    assert killed, "vehicle 0 never reached x = 9 m"
    assert result.outcome == "incomplete" and result.exit_code == 3
    assert result.summary["lost"] == [0]
    assert result.summary["exited"] == 3
    assert sup.pilots[0].reason and "no telemetry" in sup.pilots[0].reason
    assert result.summary["partitions"] >= 2  # re-partitioned around the lost vehicle
    # the others flew past the dead vehicle's last reported position, clear of it
    dead = sup.pilots[0].lost_xy
    assert dead is not None
    after = [tk for tk in sup.trace if tk.phases[0] == "lost"]
    assert after
    others = np.concatenate([tk.pos[1:][np.isin(np.array(tk.phases[1:]),
                                                 ["in_tube", "exited"])] for tk in after])
    clearance = float(np.hypot(*(others - dead).T).min())
    assert clearance >= 2 * mission.scenario.robots.r_s
    assert float(others[:, 0].max()) > dead[0] + 3.0  # they did pass it
    worst = check_safety(mission, sup.trace, lost=(0,))
    report("vehicle dies", result, worst)
    print(f"killed at ({killed[0][0]:.2f}, {killed[0][1]:.2f}); closest approach to its last "
          f"position {clearance:.3f} m")
