"""What a link believes of its vehicle (issue 33): its identity (one system id per port), its
source (one address, re-learned only by the logged path) and the plausibility of what it
reports (link/guard.py). Datagrams are fed to ``MavlinkLink.feed_datagram`` as the socket
hands them over (address and arrival time given), built with pymavlink; the end-to-end spoof
flights are in ``test_link_spoofing.py``."""

from __future__ import annotations

import logging
import math
import os
import re
from pathlib import Path

import pytest
from link_fake_vehicle import FakeVehicle, free_udp_port
from missions import PX4_SITL_3
from pymavlink.dialects.v20 import common as mav

from vtube_fleet.config.mission import load_mission
from vtube_fleet.link import (
    LinkConflict,
    LinkTimeout,
    MavlinkLink,
    TelemetryBounds,
    open_links,
)
from vtube_fleet.link.guard import SPEED_MARGIN_M_S
from vtube_fleet.link.signing import LinkSigning, TimestampStore

VEHICLE = ("127.0.0.1", 14580)
SPOOFER = ("127.0.0.1", 47001)
#: px4_sitl_3's bounds: v_max 1.6 + 5 m/s, vertical 3 + 2 m/s, accuracy cap 1 m
BOUNDS = TelemetryBounds(max_speed_m_s=6.6, max_vertical_speed_m_s=5.0)


def codec(sysid: int = 1, compid: int = 1) -> mav.MAVLink:
    return mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)


def hb(m: mav.MAVLink, autopilot: int = 12, mav_type: int = 2) -> bytes:
    return m.heartbeat_encode(mav_type, autopilot, 157, 393216, 4).pack(m)


def lpn(m: mav.MAVLink, tb: int, n: float, e: float = 0.0, d: float = -5.0, vn: float = 0.0,
        ve: float = 0.0, vd: float = 0.0) -> bytes:
    return m.local_position_ned_encode(tb, n, e, d, vn, ve, vd).pack(m)


def pinned_link(url: str = "udpin://127.0.0.1:14540", sysid: int = 1, **kw: object
                ) -> tuple[MavlinkLink, mav.MAVLink]:
    """A link that learned its vehicle (``sysid`` at :data:`VEHICLE`) from a HEARTBEAT."""
    link = MavlinkLink(url, sysid=sysid, **kw)  # type: ignore[arg-type]
    m = codec(sysid)
    link.feed_datagram(hb(m), VEHICLE, now=0.0)
    assert link.remote_address == VEHICLE
    return link, m


# -- plausibility -----------------------------------------------------------------------------
@pytest.mark.parametrize("fast", [True, False], ids=["fast_codec", "pymavlink"])
def test_what_cannot_be_true_is_refused_counted_and_changes_nothing(fast: bool) -> None:
    link, m = pinned_link(telemetry=BOUNDS, fast_codec=fast)
    st = link.state
    link.feed_datagram(lpn(m, 10_000, 0.0), VEHICLE, now=10.0)
    link.feed_datagram(lpn(m, 10_020, 0.03, vn=1.5), VEHICLE, now=10.02)
    assert (st.time_boot_ms, st.north_m, st.vn_m_s) == (10_020, pytest.approx(0.03), 1.5)
    before = (st.time_boot_ms, st.north_m, st.east_m, st.down_m, st.vn_m_s, st.last_position_s)
    bad = [
        ("speed", lpn(m, 10_040, 0.06, vn=9.0)),  # 9 m/s > 6.6
        ("speed", lpn(m, 10_040, 0.06, vd=-6.0)),  # climbing at 6 m/s > 5
        ("position_jump", lpn(m, 10_040, 14.2)),  # 14.2 m in 20 ms
        ("position_jump", lpn(m, 10_040, 0.06, d=-8.0)),  # 3 m up in 20 ms
        ("time_backwards", lpn(m, 9_000, 0.03)),
        ("time_backwards", lpn(m, 10_020, 0.5)),  # its last time again, another position
        ("time_jump", lpn(m, 900_000, 0.06)),  # 890 s ahead in 20 ms
    ]
    for k, (_, data) in enumerate(bad):
        link.feed_datagram(data, VEHICLE, now=10.04 + 0.001 * k)
    assert dict(st.telemetry_refused) == {"speed": 2, "position_jump": 2, "time_backwards": 2,
                                          "time_jump": 1}
    assert (st.time_boot_ms, st.north_m, st.east_m, st.down_m, st.vn_m_s,
            st.last_position_s) == before
    # the same sample again is no news, and no refusal; the next true one is taken
    link.feed_datagram(lpn(m, 10_020, 0.03, vn=1.5), VEHICLE, now=10.05)
    link.feed_datagram(lpn(m, 10_060, 0.09, vn=1.5), VEHICLE, now=10.06)
    assert st.north_m == pytest.approx(0.09) and st.telemetry_refused.total() == 7
    assert st.telemetry_fault is None  # 7 refusals in 7 ms: not (yet) persistent


