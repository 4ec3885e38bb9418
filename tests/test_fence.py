"""The tube as PX4's geofence (issue 15): the pure geometry (``core/fence.py``), sim_stub's
FENCE mission protocol and breach action over real UDP through the ``mavlink`` link, and the
fleet uploading, reading back and enforcing it (a vehicle pushed out is held by its own
failsafe, also while our process is stopped)."""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fleet_ports import free_ports
from missions import MISSION_TABLE, MOCK_FLEET, NARROWING, straight_mission, write_mission

import sim_stub.fence
from sim_stub import MockFleet
from sim_stub.px4 import Param
from vtube_fleet.config.mission import load_mission
from vtube_fleet.core.fence import tube_fence
from vtube_fleet.core.tube import Obstacle, Trapezoid
from vtube_fleet.fleet.launch import fly, mock_fleet
from vtube_fleet.fleet.onboard import fence_geometry, fence_items, install_fence
from vtube_fleet.link import MavlinkLink
from vtube_fleet.link.base import FenceItem, FenceRejected

pytestmark = pytest.mark.timeout(180)


# -- the pure geometry --------------------------------------------------------------------------
def test_mock_fleet_fence_follows_the_legs_with_the_margin() -> None:
    m = load_mission(MOCK_FLEET)
    g = fence_geometry(m)
    r_s, margin = m.scenario.robots.r_s, m.config.fence_margin_m
    w = r_s + margin
    L = m.scenario.tube.length
    assert g.widen_m == pytest.approx(w)
    assert g.exit_m == pytest.approx(L + m.config.exit_clear_m + w)
    assert len(g.polygons) == 1  # a [tube]: a route of one segment, one polygon
    assert len(g.polygons[0]) == 4  # straight legs: the extensions are collinear, dropped
    assert g.contains(m.slots).all()
    # just inside / outside the widened left leg (y = 10 + w), mid-tube
    assert g.contains(np.array([20.0, 10.0 + w - 0.01]))
    assert not g.contains(np.array([20.0, 10.0 + w + 0.01]))
    assert not g.contains(np.array([20.0, -10.0 - w - 0.01]))
    # behind the start base and past the finishing line
    assert g.contains(np.array([-w + 0.01, 0.0])) and not g.contains(np.array([-w - 0.01, 0.0]))
    assert g.contains(np.array([L + g.exit_m - 0.01, 0.0]))
    assert not g.contains(np.array([L + g.exit_m + 0.01, 0.0]))
    # the pole: an exclusion circle of r_o + r_s
    ob = m.scenario.obstacles[0]
    assert g.circle_radii[0] == pytest.approx(ob.radius + r_s)
    c = ob.center
    assert not g.contains(c) and not g.contains(c + [0.0, ob.radius + r_s - 0.01])
    assert g.contains(c + [0.0, ob.radius + r_s + 0.01])


def test_narrowing_tube_fence_covers_the_tube_and_goes_straight_on() -> None:
    tube = Trapezoid(np.array([0.0, 5.0]), np.array([19.0, 3.0]), np.array([0.0, -5.0]),
                     np.array([19.0, -3.5]))
    slots = np.array([[-2.0, 0.0], [2.0, 1.0]])  # one slot 2 m behind the start base
    g = tube_fence(tube, [Obstacle(np.array([10.0, 0.0]), 0.5)], 0.3, slots=slots,
                   margin_m=0.5, exit_m=6.0)
    assert g.back_m == pytest.approx(2.0 + 0.8)
    assert len(g.polygon) == 8
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-1, 20, 4000), rng.uniform(-6, 6, 4000)])
    in_tube = tube.contains(pts) & (np.hypot(*(pts - [10.0, 0.0]).T) > 0.8)
    assert g.contains(pts[in_tube]).all()
    # every allowed point is within w of the tube or in the straight extensions
    ok = g.contains(pts)
    xi = tube.xi(pts[ok])
    inside_span = (xi >= 0) & (xi <= tube.length)
    assert (tube.d_Th(pts[ok][inside_span]) >= -0.8 - 1e-9).all()
    assert (tube.d_Tr(pts[ok][inside_span]) >= -0.8 - 1e-9).all()
    # past the finishing line the polygon is as wide as the (widened) finishing line, not
    # the converging legs continued
    assert g.contains(np.array([19.0 + 5.9, 3.0 + 0.79]))
    assert not g.contains(np.array([19.0 + 5.9, 3.0 + 0.81]))
    assert g.problems(np.array([[30.0, 0.0], [10.0, 0.0]]), ["a", "b"]) == [
        "a at (30.0, 0.0) is outside the fence polygon (legs widened by 0.8 m, 2.8 m behind "
        "the start base, 6.0 m past the finishing line)",
        "b at (10.0, 0.0) is inside an obstacle's exclusion circle"]
    with pytest.raises(ValueError, match="margin"):
        tube_fence(tube, [], 0.3, margin_m=-1.0)


