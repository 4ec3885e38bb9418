"""The struct fast path of the ``mavlink`` link (vtube_fleet/link/wire.py) against pymavlink:
byte-identical frames, identical decoded values, and every frame it does not fully accept
(bad CRC, cut off, padded, signed, MAVLink 1, unknown id, too long) left to pymavlink, which
counts it as malformed exactly as before."""

from __future__ import annotations

import math
import random
import struct
import time

import numpy as np
import pytest
from link_fake_vehicle import RecordingTransport
from pymavlink.dialects.v20 import common as mavlink2
from pymavlink.generator.mavcrc import x25crc_slow

from vtube_fleet.link import LinkError, MavlinkLink
from vtube_fleet.link.wire import WireCodec, _mcrf4xx_hqx, mcrf4xx

PX4_ADDR = ("127.0.0.1", 14580)
HB, LPN, GPI, SPT = 0, 32, 33, 84
SYS_STATUS, GPS_RAW_INT, ESTIMATOR_STATUS, EXTENDED_SYS_STATE, TIMESYNC = 1, 24, 230, 245, 111
FAST = (HB, LPN, GPI, SPT, SYS_STATUS, GPS_RAW_INT, ESTIMATOR_STATUS, EXTENDED_SYS_STATE,
        TIMESYNC)
CODEC = WireCodec(FAST)


def _f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


def _random_values(rng: random.Random, msgid: int) -> list:
    cls = mavlink2.mavlink_map[msgid]
    fmt = cls.unpacker.format[1:]
    out: list = []
    for c in fmt:
        if c == "f":
            out.append(rng.choice([0.0, _f32(rng.uniform(-1e3, 1e3)), -0.0, 1.0]))
        else:
            bits = struct.calcsize(c) * 8
            lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if c.islower() else (
                0, (1 << bits) - 1)
            out.append(rng.choice([0, lo if lo < 0 else 1, hi, rng.randint(lo, hi)]))
    return out


def _pymavlink_frame(msgid: int, values: list, seq: int, sysid: int, compid: int) -> bytes:
    cls = mavlink2.mavlink_map[msgid]
    named = dict(zip(cls.ordered_fieldnames, values, strict=True))
    msg = cls(*(named[f] for f in cls.fieldnames))
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.seq = seq
    return msg.pack(mav)


def test_crc_matches_pymavlink() -> None:
    rng = random.Random(1)
    for n in (0, 1, 2, 9, 40, 255):
        data = bytes(rng.randrange(256) for _ in range(n))
        start = rng.randrange(1 << 16)
        ref = x25crc_slow()
        ref.crc = start
        ref.accumulate(data)
        assert mcrf4xx(data, start) == _mcrf4xx_hqx(data, start) == ref.crc


@pytest.mark.parametrize("msgid", FAST)
def test_pack_is_byte_identical_and_unpack_equals_pymavlink(msgid: int) -> None:
    rng = random.Random(msgid)
    dec = mavlink2.MAVLink(None)
    dec.robust_parsing = True
    cases = [[0] * len(mavlink2.mavlink_map[msgid].ordered_fieldnames)]  # all zero: 1 byte
    cases += [_random_values(rng, msgid) for _ in range(300)]
    for values in cases:
        seq, sysid, compid = rng.randrange(256), rng.randint(1, 255), rng.randrange(256)
        ref = _pymavlink_frame(msgid, values, seq, sysid, compid)
        assert CODEC.pack(msgid, seq, sysid, compid, *values) == ref
        fast = CODEC.unpack(ref)
        (slow,) = dec.parse_buffer(ref)
        assert fast is not None and slow.get_msgId() == msgid
        for name in mavlink2.mavlink_map[msgid].ordered_fieldnames:
            a, b = getattr(fast, name), getattr(slow, name)
            assert a == b or (math.isnan(a) and math.isnan(b)), (name, a, b)


