"""The preflight audit of the PX4 parameters the mission relies on (issue 15): the rules with
the mission's numbers, the mock answering PX4's defaults and honouring MPC_XY_VEL_MAX, the
fleet refusing a clipped speed before arming, and ``--fix-params`` restoring the old values on
every exit path (an interrupt, a refusal later in the preflight)."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
from pathlib import Path

import pytest
from fleet_ports import free_ports
from missions import MOCK_FLEET, straight_mission, write_mission

import sim_stub.fence
from sim_stub import MockFleet, px4
from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet import onboard
from vtube_fleet.fleet.launch import fly, mock_fleet
from vtube_fleet.fleet.onboard import audit_rules
from vtube_fleet.link import MavlinkLink

pytestmark = pytest.mark.timeout(180)

PX4_DEFAULTS = {"MPC_XY_VEL_MAX": 12.0, "MPC_ACC_HOR": 3.0, "COM_OF_LOSS_T": 1.0,
                "COM_OBL_RC_ACT": 0.0, "NAV_DLL_ACT": 0.0,
                # PX4's parameter files (geofence_params.yaml, multicopter_autonomous_params
                # .yaml, multicopter_position_control_limits_params.yaml): 0 = no ceiling
                "GF_MAX_VER_DIST": 0.0, "MPC_JERK_AUTO": 4.0, "MPC_Z_VEL_MAX_UP": 3.0,
                "MPC_Z_VEL_MAX_DN": 1.5}


def judge(values: dict[str, float]) -> dict[str, str | None]:
    rules = audit_rules(load_mission(MOCK_FLEET))
    return {r.name: r.problem(values[r.name]) for r in rules}


def test_the_rules_with_the_missions_numbers() -> None:
    rules = {r.name: r for r in audit_rules(load_mission(MOCK_FLEET))}
    assert [n for n, r in rules.items() if r.hard] == ["MPC_XY_VEL_MAX", "GF_MAX_VER_DIST"]
    got = judge(PX4_DEFAULTS)
    assert got["MPC_XY_VEL_MAX"] is None and got["MPC_ACC_HOR"] is None
    assert all(got[n] is None for n in ("GF_MAX_VER_DIST", "MPC_JERK_AUTO", "MPC_Z_VEL_MAX_UP",
                                        "MPC_Z_VEL_MAX_DN"))
    assert got["COM_OF_LOSS_T"] is None
    assert "COM_OBL_RC_ACT = 0, Position mode" in (got["COM_OBL_RC_ACT"] or "")
    assert "NAV_DLL_ACT = 0 (disabled)" in (got["NAV_DLL_ACT"] or "")
    bad = judge({**PX4_DEFAULTS, "MPC_XY_VEL_MAX": 1.2, "MPC_ACC_HOR": 1.0,
                 "COM_OF_LOSS_T": 2.0, "COM_OBL_RC_ACT": 5.0, "NAV_DLL_ACT": 3.0})
    assert bad["MPC_XY_VEL_MAX"] == ("MPC_XY_VEL_MAX = 1.2 m/s < v_max = 1.6 m/s (PX4 would "
                                     "clip the controller's speeds)")
    assert bad["MPC_ACC_HOR"].startswith("MPC_ACC_HOR = 1.0 m/s² < v_max / t63 = 1.6 m/s²")
    assert "for up to 3.2 m" in bad["COM_OF_LOSS_T"]
    assert bad["COM_OBL_RC_ACT"] is None and bad["NAV_DLL_ACT"] is None
    # the fix: v_max + D (the compensation's headroom), rounded up to 0.1 m/s
    assert rules["MPC_XY_VEL_MAX"].fix == pytest.approx(1.9)
    assert rules["MPC_XY_VEL_MAX"].problem(rules["MPC_XY_VEL_MAX"].fix) is None
    assert rules["MPC_ACC_HOR"].problem(rules["MPC_ACC_HOR"].fix) is None


def test_a_fence_ceiling_below_the_mission_altitude_is_hard() -> None:
    """configs/mock_fleet.toml flies at altitude_m = 3 m, altitude_tolerance_m = 0.3 m: a
    GF_MAX_VER_DIST below 3.3 m would breach PX4's own ceiling in the climb; 0 is PX4's "off"."""
    rule = {r.name: r for r in audit_rules(load_mission(MOCK_FLEET))}["GF_MAX_VER_DIST"]
    assert rule.hard
    assert rule.problem(3.0) == (
        "GF_MAX_VER_DIST = 3.0 m < altitude_m + altitude_tolerance_m = 3.3 m: PX4's own fence "
        "ceiling (height above home) would breach during the climb and take the vehicle out "
        "of offboard (GF_ACTION); lower altitude_m or raise GF_MAX_VER_DIST")
    assert rule.problem(0.0) is None and rule.problem(3.3) is None and rule.problem(120) is None
    assert rule.fix == 4.0 and rule.problem(rule.fix) is None  # whole metres, as PX4 steps it


def test_vertical_speed_and_jerk_rules_warn_with_the_numbers() -> None:
    """MPC_Z_VEL_MAX_UP / _DN clip what the pilot commands (climb_speed_m_s = 1.5 m/s, the
    altitude hold's max_vertical_speed_m_s = 1 m/s): soft, a slower take-off or height
    correction; MPC_JERK_AUTO against the budget's t63 like MPC_ACC_HOR (v_max 1.6, t63 1 s)."""
    rules = {r.name: r for r in audit_rules(load_mission(MOCK_FLEET))}
    assert not any(rules[n].hard for n in ("MPC_JERK_AUTO", "MPC_Z_VEL_MAX_UP",
                                           "MPC_Z_VEL_MAX_DN"))
    up = rules["MPC_Z_VEL_MAX_UP"].problem
    assert up(1.2) == ("MPC_Z_VEL_MAX_UP = 1.2 m/s < climb_speed_m_s = 1.5 m/s: PX4 clips the "
                       "climb (take-off 2.5 s instead of 2.0 s); the horizontal flight is not "
                       "affected")
    assert "longer than takeoff_timeout_s = 40.0 s: the take-off will time out" in up(0.05)
    assert up(1.5) is None
    dn = rules["MPC_Z_VEL_MAX_DN"].problem
    assert dn(0.5) == ("MPC_Z_VEL_MAX_DN = 0.5 m/s < max_vertical_speed_m_s = 1.0 m/s: PX4 "
                       "clips the altitude-hold descents (slower height corrections; the "
                       "horizontal flight is not affected)")
    assert dn(1.0) is None
    jerk = rules["MPC_JERK_AUTO"].problem
    assert jerk(1.0) == ("MPC_JERK_AUTO = 1.0 m/s³ < 1.3 v_max / t63² = 2.09 m/s³: a "
                         "jerk-limited start reaches 63 % of a v_max step later than the "
                         "tracking_t63_s = 1.0 s the safety budget assumes")
    assert jerk(2.09) is None
    assert {n: rules[n].fix for n in ("MPC_JERK_AUTO", "MPC_Z_VEL_MAX_UP",
                                      "MPC_Z_VEL_MAX_DN")} == {
        "MPC_JERK_AUTO": 2.1, "MPC_Z_VEL_MAX_UP": 1.5, "MPC_Z_VEL_MAX_DN": 1.0}
    # the factor: an S-curve from rest to V with jerk j is at 1 - 1/e of V after
    # (2 - sqrt(2/e)) sqrt(V / j); at the bound that time is exactly t63
    v, t63 = 1.6, 1.0
    j = onboard.JERK_T63_FACTOR * v / t63 ** 2
    t = (2 - math.sqrt(2 / math.e)) * math.sqrt(v / j)
    tt = 2 * math.sqrt(v / j)
    assert t == pytest.approx(t63)
    assert v - j * (tt - t) ** 2 / 2 == pytest.approx(v * (1 - 1 / math.e))
    # the rule follows the mission's numbers: a climb faster than the hold
    m = load_mission(MOCK_FLEET)
    m2 = dataclasses.replace(m, config=dataclasses.replace(m.config, climb_speed_m_s=0.5))
    up2 = {r.name: r for r in audit_rules(m2)}["MPC_Z_VEL_MAX_UP"].problem
    assert up2(0.8) == ("MPC_Z_VEL_MAX_UP = 0.8 m/s < max_vertical_speed_m_s = 1.0 m/s: PX4 "
                        "clips the altitude-hold climbs (slower height corrections; the "
                        "horizontal flight is not affected)")


class _ParamLink:
    """Just what :func:`audit_fleet` uses of a link: a name and PX4's parameter exchange."""

    def __init__(self, name: str, params: dict[str, float]) -> None:
        self.name, self.params, self.sets = name, dict(params), []

    async def read_param(self, name: str) -> float:
        return self.params[name]

    async def set_param(self, name: str, value: float) -> float:
        self.sets.append((name, value))
        self.params[name] = value
        return value


async def test_the_new_rules_refuse_warn_and_fix_in_the_audit() -> None:
    """audit_fleet with the new rules (no sockets): a low ceiling refuses naming the vehicle,
    the vertical and jerk limits warn once for both vehicles; --fix-params sets all four and
    records the old values for the restore."""
    m = load_mission(MOCK_FLEET)
    low = {**PX4_DEFAULTS, "GF_MAX_VER_DIST": 2.0, "MPC_JERK_AUTO": 1.0,
           "MPC_Z_VEL_MAX_UP": 1.0, "MPC_Z_VEL_MAX_DN": 0.5}
    links = [_ParamLink(f"vehicle {i}", low) for i in (1, 2)]
    res = await onboard.audit_fleet(links, m)
    assert res.problems == [
        f"vehicle {i}: GF_MAX_VER_DIST = 2.0 m < altitude_m + altitude_tolerance_m = 3.3 m: "
        f"PX4's own fence ceiling (height above home) would breach during the climb and take "
        f"the vehicle out of offboard (GF_ACTION); lower altitude_m or raise GF_MAX_VER_DIST"
        for i in (1, 2)]
    warned = [w for w in res.warnings if w.startswith("all 2 vehicles: MPC_")]
    assert [w.split(" = ")[0] for w in warned] == [
        "all 2 vehicles: MPC_JERK_AUTO", "all 2 vehicles: MPC_Z_VEL_MAX_UP",
        "all 2 vehicles: MPC_Z_VEL_MAX_DN"]
    assert "take-off 3.0 s instead of 2.0 s" in warned[1]
    assert not any(link.sets for link in links)
    res = await onboard.audit_fleet(links, m, fix=True)
    assert res.problems == []
    new = {"GF_MAX_VER_DIST": 4.0, "MPC_JERK_AUTO": 2.1, "MPC_Z_VEL_MAX_UP": 1.5,
           "MPC_Z_VEL_MAX_DN": 1.0}
    for link, old in zip(links, res.changed, strict=True):
        assert {k: link.params[k] for k in new} == new
        assert {k: old[k] for k in new} == {k: low[k] for k in new}
    assert any("--fix-params set GF_MAX_VER_DIST = 4.0 (restored to 2.0 on exit)" in w
               for w in res.warnings)
    assert await onboard.restore_params(links, res.changed) == []
    assert all(link.params == low for link in links)


async def test_the_mock_answers_the_new_parameters_with_px4_defaults() -> None:
    """No flight: PARAM_REQUEST_READ of the four new parameters over UDP gives PX4's defaults
    (REAL32), and a PARAM_SET of one sticks."""
    fleet = MockFleet(1, port_scheme=free_ports(1), boot_time_scale=0.3, estimator="ideal")
    await fleet.start()
    link = MavlinkLink(fleet.endpoints[0], sysid=1)
    try:
        await link.connect(10.0)
        for name in ("GF_MAX_VER_DIST", "MPC_JERK_AUTO", "MPC_JERK_MAX", "MPC_Z_VEL_MAX_UP",
                     "MPC_Z_VEL_MAX_DN"):
            want = {**PX4_DEFAULTS, "MPC_JERK_MAX": 8.0}[name]
            assert await link.read_param(name) == pytest.approx(want), name
            assert fleet.vehicles[0].params[name].type == px4.PARAM_REAL32
        assert await link.set_param("GF_MAX_VER_DIST", 4.0) == pytest.approx(4.0)
        assert fleet.vehicles[0].params["GF_MAX_VER_DIST"].value == pytest.approx(4.0)
    finally:
        await link.close()
        await fleet.stop()


async def test_the_mock_answers_px4_defaults_and_clips_to_mpc_xy_vel_max() -> None:
    fleet = MockFleet(1, port_scheme=free_ports(1), boot_time_scale=0.3, estimator="ideal",
                      params={"MPC_XY_VEL_MAX": 0.8})
    await fleet.start()
    link = MavlinkLink(fleet.endpoints[0], sysid=1)
    stop = asyncio.Event()

    async def stream(v: tuple[float, float, float]) -> None:
        while not stop.is_set():
            link.send_velocity_ned(*v)
            await asyncio.sleep(0.05)  # the control period, not a synchronisation

    try:
        await link.connect(10.0)
        for name, value in PX4_DEFAULTS.items():
            if name != "MPC_XY_VEL_MAX":
                assert await link.read_param(name) == value
        assert await link.read_param("MPC_XY_VEL_MAX") == pytest.approx(0.8)
        await link.wait_ready(20.0)
        link.send_velocity_ned(0.0, 0.0, -1.0)
        task = asyncio.get_running_loop().create_task(stream((0.0, 0.0, -1.0)))
        await link.start_offboard()
        await link.arm(timeout_s=15.0, retry_interval_s=0.25)
        await link.wait_until(lambda s: s.down_m < -2.0, 20.0, "2 m")
        stop.set()
        await task
        stop.clear()
        task = asyncio.get_running_loop().create_task(stream((0.0, 2.0, 0.0)))
        await link.wait_until(lambda s: s.ve_m_s > 0.6, 10.0, "moving east")
        speeds = []
        for _ in range(40):
            await link.wait_until(lambda s: True, 1.0, "telemetry")
            await asyncio.sleep(0.05)  # sampling the mock's truth at 20 Hz, not a sync
            vn, ve, _ = fleet.vehicles[0].velocity_ned
            speeds.append(math.hypot(vn, ve))
        stop.set()
        await task
        assert max(speeds) <= 0.8 + 0.05, max(speeds)  # PX4 clips the 2 m/s command
        assert max(speeds) > 0.6
    finally:
        stop.set()
        await link.close()
        await fleet.stop()


def _mission(tmp_path: Path):
    return write_mission(tmp_path, straight_mission(12.0, [[3.0, 4.5], [3.0, -4.5]]))


def _armed_ever(fleet) -> bool:
    return any(a for v in fleet.vehicles for _, _, a in v.mode_log)


async def test_a_clipped_speed_is_refused_before_arming(tmp_path: Path) -> None:
    m = _mission(tmp_path)
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(2), seed=1,
                          params={"MPC_XY_VEL_MAX": 1.2}) as fleet:
        result = await fly(m, endpoints=fleet.endpoints, sysids=[1, 2], out_dir=tmp_path)
        assert not _armed_ever(fleet)
    assert result.outcome == "failed" and result.exit_code == 2
    assert "nothing armed" in result.reason
    assert ("MPC_XY_VEL_MAX = 1.2 m/s < v_max = 1.6 m/s (PX4 would clip the controller's "
            "speeds)") in result.reason
    assert "--fix-params" in result.reason
    warnings = [e["text"] for e in result.summary["events"] if e["level"] == "warning"]
    assert any("COM_OBL_RC_ACT = 0" in w for w in warnings)  # soft ones only warn
    print(f"\n{result.reason}")