def test_fence_items_are_the_geometry_in_wgs84(tmp_path: Path) -> None:
    m = write_mission(tmp_path, NARROWING.replace("[robots]", "[[obstacles]]\ncenter = [10.0, "
                                                  "0.0]\nradius = 0.5\n\n[robots]")
                      + MISSION_TABLE + "fence_margin_m = 0.5\n")
    g = fence_geometry(m)
    items = fence_items(m, g)
    (poly,) = g.polygons
    k = len(poly)
    assert [it.command for it in items] == [5001] * k + [5004]
    assert all(it.param1 == k for it in items[:k]) and items[-1].param1 == pytest.approx(0.8)
    x, y = m.frame.geodetic_to_tube(np.array([it.lat_deg for it in items[:k]]),
                                    np.array([it.lon_deg for it in items[:k]]),
                                    m.config.origin_alt_m)[:2]
    np.testing.assert_allclose(np.column_stack([x, y]), poly, atol=1e-6)


ROUTE_MOCK = Path(__file__).resolve().parents[1] / "configs" / "route_mock.toml"


def _route_points(m, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random points (tube frame) inside the route's segments, away from the poles' circles,
    and points outside every widened segment (w + 0.2 m beyond every leg and end) and not
    past the route's finishing line (where the last polygon goes straight on, exit_m)."""
    corridor = m.scenario.corridor
    lo, hi = corridor.bounds()
    pts = rng.uniform(lo - 8.0, hi + 8.0, size=(20000, 2))
    r_s = m.scenario.controller.r_s
    clear = np.ones(len(pts), bool)
    for ob in corridor.obstacles:
        clear &= np.hypot(*(pts - ob.center).T) > ob.radius + r_s + 0.01
    inside = np.zeros(len(pts), bool)
    far = np.ones(len(pts), bool)
    w = r_s + m.config.fence_margin_m
    for t in corridor.segments:
        inside |= np.asarray(t.contains(pts), bool)
        far &= ~np.asarray(t.contains(pts, tol=w + 0.2), bool)
    last = corridor.segments[-1]
    far &= np.asarray(last.xi(pts), float) < last.length
    return pts[inside & clear], pts[far]


async def test_a_routes_fence_is_one_polygon_per_segment_and_px4_allows_their_union() -> None:
    """Issue 29: the fence of a route (configs/route_mock.toml, three segments) is one
    inclusion polygon per segment, uploaded in order before the exclusion circles; the mock
    vehicle (as PX4: inside ANY inclusion polygon and no exclusion) stores the three polygons
    and allows every point of every segment — also those of S2 that no other polygon holds —
    and refuses the points outside every widened segment."""
    m = load_mission(ROUTE_MOCK)
    g = fence_geometry(m)
    items = fence_items(m, g)
    assert len(g.polygons) == m.scenario.corridor.S == 3
    sizes = [len(q) for q in g.polygons]
    assert [it.command for it in items] == [5001] * sum(sizes) + [5004] * 2
    k = 0
    for n in sizes:  # each polygon's vertices carry its own count
        assert [it.param1 for it in items[k:k + n]] == [n] * n
        k += n
    assert g.contains(m.slots).all() and g.problems(m.slots, [""] * m.count) == []
    inside, outside = _route_points(m, np.random.default_rng(3))
    s1, s2, s3 = (poly_fence.inside_polygon(inside) for poly_fence in g.segments)
    only_s2 = s2 & ~s1 & ~s3
    assert g.contains(inside).all() and only_s2.sum() > 100
    assert not g.contains(outside).any() and len(outside) > 1000
    assert "outside every segment's fence polygon" in g.problems(outside[:1], ["v"])[0]
    async with one_vehicle() as (v, link):
        await link.upload_fence(items)
        polys, excl, c_in, c_out = v._fence_shapes
        assert len(polys) == 3 and excl == [] and c_in == [] and len(c_out) == 2
        lat0, lon0, alt0 = v.origin

        def px4_allows(p: np.ndarray) -> np.ndarray:
            n, e, _ = m.frame.tube_to_local_ned(p[:, 0], p[:, 1], np.zeros(len(p)),
                                                lat0, lon0, alt0)
            return np.array([sim_stub.fence.point_in_fence(float(a), float(b), polys, excl,
                                                           c_in, c_out)
                             for a, b in zip(np.atleast_1d(n), np.atleast_1d(e), strict=True)])

        assert px4_allows(inside[only_s2][:300]).all()  # the union: S2 alone holds these
        assert px4_allows(inside[:300]).all()
        assert not px4_allows(outside[:300]).any()
        for ob in m.scenario.obstacles:  # the poles' exclusion circles
            assert not px4_allows(ob.center[None])[0]


# -- sim_stub's protocol over UDP ---------------------------------------------------------------
@contextlib.asynccontextmanager
async def one_vehicle(**kwargs):
    fleet = MockFleet(1, port_scheme=free_ports(1), boot_time_scale=0.3, **kwargs)
    await fleet.start()
    link = MavlinkLink(fleet.endpoints[0], sysid=1)
    try:
        await link.connect(10.0)
        yield fleet.vehicles[0], link
    finally:
        await link.close()
        await fleet.stop()


def square(v, half_deg: float = 1e-4) -> list[FenceItem]:
    lat, lon = v.origin[0], v.origin[1]
    return [FenceItem(5001, lat + a * half_deg, lon + b * half_deg, 4)
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]


async def test_fence_upload_download_clear_and_px4_error_codes(monkeypatch) -> None:
    async with one_vehicle() as (v, link):
        items = square(v) + [FenceItem(5004, v.origin[0] + 5e-5, v.origin[1], 2.5)]
        await link.upload_fence(items)
        assert [it.command for it in v.fence_items] == [5001] * 4 + [5004]
        back = await link.download_fence()
        assert len(back) == 5
        for a, b in zip(items, back, strict=True):
            assert (a.command, round(a.lat_deg * 1e7), round(a.lon_deg * 1e7)) == (
                b.command, round(b.lat_deg * 1e7), round(b.lon_deg * 1e7))
            assert b.param1 == pytest.approx(a.param1)
        # PX4's codes: too few vertices → ERROR, a waypoint in a fence → UNSUPPORTED (mock),
        # too many items → NO_SPACE; the stored fence is unchanged by a refused upload
        bad = [FenceItem(5001, it.lat_deg, it.lon_deg, 2) for it in items[:2]]
        with pytest.raises(FenceRejected, match="MISSION_ACK ERROR") as exc:
            await link.upload_fence(bad)
        assert exc.value.result == "ERROR"
        with pytest.raises(FenceRejected, match="UNSUPPORTED"):
            await link.upload_fence([FenceItem(16, v.origin[0], v.origin[1], 0.0)])
        monkeypatch.setattr(sim_stub.fence, "FENCE_MAX_ITEMS", 4)
        with pytest.raises(FenceRejected, match="NO_SPACE"):
            await link.upload_fence(items)
        assert len(await link.download_fence()) == 5
        await link.upload_fence([])  # count 0 clears
        assert await link.download_fence() == [] and v.fence_items == []


async def test_a_lost_final_ack_and_lost_answers_do_not_fail_the_fence(monkeypatch) -> None:
    """The mission protocol over a lossy link (the mock's UDP, with the messages the link
    receives dropped as a lossy wire would): the upload's final MISSION_ACK lost once — the
    last item goes again and PX4 ACKs it again — and the download's MISSION_COUNT and an
    item lost four times in a row each (six asks each): the fence installs, no timeout."""
    from vtube_fleet.link import mavlink as mav_mod

    lose = {mav_mod.MSG_MISSION_ACK: 1, mav_mod.MSG_MISSION_COUNT: 4}
    item_losses = {2: 4}  # fence item 2's answer
    lost: list[int] = []
    real_next = mav_mod.MavlinkLink._mission_next

    async def lossy_next(self, ob, timeout_s):
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        while True:
            m = await real_next(self, ob, max(0.0, end - loop.time()))
            if m is None:
                return None
            mid = m.get_msgId()
            if lose.get(mid, 0) > 0:
                lose[mid] -= 1
                lost.append(mid)
                continue
            if mid == mav_mod.MSG_MISSION_ITEM_INT and item_losses.get(int(m.seq), 0) > 0:
                item_losses[int(m.seq)] -= 1
                lost.append(mid)
                continue
            return m

    monkeypatch.setattr(mav_mod.MavlinkLink, "_mission_next", lossy_next)
    async with one_vehicle() as (v, link):
        items = square(v) + [FenceItem(5004, v.origin[0] + 5e-5, v.origin[1], 2.5)]
        await install_fence(link, items, 2)
        assert len(v.fence_items) == 5
    assert lost.count(mav_mod.MSG_MISSION_ACK) == 1
    assert lost.count(mav_mod.MSG_MISSION_COUNT) == 4
    assert lost.count(mav_mod.MSG_MISSION_ITEM_INT) == 4


class Streamer:
    def __init__(self, link: MavlinkLink) -> None:
        self.link, self.v = link, (0.0, 0.0, 0.0)
        self.task: asyncio.Task[None] | None = None

    async def _run(self) -> None:
        while True:
            self.link.send_velocity_ned(*self.v)
            await asyncio.sleep(0.05)  # the control period, not a synchronisation

    def start(self) -> None:
        self.link.send_velocity_ned(*self.v)
        self.task = asyncio.get_running_loop().create_task(self._run())

    async def stop(self) -> None:
        if self.task is not None:
            self.task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self.task


async def _airborne_in_offboard(link: MavlinkLink, streamer: Streamer) -> None:
    await link.wait_ready(20.0)
    streamer.v = (0.0, 0.0, -1.0)
    streamer.start()
    await link.start_offboard()
    await link.arm(timeout_s=15.0, retry_interval_s=0.25)
    await link.wait_until(lambda s: s.down_m < -2.0, 20.0, "2 m in offboard")
    streamer.v = (0.0, 0.0, 0.0)


@pytest.mark.parametrize("estimator", ["ideal", "px4-sih"])
async def test_breach_holds_on_the_estimate_even_with_fresh_setpoints(estimator: str) -> None:
    """A vehicle pushed out of a 22 m square fence: PX4's hold (GF_ACTION 2) takes over at
    once with "Failsafe activated", on the *estimated* position, and our still-streaming
    setpoints do not clear it; a mode change does (user takeover)."""
    async with one_vehicle(estimator=estimator) as (v, link):
        await link.upload_fence(square(v))
        streamer = Streamer(link)
        try:
            await _airborne_in_offboard(link, streamer)
            assert v.mode_name == "OFFBOARD" and not v.fence_breached
            v.push(0.0, 3.0, 8.0)  # a gust east: out through the east edge at ~7.5 m
            await link.wait_until(lambda s: s.px4_mode == "AUTO.LOITER", 15.0,
                                  "the geofence hold")
            assert v.fence_failsafe and v.mode_name == "AUTO.LOITER"
            assert any(t[2].startswith("Failsafe activated") for t in v.statustexts)
            assert any("Failsafe activated" in t.text for t in link.state.statustexts)
            est = v.estimated_position_ned
            assert v.fence_breached and est[1] > 7.4  # outside on PX4's estimate
            assert link.state.system_status == "CRITICAL"
            # setpoints keep streaming: still held
            assert v.sp_fresh and v.mode_name == "AUTO.LOITER"
            await link.set_flight_mode("OFFBOARD")  # the user takes over
            await link.wait_until(lambda s: s.px4_mode == "OFFBOARD", 5.0, "OFFBOARD again")
            assert not v.fence_failsafe
        finally:
            await streamer.stop()


async def test_gf_action_land_holds_for_com_fail_act_t_first() -> None:
    # 3 s of Hold: the link learns the mode from the 1 Hz HEARTBEAT, so a shorter hold can be
    # missed altogether by a loaded machine's late tick
    async with one_vehicle(estimator="ideal", params={"GF_ACTION": 5,
                                                      "COM_FAIL_ACT_T": 3.0}) as (v, link):
        await link.upload_fence(square(v, 3e-5))  # ±3.3 m
        streamer = Streamer(link)
        try:
            await _airborne_in_offboard(link, streamer)
            v.push(3.0, 0.0, 3.0)
            await link.wait_until(lambda s: s.px4_mode == "AUTO.LOITER", 15.0, "the hold")
            assert any(t[2] == "Failsafe activated, entering Hold for 3 seconds\t"
                       for t in v.statustexts)
            await link.wait_until(lambda s: s.px4_mode == "AUTO.LAND", 10.0, "then land")
        finally:
            await streamer.stop()


# -- the fleet ----------------------------------------------------------------------------------
def _mission(tmp_path: Path, extra: str = ""):
    return write_mission(tmp_path, straight_mission(12.0, [[3.0, 4.5], [3.0, -4.5]],
                                                    extra=extra))


async def test_the_fleet_refuses_to_arm_when_a_vehicle_refuses_the_fence(
        tmp_path: Path, monkeypatch) -> None:
    m = _mission(tmp_path)
    monkeypatch.setattr(sim_stub.fence, "FENCE_MAX_ITEMS", 3)
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(2), seed=3) as fleet:
        result = await fly(m, endpoints=fleet.endpoints, sysids=[1, 2], out_dir=tmp_path)
        assert not any(a for v in fleet.vehicles for _, _, a in v.mode_log)  # never armed
    assert result.outcome == "failed" and result.exit_code == 2
    assert "nothing armed" in result.reason and "refused the fence" in result.reason
    assert "NO_SPACE" in result.reason
    print(f"\n{result.reason}")