def test_unpack_refuses_what_it_does_not_fully_accept() -> None:
    good = _pymavlink_frame(LPN, [1234, 1.5, -2.25, 3.0, 0.5, 0.25, -0.5], 7, 3, 1)
    assert CODEC.unpack(good) is not None
    bad_crc = good[:-1] + bytes(((good[-1] ^ 0x01),))
    flipped = good[:12] + bytes((good[12] ^ 0x80,)) + good[13:]
    cut = good[:-1]
    padded = good + b"\x00"
    signed = good[:2] + b"\x01" + good[3:]
    compat = good[:3] + b"\x01" + good[4:]
    mav1 = b"\xfe" + good[1:]
    statustext = _pymavlink_frame(253, [6, b"hi", 0, 0], 1, 3, 1)  # unknown to the codec
    # a payload longer than the dialect's (a newer extension): the length byte and CRC agree
    body = bytearray(good[:-2]) + b"\x11"
    body[1] += 1
    longer = bytes(body) + struct.pack("<H", mcrf4xx(bytes((185,)), mcrf4xx(bytes(body[1:]))))
    for frame in (bad_crc, flipped, cut, padded, signed, compat, mav1, statustext, longer,
                  b"", good[:11]):
        assert CODEC.unpack(frame) is None, frame.hex()


def test_the_link_sends_what_pymavlink_would_send_on_both_paths() -> None:
    """Heartbeat, TIMESYNC and a setpoint, fast path and pymavlink, byte for byte (the
    sequence numbers run on across both)."""
    sent = {}
    for fast in (True, False):
        link = MavlinkLink("udpin://127.0.0.1:14540", sysid=3, fast_codec=fast)
        link._transport = RecordingTransport()  # type: ignore[assignment]
        link._remote = PX4_ADDR
        link._t0 = 0.0  # time_boot_ms: the same clock on both (monotonic since 0)
        link.send_heartbeat()
        link._send_fast(TIMESYNC, 0, 123456789) or link._send(
            link._mav.timesync_encode(0, 123456789))
        link._time_boot_ms = lambda: 4321  # type: ignore[method-assign]
        link.send_velocity_ned(1.0, -0.5, 0.25)
        sent[fast] = link._transport.sent  # type: ignore[attr-defined]
    assert len(sent[True]) == 3 and sent[True] == sent[False]
    # and the heartbeat is a GCS's: type GCS (6), autopilot INVALID (8), state ACTIVE (4)
    dec = mavlink2.MAVLink(None)
    (hb,) = dec.parse_buffer(sent[True][0])
    assert (hb.type, hb.autopilot, hb.system_status, hb.get_srcSystem()) == (6, 8, 4, 255)


def _batch_links(fast_codec: list[bool]) -> list[MavlinkLink]:
    rng = random.Random(5)
    links = []
    for k, fast in enumerate(fast_codec):
        link = MavlinkLink(f"udpin://127.0.0.1:{20000 + k}", sysid=k % 255 + 1,
                           fast_codec=fast, gcs_compid=190 + k % 2)
        link._transport = RecordingTransport()  # type: ignore[assignment]
        link._remote = PX4_ADDR
        link._t0 = 0.0
        link._mav.seq = rng.randrange(256)
        links.append(link)
    return links