def test_global_position_is_checked_too() -> None:
    link, m = pinned_link(telemetry=BOUNDS)
    st = link.state
    gpi = lambda tb, lat, vx=0: m.global_position_int_encode(  # noqa: E731
        tb, lat, 85455940, 493000, 5000, vx, 0, 0, 0).pack(m)
    link.feed_datagram(gpi(10_000, 473977420), VEHICLE, now=10.0)
    link.feed_datagram(gpi(10_100, 473977430), VEHICLE, now=10.1)  # 0.11 m in 0.1 s
    assert st.lat_deg == pytest.approx(47.397743)
    link.feed_datagram(gpi(10_200, 473978430), VEHICLE, now=10.2)  # 11 m in 0.1 s
    link.feed_datagram(gpi(10_300, 473977440, vx=1500), VEHICLE, now=10.3)  # 15 m/s
    assert st.lat_deg == pytest.approx(47.397743)
    assert dict(st.telemetry_refused) == {"position_jump": 1, "speed": 1}


def test_interleaved_sources_become_a_fault_after_the_window() -> None:
    """The attack of issue 33 through one address (an attacker who forges it): the vehicle's
    own samples and fakes near the obstacle, 50 Hz each. Every fake is refused; after 0.5 s
    the link says its telemetry comes from two sources."""
    link, m = pinned_link(telemetry=BOUNDS)
    st = link.state
    t = 10.0
    for k in range(40):  # 0.8 s
        link.feed_datagram(lpn(m, 10_000 + 20 * k, 0.03 * k), VEHICLE, now=t)
        link.feed_datagram(lpn(m, 10_000 + 20 * k + 1, 14.2 + 0.03 * k, vn=3.0), VEHICLE,
                           now=t + 0.001)
        if k == 20:
            assert st.telemetry_fault is None  # 0.4 s of refusals: not yet
        t += 0.02
    assert st.telemetry_refused["position_jump"] == 40 and st.north_m == pytest.approx(1.17)
    fault = st.telemetry_fault
    assert fault is not None and link.telemetry_fault == fault
    assert fault.startswith("telemetry from two sources: position jumped 14.2 m in 1 ms ("), fault
    assert re.search(r"\(2\d of 5\d position samples refused in 0\.5\d s\)$", fault), fault


def test_a_single_glitch_is_counted_but_no_fault_and_a_persistent_jump_is_one() -> None:
    link, m = pinned_link(telemetry=BOUNDS)
    st = link.state
    link.feed_datagram(lpn(m, 10_000, 0.0), VEHICLE, now=10.0)
    link.feed_datagram(lpn(m, 10_020, 9.0), VEHICLE, now=10.02)  # one glitch
    for k in range(2, 150):  # then 3 s of good samples
        link.feed_datagram(lpn(m, 10_000 + 20 * k, 0.02 * k), VEHICLE, now=10.0 + 0.02 * k)
    assert st.telemetry_refused["position_jump"] == 1 and st.telemetry_fault is None
    # the estimate jumps by 9 m and stays there (an estimator reset, or a takeover): every
    # sample after it is refused; after 0.5 s that is a fault of one source
    for k in range(150, 200):
        link.feed_datagram(lpn(m, 10_000 + 20 * k, 9.0 + 0.02 * k), VEHICLE,
                           now=10.0 + 0.02 * k)
    assert st.telemetry_fault is not None
    assert st.telemetry_fault.startswith("position jumped 9"), st.telemetry_fault
    assert st.north_m == pytest.approx(0.02 * 149)