async def test_no_fence_flies_without_one(tmp_path: Path) -> None:
    """``fence=False`` (``--no-fence``): nothing uploaded, a warning says so (the flight is
    stopped right after take-off: an interrupt)."""
    m = _mission(tmp_path)
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(2), seed=4) as fleet:

        def hook(tick: int, sup) -> None:
            if sup.stage == "takeoff" and sup._interrupted is None:
                sup.interrupt("test")

        result = await fly(m, endpoints=fleet.endpoints, sysids=[1, 2], out_dir=tmp_path,
                           fence=False, tick_hook=hook)
        assert all(v.fence_items == [] for v in fleet.vehicles)
    assert result.outcome == "interrupted"
    assert any("--no-fence" in e["text"] and e["level"] == "warning"
               for e in result.summary["events"])
    assert result.summary["onboard"]["fence"] == "off"


_SIGSTOP_CHILD = r"""
import asyncio, json, sys
sys.path[:0] = [{root!r}, {tests!r}]
from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.launch import fly
async def main():
    m = load_mission({mission!r})
    def hook(tick, sup):
        if sup.stage == "tube" and all(p.phase.value == "in_tube" for p in sup.pilots):
            if not getattr(sup, "_told", False):
                sup._told = True
                print("IN_TUBE", flush=True)
    await fly(m, endpoints={endpoints!r}, sysids=[1, 2], tick_hook=hook)
asyncio.run(main())
"""


