"""The ``mavlink`` link backend: codec path on the real PX4 captures, and real UDP against a tiny
fake vehicle (command retries, timeouts, rejections, setpoints, garbage)."""

from __future__ import annotations

import asyncio
import json
import logging
import math
import struct
from pathlib import Path
from typing import Any

import pytest
from link_fake_vehicle import FakeVehicle, RecordingTransport, free_udp_port
from pymavlink.dialects.v20 import common as mavlink2

from vtube_fleet.errors import UserError
from vtube_fleet.link import (
    CommandRejected,
    GeoPoint,
    LinkError,
    LinkTimeout,
    MavlinkLink,
)
from vtube_fleet.link.mavlink import TYPE_MASK_VELOCITY, TYPE_MASK_VELOCITY_YAW

CAPTURES = Path(__file__).parent / "data" / "px4_sitl"  # real PX4 SITL captures
PX4_ADDR = ("127.0.0.1", 14580)


def tlog_records(path: Path) -> list[tuple[int, bytes]]:
    """README: each record = 8-byte big-endian µs timestamp + exactly one MAVLink packet."""
    data = path.read_bytes()
    out, i = [], 0
    while i < len(data):
        (ts,) = struct.unpack(">Q", data[i : i + 8])
        i += 8
        assert data[i] == 0xFD, f"{path.name}: MAVLink 2 expected at byte {i}"
        n = data[i + 1] + 12 + (13 if data[i + 2] & 1 else 0)
        out.append((ts, data[i : i + n]))
        i += n
    return out


def replay(link: MavlinkLink, path: Path, on_packet: Any = None) -> int:
    records = tlog_records(path)
    for ts, pkt in records:
        link.feed_datagram(pkt, PX4_ADDR, now=ts * 1e-6)
        if on_packet is not None:
            on_packet(link.state)
    return len(records)


# Per capture: (flight_mode, armed) phases, landed states, final origin (README tables)
EXPECTED = {
    "offboard_flight_i0": (
        [("HOLD", False), ("OFFBOARD", False), ("OFFBOARD", True), ("OFFBOARD", False)],
        ["ON_GROUND", "IN_AIR", "ON_GROUND"],
        (47.3977410, 8.5455960, 489.830),
        1,
    ),
    "three_vehicles_i0": (
        [("HOLD", False), ("OFFBOARD", False), ("OFFBOARD", True), ("OFFBOARD", False)],
        ["ON_GROUND", "IN_AIR", "ON_GROUND"],
        (47.3977459, 8.5455930, 489.056),
        1,
    ),
    "three_vehicles_i1": (
        [("HOLD", False), ("OFFBOARD", False), ("OFFBOARD", True), ("OFFBOARD", False)],
        ["ON_GROUND", "IN_AIR", "ON_GROUND"],
        (47.3977459, 8.5455930, 489.056),
        2,
    ),
    "three_vehicles_i2": (
        [("HOLD", False), ("OFFBOARD", False), ("OFFBOARD", True), ("OFFBOARD", False)],
        ["ON_GROUND", "IN_AIR", "ON_GROUND"],
        (47.3978440, 8.5455937, 489.067),
        3,
    ),
    "offboard_loss": (
        [("HOLD", False), ("OFFBOARD", True), ("POSCTL", True), ("OFFBOARD", False)],
        ["ON_GROUND", "IN_AIR", "ON_GROUND"],
        (47.3977459, 8.5455930, 489.056),
        1,
    ),
    "rejections": (
        [("HOLD", False), ("OFFBOARD", False), ("HOLD", False), ("HOLD", True), ("HOLD", False)],
        ["ON_GROUND"],
        (47.3977448, 8.5455937, 489.067),
        1,
    ),
}


