"""The ``mavsdk`` link backend with the real in-process MAVSDK client against the loopback fake
vehicle: discovery by system id, readiness, arm retries, offboard and the stall watchdog."""

from __future__ import annotations

import asyncio
import time

import pytest
from link_fake_vehicle import FakeVehicle, free_udp_port

from vtube_fleet.link import CommandRejected, LinkError, LinkTimeout
from vtube_fleet.link.mavsdk_link import MavsdkHub, MavsdkLink


def _setpoints(fake: FakeVehicle) -> int:
    return sum(1 for m in fake.received if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED")


def _is_set_mode(main: int):
    return lambda m: m.get_type() == "COMMAND_LONG" and m.command == 176 and m.param2 == main


@pytest.fixture
async def hub_fake():
    port = free_udp_port()
    fake = FakeVehicle(sysid=3, gcs_addr=("127.0.0.1", port))
    await fake.start()
    hub = MavsdkHub(watchdog_s=0.3)
    await hub.start()
    try:
        yield hub, fake, f"udpin://127.0.0.1:{port}"
    finally:
        await hub.close()
        await fake.stop()


async def test_watchdog_stops_offboard_when_loop_stalls(hub_fake) -> None:
    hub, fake, url = hub_fake
    link = hub.link(url, sysid=3)
    await link.connect(timeout_s=10.0)
    state = await link.wait_ready(timeout_s=10.0)
    assert state.sysid == 3 and state.health_ok and state.origin is not None
    assert state.flight_mode == "HOLD" and state.px4_mode == "AUTO.LOITER"

    fake.script[400] = [1, 0]  # TEMPORARILY_REJECTED once (PX4 right after boot), then ACCEPTED
    await link.arm(timeout_s=5.0, retry_interval_s=0.05)
    assert len(fake.commands(400)) == 2

    with pytest.raises(LinkError, match="stream velocity setpoints first"):
        await link.start_offboard()
    link.send_velocity_ned(0.0, 1.0, 0.0)
    await link.start_offboard()
    assert link.offboard_active
    await link.wait_until(lambda s: s.flight_mode == "OFFBOARD", 5.0, "OFFBOARD")

    # Our loop now "stalls" (no more send_velocity_ned). MAVSDK keeps resending the setpoint by
    # itself, so only the watchdog gets the vehicle out of offboard, into Hold.
    sent_by_us = link._setpoints_sent
    hold = await fake.wait_for(_is_set_mode(4), timeout_s=5.0)
    assert (hold.param2, hold.param3) == (4.0, 3.0)
    assert link.watchdog_trips == 1 and hub.watchdog_trips == 1 and not link.offboard_active
    assert _setpoints(fake) > sent_by_us  # MAVSDK resent setpoints we never sent again
    await link.wait_until(lambda s: s.flight_mode == "HOLD", 5.0, "HOLD after the watchdog")


async def test_no_trip_while_the_loop_runs_and_clean_stop(hub_fake) -> None:
    hub, fake, url = hub_fake
    link = hub.link(url, sysid=3, watchdog_s=1.5)  # > a loaded machine's stall of the test
    await link.connect(10.0)
    await link.wait_ready(10.0)
    link.send_velocity_ned(0.0, 0.0, 0.0)
    await link.start_offboard()
    for _ in range(40):  # a 20 Hz control loop for 2 s, longer than the watchdog
        link.send_velocity_ned(0.5, 0.0, 0.0)
        await asyncio.sleep(0.05)
    assert link.watchdog_trips == 0 and link.offboard_active
    await link.stop_offboard()
    assert not link.offboard_active
    await fake.wait_for(_is_set_mode(4), timeout_s=5.0)
    sp = [m for m in fake.received if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"][-1]
    assert sp.vx == pytest.approx(0.5) and sp.coordinate_frame == 1


async def test_commands_and_errors(hub_fake) -> None:
    hub, fake, url = hub_fake
    link = hub.link(url, sysid=3)
    with pytest.raises(LinkError, match="not connected"):
        await link.hold()
    await link.connect(10.0)
    await link.connect(10.0)  # idempotent
    await link.wait_ready(10.0)
    fake.script[400] = [2] * 50  # DENIED: MAVSDK reports COMMAND_DENIED; retried to the deadline
    with pytest.raises(CommandRejected) as info:
        await link.arm(timeout_s=0.3, retry_interval_s=0.05)
    assert info.value.result == "COMMAND_DENIED" and "attempt(s)" in str(info.value)
    assert f"vehicle 3 ({url})" in str(info.value)
    await link.land()
    assert len(fake.commands(21)) == 1
    await link.hold()
    await link.close()
    with pytest.raises(LinkError, match="closed"):
        link.send_velocity_ned(0.0, 0.0, 0.0)


async def test_sysid_rules_and_discovery_timeout() -> None:
    async with MavsdkHub() as hub:
        assert hub.link("udpin://127.0.0.1:14542").sysid == 3  # PX4 SITL scheme
        with pytest.raises(LinkError, match="needs the vehicle's system id"):
            hub.link("udpin://127.0.0.1:15000")
        port = free_udp_port()
        link = hub.link(f"udpin://127.0.0.1:{port}", sysid=9)
        with pytest.raises(LinkTimeout) as info:
            await link.connect(timeout_s=0.3)
        msg = str(info.value)
        assert msg.startswith(f"vehicle 9 (udpin://127.0.0.1:{port}): mavsdk: no system 9")
        assert "systems seen: none" in msg


def test_stall_detection_logic() -> None:
    hub = MavsdkHub(watchdog_s=0.5)
    link = MavsdkLink(hub, "udpin://127.0.0.1:14540")
    now = time.monotonic()
    assert link._stall_s(now) is None  # offboard not active
    link._offboard_active = True
    assert link._stall_s(now) is None  # never sent
    link._last_setpoint_s = now - 0.4
    assert link._stall_s(now) is None
    link._last_setpoint_s = now - 0.7
    assert link._stall_s(now) == pytest.approx(0.7)
    with pytest.raises(LinkError, match="watchdog_s must be > 0"):
        MavsdkHub(watchdog_s=0.0)


async def test_open_links_mavsdk_backend() -> None:
    from vtube_fleet.link import open_links

    port = free_udp_port()
    async with FakeVehicle(sysid=5, gcs_addr=("127.0.0.1", port)) as fake:
        await fake.start()
        async with open_links([f"udpin://127.0.0.1:{port}"], "mavsdk", sysids=[5],
                              watchdog_s=0.2) as links:
            (link,) = links
            assert isinstance(link, MavsdkLink) and link.watchdog_s == 0.2
            await link.connect(10.0)
            await link.wait_until(lambda s: s.flight_mode == "HOLD", 5.0, "HOLD")
        assert link.closed