@pytest.mark.slow
async def test_pushed_out_while_our_process_is_stopped_the_fence_holds_it(
        tmp_path: Path) -> None:
    """The fleet runs in a child process; once in the tube the child is SIGSTOPped and a
    gust pushes vehicle 0 out through the left leg: PX4's offboard loss fires first, then the
    vehicle's own fence failsafe holds it (AUTO.LOITER) just outside the widened leg — judged
    on the mock's true and estimated state — while our process is still stopped."""
    m = _mission(tmp_path)
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(2), seed=8,
                          estimator="ideal") as fleet:
        root = str(Path(__file__).resolve().parents[1])
        code = _SIGSTOP_CHILD.format(root=root, tests=str(Path(__file__).parent),
                                     mission=str(tmp_path / "mission.toml"),
                                     endpoints=list(fleet.endpoints))
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-c", code, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        try:
            assert proc.stdout is not None
            async with asyncio.timeout(120.0):
                while (line := await proc.stdout.readline()) and b"IN_TUBE" not in line:
                    pass
            assert line, "the child ended before the tube"
            os.kill(proc.pid, signal.SIGSTOP)
            v = fleet.vehicles[0]
            # the fleet uploaded the tube's fence and GF_ACTION = hold to every vehicle
            want = [(it.command, round(it.lat_deg * 1e7), round(it.lon_deg * 1e7))
                    for it in fence_items(m)]
            for veh in fleet.vehicles:
                assert [(it.command, it.lat_e7, it.lon_e7) for it in veh.fence_items] == want
                assert veh.params["GF_ACTION"].value == 2
            h = math.radians(m.config.heading_deg)
            left = (math.sin(h), -math.cos(h))  # tube +y as (north, east)
            v.push(2.5 * left[0], 2.5 * left[1], 8.0)
            async with asyncio.timeout(30.0):
                while not v.fence_failsafe:
                    await asyncio.sleep(0.05)  # polling the mock's state, no synchronisation
            assert v.mode_name == "AUTO.LOITER" and v.armed
            frame = m.frame
            g = fence_geometry(m)
            est = v.estimated_position_ned
            x, y, _ = frame.local_ned_to_tube(est[0], est[1], est[2], *v.origin)
            assert not g.inside_polygon(np.array([float(x), float(y)]))
            assert float(y) > m.scenario.tube.p_h0[1] + g.widen_m - 0.5
            held = v.position_ned
            async with asyncio.timeout(20.0):
                while v._push_until is not None:
                    await asyncio.sleep(0.05)
            await asyncio.sleep(2.0)  # let the hold settle (PX4's position loop, not a sync)
            after = v.position_ned
            assert v.mode_name == "AUTO.LOITER"
            assert math.hypot(after[0] - held[0], after[1] - held[1]) < 8.0
            print(f"\nheld at tube y = {float(y):.2f} m (fence at "
                  f"{m.scenario.tube.p_h0[1] + g.widen_m:.2f} m)")
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGCONT)
                proc.kill()
            await proc.wait()