@pytest.mark.parametrize("decode_all", [True, False], ids=["decode_all", "cheap_path"])
@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_vehicle_captures_decode_into_state(name: str, decode_all: bool) -> None:
    phases, landed, origin, sysid = EXPECTED[name]
    link = MavlinkLink("udpin://127.0.0.1:14540", decode_all=decode_all)
    seen_phases: list[tuple[str, bool]] = []
    seen_landed: list[str] = []
    modes: set[tuple[str, str, int | None]] = set()

    def watch(s: Any) -> None:
        if s.armed is not None and (not seen_phases or seen_phases[-1] != (s.flight_mode, s.armed)):
            seen_phases.append((s.flight_mode, s.armed))
        if s.landed_state != "UNKNOWN" and (not seen_landed or seen_landed[-1] != s.landed_state):
            seen_landed.append(s.landed_state)
        modes.add((s.flight_mode, s.px4_mode, s.custom_mode))

    n = replay(link, CAPTURES / f"{name}_vehicle_to_gcs.tlog", watch)
    s = link.state
    assert (s.rx_packets, s.bad_packets, s.foreign_packets) == (n, 0, 0)
    assert s.sysid == sysid and link.sysid == sysid
    assert seen_phases == phases
    assert seen_landed == landed
    assert ("HOLD", "AUTO.LOITER", 50593792) in modes
    assert ("OFFBOARD", "OFFBOARD", 393216) in modes
    assert (("POSCTL", "POSCTL", 196608) in modes) == (name == "offboard_loss")
    assert s.origin == pytest.approx(GeoPoint(*origin), abs=1e-7)
    assert s.home is not None and s.time_boot_ms is not None
    assert math.isfinite(s.north_m) and math.isfinite(s.lat_deg) and math.isfinite(s.alt_m)
    texts = [t.text for t in s.statustexts]
    assert all(not t.endswith("\t") for t in texts)
    if name == "offboard_loss":
        assert "Failsafe activated" in texts
    else:  # two 50-char chunks joined
        assert "Arming denied: Resolve system health failures first" in texts


def test_capture_health_and_home_details() -> None:
    link = MavlinkLink("udpin://127.0.0.1:14540")
    health: list[bool] = []
    statuses: list[str] = []

    def watch(s: Any) -> None:
        if s.health_problems != ("no SYS_STATUS",) and (not health or health[-1] != s.health_ok):
            health.append(s.health_ok)
        if not statuses or statuses[-1] != s.system_status:
            statuses.append(s.system_status)

    replay(link, CAPTURES / "offboard_flight_i0_vehicle_to_gcs.tlog", watch)
    assert health == [False, True, False]  # pre-arm checks fail, pass, fail after landing
    assert statuses == ["UNKNOWN", "UNINIT", "STANDBY", "ACTIVE", "STANDBY", "UNINIT"]
    assert link.state.home == pytest.approx(GeoPoint(47.3978269, 8.5456955, 490.161), abs=1e-7)
    assert link.state.heading_deg == pytest.approx(link.state.heading_deg)  # finite


@pytest.mark.parametrize(
    "path", sorted(CAPTURES.glob("*_gcs_to_vehicle.tlog")), ids=lambda p: p.stem
)
def test_gcs_captures_parse_and_count_as_foreign(path: Path) -> None:
    """The GCS side (255/190) parses without errors; it is not a vehicle, so all foreign."""
    link = MavlinkLink("udpin://127.0.0.1:14540")
    n = replay(link, path)
    s = link.state
    assert (s.rx_packets, s.bad_packets, s.foreign_packets) == (0, 0, n)
    assert s.sysid is None and s.last_heartbeat_s is None


def _attach(link: MavlinkLink, sysid: int = 1) -> RecordingTransport:
    t = RecordingTransport()
    link._transport = t  # type: ignore[assignment]
    link._remote = PX4_ADDR
    link._sysid = link.state.sysid = sysid
    return t


def test_encoder_matches_capture_gcs_bytes() -> None:
    """Our HEARTBEAT, COMMAND_LONG and setpoint packets equal the capture GCS's byte for byte."""
    packets = [p for _, p in tlog_records(CAPTURES / "offboard_flight_i0_gcs_to_vehicle.tlog")]
    by_id: dict[int, bytes] = {}
    for p in packets:
        by_id.setdefault(p[7] | p[8] << 8, p)
    link = MavlinkLink("udpin://127.0.0.1:14540")
    t = _attach(link)

    link._mav.seq = by_id[0][4]
    link.send_heartbeat()
    assert t.sent[-1] == by_id[0]

    sp = by_id[84]
    link._mav.seq = sp[4]
    link._time_boot_ms = lambda: 1468  # type: ignore[method-assign]
    link.send_velocity_ned(0.0, 0.0, 0.0)
    assert t.sent[-1] == sp

    cmd = by_id[76]  # first COMMAND_LONG: SET_MESSAGE_INTERVAL(32, 20000 us)
    link._mav.seq = cmd[4]
    link._send(link._mav.command_long_encode(1, 1, 511, 0, 32.0, 20000.0, 0, 0, 0, 0, 0))
    assert t.sent[-1] == cmd