def test_a_chain_of_small_jumps_is_held_by_the_anchor() -> None:
    """Fakes every 2 ms, each within a sample's allowance of the one before (0.3 m): without
    the anchor they would walk at 150 m/s; with it the second step is refused."""
    link, m = pinned_link(telemetry=BOUNDS)
    st = link.state
    link.feed_datagram(lpn(m, 10_000, 0.0), VEHICLE, now=10.0)
    link.feed_datagram(lpn(m, 10_002, 0.3), VEHICLE, now=10.002)
    assert st.north_m == pytest.approx(0.3)
    link.feed_datagram(lpn(m, 10_004, 0.6), VEHICLE, now=10.004)
    assert st.north_m == pytest.approx(0.3) and st.telemetry_refused["position_jump"] == 1


def test_the_reported_accuracy_widens_the_allowance_up_to_its_cap() -> None:
    link, m = pinned_link(telemetry=BOUNDS)
    st = link.state
    est = lambda sigma: m.estimator_status_encode(  # noqa: E731
        0, 0, 0, 0, 0, 0, 0, 0, sigma, 0.5).pack(m)
    link.feed_datagram(lpn(m, 10_000, 0.0), VEHICLE, now=10.0)
    link.feed_datagram(lpn(m, 10_001, 0.5), VEHICLE, now=10.001)  # 0.3 m floor only
    assert st.telemetry_refused["position_jump"] == 1
    link.feed_datagram(est(0.3), VEHICLE, now=10.002)  # σ 0.3 m: 0.6 m allowed
    link.feed_datagram(lpn(m, 10_003, 0.5), VEHICLE, now=10.003)
    assert st.north_m == pytest.approx(0.5)
    link.feed_datagram(est(500.0), VEHICLE, now=10.004)  # a spoofed σ: capped at 1 m
    link.feed_datagram(lpn(m, 10_005, 2.5), VEHICLE, now=10.005)
    assert st.north_m == pytest.approx(0.5) and st.telemetry_refused["position_jump"] == 2
    assert st.pos_accuracy_m == 500.0  # (reported as is; the budget refuses it)


def test_bounds_come_from_the_mission() -> None:
    mission = load_mission(PX4_SITL_3)
    b = TelemetryBounds.for_mission(mission)
    assert b.max_speed_m_s == pytest.approx(1.6 + SPEED_MARGIN_M_S)
    assert b.max_vertical_speed_m_s == pytest.approx(3.0 + 2.0)
    assert b.accuracy_cap_m == mission.config.max_position_accuracy_m
    with pytest.raises(ValueError, match="max_speed_m_s must be finite and > 0"):
        TelemetryBounds(max_speed_m_s=math.nan)


def test_the_test_switch_turns_the_checks_off() -> None:
    link, m = pinned_link(telemetry=None)
    link.feed_datagram(lpn(m, 10_000, 0.0), VEHICLE, now=10.0)
    link.feed_datagram(lpn(m, 10_020, 14.2, vn=9.0), VEHICLE, now=10.02)
    assert link.state.north_m == pytest.approx(14.2) and not link.state.telemetry_refused