async def test_one_agent_audits_and_fences_its_vehicle(tmp_path: Path) -> None:
    """One-agent-per-process operation: the preflight's parameter audit and fence
    (:func:`~vtube_fleet.fleet.preflight.audit_and_fence`, run by :meth:`VehiclePilot.fly`
    before arming) for one pilot on a table of one row."""
    from vtube_fleet.fleet.pilot import VehiclePilot
    from vtube_fleet.fleet.preflight import PreflightError, audit_and_fence
    from vtube_fleet.fleet.table import FleetTable

    m = _mission(tmp_path).with_vehicles(1)
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(1), seed=5,
                          params={"GF_ACTION": 0}) as fleet:
        link = MavlinkLink(fleet.endpoints[0], sysid=1)
        try:
            await link.connect(10.0)
            pilot = VehiclePilot(link, FleetTable([0], m), 0, m)
            pilot.table.xy[0] = m.slots[0]  # where the tick would have sensed it
            await audit_and_fence([pilot], m)
            v = fleet.vehicles[0]
            assert len(v.fence_items) == len(fence_items(m)) and v.params["GF_ACTION"].value == 2
            v.params["MPC_XY_VEL_MAX"] = Param("MPC_XY_VEL_MAX", 1.0, 9)  # changed since
            with pytest.raises(PreflightError, match=r"MPC_XY_VEL_MAX = 1.0 m/s < v_max = 1.6"):
                await audit_and_fence([pilot], m)
            assert not v.armed
        finally:
            await link.close()