def test_garbage_datagrams_counted_not_fatal(caplog: pytest.LogCaptureFixture) -> None:
    garbage = json.loads((CAPTURES / "rejections_garbage_datagrams.json").read_text())
    datagrams = [bytes.fromhex(h) for h in garbage["datagrams_hex"]]
    records = tlog_records(CAPTURES / "rejections_vehicle_to_gcs.tlog")
    link = MavlinkLink("udpin://127.0.0.1:14540")
    for _, pkt in records[:2000]:
        link.feed_datagram(pkt, PX4_ADDR)
    before = link.state.rx_packets
    with caplog.at_level(logging.WARNING, logger="vtube_fleet.link.mavlink"):
        for d in datagrams:
            link.feed_datagram(d, PX4_ADDR)
        link.feed_datagram(records[2000][1][:-5], PX4_ADDR)  # a cut-off packet
        link.feed_datagram(b"", PX4_ADDR)
    assert link.state.bad_packets == 4
    assert link.state.rx_packets == before
    warnings = [r for r in caplog.records if "malformed datagram" in r.getMessage()]
    assert len(warnings) == 1  # rate-limited
    assert "vehicle 1 (udpin://127.0.0.1:14540)" in warnings[0].getMessage()
    # the codec is not stuck: the rest of the capture still decodes
    for _, pkt in records[2000:]:
        link.feed_datagram(pkt, PX4_ADDR)
    assert link.state.rx_packets == before + len(records) - 2000
    assert link.state.bad_packets == 4


def test_foreign_and_gcs_packets_ignored() -> None:
    vehicle = mavlink2.MAVLink(None, 1, 1)
    other = mavlink2.MAVLink(None, 7, 1)
    gcs = mavlink2.MAVLink(None, 1, 190)  # a GCS that (wrongly) uses the vehicle's id
    link = MavlinkLink("udpin://127.0.0.1:14540")
    link.feed_datagram(vehicle.heartbeat_encode(2, 12, 29, 50593792, 3).pack(vehicle), PX4_ADDR)
    assert link.sysid == 1 and link.state.flight_mode == "HOLD"
    link.feed_datagram(other.heartbeat_encode(2, 12, 157, 393216, 4).pack(other), PX4_ADDR)
    link.feed_datagram(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs), PX4_ADDR)
    pos = other.local_position_ned_encode(5, 9.0, 9.0, 9.0, 0, 0, 0).pack(other)
    link.feed_datagram(pos, PX4_ADDR)
    s = link.state
    assert (s.foreign_packets, s.rx_packets) == (3, 1)
    assert s.flight_mode == "HOLD" and s.armed is False and math.isnan(s.north_m)
    # before any vehicle is known, a GCS heartbeat does not lock the link onto the GCS
    fresh = MavlinkLink("udpin://127.0.0.1:14540")
    fresh.feed_datagram(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs), PX4_ADDR)
    assert fresh.sysid is None and fresh.state.foreign_packets == 1
    # an explicit sysid only accepts that vehicle
    pinned = MavlinkLink("udpin://127.0.0.1:14540", sysid=7)
    pinned.feed_datagram(vehicle.heartbeat_encode(2, 12, 29, 50593792, 3).pack(vehicle), PX4_ADDR)
    pinned.feed_datagram(other.heartbeat_encode(2, 12, 157, 393216, 4).pack(other), PX4_ADDR)
    assert pinned.state.foreign_packets == 1 and pinned.state.flight_mode == "OFFBOARD"