BAD = {"MPC_XY_VEL_MAX": 1.2, "COM_OBL_RC_ACT": 0, "NAV_DLL_ACT": 0, "MPC_ACC_HOR": 1.0}


def _values(v) -> dict[str, float]:
    return {k: v.params[k].value for k in BAD}


async def test_fix_params_sets_them_for_the_flight_and_restores_on_an_interrupt(
        tmp_path: Path) -> None:
    m = _mission(tmp_path)
    seen: list[dict[str, float]] = []
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(2), seed=2,
                          params=BAD) as fleet:

        def hook(tick: int, sup) -> None:
            if sup.stage == "takeoff" and sup._interrupted is None:
                seen.extend(_values(v) for v in fleet.vehicles)
                sup.interrupt("SIGINT")

        result = await fly(m, endpoints=fleet.endpoints, sysids=[1, 2], out_dir=tmp_path,
                           fix_params=True, tick_hook=hook)
        after = [_values(v) for v in fleet.vehicles]
    assert result.outcome == "interrupted", result.reason
    assert seen and all(s == {"MPC_XY_VEL_MAX": pytest.approx(1.9), "COM_OBL_RC_ACT": 5,
                              "NAV_DLL_ACT": 3, "MPC_ACC_HOR": pytest.approx(1.6)}
                        for s in seen)
    assert all(a == {k: pytest.approx(x) for k, x in BAD.items()} for a in after)
    assert any("restored" in e["text"] for e in result.summary["events"])
    onboard = result.summary["onboard"]
    assert onboard["fence"] == "uploaded" and onboard["gf_action"] == "hold"
    assert onboard["fence_items"] == 4 and len(onboard["px4_params"]) == 2
    assert onboard["px4_params"][0]["MPC_XY_VEL_MAX"] == pytest.approx(1.2)
    assert sorted(onboard["params_fixed"]) == [f"slot {i} ({fleet.endpoints[i]})" for i in (0, 1)]
    assert onboard["params_fixed"]["slot 0 (" + fleet.endpoints[0] + ")"] == {
        k: pytest.approx(x) for k, x in BAD.items()}