def test_a_fleets_setpoints_sent_at_once_are_the_bytes_each_link_sends(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """:meth:`MavlinkLink.send_velocities_ned` (frames built together, one CRC table lookup
    per byte) against :meth:`MavlinkLink.send_velocity_ned` link by link: the same datagrams,
    sequence numbers and counters; links off the fast path (pymavlink codec), not connected
    or closed are handled one by one, with their errors returned in place."""
    from vtube_fleet.link.base import send_velocities_ned

    rng = random.Random(9)
    n = 300
    modes = [k % 7 != 3 for k in range(n)]  # every 7th from 3 on through pymavlink
    north = [_f32(rng.uniform(-5, 5)) for _ in range(n)]
    east = [rng.uniform(-5, 5) for _ in range(n)]  # (rounded to float32 on both paths)
    down = [rng.choice([0.0, -0.0, rng.uniform(-2, 2)]) for _ in range(n)]
    sent = []
    monkeypatch.setattr(time, "monotonic", lambda: 1000.0)  # time_boot_ms: one clock for both
    for batch in (True, False):
        links = _batch_links(modes)
        links[10]._remote = None  # not connected yet
        links[11]._closed = True
        for k, link in enumerate(links):
            link._t0 = 12.345 + 0.01 * k
        if batch:
            errors = send_velocities_ned(links, np.array(north), np.array(east),
                                         np.array(down))
        else:
            errors = []
            for link, *v in zip(links, north, east, down, strict=True):
                try:
                    link.send_velocity_ned(*v)
                except LinkError as exc:
                    errors.append(exc)
                else:
                    errors.append(None)
        assert [k for k, e in enumerate(errors) if e is not None] == [10, 11]
        assert all(isinstance(e, LinkError) for e in errors if e is not None)
        assert "not seen yet" in str(errors[10]) and "closed" in str(errors[11])
        sent.append([(lk._transport.sent, lk._mav.seq, lk._setpoints_sent, lk.tx_packets)
                     for lk in links])
    assert sent[0] == sent[1]
    assert sum(len(x[0]) for x in sent[0]) == n - 2


def test_a_fleets_setpoints_with_a_non_finite_value_send_nothing() -> None:
    from vtube_fleet.link.base import send_velocities_ned

    links = _batch_links([True] * 4)
    seqs = [lk._mav.seq for lk in links]
    with pytest.raises(ValueError, match=r"vehicle 3 .*must be finite"):
        send_velocities_ned(links, np.zeros(4), np.array([0.0, 0.0, math.nan, 0.0]),
                            np.zeros(4))
    # finite, but not in the float32 of the wire (send_velocity_ned refuses it too)
    with pytest.raises(ValueError, match=r"vehicle 2 .*must be finite"):
        send_velocities_ned(links, np.array([0.0, 1e39, 0.0, 0.0]), np.zeros(4), np.zeros(4))
    assert all(not lk._transport.sent for lk in links)
    assert [lk._mav.seq for lk in links] == seqs and all(lk.tx_packets == 0 for lk in links)


@pytest.mark.parametrize("fast", [True, False], ids=["fast_codec", "pymavlink"])
def test_link_counts_bad_frames_and_decodes_good_ones_alike(fast: bool) -> None:
    v = mavlink2.MAVLink(None, 3, 1)
    link = MavlinkLink("udpin://127.0.0.1:14540", sysid=3, fast_codec=fast)
    slow: list[bytes] = []
    decode = link._decode

    def counting_decode(data: bytes, addr: object, now: float) -> None:
        slow.append(data)
        decode(data, addr, now)

    link._decode = counting_decode  # type: ignore[method-assign]
    link.feed_datagram(v.heartbeat_encode(2, 12, 29, 50593792, 3).pack(v), PX4_ADDR)
    assert link.state.flight_mode == "HOLD" and link.state.armed is False
    link.feed_datagram(v.heartbeat_encode(2, 12, 29 | 0x80, 393216, 4).pack(v), PX4_ADDR)
    assert link.state.flight_mode == "OFFBOARD" and link.state.armed is True
    good = v.local_position_ned_encode(1234, 1.5, -2.25, 3.0, 0.5, 0.25, -0.5).pack(v)
    link.feed_datagram(good[:-1] + bytes((good[-1] ^ 1,)), PX4_ADDR)  # bad CRC
    link.feed_datagram(good[:-3], PX4_ADDR)  # cut off
    s = link.state
    assert s.bad_packets == 2 and math.isnan(s.north_m)
    link.feed_datagram(good, PX4_ADDR, now=50.0)
    assert (s.time_boot_ms, s.north_m, s.east_m, s.down_m, s.vn_m_s, s.ve_m_s, s.vd_m_s) == (
        1234, 1.5, -2.25, 3.0, 0.5, 0.25, -0.5)
    assert s.last_position_s == 50.0
    link.feed_datagram(v.global_position_int_encode(1, 473977420, 85455940, 489400, 2500,
                                                    0, 0, 0, 65535).pack(v), PX4_ADDR)
    assert s.lat_deg == pytest.approx(47.397742) and s.alt_m == pytest.approx(489.4)
    assert math.isnan(s.heading_deg)
    # a GCS using the vehicle's id, another vehicle: ignored on both paths
    gcs = mavlink2.MAVLink(None, 3, 190)
    other = mavlink2.MAVLink(None, 4, 1)
    link.feed_datagram(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs), PX4_ADDR)
    link.feed_datagram(other.local_position_ned_encode(5, 9.0, 9.0, 9.0, 0, 0, 0).pack(other),
                       PX4_ADDR)
    assert s.foreign_packets == 2 and s.armed is True and s.north_m == 1.5
    assert (s.rx_packets, s.bad_packets) == (4, 2)
    # pymavlink saw: the first packet (address not known yet), the two bad ones, the foreign
    # vehicle's; or everything
    assert len(slow) == (4 if fast else 8)