def test_statustext_chunks() -> None:
    v = mavlink2.MAVLink(None, 1, 1)
    link = MavlinkLink("udpin://127.0.0.1:14540")
    link.feed_datagram(v.heartbeat_encode(2, 12, 29, 50593792, 3).pack(v), PX4_ADDR)
    text = "x" * 50 + "yz\t"
    for seq, chunk in enumerate((text[:50], text[50:])):
        link.feed_datagram(v.statustext_encode(2, chunk.encode(), 7, seq).pack(v), PX4_ADDR)
    assert link.state.statustexts[-1].text == "x" * 50 + "yz"
    # exactly 50 characters: no NUL-terminated last chunk ever comes; flushed after 0.5 s
    link.feed_datagram(v.statustext_encode(6, b"a" * 50, 8, 0).pack(v), PX4_ADDR, now=100.0)
    assert link.state.statustexts[-1].text != "a" * 50
    link._flush_statustexts(now=100.6)
    assert link.state.statustexts[-1].text == "a" * 50
    assert link.state.statustexts[-1].severity == 6


def test_setpoint_type_masks() -> None:
    link = MavlinkLink("udpin://127.0.0.1:14540")
    t = _attach(link, sysid=4)
    link.send_velocity_ned(1.5, -2.0, 0.25)
    link.send_velocity_ned(0.0, 1.0, 0.0, yaw_deg=90.0)
    dec = mavlink2.MAVLink(None)
    a, b = (dec.parse_buffer(p)[0] for p in t.sent)
    assert (a.target_system, a.target_component, a.coordinate_frame) == (4, 1, 1)
    assert a.type_mask == TYPE_MASK_VELOCITY == 3527
    assert (a.vx, a.vy, a.vz) == pytest.approx((1.5, -2.0, 0.25))
    assert b.type_mask == TYPE_MASK_VELOCITY_YAW == 2503
    assert b.yaw == pytest.approx(math.pi / 2)
    with pytest.raises(ValueError, match="must be finite"):
        link.send_velocity_ned(math.nan, 0.0, 0.0)


# -- real UDP against the fake vehicle ----------------------------------------------------------
@pytest.fixture
async def pair():
    port = free_udp_port()
    fake = FakeVehicle(sysid=1, gcs_addr=("127.0.0.1", port))
    # 1 s per try: an acknowledgement late by a loaded machine's stall must not be a lost one
    # (the retry counts below are exact)
    link = MavlinkLink(f"udpin://127.0.0.1:{port}", command_timeout_s=1.0)
    await fake.start()
    try:
        yield link, fake
    finally:
        await link.close()
        await fake.stop()


async def test_connect_requests_streams_and_becomes_ready(pair) -> None:
    link, fake = pair
    await link.connect(timeout_s=5.0)
    state = await link.wait_ready(timeout_s=5.0)
    assert state.sysid == 1 and state.health_ok and state.flight_mode == "HOLD"
    assert state.origin == pytest.approx(GeoPoint(47.3977459, 8.545593, 489.056), abs=2e-7)
    intervals = {int(m.param1): m.param2 for m in fake.commands(511)}
    assert intervals == {32: 20000.0, 33: 100000.0, 245: 200000.0, 242: 1000000.0, 230: 500000.0}
    assert sorted(int(m.param1) for m in fake.commands(512)) == [49, 242]
    hb = await fake.wait_for(lambda m: m.get_type() == "HEARTBEAT")
    assert (hb.get_srcSystem(), hb.get_srcComponent(), hb.type, hb.autopilot) == (255, 190, 6, 8)
    assert link.remote_address == fake.transport.get_extra_info("sockname")
    # ATTITUDE is streamed but never decoded by the cheap path, yet counted
    assert state.rx_packets > 0 and state.bad_packets == 0
    await link.wait_until(lambda s: link.latency_source == "TIMESYNC", 5.0, "a TIMESYNC reply")
    assert 0.0 < link.latency_s < 1.0