# -- source ------------------------------------------------------------------------------------
@pytest.mark.parametrize("fast", [True, False], ids=["fast_codec", "pymavlink"])
def test_the_vehicle_id_from_another_address_is_refused(fast: bool) -> None:
    link, m = pinned_link(telemetry=BOUNDS, fast_codec=fast)
    st = link.state
    link.feed_datagram(lpn(m, 10_000, 0.0), VEHICLE, now=10.0)
    for k in range(5):  # a naive spoofer: its own address, the vehicle's id
        link.feed_datagram(lpn(m, 10_010 + k, 22.0, vn=3.0), SPOOFER, now=10.01)
        link.feed_datagram(m.attitude_encode(10_010, 0, 0, 0, 0, 0, 0).pack(m), SPOOFER,
                           now=10.01)
    link.feed_datagram(m.heartbeat_encode(2, 12, 29, 50593792, 3).pack(m), SPOOFER, now=10.01)
    assert st.telemetry_refused["other_source"] == 11
    assert st.north_m == 0.0 and st.armed is True and st.flight_mode == "OFFBOARD"
    assert link.remote_address == VEHICLE  # setpoints still go to the vehicle
    link.feed_datagram(lpn(m, 10_020, 0.03), VEHICLE, now=10.02)
    assert st.north_m == pytest.approx(0.03) and st.telemetry_fault is None


def test_without_source_pinning_anyone_speaks_but_setpoints_stay_with_the_vehicle() -> None:
    link, m = pinned_link(telemetry=None, pin_source=False)
    link.feed_datagram(lpn(m, 10_000, 22.0), SPOOFER, now=10.0)
    assert link.state.north_m == 22.0 and link.remote_address == VEHICLE


def test_the_address_is_relearned_only_after_silence_and_three_heartbeats(
        caplog: pytest.LogCaptureFixture) -> None:
    link, m = pinned_link(telemetry=BOUNDS)
    new = ("127.0.0.1", 40123)
    link.feed_datagram(lpn(m, 10_000, 0.0), VEHICLE, now=1.0)
    for t in (2.0, 3.0, 3.5):  # the old address spoke 1-2.5 s ago: refused
        link.feed_datagram(hb(m), new, now=t)
    assert link.remote_address == VEHICLE and link.state.telemetry_refused["other_source"] == 3
    with caplog.at_level(logging.WARNING, logger="vtube_fleet.link.mavlink"):
        for t in (4.5, 5.5):  # silent 3.5 s and more: candidates
            link.feed_datagram(hb(m), new, now=t)
        assert link.remote_address == VEHICLE
        link.feed_datagram(lpn(m, 15_000, 0.1), new, now=6.0)  # not a HEARTBEAT: refused
        link.feed_datagram(hb(m), new, now=6.5)
    assert link.remote_address == new and link.state.source_changes == 1
    assert "vehicle address re-learned: 127.0.0.1:14580 -> 127.0.0.1:40123 (3 HEARTBEATs" in (
        caplog.text)
    link.feed_datagram(lpn(m, 16_000, 0.1), new, now=7.0)
    assert link.state.north_m == pytest.approx(0.1)
    link.feed_datagram(lpn(m, 16_020, 0.1), VEHICLE, now=7.02)  # the old one: refused now
    assert link.state.telemetry_refused["other_source"] == 7  # 3 + 2 candidates + 1 + 1
    # it spoke from the new address while the old one was alive: refused before arming
    with pytest.raises(LinkConflict, match="system 1 speaks from 2 addresses"):
        link.check_identity()


def test_a_heartbeat_stream_from_an_address_that_is_alive_never_takes_over() -> None:
    link, m = pinned_link(telemetry=BOUNDS)
    for k in range(20):  # the vehicle streams 20 s; the spoofer's HEARTBEATs every second
        link.feed_datagram(lpn(m, 10_000 + 1000 * k, 0.0), VEHICLE, now=1.0 + k)
        link.feed_datagram(hb(m), SPOOFER, now=1.5 + k)
    assert link.remote_address == VEHICLE and link.state.source_changes == 0