# -- connect: stream requests repeated within the connect timeout ---------------------------
async def test_connect_retries_unanswered_stream_requests_within_its_timeout() -> None:
    """A busy vehicle loses the first ACKs: connect repeats the request beyond the usual 3
    tries (as a GCS does) while its timeout lasts, the streams turned off first."""
    from link_fake_vehicle import FakeVehicle, free_udp_port

    port = free_udp_port()
    fake = FakeVehicle(sysid=1, gcs_addr=("127.0.0.1", port))
    link = MavlinkLink(f"udpin://127.0.0.1:{port}", command_timeout_s=0.1,
                       message_rates_hz={30: 0.0})
    await fake.start()
    try:
        fake.script[511] = [None] * 5  # five requests without an ACK, then ACCEPTED
        await link.connect(timeout_s=10.0)
        sent = fake.commands(511)
        assert [int(m.param1) for m in sent[:6]] == [30] * 6  # ATTITUDE off goes first
        assert [m.confirmation for m in sent[:6]] == [0, 1, 2, 3, 4, 5]
        assert {int(m.param1) for m in sent} == {30, 32, 33, 245, 242, 230}
    finally:
        await link.close()
        await fake.stop()


async def test_connect_to_a_vehicle_that_never_acks_ends_with_the_numbers() -> None:
    from link_fake_vehicle import FakeVehicle, free_udp_port

    from vtube_fleet.link import LinkTimeout

    port = free_udp_port()
    fake = FakeVehicle(sysid=1, gcs_addr=("127.0.0.1", port))
    link = MavlinkLink(f"udpin://127.0.0.1:{port}", command_timeout_s=0.1)
    await fake.start()
    try:
        fake.script[511] = [None] * 1000
        with pytest.raises(LinkTimeout) as info:
            await link.connect(timeout_s=1.5)
        msg = str(info.value)
        assert "no COMMAND_ACK for SET_MESSAGE_INTERVAL after" in msg
        tries = int(msg.split(" after ")[1].split(" tries")[0])
        assert tries > 3 and len(fake.commands(511)) == tries
    finally:
        await link.close()
        await fake.stop()


# -- the burst-reading socket (vtube_fleet/link/udp.py) --------------------------------------
async def test_datagram_socket_drains_in_bursts_and_sends() -> None:
    """One wake-up reads up to ``burst`` queued datagrams (asyncio's transport reads one), in
    order; sending works both ways; closed: nothing more is read or sent."""
    import socket

    from vtube_fleet.link.udp import DatagramSocket

    got: list[tuple[bytes, object]] = []
    errors: list[OSError] = []
    ds = await DatagramSocket.open("127.0.0.1", 0, listens=True,
                                   on_datagram=lambda d, a, t: got.append((d, a)),
                                   on_error=errors.append, burst=64)
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    try:
        here = ds.get_extra_info("sockname")
        for k in range(100):
            peer.sendto(k.to_bytes(2, "little"), here)
        ds._readable()
        assert [int.from_bytes(d, "little") for d, _ in got] == list(range(64))
        ds._readable()
        assert len(got) == 100 and got[-1] == ((99).to_bytes(2, "little"), peer.getsockname())
        ds._readable()  # nothing queued: returns at once
        assert len(got) == 100 and not errors
        ds.sendto(b"pong", peer.getsockname())
        assert peer.recvfrom(16) == (b"pong", here)
        ds.close()
        assert ds.is_closing()
        ds.sendto(b"late", peer.getsockname())  # ignored, no error
        peer.setblocking(False)
        with pytest.raises(BlockingIOError):
            peer.recvfrom(16)
    finally:
        ds.close()
        peer.close()