async def test_positions_stream_yields_updates(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    got = []
    async with asyncio.timeout(5.0):
        async for s in link.positions():
            fake.north_m += 1.0
            got.append(s.north_m)
            if len(got) == 3:
                break
    assert got[0] < got[-1]


async def test_arm_retries_temporarily_rejected(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    fake.script[400] = [1, 1, 0]
    await link.arm(timeout_s=5.0, retry_interval_s=0.01)
    assert [m.param1 for m in fake.commands(400)] == [1.0, 1.0, 1.0]
    await link.wait_until(lambda s: s.armed, 5.0, "armed heartbeat")


async def test_arm_gives_up_with_last_statustext(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    fake.script[400] = [1] * 100
    fake.statustext_on_reject = "Arming denied: Resolve system health failures first\t"
    with pytest.raises(CommandRejected) as info:
        await link.arm(timeout_s=0.2, retry_interval_s=0.05)
    e = info.value
    assert (e.command, e.result) == ("COMPONENT_ARM_DISARM", "TEMPORARILY_REJECTED")
    msg = str(e)
    assert msg.startswith(f"vehicle 1 ({link.endpoint.url}): COMPONENT_ARM_DISARM (arm)")
    assert "attempt(s)" in msg and 'vehicle says "Arming denied' in msg and "\n" not in msg
    assert isinstance(e, UserError)


async def test_denied_is_not_retried(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    fake.script[400] = [2]
    with pytest.raises(CommandRejected, match="DENIED after 1 attempt"):
        await link.arm(timeout_s=5.0)
    fake.script[31999] = [3]
    with pytest.raises(CommandRejected) as info:
        await link.command_long(31999, 1, 2, 3, 4, 5, 6, 7)
    assert info.value.result == "UNSUPPORTED" and info.value.command == "MAV_CMD(31999)"


async def test_command_retries_lost_acks_with_confirmation(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    fake.script[176] = [None, None, 0]
    await link.hold()
    sent = fake.commands(176)
    assert [m.confirmation for m in sent] == [0, 1, 2]
    assert [(m.param1, m.param2, m.param3) for m in sent] == [(1.0, 4.0, 3.0)] * 3


async def test_command_timeout_names_vehicle_and_numbers(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    fake.script[176] = [None] * 3
    with pytest.raises(LinkTimeout) as info:
        await link.set_flight_mode("POSCTL")
    msg = str(info.value)
    assert "vehicle 1 (udpin://127.0.0.1:" in msg
    assert "no COMMAND_ACK for DO_SET_MODE after 3 tries of 1.00 s" in msg
    assert len(fake.commands(176)) == 3


async def test_offboard_requires_streaming_setpoints(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    with pytest.raises(LinkError, match="stream velocity setpoints first .*never sent one"):
        await link.start_offboard()
    assert fake.commands(176) == []
    link.send_velocity_ned(0.0, 0.0, -0.5)
    await link.start_offboard()
    cmd = fake.commands(176)[-1]
    assert (cmd.param1, cmd.param2, cmd.param3) == (1.0, 6.0, 0.0)
    await link.wait_until(lambda s: s.flight_mode == "OFFBOARD", 5.0, "OFFBOARD")
    sp = await fake.wait_for(lambda m: m.get_type() == "SET_POSITION_TARGET_LOCAL_NED")
    assert (sp.type_mask, sp.vz) == (3527, pytest.approx(-0.5))
    await link.stop_offboard()
    await link.wait_until(lambda s: s.flight_mode == "HOLD", 5.0, "HOLD")


async def test_takeoff_and_land_commands(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    await link.wait_ready(5.0)
    await link.takeoff(5.0)
    cmd = fake.commands(22)[-1]
    assert cmd.param7 == pytest.approx(link.state.alt_m + 5.0, abs=1e-3)
    assert math.isnan(cmd.param5) and math.isnan(cmd.param6)
    await link.land()
    assert len(fake.commands(21)) == 1
    with pytest.raises(LinkError, match="takeoff altitude must be > 0 m, got -1"):
        await link.takeoff(-1.0)


async def test_garbage_over_udp_and_link_keeps_working(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    for h in ("e13b032e112a32b579080f08b1f7ed4c", "fd09000007ffbe0000000000000000000000000000",
              "68656c6c6f207078342c2074686973206973206e6f74206d61766c696e6b0a"):
        fake.send_raw(bytes.fromhex(h))
    await link.wait_until(lambda s: s.bad_packets == 3, 5.0, "3 bad datagrams counted")
    await link.hold()  # still talking


async def test_wait_ready_names_what_is_missing(pair) -> None:
    link, fake = pair
    fake.health = 0x320883F  # pre-arm checks failing (captures, first 3 s)
    await link.connect(5.0)
    with pytest.raises(LinkTimeout) as info:
        await link.wait_ready(timeout_s=0.3)
    msg = str(info.value)
    assert "not ready after 0.3 s" in msg and "not healthy (prearm" in msg


async def test_close_fails_pending_and_ends_streams(pair) -> None:
    link, fake = pair
    await link.connect(5.0)
    fake.script[176] = [None] * 3
    states = link.states()
    first = await anext(states)
    assert first is link.state
    pending = asyncio.ensure_future(link.hold())
    await fake.wait_for(lambda m: m.get_type() == "COMMAND_LONG" and m.command == 176)
    await link.close()
    with pytest.raises(LinkError, match="link closed"):
        await pending
    with pytest.raises(StopAsyncIteration):
        await anext(states)
    with pytest.raises(LinkError, match="closed"):
        link.send_velocity_ned(0.0, 0.0, 0.0)
    await link.close()  # idempotent


async def test_stall_warning_while_offboard(caplog: pytest.LogCaptureFixture) -> None:
    port = free_udp_port()
    link = MavlinkLink(f"udpin://127.0.0.1:{port}", heartbeat_period_s=0.05)
    hit = asyncio.Event()

    class Catch(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if "no velocity setpoint sent" in record.getMessage():
                hit.set()

    handler = Catch()
    logging.getLogger("vtube_fleet.link.mavlink").addHandler(handler)
    async with FakeVehicle(gcs_addr=("127.0.0.1", port)) as fake:
        await fake.start()
        try:
            await link.connect(5.0)
            fake.armed = True
            link.send_velocity_ned(0.0, 0.0, 0.0)
            await link.start_offboard()
            await link.wait_until(lambda s: s.flight_mode == "OFFBOARD" and s.armed, 5.0, "ofb")
            async with asyncio.timeout(5.0):
                await hit.wait()  # we stopped sending: PX4's failsafe would take over now
        finally:
            logging.getLogger("vtube_fleet.link.mavlink").removeHandler(handler)
            await link.close()


async def test_connect_timeout_and_bind_conflict() -> None:
    port = free_udp_port()
    link = MavlinkLink(f"udpin://127.0.0.1:{port}")
    with pytest.raises(LinkTimeout, match=r"no HEARTBEAT within 0\.2 s \(nothing received"):
        await link.connect(timeout_s=0.2)
    other = MavlinkLink(f"udpin://127.0.0.1:{port}")
    with pytest.raises(LinkError, match=f"cannot bind udpin://127.0.0.1:{port}"):
        await other.connect(timeout_s=0.2)
    await link.close()
    await other.close()
    with pytest.raises(LinkError, match="call connect"):
        await MavlinkLink("udpin://127.0.0.1:14540").hold()


async def test_udpout_endpoint() -> None:
    """udpout: we send first (GCS heartbeat); the vehicle learns our address from it."""
    async with FakeVehicle(sysid=2, gcs_addr=None) as fake:
        host, port = await fake.start()
        link = MavlinkLink(f"udpout://{host}:{port}", sysid=2, command_timeout_s=0.2)
        try:
            await link.connect(5.0)
            await link.hold()
            assert link.state.sysid == 2 and fake.gcs_addr is not None
        finally:
            await link.close()


async def test_concurrent_connects_share_one_socket() -> None:
    port = free_udp_port()
    link = MavlinkLink(f"udpin://127.0.0.1:{port}")
    async with FakeVehicle(gcs_addr=("127.0.0.1", port)) as fake:
        await fake.start()
        try:
            await asyncio.gather(link.connect(5.0), link.connect(5.0), link.connect(5.0))
            assert len(fake.commands(511)) == 5  # streams requested once
        finally:
            await link.close()


async def test_open_links_factory() -> None:
    from vtube_fleet.link import EndpointError, open_links

    port = free_udp_port()
    async with FakeVehicle(gcs_addr=("127.0.0.1", port)) as fake:
        await fake.start()
        async with open_links([f"udp://:{port}"], command_timeout_s=0.3) as links:
            (link,) = links
            assert isinstance(link, MavlinkLink) and link.command_timeout_s == 0.3
            await link.connect(5.0)
            assert link.endpoint.url == f"udpin://0.0.0.0:{port}"
        assert link.closed
    with pytest.raises(LinkError, match="unknown link backend 'grpc'"):
        async with open_links(["udpin://127.0.0.1:14540"], "grpc"):
            pass
    with pytest.raises(EndpointError, match="more than once: udpin://0.0.0.0:14540"):
        async with open_links(["udpin://0.0.0.0:14540", "udp://:14540"]):
            pass