# -- identity ----------------------------------------------------------------------------------
def test_several_vehicles_on_the_gcs_port_14550_are_refused_naming_them_and_the_cause() -> None:
    """PX4 SITL instance 10's API port is 14550, where instances 0-9 send their GCS link:
    the link of instance 10 (system 11) hears ten other vehicles."""
    link, m = pinned_link("udpin://127.0.0.1:14550", sysid=11)
    st = link.state
    link.feed_datagram(hb(codec(255, 190), autopilot=8, mav_type=6), ("127.0.0.1", 14570),
                       now=0.1)  # a GCS's HEARTBEAT (PX4 forwards them): not a vehicle
    link.check_identity()
    for i in range(10):
        o = codec(i + 1)
        link.feed_datagram(hb(o), ("127.0.0.1", 18570 + i), now=0.5)
        link.feed_datagram(lpn(o, 5_000, 3.0), ("127.0.0.1", 18570 + i), now=0.5)
    assert st.foreign_packets == 21 and st.telemetry_refused["other_sysid"] == 20
    assert math.isnan(st.north_m)
    with pytest.raises(LinkConflict) as err:
        link.check_identity()
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("vehicle 11 (udpin://127.0.0.1:14550): ")
    assert "hears 11 vehicles, systems 1, 2, 3" in msg and "and 11" in msg
    assert "this link flies system 11" in msg and "127.0.0.1:18570" in msg
    assert "14550 is where PX4 SITL's GCS link sends" in msg
    assert "move the GCS link" in msg and "another API port scheme" in msg


def test_two_instances_with_one_id_on_a_port_are_refused() -> None:
    link, m = pinned_link("udpin://127.0.0.1:24000", sysid=2)
    link.feed_datagram(hb(m), ("127.0.0.1", 24101), now=0.5)
    with pytest.raises(LinkConflict, match=r"system 2 speaks from 2 addresses, 127\.0\.0\.1:"
                                           r"14580 and 127\.0\.0\.1:24101: two vehicles with one "
                                           r"MAV_SYS_ID"):
        link.check_identity()


async def test_a_wrong_id_names_the_one_heard_and_the_endpoint_syntax() -> None:
    port = free_udp_port()
    async with FakeVehicle(sysid=1, gcs_addr=("127.0.0.1", port), heartbeat_hz=20.0) as fake:
        await fake.start()
        link = MavlinkLink(f"udpin://127.0.0.1:{port}", sysid=4)
        try:
            with pytest.raises(LinkTimeout) as err:
                await link.connect(timeout_s=0.8)
        finally:
            await link.close()
    msg = str(err.value)
    assert "heard system 1 instead: this link flies system 4" in msg
    assert f"udpin://127.0.0.1:{port}?sysid=1" in msg


async def test_open_links_takes_the_endpoint_id_and_refuses_a_contradiction() -> None:
    async with open_links(["udpin://127.0.0.1:24540?sysid=7"], "mavlink") as links:
        assert links[0].sysid == 7 and links[0].name == (
            "vehicle 7 (udpin://127.0.0.1:24540?sysid=7)")
    with pytest.raises(Exception, match="system id 3 given for an endpoint that says sysid=7"):
        async with open_links(["udpin://127.0.0.1:24540?sysid=7"], "mavlink", sysids=[3]):
            pass
    with pytest.raises(Exception, match="listed more than once"):
        async with open_links(["udpin://127.0.0.1:24541?sysid=1",
                               "udpin://127.0.0.1:24541?sysid=2"], "mavlink"):
            pass


# -- signing first -----------------------------------------------------------------------------
def test_with_a_key_unsigned_fakes_are_refused_before_any_of_this(tmp_path: Path) -> None:
    key = bytes(range(1, 33))
    store_file = tmp_path / "fleet.key.timestamp"
    link = MavlinkLink("udpin://127.0.0.1:14540", sysid=1, telemetry=BOUNDS, signing=LinkSigning(
        key, TimestampStore(store_file)))
    os.chmod(store_file, 0o600)
    signed = codec(1)
    signed.signing.secret_key = key
    signed.signing.sign_outgoing = True
    signed.signing.timestamp = TimestampStore(tmp_path / "v.ts").now()
    link.feed_datagram(hb(signed), VEHICLE, now=0.0)
    link.feed_datagram(lpn(signed, 10_000, 0.0), VEHICLE, now=10.0)
    assert link.remote_address == VEHICLE and link.state.north_m == 0.0
    m = codec(1)
    for src in (SPOOFER, VEHICLE):  # unsigned: from anywhere, even the vehicle's address
        link.feed_datagram(lpn(m, 10_001, 22.0), src, now=10.01)
        link.feed_datagram(hb(m), src, now=10.01)
    assert link.signing_refused["unsigned"] == 4
    assert not link.state.telemetry_refused and link.state.north_m == 0.0