async def test_the_mavsdk_backend_audits_and_fences_the_fleet(tmp_path: Path) -> None:
    """``--backend mavsdk``: the same preflight as mavlink (GF_ACTION, upload, read back and
    compare, through MAVSDK's param and geofence plugins); stopped after take-off."""
    m = _mission(tmp_path)
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(2), seed=6,
                          params={"GF_ACTION": 0}) as fleet:

        def hook(tick: int, sup) -> None:
            if sup.stage == "takeoff" and sup._interrupted is None:
                sup.interrupt("test")

        result = await fly(m, backend="mavsdk", endpoints=fleet.endpoints, sysids=[1, 2],
                           out_dir=tmp_path, tick_hook=hook)
        want = fence_items(m)
        for v in fleet.vehicles:
            assert [(it.command, it.lat_e7, it.lon_e7) for it in v.fence_items] == [
                (it.command, round(it.lat_deg * 1e7), round(it.lon_deg * 1e7)) for it in want]
            assert v.params["GF_ACTION"].value == 2
    assert result.outcome == "interrupted", result.reason
    texts = [e["text"] for e in result.summary["events"] if e["level"] == "warning"]
    assert not any("NOT uploaded" in t or "audit skipped" in t for t in texts), texts
    onboard = result.summary["onboard"]
    assert onboard["fence"] == "uploaded" and onboard["fence_items"] == len(want)
    assert onboard["px4_params"][0]["MPC_XY_VEL_MAX"] == pytest.approx(12.0)


@contextlib.asynccontextmanager
async def one_vehicle_mavsdk(**kwargs):
    from vtube_fleet.link.mavsdk_link import MavsdkHub

    fleet = MockFleet(1, port_scheme=free_ports(1), boot_time_scale=0.3, **kwargs)
    await fleet.start()
    try:
        async with MavsdkHub() as hub:
            link = hub.link(fleet.endpoints[0], sysid=1)
            await link.connect(10.0)
            yield fleet.vehicles[0], link
    finally:
        await fleet.stop()