async def test_the_loops_sockets_share_one_epoll_read_in_rounds() -> None:
    """Every socket of a loop sits behind one hub: one wake-up reads one datagram per ready
    socket per round, each socket in order, at most HUB_ROUNDS each (the loop gets its turn);
    a socket closed by its own callback is read no more; the last one closed gives the
    epoll back."""
    import asyncio
    import socket

    from vtube_fleet.link.udp import HUB_ROUNDS, DatagramHub, DatagramSocket

    loop = asyncio.get_running_loop()
    got: dict[int, list[int]] = {k: [] for k in range(3)}
    socks: list[DatagramSocket] = []

    def on(k: int):
        def handle(d: bytes, a: object, t: float) -> None:
            got[k].append(int.from_bytes(d, "little"))
            if k == 2 and len(got[2]) == 2:
                socks[2].close()  # closed by its own callback, mid-wake-up
        return handle

    for k in range(3):
        socks.append(await DatagramSocket.open("127.0.0.1", 0, listens=True,
                                               on_datagram=on(k), on_error=print))
    hub = DatagramHub.of(loop)
    assert hub is not None and all(ds._hub is hub for ds in socks)
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for k, ds in enumerate(socks):
            for i in range(HUB_ROUNDS + 3 if k == 0 else 2 if k == 1 else 5):
                peer.sendto(i.to_bytes(2, "little"), ds.get_extra_info("sockname"))
        hub._ready()
        assert got[0] == list(range(HUB_ROUNDS))  # the rest waits for the next wake-up
        assert got[1] == [0, 1] and got[2] == [0, 1]
        hub._ready()
        assert got[0] == list(range(HUB_ROUNDS + 3)) and got[2] == [0, 1]
        hub._ready()  # nothing left: returns at once
        # a handler that raises loses only its own datagram, not the rest of the round
        # (each of the two broken in turn: one of the rounds hands it its datagram first)
        for bad, good in ((1, 0), (0, 1)):
            before = list(got[bad])
            handler = socks[bad]._on_datagram
            socks[bad]._on_datagram = lambda d, a, t: 1 / 0  # type: ignore[method-assign]
            for ds in socks[:2]:
                peer.sendto((7 + bad).to_bytes(2, "little"), ds.get_extra_info("sockname"))
            hub._ready()
            assert got[good][-1] == 7 + bad and got[bad] == before
            socks[bad]._on_datagram = handler  # type: ignore[method-assign]
        socks[0].close()
        socks[1].close()
        assert hub._epoll.closed and loop not in DatagramHub._hubs  # the last one closed
    finally:
        for ds in socks:
            ds.close()
        peer.close()


