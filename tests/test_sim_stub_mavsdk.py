"""The real MAVSDK client (mavsdk 4 native asyncio API) flies sim_stub vehicles over UDP.

PX4-faithful timing (no boot shortening): connect, wait until MAVSDK reports the vehicle healthy,
arm, take off (NAV_TAKEOFF with MIS_TAKEOFF_ALT), start offboard, fly velocity setpoints, stop
offboard (→ Hold), land, auto-disarm. Once with one mock, once with three at once through one
``Mavsdk`` instance (systems found by sysid, not by order).
"""

from __future__ import annotations

import asyncio

import pytest

mavsdk = pytest.importorskip("mavsdk")

from mavsdk import ComponentType, Configuration  # noqa: E402
from mavsdk.asyncio import Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync  # noqa: E402
from mavsdk.plugins.offboard import VelocityNedYaw  # noqa: E402

from sim_stub import MockFleet, MockVehicle  # noqa: E402
from sim_stub.ports import free_port_scheme  # noqa: E402

pytestmark = pytest.mark.timeout(150)


async def first(agen, pred, timeout: float, what: str):
    """First item of an async generator satisfying ``pred`` (with a timeout)."""

    async def scan():
        async for item in agen:
            if pred(item):
                return item

    try:
        return await asyncio.wait_for(scan(), timeout)
    except TimeoutError:
        raise AssertionError(f"MAVSDK: no {what} within {timeout} s") from None


async def fly(system, vehicle: MockVehicle, east_m_s: float) -> None:
    tel, act, off = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)
    await first(tel.subscribe_health_all_ok(), bool, 30.0, "health_all_ok")
    assert vehicle.system_status == 3  # STANDBY: PX4's prearm checks pass
    await act.arm()
    assert vehicle.armed
    await act.takeoff()
    await first(tel.subscribe_in_air(), bool, 15.0, "in_air")
    await first(tel.subscribe_position_velocity_ned(), lambda p: p.position.down_m < -2.0, 20.0,
                "2 m altitude")  # fmt: skip
    await off.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.0, 0.0))
    await off.start()
    assert vehicle.mode_name == "OFFBOARD"
    await off.set_velocity_ned(VelocityNedYaw(0.0, east_m_s, 0.0, 90.0))
    p = await first(tel.subscribe_position_velocity_ned(), lambda p: p.position.east_m > 2.0,
                    20.0, "2 m east")  # fmt: skip
    loop = asyncio.get_running_loop()
    received = loop.time()
    assert p.velocity.east_m_s > 0.5
    # MAVSDK's view is the vehicle's estimate (LOCAL_POSITION_NED, relative to its origin), as it
    # was when sent (<= 0.5 s before it arrived): since then the vehicle flew on east at most
    # 2 east_m_s per second (the estimate is not the truth: the px4-sih error profile is
    # checked in test_sim_stub_estimator)
    moved = vehicle.estimated_position_ned[1] - p.position.east_m
    assert -0.05 <= moved <= 2.0 * east_m_s * (loop.time() - received + 0.5)
    await off.stop()
    assert vehicle.mode_name == "AUTO.LOITER"  # MAVSDK: offboard.stop() leaves PX4 in Hold
    await act.land()
    await first(tel.subscribe_in_air(), lambda a: not a, 40.0, "landed")
    await first(tel.subscribe_armed(), lambda a: not a, 10.0, "auto-disarm")
    assert vehicle.position_ned[2] == 0.0 and not vehicle.armed
    texts = [t[2] for t in vehicle.statustexts]
    assert "Landing detected\t" in texts and "Disarmed by landing\t" in texts


def _config() -> Configuration:
    return Configuration.create_with_component_type(ComponentType.GROUND_STATION)


async def discover(m: Mavsdk, n: int, timeout: float = 10.0) -> dict[int, object]:
    """The first ``n`` systems MAVSDK discovers, by sysid (woken by ``on_new_system``)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    events = m.on_new_system()
    try:
        while True:
            found = {await s.get_system_id(): s for s in await m.get_systems()}
            if len(found) >= n:
                return found
            left = deadline - loop.time()
            if left <= 0:
                raise AssertionError(f"MAVSDK found {sorted(found)} of {n} systems in {timeout} s")
            try:  # re-check at least every second: an event may fire before we subscribed
                await asyncio.wait_for(events.__anext__(), min(1.0, left))
            except TimeoutError:
                pass
    finally:
        await events.aclose()


async def one_mock() -> None:
    ports = free_port_scheme(1)
    async with MockVehicle(0, ports=ports) as v, Mavsdk(_config()) as m:
        await m.add_any_connection(ports.endpoint(0))
        found = await discover(m, 1)
        assert sorted(found) == [1]
        await fly(found[1], v, 1.5)
        assert v.counters.rx_malformed == 0 and v.commands[400] >= 1 and v.commands[22] == 1


async def three_mocks() -> None:
    ports = free_port_scheme(3)
    async with MockFleet(3, port_scheme=ports, spacing_m=8.0) as fleet, Mavsdk(_config()) as m:
        for url in fleet.endpoints:
            await m.add_any_connection(url)
        found = await discover(m, 3)
        assert sorted(found) == [1, 2, 3]
        await asyncio.gather(
            *(fly(found[v.sysid], v, 1.0 + 0.5 * i) for i, v in enumerate(fleet.vehicles))
        )
        # each vehicle landed 2+ m east of its own start point, i.e. at its own place
        lats = {round(v.global_position[0], 6) for v in fleet.vehicles}
        assert len(lats) >= 2


async def test_mavsdk_flies_one_mock_and_three_at_once() -> None:
    """Two independent MAVSDK instances, concurrently (saves CI time): one with one mock, one
    with a fleet of three mocks."""
    await asyncio.gather(one_mock(), three_mocks())