async def test_mavsdk_fence_upload_download_install_and_refusals(monkeypatch) -> None:
    """The real MAVSDK client's geofence plugin against the mock's FENCE protocol: what the
    vehicle stores is what we meant (degrees * 1e7), the read-back matches, install_fence sets
    GF_ACTION; a refusal is a FenceRejected with MAVSDK's result and keeps the stored fence."""
    from vtube_fleet.fleet.onboard import install_fence

    async with one_vehicle_mavsdk() as (v, link):
        items = square(v) + [FenceItem(5004, v.origin[0] + 5e-5, v.origin[1], 2.5)]
        await link.upload_fence(items)
        assert [(it.command, it.lat_e7, it.lon_e7, it.param1) for it in v.fence_items] == [
            (a.command, round(a.lat_deg * 1e7), round(a.lon_deg * 1e7), a.param1)
            for a in items]
        back = await link.download_fence()
        assert [(b.command, round(b.lat_deg * 1e7), round(b.lon_deg * 1e7)) for b in back] == [
            (a.command, round(a.lat_deg * 1e7), round(a.lon_deg * 1e7)) for a in items]
        assert [b.param1 for b in back] == pytest.approx([a.param1 for a in items])
        await install_fence(link, items, 3)
        assert v.params["GF_ACTION"].value == 3 and len(v.fence_items) == 5
        # refusals: too many items (PX4 NO_SPACE), a waypoint is not a fence item (refused
        # before sending), a circle before a polygon (MAVSDK would reorder them)
        monkeypatch.setattr(sim_stub.fence, "FENCE_MAX_ITEMS", 4)
        with pytest.raises(FenceRejected, match="fence upload refused: MAVSDK") as exc:
            await link.upload_fence(items)
        print(f"\n{exc.value}")
        assert exc.value.result != "SUCCESS"
        with pytest.raises(FenceRejected, match="command 16 is not a fence"):
            await link.upload_fence([FenceItem(16, v.origin[0], v.origin[1], 0.0)])
        with pytest.raises(FenceRejected, match="polygons before circles"):
            await link.upload_fence(items[-1:] + items[:-1])
        with pytest.raises(FenceRejected, match="polygon of 4 vertices"):
            await link.upload_fence(items[:3])
        assert len(v.fence_items) == 5 and len(await link.download_fence()) == 5
        await link.upload_fence([])  # clear_geofence
        assert v.fence_items == [] and await link.download_fence() == []


def test_run_has_no_fence_and_fix_params_flags() -> None:
    out = subprocess.run([sys.executable, "-m", "vtube_fleet", "run", "--help"],
                         capture_output=True, text=True, check=True).stdout
    assert "--no-fence" in out and "--fix-params" in out
    out = subprocess.run([sys.executable, "-m", "vtube_fleet", "agent", "--help"],
                         capture_output=True, text=True, check=True).stdout
    assert "--no-fence" in out


class RawGcs(asyncio.DatagramProtocol):
    """A bare pymavlink GCS (sysid 255, compid 190) on the vehicle's GCS port."""

    def __init__(self, v) -> None:
        from pymavlink.dialects.v20 import common as mav

        self.v = v
        self.mav = mav.MAVLink(None, 255, 190)
        self.rx = mav.MAVLink(None, 255, 190)
        self.rx.robust_parsing = True
        self.msgs: list = []
        self.new = asyncio.Event()
        self.transport = None

    def datagram_received(self, data: bytes, addr) -> None:
        self.msgs.extend(self.rx.parse_buffer(data) or [])
        self.new.set()

    def send(self, msg) -> None:
        self.transport.sendto(msg.pack(self.mav), self.v.bind_address)

    async def wait(self, pred, since: int, what: str, timeout: float = 10.0):
        async with asyncio.timeout(timeout):
            i = since
            while True:
                while i < len(self.msgs):
                    m = self.msgs[i]
                    i += 1
                    if pred(m):
                        return m, i
                self.new.clear()
                await self.new.wait()

    def of(self, type_: str, since: int = 0) -> list:
        return [m for m in self.msgs[since:] if m.get_type() == type_]