async def test_datagram_socket_counts_sends_the_kernel_refuses() -> None:
    """A full send buffer (EAGAIN) drops that datagram and counts it (the event loop never
    blocks); other socket errors go to ``on_error``."""
    import asyncio
    import errno
    import socket

    from vtube_fleet.link.udp import DatagramSocket

    class FullSocket:
        """A real UDP socket (for the loop's reader) whose sends the kernel refuses: first
        for a full buffer, then because the peer is gone."""

        def __init__(self) -> None:
            self.real = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.refusal: OSError = BlockingIOError(errno.EAGAIN, "full")

        def sendto(self, data: bytes, addr: object) -> int:
            raise self.refusal

        def recvfrom(self, size: int) -> tuple[bytes, object]:
            return self.real.recvfrom(size)

        def fileno(self) -> int:
            return self.real.fileno()

        def close(self) -> None:
            self.real.close()

    errors: list[OSError] = []
    sock = FullSocket()
    ds = DatagramSocket(asyncio.get_running_loop(), sock, lambda d, a, t: None, errors.append)
    ds.sendto(b"a", ("127.0.0.1", 9))
    ds.sendto(b"b", ("127.0.0.1", 9))
    assert ds.tx_dropped == 2 and not errors
    sock.refusal = ConnectionRefusedError(errno.ECONNREFUSED, "refused")
    ds.sendto(b"c", ("127.0.0.1", 9))
    assert ds.tx_dropped == 2 and [e.errno for e in errors] == [errno.ECONNREFUSED]
    # a fleet's batch of setpoints sends through the socket itself, by the same rules
    from vtube_fleet.link.base import send_velocities_ned

    link = MavlinkLink("udpin://127.0.0.1:14540", sysid=1)
    link._transport, link._remote = ds, ("127.0.0.1", 9)  # type: ignore[assignment]
    sock.refusal = BlockingIOError(errno.EAGAIN, "full")
    assert send_velocities_ned([link], np.zeros(1), np.zeros(1), np.zeros(1)) == [None]
    sock.refusal = ConnectionRefusedError(errno.ECONNREFUSED, "refused")
    assert send_velocities_ned([link], np.zeros(1), np.zeros(1), np.zeros(1)) == [None]
    assert ds.tx_dropped == 3 and len(errors) == 2 and link.tx_packets == 2
    ds.close()


async def test_a_fleets_setpoints_reach_real_sockets_as_each_link_sends_them() -> None:
    """Over loopback UDP (a udpout and two udpin links): a batch delivers to each vehicle the
    setpoint its own send_velocity_ned delivers, the sequence numbers running on across both
    (the bytes themselves: test_a_fleets_setpoints_sent_at_once_are_the_bytes_each_link_sends)."""
    import asyncio
    import socket

    from link_fake_vehicle import free_udp_port

    from vtube_fleet.link.base import send_velocities_ned

    vehicles = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
    links: list[MavlinkLink] = []
    try:
        for v in vehicles:
            v.bind(("127.0.0.1", 0))
            v.settimeout(5.0)
        links.append(MavlinkLink(f"udpout://127.0.0.1:{vehicles[0].getsockname()[1]}",
                                 sysid=1, heartbeat_period_s=3600.0))
        for k in (2, 3):
            links.append(MavlinkLink(f"udpin://127.0.0.1:{free_udp_port()}", sysid=k,
                                     heartbeat_period_s=3600.0))
        for link in links:
            await link.open()
        for link, v in zip(links[1:], vehicles[1:], strict=True):
            link._remote = v.getsockname()  # (learned from its first packet in flight)
        north, east = np.array([1.0, -2.0, 0.5]), np.array([0.25, 0.0, -1.0])
        down = np.array([0.0, 0.1, -0.1])
        await asyncio.sleep(0)  # the heartbeat tasks' first step (what they send: skipped)
        dec = mavlink2.MAVLink(None)
        seq0 = [link._mav.seq for link in links]
        for round_no, batch in enumerate((True, False, True)):
            if batch:
                assert send_velocities_ned(links, north, east, down) == [None] * 3
            else:
                for link, *v in zip(links, north.tolist(), east.tolist(), down.tolist(),
                                    strict=True):
                    link.send_velocity_ned(*v)
            for k, v in enumerate(vehicles):
                (m,) = dec.parse_buffer(v.recvfrom(256)[0])
                while m.get_type() != "SET_POSITION_TARGET_LOCAL_NED":  # a heartbeat
                    (m,) = dec.parse_buffer(v.recvfrom(256)[0])
                assert m.get_seq() == seq0[k] + round_no and m.target_system == k + 1
                assert (m.vx, m.vy, m.vz) == (_f32(north[k]), _f32(east[k]), _f32(down[k]))
                assert m.type_mask == 3527 and m.coordinate_frame == 1
    finally:
        for link in links:
            await link.close()
        for v in vehicles:
            v.close()
