"""Both link backends against the wire-level PX4 mock (``sim_stub``), one boot, concurrently:
vehicle 1 through the ``mavlink`` backend, vehicle 2 through ``mavsdk`` (the real MAVSDK client).

Each: connect, arm right away (the mock, like PX4, answers TEMPORARILY_REJECTED for the first
seconds after boot), wait_ready, takeoff, offboard velocity, then our control loop "stalls":
with ``mavlink`` PX4's own offboard-loss failsafe takes over (POSCTL), with ``mavsdk`` our
watchdog stops offboard (Hold) because MAVSDK keeps resending; then land until auto-disarm.
"""

from __future__ import annotations

import asyncio
import contextlib

import pytest
from fleet_ports import PX4_PORTS

from vtube_fleet.link import MavlinkLink, VehicleLink
from vtube_fleet.link.mavsdk_link import MavsdkHub, MavsdkLink

sim_stub = pytest.importorskip("sim_stub")

pytestmark = pytest.mark.timeout(180)


class Streamer:
    """A 20 Hz control loop that sends the current velocity setpoint until stopped."""

    def __init__(self, link: VehicleLink) -> None:
        self.link = link
        self.setpoint = (0.0, 0.0, 0.0)
        self.task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self.link.send_velocity_ned(*self.setpoint)
        self.task = asyncio.get_running_loop().create_task(self._run())

    async def _run(self) -> None:
        while True:
            self.link.send_velocity_ned(*self.setpoint)
            await asyncio.sleep(0.05)  # the control period, not a synchronisation

    async def stop(self) -> None:
        if self.task is not None:
            self.task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self.task


async def fly(link: VehicleLink, vehicle) -> None:
    await link.connect(timeout_s=15.0)
    await link.arm(timeout_s=15.0, retry_interval_s=0.25)
    rejected = [t for t in vehicle.statustexts if "Arming denied" in t[2]]
    assert rejected, "the boot-time arming rejection was expected"
    state = await link.wait_ready(timeout_s=20.0)
    assert state.origin is not None and state.home is not None and state.health_ok

    await link.takeoff(3.0)
    await link.wait_until(lambda s: s.down_m < -2.5, 30.0, "2.5 m climb in AUTO.TAKEOFF")

    streamer = Streamer(link)
    try:
        streamer.start()
        await link.start_offboard()
        await link.wait_until(lambda s: s.flight_mode == "OFFBOARD", 5.0, "OFFBOARD")
        north0 = link.state.north_m
        streamer.setpoint = (1.0, 0.0, 0.0)
        await link.wait_until(lambda s: s.north_m > north0 + 1.5, 20.0, "1.5 m north")
    finally:
        await streamer.stop()  # the control loop stalls from here on

    if isinstance(link, MavlinkLink):  # nothing resends: PX4's failsafe sees the stall
        await link.wait_until(lambda s: s.flight_mode == "POSCTL", 10.0, "offboard-loss failsafe")
        assert any(t.text == "Failsafe activated" for t in link.state.statustexts)
    else:
        assert isinstance(link, MavsdkLink)
        await link.wait_until(lambda s: s.flight_mode == "HOLD", 10.0, "Hold by the watchdog")
        assert link.watchdog_trips == 1

    await link.land()
    await link.wait_until(
        lambda s: s.landed_state == "ON_GROUND" and s.armed is False, 60.0, "landed and disarmed"
    )


@pytest.mark.xdist_group(PX4_PORTS)  # PX4 SITL's own ports: one at a time, and
@pytest.mark.solo  # nothing else beside it (another test's mock bound 18570 once)
async def test_both_backends_fly_the_mock() -> None:
    async with sim_stub.MockFleet(count=2, spacing_m=5.0) as fleet, MavsdkHub(
        watchdog_s=0.5
    ) as hub:
        mav = MavlinkLink(fleet.endpoints[0])
        sdk = hub.link(fleet.endpoints[1])
        assert sdk.sysid == 2
        try:
            await asyncio.gather(fly(mav, fleet.vehicles[0]), fly(sdk, fleet.vehicles[1]))
        finally:
            await mav.close()
        assert mav.state.bad_packets == 0 and mav.state.foreign_packets == 0
        assert mav.latency_s is not None and mav.latency_source == "TIMESYNC"