async def test_fix_params_restores_when_a_later_preflight_step_refuses(
        tmp_path: Path, monkeypatch) -> None:
    m = _mission(tmp_path)
    monkeypatch.setattr(sim_stub.fence, "FENCE_MAX_ITEMS", 3)  # the fence is refused
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(2), seed=3,
                          params=BAD) as fleet:
        result = await fly(m, endpoints=fleet.endpoints, sysids=[1, 2], out_dir=tmp_path,
                           fix_params=True)
        after = [_values(v) for v in fleet.vehicles]
        assert not _armed_ever(fleet)
    assert result.outcome == "failed" and "refused the fence" in result.reason
    assert all(a == {k: pytest.approx(x) for k, x in BAD.items()} for a in after)
    with contextlib.suppress(StopIteration):
        next(e for e in result.summary["events"] if "restored" in e["text"])


# -- the mavsdk backend (the real MAVSDK client's param plugin) ---------------------------------
async def test_mavsdk_reads_and_sets_px4_typed_params() -> None:
    """PX4's INT32 and FLOAT parameters through MAVSDK's get/set_param_int/_float (the type
    PX4 declared is found once and kept: the mock's PARAM_VALUE keeps its type), the same
    values as the mavlink link; an unknown name is a LinkTimeout."""
    from vtube_fleet.link import LinkTimeout
    from vtube_fleet.link.mavsdk_link import MavsdkHub

    fleet = MockFleet(1, port_scheme=free_ports(1), boot_time_scale=0.3, estimator="ideal",
                      params={"MPC_XY_VEL_MAX": 0.8})
    await fleet.start()
    v = fleet.vehicles[0]
    try:
        async with MavsdkHub() as hub:
            link = hub.link(fleet.endpoints[0], sysid=1)
            await link.connect(10.0)
            for name, value in PX4_DEFAULTS.items():
                if name != "MPC_XY_VEL_MAX":
                    assert await link.read_param(name) == value
            assert await link.read_param("MPC_XY_VEL_MAX") == pytest.approx(0.8)
            types = {n: v.params[n].type for n in PX4_DEFAULTS}
            assert await link.set_param("NAV_DLL_ACT", 3.2) == 3.0  # int32: rounded
            assert await link.set_param("MPC_XY_VEL_MAX", 1.9) == pytest.approx(1.9)
            assert v.params["NAV_DLL_ACT"].value == 3
            assert v.params["MPC_XY_VEL_MAX"].value == pytest.approx(1.9)
            assert {n: v.params[n].type for n in PX4_DEFAULTS} == types
            assert await link.read_param("NAV_DLL_ACT") == 3.0
            with pytest.raises(LinkTimeout, match="NO_SUCH_PARAM"):
                await link.read_param("NO_SUCH_PARAM")
    finally:
        await fleet.stop()