def test_a_stall_of_our_loop_with_lost_datagrams_is_no_refusal() -> None:
    """The reference read 1 s late (our loop stalled), the datagrams after it lost (a full
    socket buffer), the next one read in the same round: it looks 1 s early, and is still
    taken (the cap of Δt, no time_jump below 2 s)."""
    link, m = pinned_link(telemetry=BOUNDS)
    st = link.state
    link.feed_datagram(lpn(m, 10_000, 0.0), VEHICLE, now=10.0)
    link.feed_datagram(lpn(m, 10_020, 0.03), VEHICLE, now=11.0)  # read 0.98 s late
    for k in range(50):  # lost: 10_040 .. 11_020; read promptly from 11_040 on
        link.feed_datagram(lpn(m, 11_040 + 20 * k, 1.56 + 0.03 * k), VEHICLE,
                           now=11.0 + 0.02 * k)
    assert not st.telemetry_refused and st.north_m == pytest.approx(1.56 + 0.03 * 49)


def test_a_reference_read_very_late_costs_one_refusal_not_a_fault() -> None:
    """As above with a 2.5 s stall: the first prompt sample looks 2.5 s early (time_jump,
    compared with the last sample seen); the next ones are compared with it and taken once
    our clock has moved a little (the cap of Δt heals)."""
    link, m = pinned_link(telemetry=BOUNDS)
    st = link.state
    link.feed_datagram(lpn(m, 10_000, 0.0), VEHICLE, now=10.0)
    link.feed_datagram(lpn(m, 10_020, 0.03), VEHICLE, now=12.5)  # read 2.48 s late
    for k in range(50):  # lost until 12_520; prompt from then on, at 1.5 m/s
        link.feed_datagram(lpn(m, 12_520 + 20 * k, 3.78 + 0.03 * k), VEHICLE,
                           now=12.52 + 0.02 * k)
    assert st.telemetry_refused["time_jump"] == 1
    assert st.telemetry_refused.total() < 25 and st.telemetry_fault is None
    assert st.north_m == pytest.approx(3.78 + 0.03 * 49)


def test_another_vehicles_position_stream_alone_is_a_conflict() -> None:
    """Its autopilot's packets (compid 1) are enough, before any HEARTBEAT of it (PX4 streams
    LOCAL_POSITION_NED from 0.5 s after boot, its first HEARTBEAT comes at 1.3 s); a
    companion's or a GCS's packets of another id are not a vehicle."""
    link, m = pinned_link("udpin://127.0.0.1:24010", sysid=3)
    link.feed_datagram(lpn(codec(7, 191), 5_000, 1.0), ("127.0.0.1", 24111), now=0.2)
    link.check_identity()
    link.feed_datagram(lpn(codec(7), 5_000, 1.0), ("127.0.0.1", 24111), now=0.3)
    with pytest.raises(LinkConflict, match=r"its port hears 2 vehicles, systems 3 and 7 \(this "
                                           r"link flies system 3; the others from 127\.0\.0\.1:"
                                           r"24111\)"):
        link.check_identity()
    # a tool of a ground station (ids 245-255) sending from compid 1: only by a HEARTBEAT
    tool, _ = pinned_link("udpin://127.0.0.1:24011", sysid=3)
    tool.feed_datagram(lpn(codec(250), 5_000, 1.0), ("127.0.0.1", 24112), now=0.3)
    tool.check_identity()
    assert tool.state.telemetry_refused["other_sysid"] == 1