async def test_fence_protocol_retries_busy_duplicates_and_timeout() -> None:
    """PX4's mission-protocol rules as a raw GCS sees them: MISSION_REQUEST_INT(0) is repeated
    while no item comes; an out-of-order item is ignored; a MISSION_COUNT during a transfer is
    "WPM: REJ. CMD: Busy" + ACK ERROR and the transfer goes on; the last item repeated after
    the final ACK is ACKed ACCEPTED again; a silent transfer ends with "Operation timeout"."""
    from sim_stub import MockVehicle

    v = MockVehicle(0, ports=free_ports(1), boot_time_scale=0.3, estimator="ideal")
    await v.start()
    g = RawGcs(v)
    loop = asyncio.get_running_loop()
    g.transport, _ = await loop.create_datagram_endpoint(lambda: g, local_addr=v.gcs_address)
    try:
        await g.wait(lambda m: m.get_type() == "HEARTBEAT", 0, "heartbeat")
        lat, lon = round(v.origin[0] * 1e7), round(v.origin[1] * 1e7)

        def item(seq: int):
            return g.mav.mission_item_int_encode(1, 1, seq, 5, 5004, 0, 0, 3.0, 0, 0, 0,
                                                 lat + 1000 * seq, lon, 0.0, 1)

        def is_req(seq: int):
            return lambda m: m.get_type() == "MISSION_REQUEST_INT" and m.seq == seq

        mark = len(g.msgs)
        g.send(g.mav.mission_count_encode(1, 1, 2, 1))
        i = mark
        for _ in range(3):  # asked, and asked again while we stay silent
            _, i = await g.wait(is_req(0), i, "request 0")
        g.send(item(1))  # out of order: ignored, 0 is asked for again
        mark = len(g.msgs)
        await g.wait(is_req(0), mark, "request 0 after the wrong item")
        assert not g.of("MISSION_ACK", mark)
        g.send(item(0))
        await g.wait(is_req(1), mark, "request 1")
        mark = len(g.msgs)
        g.send(g.mav.mission_count_encode(1, 1, 2, 1))  # busy
        ack, _ = await g.wait(lambda m: m.get_type() == "MISSION_ACK", mark, "busy ack")
        assert ack.type == 1 and ack.mission_type == 1
        await g.wait(lambda m: m.get_type() == "STATUSTEXT" and "REJ. CMD: Busy" in m.text,
                     mark, "busy text")
        mark = len(g.msgs)
        g.send(item(1))
        ack, _ = await g.wait(lambda m: m.get_type() == "MISSION_ACK", mark, "final ack")
        assert ack.type == 0 and len(v.fence_items) == 2
        mark = len(g.msgs)
        g.send(item(1))  # the GCS missed the ACK: the same ACK again
        ack, _ = await g.wait(lambda m: m.get_type() == "MISSION_ACK", mark, "repeat ack")
        assert ack.type == 0 and len(v.fence_items) == 2
        mark = len(g.msgs)
        g.send(g.mav.mission_count_encode(1, 1, 3, 1))  # and now silence
        await g.wait(lambda m: m.get_type() == "STATUSTEXT" and "Operation timeout" in m.text,
                     mark, "timeout", timeout=15.0)
        assert len(v.fence_items) == 2  # the stored fence is kept
        mark = len(g.msgs)
        g.send(g.mav.mission_count_encode(1, 1, 1, 1))  # idle again: a new transfer starts
        await g.wait(is_req(0), mark, "a new transfer")
    finally:
        g.transport.close()
        await v.stop()


@pytest.mark.slow
@pytest.mark.parametrize("no_fence", [True, False])
async def test_agent_process_no_fence(tmp_path: Path, no_fence: bool) -> None:
    """``vtube-fleet agent --no-fence`` (one agent process, a real mosquitto, the coordinator
    process, a mock vehicle): nothing uploaded and the run's warning printed; without the flag
    the agent's vehicle has the tube fence before it arms. Interrupted (SIGINT) once armed."""
    from broker import LocalBroker

    m = load_mission(MOCK_FLEET).with_vehicles(1)
    root = Path(__file__).resolve().parents[1]
    log_path = tmp_path / "agent.log"
    with LocalBroker() as broker:
        async with mock_fleet(m, 1, boot_time_scale=0.3, port_scheme=free_ports(1)) as fleet:
            v = fleet.vehicles[0]
            with open(log_path, "wb") as fh:
                agent = await asyncio.create_subprocess_exec(
                    sys.executable, "-m", "vtube_fleet", "agent", str(MOCK_FLEET),
                    "--vehicle", "0", "--endpoint", fleet.endpoints[0], "--broker", broker.url,
                    "--join-timeout", "120", *(["--no-fence"] if no_fence else []),
                    stdout=fh, stderr=fh, cwd=root)
            coord = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "vtube_fleet", "mission", "start", str(MOCK_FLEET),
                "--broker", broker.url, "--vehicles", "1", "--wait", "--out",
                str(tmp_path / "out"), "--ready-timeout", "90", "--timeout", "200",
                stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL, cwd=root)
            try:
                loop = asyncio.get_running_loop()
                deadline = loop.time() + 120
                while not v.armed and agent.returncode is None:
                    assert loop.time() < deadline, log_path.read_text(errors="replace")[-2000:]
                    await asyncio.sleep(0.05)  # polling period of the condition
                fenced = list(v.fence_items)
                agent.send_signal(signal.SIGINT)
                await asyncio.wait_for(agent.wait(), 120)
            finally:
                for p in (agent, coord):
                    if p.returncode is None:
                        p.send_signal(signal.SIGTERM)
                        with contextlib.suppress(TimeoutError):
                            await asyncio.wait_for(p.wait(), 60)
                    if p.returncode is None:
                        p.kill()
                        await p.wait()
    text = log_path.read_text(errors="replace")
    from vtube_fleet.fleet.onboard import NO_FENCE_WARNING

    if no_fence:
        assert fenced == [] and NO_FENCE_WARNING in text, text[-2000:]
    else:
        assert len(fenced) == len(fence_items(m)) and NO_FENCE_WARNING not in text, text[-2000:]