async def test_mavsdk_backend_refuses_a_clipped_speed_and_fix_params_restores(
        tmp_path: Path) -> None:
    m = _mission(tmp_path)
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(2), seed=1,
                          params={"MPC_XY_VEL_MAX": 1.2}) as fleet:
        result = await fly(m, backend="mavsdk", endpoints=fleet.endpoints, sysids=[1, 2],
                           out_dir=tmp_path)
        assert not _armed_ever(fleet)
    assert result.outcome == "failed" and result.exit_code == 2
    assert ("MPC_XY_VEL_MAX = 1.2 m/s < v_max = 1.6 m/s (PX4 would clip the controller's "
            "speeds)") in result.reason
    seen: list[dict[str, float]] = []
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(2), seed=2,
                          params=BAD) as fleet:

        def hook(tick: int, sup) -> None:
            if sup.stage == "takeoff" and sup._interrupted is None:
                seen.extend(_values(v) for v in fleet.vehicles)
                sup.interrupt("SIGINT")

        result = await fly(m, backend="mavsdk", endpoints=fleet.endpoints, sysids=[1, 2],
                           out_dir=tmp_path, fix_params=True, tick_hook=hook)
        after = [_values(v) for v in fleet.vehicles]
    assert result.outcome == "interrupted", result.reason
    assert seen and all(s == {"MPC_XY_VEL_MAX": pytest.approx(1.9), "COM_OBL_RC_ACT": 5,
                              "NAV_DLL_ACT": 3, "MPC_ACC_HOR": pytest.approx(1.6)}
                        for s in seen)
    assert all(a == {k: pytest.approx(x) for k, x in BAD.items()} for a in after)
